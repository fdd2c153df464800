"""CPU rasteriser of anisotropic 3D Gaussians (the 3D Gaussian Splatting forward pass).

The image model is the one of Kerbl et al. 2023 / gsplat (EWA splatting):

1. Means go to the camera frame (OpenCV: x right, y down, z forward). Gaussians with ``z < near_m``
   are dropped.
2. The world covariance ``Sigma = R S S^T R^T`` becomes the pixel covariance
   ``cov2d = J W Sigma W^T J^T + 0.3 I`` with ``W`` the world-to-camera rotation and ``J`` the
   perspective Jacobian at the mean (its x/z, y/z clamped to 1.3x the half field of view, as in
   gsplat, so Gaussians far outside the image do not get huge footprints). The 0.3 px^2 low-pass
   makes even sub-pixel Gaussians cover a pixel.
3. ``radius = ceil(3 sqrt(lambda_max(cov2d)))``; a Gaussian touches only the pixels whose centres
   lie in the square of half-side ``radius`` around its projected mean (its "3-sigma box").
   Gaussians whose box misses the image are dropped. (The compiled path further trims the box to
   the ellipse outside of which ``alpha < 1/255``; those pixels would be skipped anyway, so the
   image is the same.)
4. Per pixel, front to back in camera depth (ties keep input order):
   ``alpha_i = min(0.99, opacity_i exp(-0.5 d^T conic_i d))``, skipped when ``alpha_i < 1/255``;
   ``C += T alpha_i c_i``, ``D += T alpha_i z_i``, ``T *= 1 - alpha_i``; a pixel stops as soon as
   ``T < 1e-4`` (early termination; the contribution that crosses the threshold is kept).
5. ``rgb = round(C + T background)``, ``alpha = 1 - T``, ``depth = D / alpha`` where
   ``alpha >= 0.5``, else 0.

Pixel centres are at integer pixel coordinates, so a point projecting to ``(u, v) = K p / z``
lands in the centre of pixel ``(round(u), round(v))`` (the convention of ``CameraIntrinsics``).
Skew in ``K`` is ignored.

``render_gaussians`` is the fast path: numba-compiled, tiled (16x16 pixel tiles, per-tile lists of
Gaussians in depth order), multi-threaded over tiles. ``render_gaussians_reference`` is a plain
NumPy version of the same model used to check it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from atlas_pipeline.geometry import invert_se3, quat_xyzw_to_rotmat

__all__ = ["RenderResult", "render_gaussians", "render_gaussians_reference", "TILE_SIZE"]

logger = logging.getLogger(__name__)

TILE_SIZE = 16
ALPHA_MAX = 0.99  # never fully opaque, so the compositing weights stay well defined
ALPHA_MIN = 1.0 / 255.0  # contributions below one colour level are skipped
T_MIN = 1e-4  # transmittance below which a pixel stops accumulating
LOW_PASS_PX2 = 0.3  # screen-space dilation of 3DGS
FRUSTUM_MARGIN = 0.3  # Jacobian clamp: tan(half fov) * (1 + margin), as in gsplat
DEPTH_MIN_ALPHA = 0.5  # depth is reported only where the rendered surface is mostly opaque


@dataclass
class RenderResult:
    """One rendered view.

    Attributes:
        rgb: ``[H, W, 3]`` uint8 colour, background blended in where the Gaussians are transparent.
        depth_m: ``[H, W]`` float32 expected depth (alpha-weighted camera z, normalised by the
            accumulated alpha); 0 where ``alpha < 0.5``.
        alpha: ``[H, W]`` float32 accumulated opacity in ``[0, 1]``.
        depth_median_m: ``[H, W]`` float32 depth at which the accumulated opacity crosses 0.5
            (the first surface that hides what lies behind it; not pulled towards the background
            at silhouettes or through half-transparent Gaussians as the expected depth is); 0
            where it never does. None from the reference renderer.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    alpha: np.ndarray
    depth_median_m: np.ndarray | None = None


# --------------------------------------------------------------------------------------------
# Input checks shared by both renderers
# --------------------------------------------------------------------------------------------


def _as_float_array(name: str, x, shape_tail: tuple[int, ...], dtype=np.float32) -> np.ndarray:
    try:
        a = np.ascontiguousarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot convert to {np.dtype(dtype).name}: {exc}") from exc
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        want = "[N" + "".join(f", {d}" for d in shape_tail) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return a


def _validate(
    positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width, height,
    background, near_m,
):
    """Check and convert the inputs; returns contiguous float32 arrays and float64 camera."""
    pos = _as_float_array("positions", positions, (3,))
    n = pos.shape[0]
    scl = _as_float_array("scales", scales, (3,))
    quat = _as_float_array("rotations_xyzw", rotations_xyzw, (4,))
    col_raw = np.asarray(colors)
    if col_raw.dtype == np.bool_ or not (
        np.issubdtype(col_raw.dtype, np.integer) or np.issubdtype(col_raw.dtype, np.floating)
    ):
        raise ValueError(f"colors: expected uint8 RGB values, got dtype {col_raw.dtype}")
    col = _as_float_array("colors", col_raw, (3,))
    opa_raw = np.asarray(opacities)
    if opa_raw.ndim == 2 and opa_raw.shape[1] == 1:  # [N, 1] as stored by some PLY writers
        opa_raw = opa_raw[:, 0]
    opa = _as_float_array("opacities", opa_raw, ())
    for name, a in (("scales", scl), ("rotations_xyzw", quat), ("colors", col), ("opacities", opa)):
        if a.shape[0] != n:
            raise ValueError(f"{name}: has {a.shape[0]} rows but positions has {n}")
    if n:
        if np.any(scl < 0):
            raise ValueError("scales: standard deviations must be >= 0")
        if np.any(np.einsum("ij,ij->i", quat, quat) < 1e-12):
            raise ValueError("rotations_xyzw: quaternion with zero norm")
        if col.min() < 0 or col.max() > 255:
            raise ValueError("colors: values must be in [0, 255]")
        if opa.min() < 0 or opa.max() > 1:
            raise ValueError("opacities: values must be in [0, 1]")
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_world_cam: expected a finite [4, 4] matrix, got shape {list(T.shape)}")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise ValueError("T_world_cam: the rotation block is not a proper rotation matrix")
    Km = np.asarray(K, dtype=np.float64)
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)):
        raise ValueError(f"K: expected a finite [3, 3] matrix, got shape {list(Km.shape)}")
    if Km[0, 0] <= 0 or Km[1, 1] <= 0:
        raise ValueError(f"K: focal lengths must be positive, got fx={Km[0, 0]} fy={Km[1, 1]}")
    try:
        size_ok = int(width) == width and int(height) == height and width > 0 and height > 0
    except (TypeError, ValueError):
        size_ok = False
    if not size_ok:
        raise ValueError(f"image size must be positive integers, got {width!r}x{height!r}")
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)) or bg.min() < 0 or bg.max() > 255:
        raise ValueError(f"background: expected 3 values in [0, 255], got {background!r}")
    try:
        near_ok = bool(np.isfinite(near_m) and near_m > 0)
    except TypeError:
        near_ok = False
    if not near_ok:
        raise ValueError(f"near_m must be a positive number, got {near_m!r}")
    return pos, scl, quat, col, opa, T, Km, int(width), int(height), bg, float(near_m)


def _empty_result(width: int, height: int, bg: np.ndarray) -> RenderResult:
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    rgb[:] = np.clip(np.floor(bg + 0.5), 0, 255).astype(np.uint8)
    return RenderResult(
        rgb=rgb,
        depth_m=np.zeros((height, width), dtype=np.float32),
        alpha=np.zeros((height, width), dtype=np.float32),
        depth_median_m=np.zeros((height, width), dtype=np.float32),
    )


# --------------------------------------------------------------------------------------------
# Compiled renderer
# --------------------------------------------------------------------------------------------

# Columns of the per-Gaussian feature rows handed from projection to rasterisation.
_F_U, _F_V, _F_A, _F_B, _F_C, _F_OP, _F_R, _F_G, _F_BL, _F_Z = range(10)
_N_FEAT = 10


@njit(cache=True, inline="always")
def _world_to_camera(pos, i, Rcw, tcw):
    """Camera coordinates ``R_cw (p_i - c)`` of row ``i`` of ``pos`` [N, 3] (``c`` the camera centre)."""
    px = np.float64(pos[i, 0]) - tcw[0]
    py = np.float64(pos[i, 1]) - tcw[1]
    pz = np.float64(pos[i, 2]) - tcw[2]
    x = Rcw[0, 0] * px + Rcw[0, 1] * py + Rcw[0, 2] * pz
    y = Rcw[1, 0] * px + Rcw[1, 1] * py + Rcw[1, 2] * pz
    z = Rcw[2, 0] * px + Rcw[2, 1] * py + Rcw[2, 2] * pz
    return x, y, z


@njit(cache=True, inline="always")
def _rotmat_from_quat(quat, i):
    """Row-major entries ``r00 .. r22`` of the rotation of quaternion row ``i`` of ``quat [N, 4]``
    (x, y, z, w; normalised here): the Gaussian's local axes to world."""
    qx = np.float64(quat[i, 0])
    qy = np.float64(quat[i, 1])
    qz = np.float64(quat[i, 2])
    qw = np.float64(quat[i, 3])
    qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    qx /= qn
    qy /= qn
    qz /= qn
    qw /= qn
    return (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw),
            2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw),
            2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy))


@njit(cache=True, inline="always")
def _pixel_alpha(feat, box, g, px, py):
    """``(alpha, gauss, dx, dy)`` of sorted Gaussian row ``g`` at pixel ``(px, py)``, the scalar form
    of the rasteriser's test: alpha 0 where the pixel is outside the box, beyond the ``power < -6``
    cut or below 1/255; ``gauss = exp(power)``, so ``alpha = min(opacity gauss, 0.99)``."""
    if px < box[g, 0] or px > box[g, 1] or py < box[g, 2] or py > box[g, 3]:
        return 0.0, 0.0, 0.0, 0.0
    dx = px - np.float64(feat[g, _F_U])
    dy = py - np.float64(feat[g, _F_V])
    power = -0.5 * (feat[g, _F_A] * dx * dx + feat[g, _F_C] * dy * dy) - feat[g, _F_B] * dx * dy
    if power < -6.0:
        return 0.0, 0.0, dx, dy
    gauss = math.exp(power)
    alpha = min(feat[g, _F_OP] * gauss, ALPHA_MAX)
    if alpha < ALPHA_MIN:
        return 0.0, gauss, dx, dy
    return alpha, gauss, dx, dy


@njit(cache=True, parallel=True)
def _preprocess(pos, scl, quat, col, opa, Rcw, tcw, fx, fy, cx, cy, width, height, near):
    """Project every Gaussian. Inputs ``[N, ...]`` float32, camera float64.

    Returns ``(valid [N] bool, depth [N] f64, feat [N, 10] f32, box [N, 4] i32)``: ``feat`` rows are
    (u, v, conic a, b, c, opacity, r, g, b, z) with conic ``[[a, b], [b, c]]``; ``box`` is the
    inclusive pixel range (x0, x1, y0, y1) the Gaussian may touch. That range is the 3-sigma box cut
    to the bounding box of the ellipse ``d^T conic d <= 2 ln(255 opacity)``, outside of which
    ``alpha < 1/255`` anyway, so the cut saves tiles without changing the image.
    """
    n = pos.shape[0]
    valid = np.zeros(n, dtype=np.bool_)
    depth = np.zeros(n, dtype=np.float64)
    feat = np.zeros((n, _N_FEAT), dtype=np.float32)
    box = np.zeros((n, 4), dtype=np.int32)
    lim_x_pos = (width - cx) / fx + FRUSTUM_MARGIN * 0.5 * width / fx
    lim_x_neg = cx / fx + FRUSTUM_MARGIN * 0.5 * width / fx
    lim_y_pos = (height - cy) / fy + FRUSTUM_MARGIN * 0.5 * height / fy
    lim_y_neg = cy / fy + FRUSTUM_MARGIN * 0.5 * height / fy
    for i in prange(n):
        o = np.float64(opa[i])
        if o * 255.0 < 1.0:  # can never reach alpha >= 1/255
            continue
        x, y, z = _world_to_camera(pos, i, Rcw, tcw)  # p_cam = R_cw (p_world - c)
        if not (z >= near):
            continue
        # local->world rotation of the Gaussian from its (normalised) quaternion
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotmat_from_quat(quat, i)
        sx = np.float64(scl[i, 0])
        sy = np.float64(scl[i, 1])
        sz = np.float64(scl[i, 2])
        # M = R S, so Sigma = M M^T
        m00 = r00 * sx
        m01 = r01 * sy
        m02 = r02 * sz
        m10 = r10 * sx
        m11 = r11 * sy
        m12 = r12 * sz
        m20 = r20 * sx
        m21 = r21 * sy
        m22 = r22 * sz
        # P = J W (2x3) with J at the clamped mean; cov2d = P Sigma P^T = (P M)(P M)^T
        txz = min(lim_x_pos, max(-lim_x_neg, x / z))
        tyz = min(lim_y_pos, max(-lim_y_neg, y / z))
        j00 = fx / z
        j02 = -fx * txz / z
        j11 = fy / z
        j12 = -fy * tyz / z
        p00 = j00 * Rcw[0, 0] + j02 * Rcw[2, 0]
        p01 = j00 * Rcw[0, 1] + j02 * Rcw[2, 1]
        p02 = j00 * Rcw[0, 2] + j02 * Rcw[2, 2]
        p10 = j11 * Rcw[1, 0] + j12 * Rcw[2, 0]
        p11 = j11 * Rcw[1, 1] + j12 * Rcw[2, 1]
        p12 = j11 * Rcw[1, 2] + j12 * Rcw[2, 2]
        a0 = p00 * m00 + p01 * m10 + p02 * m20
        a1 = p00 * m01 + p01 * m11 + p02 * m21
        a2 = p00 * m02 + p01 * m12 + p02 * m22
        b0 = p10 * m00 + p11 * m10 + p12 * m20
        b1 = p10 * m01 + p11 * m11 + p12 * m21
        b2 = p10 * m02 + p11 * m12 + p12 * m22
        cxx = a0 * a0 + a1 * a1 + a2 * a2 + LOW_PASS_PX2
        cxy = a0 * b0 + a1 * b1 + a2 * b2
        cyy = b0 * b0 + b1 * b1 + b2 * b2 + LOW_PASS_PX2
        det = cxx * cyy - cxy * cxy
        if not (det > 0.0):
            continue
        mid = 0.5 * (cxx + cyy)
        lam = mid + math.sqrt(max(0.0, mid * mid - det))
        radius = math.ceil(3.0 * math.sqrt(lam))
        u = fx * x / z + cx
        v = fy * y / z + cy
        thr = 2.0 * math.log(255.0 * o)
        ex = min(radius, math.sqrt(thr * cxx) + 1e-3)
        ey = min(radius, math.sqrt(thr * cyy) + 1e-3)
        x0 = max(0.0, math.ceil(u - ex))
        x1 = min(width - 1.0, math.floor(u + ex))
        y0 = max(0.0, math.ceil(v - ey))
        y1 = min(height - 1.0, math.floor(v + ey))
        if x0 > x1 or y0 > y1:
            continue
        valid[i] = True
        depth[i] = z
        feat[i, _F_U] = u
        feat[i, _F_V] = v
        feat[i, _F_A] = cyy / det
        feat[i, _F_B] = -cxy / det
        feat[i, _F_C] = cxx / det
        feat[i, _F_OP] = opa[i]
        feat[i, _F_R] = col[i, 0]
        feat[i, _F_G] = col[i, 1]
        feat[i, _F_BL] = col[i, 2]
        feat[i, _F_Z] = z
        box[i, 0] = np.int32(x0)
        box[i, 1] = np.int32(x1)
        box[i, 2] = np.int32(y0)
        box[i, 3] = np.int32(y1)
    return valid, depth, feat, box


@njit(cache=True)
def _radix_argsort_positive(keys):
    """Stable argsort ``[M]`` int32 of positive float64 ``keys [M]`` (LSD radix sort on the bits).

    For positive doubles the IEEE bit pattern read as an unsigned integer is monotone in the value,
    and LSD radix sort is stable, so this equals ``np.argsort(keys, kind="stable")`` in O(M).
    """
    m = keys.shape[0]
    bits = keys.view(np.uint64)
    idx = np.arange(m).astype(np.int32)
    tmp = np.empty(m, dtype=np.int32)
    counts = np.empty(65536, dtype=np.int64)
    mask = np.uint64(0xFFFF)
    for p in range(4):
        shift = np.uint64(16 * p)
        # skip passes where all keys share the digit (the high bits, for depths in a narrow range)
        d0 = (bits[0] >> shift) & mask
        same = True
        for k in range(m):
            if ((bits[k] >> shift) & mask) != d0:
                same = False
                break
        if same:
            continue
        counts[:] = 0
        for k in range(m):
            counts[np.int64((bits[k] >> shift) & mask)] += 1
        total = 0
        for d in range(65536):
            c = counts[d]
            counts[d] = total
            total += c
        for k in range(m):
            j = idx[k]
            d = np.int64((bits[j] >> shift) & mask)
            tmp[counts[d]] = j
            counts[d] += 1
        idx, tmp = tmp, idx
    return idx


@njit(cache=True, parallel=True)
def _gather_rows(order, feat, box):
    """``feat[order]``, ``box[order]`` (``[M, 10]``, ``[M, 4]``), threaded.

    Sorted, contiguous copies: each tile then reads its Gaussians front to back in memory order.
    """
    m = order.shape[0]
    feat_s = np.empty((m, feat.shape[1]), dtype=feat.dtype)
    box_s = np.empty((m, 4), dtype=box.dtype)
    for k in prange(m):
        g = order[k]
        for j in range(feat.shape[1]):
            feat_s[k, j] = feat[g, j]
        for j in range(4):
            box_s[k, j] = box[g, j]
    return feat_s, box_s


@njit(cache=True)
def _bin_tiles(box, tiles_x, n_tiles):
    """Per-tile lists of Gaussians; ``box [M, 4]`` of the Gaussians already sorted front to back.

    Returns ``(tile_start [n_tiles + 1] int64, tile_ids [P] int32)``: tile ``t`` holds the rows
    ``tile_ids[tile_start[t]:tile_start[t + 1]]`` of ``box``, still front to back (counting sort,
    which is stable).
    """
    m = box.shape[0]
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    for k in range(m):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE
        for ty in range(box[k, 2] // TILE_SIZE, box[k, 3] // TILE_SIZE + 1):
            for tx in range(tx0, tx1 + 1):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    fill = counts[:-1].copy()
    tile_ids = np.empty(counts[n_tiles], dtype=np.int32)
    for k in range(m):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE
        for ty in range(box[k, 2] // TILE_SIZE, box[k, 3] // TILE_SIZE + 1):
            for tx in range(tx0, tx1 + 1):
                t = ty * tiles_x + tx
                tile_ids[fill[t]] = k
                fill[t] += 1
    return counts, tile_ids


@njit(cache=True, inline="always")
def _exp_neg(x):
    """``exp(x)`` for float32 ``x`` in [-6, 0] to ~2e-6 relative error, with plain arithmetic.

    ``math.exp`` is a libm call that blocks SIMD; this (Taylor polynomial of ``exp(x / 16)``,
    squared four times) lets the compiler vectorise a whole tile row.
    """
    y = x * np.float32(1.0 / 16.0)
    p = np.float32(1.0 / 5040.0)
    p = p * y + np.float32(1.0 / 720.0)
    p = p * y + np.float32(1.0 / 120.0)
    p = p * y + np.float32(1.0 / 24.0)
    p = p * y + np.float32(1.0 / 6.0)
    p = p * y + np.float32(0.5)
    p = p * y + np.float32(1.0)
    p = p * y + np.float32(1.0)
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(cache=True, inline="always")
def _to_u8(x):
    """Round half up and clip to a uint8 colour level."""
    return np.uint8(min(255.0, max(0.0, math.floor(x + 0.5))))


@njit(cache=True)
def _rasterize_tiles(
    worker, n_workers, tile_start, tile_ids, feat, box, width, height, tiles_x, n_tiles, bg,
    rgb, depth_out, alpha_out, median_out,
):
    """Composite tiles ``worker, worker + n_workers, ...`` front to back into the output images.

    ``feat [M, 10]`` / ``box [M, 4]`` are the sorted Gaussians, ``tile_start``/``tile_ids`` from
    ``_bin_tiles``; writes rgb ``[H, W, 3]`` uint8, depth and alpha ``[H, W]`` float32 in place.

    For each (tile, Gaussian) pair every touched tile row is processed as one 16-wide branch-free
    vector (lanes outside the Gaussian's box, below 1/255 or already terminated get alpha 0):
    several times faster than a scalar loop over the box. Kept out of the ``prange`` body so the
    parallel transform cannot get in the way of that vectorisation.
    """
    t_min = np.float32(T_MIN)
    a_min = np.float32(ALPHA_MIN)
    a_max = np.float32(ALPHA_MAX)
    p_min = np.float32(-6.0)  # exp(-6) < 1/255: lanes clamped here are rejected by the alpha test
    one = np.float32(1.0)
    zero = np.float32(0.0)
    # unsigned loop index: no negative-index wraparound code, so the row loop vectorises
    lanes = np.uint64(TILE_SIZE)
    T = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cr = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cg = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cb = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    D = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Dm = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    half = np.float32(0.5)
    for t in range(worker, n_tiles, n_workers):
        px0 = (t % tiles_x) * TILE_SIZE
        py0 = (t // tiles_x) * TILE_SIZE
        px1 = min(px0 + TILE_SIZE, width) - 1
        py1 = min(py0 + TILE_SIZE, height) - 1
        T[:] = 1.0
        Cr[:] = 0.0
        Cg[:] = 0.0
        Cb[:] = 0.0
        D[:] = 0.0
        Dm[:] = 0.0
        n_active = (px1 - px0 + 1) * (py1 - py0 + 1)
        for k in range(tile_start[t], tile_start[t + 1]):
            if n_active <= 0:  # every pixel of the tile has terminated
                break
            g = tile_ids[k]
            ux = feat[g, _F_U] - np.float32(px0)  # mean relative to the tile's left column
            v = feat[g, _F_V]
            nha = np.float32(-0.5) * feat[g, _F_A]
            cb = feat[g, _F_B]
            nhc = np.float32(-0.5) * feat[g, _F_C]
            op = feat[g, _F_OP]
            cr = feat[g, _F_R]
            cgr = feat[g, _F_G]
            cbl = feat[g, _F_BL]
            z = feat[g, _F_Z]
            lx0 = np.float32(max(box[g, 0], px0) - px0)
            lx1 = np.float32(min(box[g, 1], px1) - px0)
            for py in range(max(box[g, 2], py0), min(box[g, 3], py1) + 1):
                dy = np.float32(py) - v
                qy = nhc * dy * dy
                by = cb * dy
                r = py - py0
                Tv = T[r]
                Crv = Cr[r]
                Cgv = Cg[r]
                Cbv = Cb[r]
                Dv = D[r]
                Dmv = Dm[r]
                done = np.uint64(0)
                for j in range(lanes):
                    lj = np.float32(j)
                    dx = lj - ux
                    power = nha * dx * dx + qy - by * dx
                    power = power if power > p_min else p_min
                    e = op * _exp_neg(power)
                    alpha = e if e < a_max else a_max
                    Tl = Tv[j]
                    ok = (alpha >= a_min) & (Tl >= t_min) & (lj >= lx0) & (lj <= lx1)
                    a = alpha if ok else zero
                    wgt = a * Tl
                    Crv[j] += wgt * cr
                    Cgv[j] += wgt * cgr
                    Cbv[j] += wgt * cbl
                    Dv[j] += wgt * z
                    Tn = Tl * (one - a)
                    Dmv[j] = z if (Tl > half) & (Tn <= half) else Dmv[j]
                    Tv[j] = Tn
                    done += np.uint64(ok & (Tn < t_min))
                n_active -= np.int64(done)
        for py in range(py0, py1 + 1):
            r = py - py0
            for px in range(px0, px1 + 1):
                c = px - px0
                Tl = T[r, c]
                rgb[py, px, 0] = _to_u8(Cr[r, c] + Tl * bg[0])
                rgb[py, px, 1] = _to_u8(Cg[r, c] + Tl * bg[1])
                rgb[py, px, 2] = _to_u8(Cb[r, c] + Tl * bg[2])
                acc = one - Tl
                alpha_out[py, px] = acc
                depth_out[py, px] = D[r, c] / acc if acc >= DEPTH_MIN_ALPHA else 0.0
                median_out[py, px] = Dm[r, c]


@njit(cache=True, parallel=True)
def _rasterize(tile_start, tile_ids, feat, box, width, height, tiles_x, n_tiles, bg, n_workers):
    """All tiles, ``n_workers`` threads. Returns rgb ``[H, W, 3]`` uint8, depth/alpha ``[H, W]``."""
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    depth_out = np.empty((height, width), dtype=np.float32)
    alpha_out = np.empty((height, width), dtype=np.float32)
    median_out = np.empty((height, width), dtype=np.float32)
    # Worker w takes tiles w, w + n_workers, ...: interleaving balances busy and empty regions.
    for w in prange(n_workers):
        _rasterize_tiles(
            w, n_workers, tile_start, tile_ids, feat, box, width, height, tiles_x, n_tiles, bg,
            rgb, depth_out, alpha_out, median_out,
        )
    return rgb, depth_out, alpha_out, median_out


def render_gaussians(
    positions: np.ndarray,
    scales: np.ndarray,
    rotations_xyzw: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = 0.05,
) -> RenderResult:
    """Render Gaussians into one view (numba-compiled, tiled, multi-threaded).

    Args:
        positions: ``[N, 3]`` world-frame means (metres).
        scales: ``[N, 3]`` standard deviations (metres) along each Gaussian's local axes, ``>= 0``.
        rotations_xyzw: ``[N, 4]`` quaternions (x, y, z, w), local -> world; normalised here.
        colors: ``[N, 3]`` RGB in ``[0, 255]`` (uint8 or any numeric dtype).
        opacities: ``[N]`` (or ``[N, 1]``) in ``[0, 1]``.
        T_world_cam: ``[4, 4]`` camera-to-world pose (OpenCV camera axes).
        K: ``[3, 3]`` pinhole intrinsics.
        width, height: image size in pixels.
        background: RGB shown where the Gaussians are transparent.
        near_m: Gaussians whose mean has camera ``z < near_m`` are not drawn.

    Returns:
        ``RenderResult`` with rgb ``[H, W, 3]`` uint8, depth_m and alpha ``[H, W]`` float32.

    Raises:
        ValueError: malformed shapes, non-finite values or values out of range.
    """
    pos, scl, quat, col, opa, T, Km, width, height, bg, near_m = _validate(
        positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width, height,
        background, near_m,
    )
    if pos.shape[0] == 0:
        return _empty_result(width, height, bg)
    Rcw = np.ascontiguousarray(T[:3, :3].T)
    centre = np.ascontiguousarray(T[:3, 3])
    fx, fy, cx, cy = float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])
    valid, depth, feat, box = _preprocess(
        pos, scl, quat, col, opa, Rcw, centre, fx, fy, cx, cy, width, height, near_m
    )
    ids = np.flatnonzero(valid)
    if ids.size == 0:
        return _empty_result(width, height, bg)
    order = ids[_radix_argsort_positive(depth[ids])]
    feat, box = _gather_rows(order, feat, box)
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * tiles_y
    tile_start, tile_ids = _bin_tiles(box, tiles_x, n_tiles)
    n_workers = min(n_tiles, max(1, numba.get_num_threads()))
    rgb, depth_m, alpha, depth_median_m = _rasterize(
        tile_start, tile_ids, feat, box, width, height, tiles_x, n_tiles,
        bg.astype(np.float32), n_workers,
    )
    return RenderResult(rgb=rgb, depth_m=depth_m, alpha=alpha, depth_median_m=depth_median_m)


# --------------------------------------------------------------------------------------------
# NumPy reference
# --------------------------------------------------------------------------------------------


def render_gaussians_reference(
    positions: np.ndarray,
    scales: np.ndarray,
    rotations_xyzw: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = 0.05,
) -> RenderResult:
    """Straightforward NumPy splat of the same model (no tiling, no compiled code).

    Used as the correctness and speed reference of ``render_gaussians``: vectorised projection,
    then one Python-level step per Gaussian (front to back) that updates the pixels of its 3-sigma
    box. Slow (seconds for 10^5 Gaussians) but easy to check. Same arguments and result.
    """
    pos, scl, quat, col, opa, T, Km, width, height, bg, near_m = _validate(
        positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width, height,
        background, near_m,
    )
    n = pos.shape[0]
    if n == 0:
        return _empty_result(width, height, bg)
    fx, fy, cx, cy = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]
    T_cw = invert_se3(T)
    W = T_cw[:3, :3]
    p_cam = pos.astype(np.float64) @ W.T + T_cw[:3, 3]
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    keep = z >= near_m
    zs = np.where(keep, z, 1.0)  # placeholder depth for culled ones avoids division warnings

    R = quat_xyzw_to_rotmat(quat)
    M = R * scl.astype(np.float64)[:, None, :]  # R S
    Sigma = M @ np.swapaxes(M, 1, 2)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x = (cx / fx + FRUSTUM_MARGIN * tan_x, (width - cx) / fx + FRUSTUM_MARGIN * tan_x)
    lim_y = (cy / fy + FRUSTUM_MARGIN * tan_y, (height - cy) / fy + FRUSTUM_MARGIN * tan_y)
    txz = np.clip(x / zs, -lim_x[0], lim_x[1])
    tyz = np.clip(y / zs, -lim_y[0], lim_y[1])
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * txz / zs
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * tyz / zs
    JW = J @ W
    cov2d = JW @ Sigma @ np.swapaxes(JW, 1, 2)
    cov2d[:, 0, 0] += LOW_PASS_PX2
    cov2d[:, 1, 1] += LOW_PASS_PX2
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
    keep &= det > 0
    dets = np.where(keep, det, 1.0)
    conic_a = cov2d[:, 1, 1] / dets
    conic_b = -cov2d[:, 0, 1] / dets
    conic_c = cov2d[:, 0, 0] / dets
    mid = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
    lam_max = mid + np.sqrt(np.maximum(0.0, mid**2 - det))
    radius = np.ceil(3.0 * np.sqrt(np.maximum(lam_max, 0.0)))
    u = fx * x / zs + cx
    v = fy * y / zs + cy
    x0 = np.maximum(0, np.ceil(u - radius))
    x1 = np.minimum(width - 1, np.floor(u + radius))
    y0 = np.maximum(0, np.ceil(v - radius))
    y1 = np.minimum(height - 1, np.floor(v + radius))
    keep &= (x0 <= x1) & (y0 <= y1)

    ids = np.flatnonzero(keep)
    ids = ids[np.argsort(z[ids], kind="stable")]  # front to back, ties in input order
    Tr = np.ones((height, width))
    C = np.zeros((height, width, 3))
    D = np.zeros((height, width))
    colf = col.astype(np.float64)
    for g in ids:
        ys = slice(int(y0[g]), int(y1[g]) + 1)
        xs = slice(int(x0[g]), int(x1[g]) + 1)
        dx = np.arange(xs.start, xs.stop)[None, :] - u[g]
        dy = np.arange(ys.start, ys.stop)[:, None] - v[g]
        power = -0.5 * (conic_a[g] * dx * dx + conic_c[g] * dy * dy) - conic_b[g] * dx * dy
        alpha = np.minimum(ALPHA_MAX, opa[g] * np.exp(power))
        Tp = Tr[ys, xs]
        # pixels already terminated (T < 1e-4) and too-faint contributions are skipped
        alpha = np.where((alpha >= ALPHA_MIN) & (Tp >= T_MIN), alpha, 0.0)
        wgt = alpha * Tp
        C[ys, xs] += wgt[..., None] * colf[g]
        D[ys, xs] += wgt * z[g]
        Tr[ys, xs] = Tp * (1.0 - alpha)
    acc = 1.0 - Tr
    rgb = np.clip(np.floor(C + Tr[..., None] * bg + 0.5), 0, 255).astype(np.uint8)
    depth_m = np.where(acc >= DEPTH_MIN_ALPHA, D / np.maximum(acc, 1e-12), 0.0)
    return RenderResult(rgb=rgb, depth_m=depth_m.astype(np.float32), alpha=acc.astype(np.float32))

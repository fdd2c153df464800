"""The raster core shared by the renderer, the colour fit and the keyframe fit.

One implementation of the 3D Gaussian Splatting forward pass (Kerbl et al. 2023 / gsplat, EWA
splatting), in named stages as gsplat's ``rendering.py`` has them:

1. ``validate_inputs``: shapes, dtypes and ranges of the Gaussians and the camera.
2. ``view_from_pose``: the camera ``T_world_cam`` / ``K`` as the rasteriser reads it.
3. ``project_gaussians``: means to the camera frame (OpenCV: x right, y down, z forward), dropped
   when ``z < near_m``; pixel covariance ``cov2d = J W Sigma W^T J^T + LOW_PASS_PX2 I`` with ``J``
   the perspective Jacobian at the mean, its x/z and y/z clamped to ``1 + FRUSTUM_MARGIN`` times the
   half field of view (as gsplat: Gaussians far outside the image do not get huge footprints);
   conic ``cov2d^-1`` and the pixel box the Gaussian may touch (its ``SIGMA_EXTENT``-sigma square,
   trimmed to the ellipse outside of which ``alpha < ALPHA_MIN`` anyway). With ``keep_aux`` it also
   keeps the intermediates (``AUX_*``: camera-frame mean, ``J W``, ``J W R S``, covariance, the
   depth slopes of the Gaussian's plane) that a backward pass needs, so the keyframe fit never
   projects a view twice.
4. ``sort_by_depth``: front to back in camera depth, ties in input order.
5. ``bin_tiles``: per ``TILE_SIZE`` x ``TILE_SIZE`` tile, the Gaussians whose box touches it, still
   front to back. ``pair_slots`` (5b, for backward passes) numbers every (tile, Gaussian) pair
   Gaussian by Gaussian, so per-pair results written by tile can be summed per Gaussian after.
6. ``composite_tiles``: per pixel, front to back,
   ``alpha_i = min(ALPHA_MAX, opacity_i exp(-0.5 d^T conic_i d))``, skipped below ``ALPHA_MIN``;
   ``C += T alpha_i c_i``, ``D += T alpha_i z_i``, ``T *= 1 - alpha_i``; a pixel stops once
   ``T < T_MIN`` (the contribution that crosses the threshold is kept). ``rgb = round(C + T bg)``,
   ``alpha = 1 - T``, ``depth = D / alpha`` where ``alpha >= DEPTH_MIN_ALPHA``, else 0.

``prepare_splats`` runs stages 3-5 (what every caller needs before its own tile loop).

The renderer runs the same stages in bounded memory (``render.render_gaussians``; same image bit
for bit): ``project_visible`` projects ``PROJECT_CHUNK`` Gaussians at a time and keeps only the
drawn ones (compacted, input order); ``sort_visible`` puts them front to back in place (no sorted
copy); ``tile_pair_counts`` counts the (tile, Gaussian) pairs per tile without listing them;
``tile_batches`` cuts the tiles (row-major) into runs of at most ``max_tile_pairs`` pairs;
``bin_tile_batch`` lists one run's pairs and ``composite_tile_batch`` draws it into the output
images. Peak memory is then O(N) with a small constant plus O(pairs per batch), whatever the
view (``render.render_peak_bytes`` states it). Compiled
kernels elsewhere (the fits' backward passes) build on the device helpers ``world_to_camera``,
``rotmat_from_quat``, ``jacobian_clamp_limits``, ``projection_rows``, ``pixel_covariance``,
``pixel_alpha``, ``exp_neg_fast`` and ``tile_pixel_bounds``, so their forward model is this one by
construction.

Pixel centres are at integer pixel coordinates: a point at ``(u, v) = K p / z`` lands in the centre
of pixel ``(round(u), round(v))``, pixel ``i`` covers ``[i - 0.5, i + 0.5)``. ``scale_intrinsics`` /
``scale_camera`` keep that convention when an image is resampled. Skew in ``K`` is ignored.

Plain NumPy versions of every stage, used to check these, are in ``_raster_reference``.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.cores import kernel_threads

logger = logging.getLogger(__name__)

__all__ = [
    "TILE_SIZE", "ALPHA_MAX", "COLOR_LEVELS", "ALPHA_MIN", "T_MIN", "LOW_PASS_PX2", "FRUSTUM_MARGIN", "DEPTH_MIN_ALPHA",
    "SIGMA_EXTENT", "POWER_MIN", "BOX_SLACK_PX", "MEDIAN_DEPTH_T", "NEAR_M",
    "FEAT_U", "FEAT_V", "FEAT_CONIC_A", "FEAT_CONIC_B", "FEAT_CONIC_C", "FEAT_OPACITY", "FEAT_RED",
    "FEAT_GREEN", "FEAT_BLUE", "FEAT_Z", "N_FEAT", "AUX_X", "AUX_Y", "AUX_Z", "AUX_P", "AUX_A", "AUX_B",
    "AUX_CXX", "AUX_CXY", "AUX_CYY", "AUX_TXZ", "AUX_TYZ", "AUX_SLOPE_U", "AUX_SLOPE_V", "N_AUX",
    "PLANE_FLATNESS", "PLANE_MAX_SLOPE",
    "RasterInputs", "PinholeView", "Projection", "TileBins", "SplatTiles",
    "validate_inputs", "view_from_pose", "project_gaussians", "sort_by_depth", "gather_sorted", "bin_tiles",
    "pair_slots", "prepare_splats", "composite_tiles", "scale_intrinsics", "scaled_image_size", "scale_camera",
    "PROJECT_CHUNK", "MAX_TILE_PAIRS", "VisibleSplats", "project_visible", "sort_visible", "tile_pair_counts",
    "tile_batches", "bin_tile_batch", "composite_tile_batch",
    "world_to_camera", "rotmat_from_quat", "jacobian_clamp_limits", "projection_rows", "pixel_covariance",
    "plane_depth_slopes", "pixel_alpha", "tile_pixel_bounds", "exp_neg_fast",
]

# --------------------------------------------------------------------------------------------
# Constants of the image model
# --------------------------------------------------------------------------------------------

TILE_SIZE = 16  # pixels per tile side; 16 lanes of float32 make one vectorised tile row
ALPHA_MAX = 0.99  # never fully opaque, so the compositing weights stay well defined
COLOR_LEVELS = 255.0  # uint8 colour levels
ALPHA_MIN = 1.0 / COLOR_LEVELS  # contributions below one colour level are skipped
T_MIN = 1e-4  # transmittance below which a pixel stops accumulating
LOW_PASS_PX2 = 0.3  # screen-space dilation of 3DGS: even sub-pixel Gaussians cover a pixel
FRUSTUM_MARGIN = 0.3  # Jacobian clamp: tan(half fov) * (1 + margin), as in gsplat
DEPTH_MIN_ALPHA = 0.5  # depth is reported only where the rendered surface is mostly opaque
SIGMA_EXTENT = 3.0  # a Gaussian's footprint: the square of half-side 3 sqrt(lambda_max(cov2d))
POWER_MIN = -6.0  # exp(-6) = 0.0025 < ALPHA_MIN: beyond it no opacity <= 1 gives a visible alpha
BOX_SLACK_PX = 1e-3  # widening of the alpha-cut box, so rounding never drops a visible pixel
CULL_SLACK_PX = 2.0  # margin of the projection's off-image test: covers the box's ceil (1 px) and rounding
MEDIAN_DEPTH_T = 0.5  # the median depth is read where the transmittance crosses this
NEAR_M = 0.05  # default near plane (metres)
# Bounded-memory rendering (``project_visible`` ... ``composite_tile_batch``):
PROJECT_CHUNK = 1 << 18  # Gaussians projected at a time: 17 MB of per-chunk buffers at any N, and
#                          few enough launches of the threaded kernel (each costs ms on a busy machine)
MAX_TILE_PAIRS = 1 << 22  # (tile, Gaussian) pairs listed at once: 16 MB of int32; a 640x480 view of
#                           a few million Gaussians usually fits in one or two batches

# Columns of the per-Gaussian feature rows handed from projection to compositing.
FEAT_U, FEAT_V, FEAT_CONIC_A, FEAT_CONIC_B, FEAT_CONIC_C, FEAT_OPACITY, FEAT_RED, FEAT_GREEN, FEAT_BLUE, FEAT_Z = (
    range(10))
N_FEAT = 10
# Columns of the projection intermediates a backward pass reads (``project_gaussians(keep_aux=True)``):
# camera-frame mean, ``P = J W`` (2x3, row major), rows ``a``, ``b`` of ``P R S``, the pixel
# covariance (low-pass included) and the clamped ``x / z``, ``y / z`` the Jacobian was taken at.
# ``AUX_SLOPE_U`` / ``_V``: the screen-space slopes ``(dz/du, dz/dv)`` of the plane through the mean
# normal to the Gaussian's shortest axis (``plane_depth_slopes``), for depths read on the surface.
AUX_X, AUX_Y, AUX_Z, AUX_P, AUX_A, AUX_B, AUX_CXX, AUX_CXY, AUX_CYY, AUX_TXZ, AUX_TYZ, AUX_SLOPE_U, AUX_SLOPE_V = (
    0, 1, 2, 3, 9, 12, 15, 16, 17, 18, 19, 20, 21)
N_AUX = 22
PLANE_FLATNESS = 0.5  # a Gaussian is a plane when its shortest scale is at most this times the middle one
PLANE_MAX_SLOPE = 3.0  # plane depth slopes clamped at tan(72 deg): 3 m of depth per metre across


# --------------------------------------------------------------------------------------------
# Stage 1-2: inputs and camera
# --------------------------------------------------------------------------------------------


class RasterInputs(NamedTuple):
    """Checked inputs: contiguous float32 Gaussians, float64 camera."""

    positions: np.ndarray  # [N, 3] float32, world frame (metres)
    scales: np.ndarray  # [N, 3] float32, standard deviations (metres)
    rotations_xyzw: np.ndarray  # [N, 4] float32
    colors: np.ndarray  # [N, 3] float32 in [0, 255] (uint8 when validated with float_colors=False)
    opacities: np.ndarray  # [N] float32 in [0, 1]
    T_world_cam: np.ndarray  # [4, 4] float64 camera-to-world
    K: np.ndarray  # [3, 3] float64
    width: int
    height: int
    background: np.ndarray  # [3] float64 in [0, 255]
    near_m: float


class PinholeView(NamedTuple):
    """The camera as the compiled stages read it."""

    R_cam_world: np.ndarray  # [3, 3] float64, world -> camera rotation
    centre_world: np.ndarray  # [3] float64, camera centre (metres)
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


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


def validate_inputs(
    positions,  # [N, 3]
    scales,  # [N, 3]
    rotations_xyzw,  # [N, 4]
    colors,  # [N, 3]
    opacities,  # [N] or [N, 1]
    T_world_cam,  # [4, 4]
    K,  # [3, 3]
    width,
    height,
    background,  # [3]
    near_m,
    float_colors: bool = True,
) -> RasterInputs:
    """Check and convert the renderer's inputs; ``ValueError`` naming the bad one otherwise.

    ``float_colors=False``: uint8 colours are kept as they are (no float32 copy of 12 bytes per
    Gaussian; the projection converts each to the same float32); other dtypes are converted."""
    pos = _as_float_array("positions", positions, (3,))
    n = pos.shape[0]
    scl = _as_float_array("scales", scales, (3,))
    quat = _as_float_array("rotations_xyzw", rotations_xyzw, (4,))
    col_raw = np.asarray(colors)
    if col_raw.dtype == np.bool_ or not (
        np.issubdtype(col_raw.dtype, np.integer) or np.issubdtype(col_raw.dtype, np.floating)
    ):
        raise ValueError(f"colors: expected uint8 RGB values, got dtype {col_raw.dtype}")
    if not float_colors and col_raw.dtype == np.uint8:
        col = np.ascontiguousarray(col_raw)
        if col.ndim != 2 or col.shape[1:] != (3,):
            raise ValueError(f"colors: expected shape [N, 3], got {list(col.shape)}")
    else:
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
    return RasterInputs(pos, scl, quat, col, opa, T, Km, int(width), int(height), bg, float(near_m))


def view_from_pose(
    T_world_cam: np.ndarray,  # [4, 4] camera-to-world
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
) -> PinholeView:
    """The camera of one raster pass (no checks: see ``validate_inputs``)."""
    T = np.asarray(T_world_cam, np.float64)
    Km = np.asarray(K, np.float64)
    return PinholeView(
        np.ascontiguousarray(T[:3, :3].T), np.ascontiguousarray(T[:3, 3]),
        float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2]), int(width), int(height),
    )


# --------------------------------------------------------------------------------------------
# Intrinsics of a resampled image
# --------------------------------------------------------------------------------------------


def scale_intrinsics(
    K: np.ndarray,  # [3, 3]
    scale_x: float,
    scale_y: float | None = None,
) -> np.ndarray:
    """``[3, 3]`` intrinsics of the image resampled by ``scale_x`` (and ``scale_y``, default the same).

    With pixel centres at integer coordinates pixel ``i`` covers ``[i - 0.5, i + 0.5)``, so the
    image edges ``-0.5`` and ``W - 0.5`` map to ``-0.5`` and ``s W - 0.5``: ``u' = s (u + 0.5) - 0.5``
    (a plain ``s u`` would shift the view by ``(1 - s) / 2`` pixels: a quarter pixel at half size).
    """
    if scale_y is None:
        scale_y = scale_x
    Ks = np.asarray(K, np.float64).copy()
    Ks[0, 0] *= scale_x
    Ks[1, 1] *= scale_y
    Ks[0, 2] = (Ks[0, 2] + 0.5) * scale_x - 0.5
    Ks[1, 2] = (Ks[1, 2] + 0.5) * scale_y - 0.5
    return Ks


def scaled_image_size(width: int, height: int, scale: float, multiple: int = 1) -> tuple[int, int]:
    """``(w, h)`` of an image scaled by ``scale``, rounded, then down to a multiple of ``multiple``
    (2 for yuv420p video)."""
    return (int(round(width * scale)) // multiple * multiple,
            int(round(height * scale)) // multiple * multiple)


def scale_camera(
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
    scale: float,
    multiple: int = 1,
) -> tuple[int, int, np.ndarray]:
    """``(w, h, K_scaled [3, 3])`` of the image scaled by about ``scale`` (``scaled_image_size``).

    The intrinsics use the exact per-axis ratios ``w / width`` and ``h / height``, so the scaled
    image shows the same field of view as the full one, edge to edge.
    """
    w, h = scaled_image_size(width, height, scale, multiple)
    return w, h, scale_intrinsics(K, w / width, h / height)


# --------------------------------------------------------------------------------------------
# Compiled device helpers (inlined into the kernels here and in the fits' backward passes)
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def world_to_camera(pos, i, Rcw, tcw):
    """Camera coordinates ``R_cw (p_i - c)`` of row ``i`` of ``pos`` ``[N, 3]``.

    ``Rcw`` ``[3, 3]`` world -> camera rotation, ``tcw`` ``[3]`` the camera centre ``c`` (world).
    """
    px = np.float64(pos[i, 0]) - tcw[0]
    py = np.float64(pos[i, 1]) - tcw[1]
    pz = np.float64(pos[i, 2]) - tcw[2]
    x = Rcw[0, 0] * px + Rcw[0, 1] * py + Rcw[0, 2] * pz
    y = Rcw[1, 0] * px + Rcw[1, 1] * py + Rcw[1, 2] * pz
    z = Rcw[2, 0] * px + Rcw[2, 1] * py + Rcw[2, 2] * pz
    return x, y, z


@njit(cache=True, inline="always")
def rotmat_from_quat(quat, i):
    """Row-major entries ``r00 .. r22`` of the rotation of row ``i`` of ``quat`` ``[N, 4]``
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
def jacobian_clamp_limits(fx, fy, cx, cy, width, height):
    """``(lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg)``: the range ``-lim_neg <= x / z <= lim_pos``
    (likewise y / z) the Jacobian is evaluated in: the image plus ``FRUSTUM_MARGIN`` of the half
    field of view on each side."""
    lim_x_pos = (width - cx) / fx + FRUSTUM_MARGIN * 0.5 * width / fx
    lim_x_neg = cx / fx + FRUSTUM_MARGIN * 0.5 * width / fx
    lim_y_pos = (height - cy) / fy + FRUSTUM_MARGIN * 0.5 * height / fy
    lim_y_neg = cy / fy + FRUSTUM_MARGIN * 0.5 * height / fy
    return lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg


@njit(cache=True, inline="always")
def projection_rows(Rcw, fx, fy, x, y, z, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg):
    """``(p00, p01, p02, p10, p11, p12, txz, tyz)``: ``P = J W`` (2x3) with ``J`` the perspective
    Jacobian at the camera-frame mean ``(x, y, z)``, its ``x / z``, ``y / z`` clamped to
    ``(txz, tyz)``; ``W = Rcw`` ``[3, 3]``."""
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
    return p00, p01, p02, p10, p11, p12, txz, tyz


@njit(cache=True, inline="always")
def pixel_covariance(p00, p01, p02, p10, p11, p12, m00, m01, m02, m10, m11, m12, m20, m21, m22):
    """``(a0, a1, a2, b0, b1, b2, cxx, cxy, cyy)``: rows ``a``, ``b`` of ``P M`` and the pixel
    covariance ``cov2d = (P M)(P M)^T + LOW_PASS_PX2 I`` (``[[cxx, cxy], [cxy, cyy]]``), with ``P``
    from ``projection_rows`` and ``M = R S`` the Gaussian's rotation times its scales (row major)."""
    a0 = p00 * m00 + p01 * m10 + p02 * m20
    a1 = p00 * m01 + p01 * m11 + p02 * m21
    a2 = p00 * m02 + p01 * m12 + p02 * m22
    b0 = p10 * m00 + p11 * m10 + p12 * m20
    b1 = p10 * m01 + p11 * m11 + p12 * m21
    b2 = p10 * m02 + p11 * m12 + p12 * m22
    cxx = a0 * a0 + a1 * a1 + a2 * a2 + LOW_PASS_PX2
    cxy = a0 * b0 + a1 * b1 + a2 * b2
    cyy = b0 * b0 + b1 * b1 + b2 * b2 + LOW_PASS_PX2
    return a0, a1, a2, b0, b1, b2, cxx, cxy, cyy


@njit(cache=True, inline="always")
def plane_depth_slopes(r00, r01, r02, r10, r11, r12, r20, r21, r22, sx, sy, sz, Rcw, x, y, z, fx, fy):
    """``(dz/du, dz/dv)``: how the depth of the plane through the camera-frame mean ``(x, y, z)``,
    normal to the Gaussian's shortest axis (rotation ``r``, scales ``s``), changes along the pixel
    rays: ``z(u, v) ~ z + dz/du (u - u0) + dz/dv (v - v0)``. A Gaussian then reports the depth of its
    surface at a pixel, not of its centre (which on a slanted surface reads nearer for the front-most
    Gaussians). ``(0, 0)`` for Gaussians that are not flat (``PLANE_FLATNESS``) or seen edge-on;
    clamped at ``PLANE_MAX_SLOPE``."""
    a = 0 if (sx <= sy and sx <= sz) else (1 if sy <= sz else 2)
    smid = sx + sy + sz - min(sx, min(sy, sz)) - max(sx, max(sy, sz))
    smin = sx if a == 0 else (sy if a == 1 else sz)
    if smin > PLANE_FLATNESS * smid:
        return 0.0, 0.0
    if a == 0:  # the shortest axis: column a of the rotation
        n0, n1, n2 = r00, r10, r20
    elif a == 1:
        n0, n1, n2 = r01, r11, r21
    else:
        n0, n1, n2 = r02, r12, r22
    nx = Rcw[0, 0] * n0 + Rcw[0, 1] * n1 + Rcw[0, 2] * n2
    ny = Rcw[1, 0] * n0 + Rcw[1, 1] * n1 + Rcw[1, 2] * n2
    nz = Rcw[2, 0] * n0 + Rcw[2, 1] * n1 + Rcw[2, 2] * n2
    c = nx * x + ny * y + nz * z  # n . mu: z(u, v) = c / (n . ray(u, v))
    if abs(c) < 1e-9:
        return 0.0, 0.0
    lim_u = PLANE_MAX_SLOPE * z / fx
    lim_v = PLANE_MAX_SLOPE * z / fy
    return (min(lim_u, max(-lim_u, -z * z * nx / (fx * c))),
            min(lim_v, max(-lim_v, -z * z * ny / (fy * c))))


@njit(cache=True, inline="always")
def pixel_alpha(feat, box, g, px, py):
    """``(alpha, gauss, dx, dy)`` of sorted Gaussian row ``g`` of ``feat`` ``[M, N_FEAT]`` /
    ``box`` ``[M, 4]`` at pixel ``(px, py)``: the scalar form of the compositing test. alpha is 0
    outside the box, beyond ``POWER_MIN`` or below ``ALPHA_MIN``; ``gauss = exp(power)``, so
    ``alpha = min(opacity gauss, ALPHA_MAX)``."""
    if px < box[g, 0] or px > box[g, 1] or py < box[g, 2] or py > box[g, 3]:
        return 0.0, 0.0, 0.0, 0.0
    dx = px - np.float64(feat[g, FEAT_U])
    dy = py - np.float64(feat[g, FEAT_V])
    power = (-0.5 * (feat[g, FEAT_CONIC_A] * dx * dx + feat[g, FEAT_CONIC_C] * dy * dy)
             - feat[g, FEAT_CONIC_B] * dx * dy)
    if power < POWER_MIN:
        return 0.0, 0.0, dx, dy
    gauss = math.exp(power)
    alpha = min(feat[g, FEAT_OPACITY] * gauss, ALPHA_MAX)
    if alpha < ALPHA_MIN:
        return 0.0, gauss, dx, dy
    return alpha, gauss, dx, dy


@njit(cache=True, inline="always")
def tile_pixel_bounds(t, tiles_x, width, height):
    """``(px0, py0, px1, py1)``: the inclusive pixel range of tile ``t`` (row-major tiles,
    ``tiles_x`` per row), cut at the image edge."""
    px0 = (t % tiles_x) * TILE_SIZE
    py0 = (t // tiles_x) * TILE_SIZE
    px1 = min(px0 + TILE_SIZE, width) - 1
    py1 = min(py0 + TILE_SIZE, height) - 1
    return px0, py0, px1, py1


# --------------------------------------------------------------------------------------------
# Stage 3: projection
# --------------------------------------------------------------------------------------------


class Projection(NamedTuple):
    """Every Gaussian projected into one view (rows in input order)."""

    valid: np.ndarray  # [N] bool: drawn (in front of the near plane, box inside the image, visible)
    depth: np.ndarray  # [N] float64 camera z (0 where not valid)
    feat: np.ndarray  # [N, N_FEAT] float32 (u, v, conic a, b, c, opacity, r, g, b, z)
    box: np.ndarray  # [N, 4] int32 inclusive pixel range (x0, x1, y0, y1)
    # [N, N_AUX] float64 projection intermediates (AUX_* columns; rows of drawn Gaussians), kept for a
    # backward pass so it need not project the view again; [0, N_AUX] when not asked for
    aux: np.ndarray


@njit(cache=True, parallel=True)
def _project_kernel(pos, scl, quat, col, opa, Rcw, tcw, fx, fy, cx, cy, width, height, near, aux):
    """``Projection`` fields of ``pos``, ``scl`` ``[N, 3]``, ``quat`` ``[N, 4]``, ``col`` ``[N, 3]``,
    ``opa`` ``[N]`` (float32 or float64), ``Rcw`` ``[3, 3]``, ``tcw`` ``[3]``; the ``AUX_*``
    intermediates of each drawn Gaussian into ``aux`` ``[N, N_AUX]`` float64 when it has N rows
    (``[0, N_AUX]``: not kept).

    The box is the ``SIGMA_EXTENT``-sigma square cut to the bounding box of the ellipse
    ``d^T conic d <= 2 ln(opacity / ALPHA_MIN)``, outside of which ``alpha < ALPHA_MIN`` anyway, so
    the cut saves tiles without changing the image.
    """
    n = pos.shape[0]
    valid = np.zeros(n, dtype=np.bool_)
    depth = np.zeros(n, dtype=np.float64)
    feat = np.zeros((n, N_FEAT), dtype=np.float32)
    box = np.zeros((n, 4), dtype=np.int32)
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = jacobian_clamp_limits(fx, fy, cx, cy, width, height)
    # |J|_F^2 z^2 with x / z, y / z at their clamps: bounds a Gaussian's pixel footprint from its
    # largest scale alone (below), before its rotation and covariance are computed
    lim_x = max(lim_x_pos, lim_x_neg)
    lim_y = max(lim_y_pos, lim_y_neg)
    jac_f2 = fx * fx * (1.0 + lim_x * lim_x) + fy * fy * (1.0 + lim_y * lim_y)
    keep_aux = aux.shape[0] == n
    for i in prange(n):
        o = np.float64(opa[i])
        if o * COLOR_LEVELS < 1.0:  # can never reach alpha >= ALPHA_MIN
            continue
        x, y, z = world_to_camera(pos, i, Rcw, tcw)  # p_cam = R_cw (p_world - c)
        if not (z >= near):
            continue
        u = fx * x / z + cx
        v = fy * y / z + cy
        # Off the image: lambda_max(cov2d) <= |J|^2 s_max^2 + LOW_PASS_PX2 (|P| = |J|, W a
        # rotation; |M| = s_max), so the box below lies within reach_px of (u, v) and is empty
        # when (u, v) is farther than that outside the image. Most Gaussians in front of the
        # camera are outside its field of view; this skips their covariance, never a drawn pixel.
        sx = np.float64(scl[i, 0])
        sy = np.float64(scl[i, 1])
        sz = np.float64(scl[i, 2])
        s_max = max(sx, max(sy, sz))
        reach_px = SIGMA_EXTENT * math.sqrt(jac_f2 * s_max * s_max / (z * z) + LOW_PASS_PX2) + CULL_SLACK_PX
        if u + reach_px < 0.0 or u - reach_px > width - 1.0 or v + reach_px < 0.0 or v - reach_px > height - 1.0:
            continue
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotmat_from_quat(quat, i)
        # cov2d = P Sigma P^T = (P M)(P M)^T with M = R S, P = J W
        p00, p01, p02, p10, p11, p12, txz, tyz = projection_rows(
            Rcw, fx, fy, x, y, z, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg)
        a0, a1, a2, b0, b1, b2, cxx, cxy, cyy = pixel_covariance(
            p00, p01, p02, p10, p11, p12,
            r00 * sx, r01 * sy, r02 * sz, r10 * sx, r11 * sy, r12 * sz, r20 * sx, r21 * sy, r22 * sz)
        det = cxx * cyy - cxy * cxy
        if not (det > 0.0):
            continue
        mid = 0.5 * (cxx + cyy)
        lam = mid + math.sqrt(max(0.0, mid * mid - det))
        radius = math.ceil(SIGMA_EXTENT * math.sqrt(lam))
        thr = 2.0 * math.log(COLOR_LEVELS * o)  # d^T conic d beyond which alpha < ALPHA_MIN
        ex = min(radius, math.sqrt(thr * cxx) + BOX_SLACK_PX)
        ey = min(radius, math.sqrt(thr * cyy) + BOX_SLACK_PX)
        x0 = max(0.0, math.ceil(u - ex))
        x1 = min(width - 1.0, math.floor(u + ex))
        y0 = max(0.0, math.ceil(v - ey))
        y1 = min(height - 1.0, math.floor(v + ey))
        if x0 > x1 or y0 > y1:
            continue
        valid[i] = True
        depth[i] = z
        feat[i, FEAT_U] = u
        feat[i, FEAT_V] = v
        feat[i, FEAT_CONIC_A] = cyy / det
        feat[i, FEAT_CONIC_B] = -cxy / det
        feat[i, FEAT_CONIC_C] = cxx / det
        feat[i, FEAT_OPACITY] = opa[i]
        feat[i, FEAT_RED] = col[i, 0]
        feat[i, FEAT_GREEN] = col[i, 1]
        feat[i, FEAT_BLUE] = col[i, 2]
        feat[i, FEAT_Z] = z
        box[i, 0] = np.int32(x0)
        box[i, 1] = np.int32(x1)
        box[i, 2] = np.int32(y0)
        box[i, 3] = np.int32(y1)
        if keep_aux:
            aux[i, AUX_X] = x
            aux[i, AUX_Y] = y
            aux[i, AUX_Z] = z
            aux[i, AUX_P + 0] = p00
            aux[i, AUX_P + 1] = p01
            aux[i, AUX_P + 2] = p02
            aux[i, AUX_P + 3] = p10
            aux[i, AUX_P + 4] = p11
            aux[i, AUX_P + 5] = p12
            aux[i, AUX_A + 0] = a0
            aux[i, AUX_A + 1] = a1
            aux[i, AUX_A + 2] = a2
            aux[i, AUX_B + 0] = b0
            aux[i, AUX_B + 1] = b1
            aux[i, AUX_B + 2] = b2
            aux[i, AUX_CXX] = cxx
            aux[i, AUX_CXY] = cxy
            aux[i, AUX_CYY] = cyy
            aux[i, AUX_TXZ] = txz
            aux[i, AUX_TYZ] = tyz
            aux[i, AUX_SLOPE_U], aux[i, AUX_SLOPE_V] = plane_depth_slopes(
                r00, r01, r02, r10, r11, r12, r20, r21, r22, sx, sy, sz, Rcw, x, y, z, fx, fy)
    return valid, depth, feat, box, aux


def project_gaussians(
    positions: np.ndarray,  # [N, 3] world (metres)
    scales: np.ndarray,  # [N, 3] standard deviations (metres)
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3] any range (copied to the feature rows)
    opacities: np.ndarray,  # [N] in [0, 1]
    view: PinholeView,
    near_m: float = NEAR_M,
    keep_aux: bool = False,
) -> Projection:
    """Stage 3: project every Gaussian (compiled, threaded). Arrays all float32 or all float64.
    ``keep_aux``: also return each drawn Gaussian's ``AUX_*`` intermediates (for a backward pass)."""
    aux = np.empty((len(positions) if keep_aux else 0, N_AUX))
    return Projection(*_project_kernel(
        positions, scales, rotations_xyzw, colors, opacities, view.R_cam_world, view.centre_world,
        view.fx, view.fy, view.cx, view.cy, view.width, view.height, near_m, aux))


# --------------------------------------------------------------------------------------------
# Stage 4: depth sort
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def _radix_argsort_positive(keys):
    """Stable argsort ``[M]`` int32 of positive float64 ``keys`` ``[M]`` (LSD radix sort on the bits).

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


def sort_by_depth(
    valid: np.ndarray,  # [N] bool
    depth: np.ndarray,  # [N] float64, positive where valid
) -> np.ndarray:
    """Stage 4: ``[M]`` int64 rows of the valid Gaussians, front to back, ties in input order."""
    ids = np.flatnonzero(valid)
    return ids[_radix_argsort_positive(depth[ids])]


@njit(cache=True, parallel=True)
def _gather_rows(order, feat, box):
    """``feat[order]``, ``box[order]`` (``[M, N_FEAT]``, ``[M, 4]``), threaded."""
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


def gather_sorted(
    order: np.ndarray,  # [M] int64
    feat: np.ndarray,  # [N, N_FEAT] float32
    box: np.ndarray,  # [N, 4] int32
) -> tuple[np.ndarray, np.ndarray]:
    """``(feat[order], box[order])`` as contiguous copies: each tile then reads its Gaussians front to
    back in memory order."""
    return _gather_rows(order, feat, box)


# --------------------------------------------------------------------------------------------
# Stage 5: tile binning
# --------------------------------------------------------------------------------------------


class TileBins(NamedTuple):
    """Per-tile lists of sorted Gaussians: tile ``t`` holds rows ``tile_ids[tile_start[t]:tile_start[t + 1]]``."""

    tile_start: np.ndarray  # [n_tiles + 1] int64
    tile_ids: np.ndarray  # [P] int32 rows of the sorted Gaussians, front to back within a tile
    tiles_x: int  # tiles per row
    n_tiles: int


@njit(cache=True)
def _bin_tiles_kernel(box, tiles_x, n_tiles):
    """``(tile_start, tile_ids)`` of ``box`` ``[M, 4]`` (counting sort, which is stable)."""
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


def bin_tiles(
    box: np.ndarray,  # [M, 4] int32 boxes of the sorted Gaussians
    width: int,
    height: int,
) -> TileBins:
    """Stage 5: per ``TILE_SIZE`` tile (row major), the rows of ``box`` that touch it, in row order."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    n_tiles = tiles_x * ((height + TILE_SIZE - 1) // TILE_SIZE)
    tile_start, tile_ids = _bin_tiles_kernel(box, tiles_x, n_tiles)
    return TileBins(tile_start, tile_ids, tiles_x, n_tiles)


@njit(cache=True)
def _pair_slots_kernel(box, tile_start, tiles_x):
    m = box.shape[0]
    n_tiles = tile_start.shape[0] - 1
    gauss_start = np.empty(m + 1, dtype=np.int64)
    tile_slot = np.empty(tile_start[n_tiles], dtype=np.int32)
    fill = tile_start[:-1].copy()
    s = 0
    for k in range(m):  # the order _bin_tiles_kernel fills the tiles in
        gauss_start[k] = s
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE
        for ty in range(box[k, 2] // TILE_SIZE, box[k, 3] // TILE_SIZE + 1):
            for tx in range(tx0, tx1 + 1):
                t = ty * tiles_x + tx
                tile_slot[fill[t]] = s
                fill[t] += 1
                s += 1
    gauss_start[m] = s
    return tile_slot, gauss_start


def pair_slots(
    box: np.ndarray,  # [M, 4] int32 boxes of the sorted Gaussians (as given to bin_tiles)
    tile_start: np.ndarray,  # [n_tiles + 1] int64, from bin_tiles
    tiles_x: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 5b, for backward passes: ``(tile_slot [P] int32, gauss_start [M + 1] int64)``.

    Every (tile, Gaussian) pair ``tile_ids[k]`` (``bin_tiles``) gets a slot ``tile_slot[k]``; the slots of
    sorted Gaussian ``g`` are ``gauss_start[g] .. gauss_start[g + 1] - 1``, its tiles in row-major
    order. A tile loop writes a per-pair result into its slot (no two tiles share one: no atomics,
    no locks), and a per-Gaussian loop sums its slots in a fixed order (the same bits whatever the
    number of threads).
    """
    return _pair_slots_kernel(box, tile_start, tiles_x)


class SplatTiles(NamedTuple):
    """What every tile loop reads: the drawn Gaussians sorted front to back, binned into tiles."""

    order: np.ndarray  # [M] int64 input rows, front to back
    feat: np.ndarray  # [M, N_FEAT] float32 feature rows in that order
    box: np.ndarray  # [M, 4] int32 pixel boxes in that order
    tile_start: np.ndarray  # [n_tiles + 1] int64
    tile_ids: np.ndarray  # [P] int32 rows of feat / box
    tiles_x: int
    n_tiles: int
    width: int
    height: int
    aux: np.ndarray  # [N, N_AUX] float64 projection intermediates, input rows ([0, N_AUX]: not kept)


def prepare_splats(
    positions: np.ndarray,  # [N, 3]
    scales: np.ndarray,  # [N, 3]
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3]
    opacities: np.ndarray,  # [N]
    view: PinholeView,
    near_m: float = NEAR_M,
    keep_aux: bool = False,
) -> SplatTiles | None:
    """Stages 3-5: project, sort and bin; None when the view draws no Gaussian. ``keep_aux``: the
    projection intermediates ride along (``SplatTiles.aux``, input row order)."""
    proj = project_gaussians(positions, scales, rotations_xyzw, colors, opacities, view, near_m, keep_aux)
    order = sort_by_depth(proj.valid, proj.depth)
    if order.size == 0:
        return None
    feat, box = gather_sorted(order, proj.feat, proj.box)
    bins = bin_tiles(box, view.width, view.height)
    return SplatTiles(order, feat, box, bins.tile_start, bins.tile_ids, bins.tiles_x, bins.n_tiles,
                      view.width, view.height, proj.aux)


# --------------------------------------------------------------------------------------------
# Bounded memory: stages 3-5 without per-input-Gaussian buffers or a whole-view pair list
# --------------------------------------------------------------------------------------------


class VisibleSplats(NamedTuple):
    """The drawn Gaussians of one view, compacted (``project_visible``; ``sort_visible`` puts them
    front to back in place)."""

    feat: np.ndarray  # [M, N_FEAT] float32 feature rows
    box: np.ndarray  # [M, 4] int32 inclusive pixel boxes (x0, x1, y0, y1)
    depth: np.ndarray  # [M] float64 camera z


@njit(cache=True)
def _compact_rows(valid, depth, feat, box, depth_out, feat_out, box_out, m):
    """Append the rows of ``feat`` ``[C, N_FEAT]`` / ``box`` ``[C, 4]`` / ``depth`` ``[C]`` where
    ``valid`` ``[C]`` to the outputs at row ``m``, in order; returns the new row count."""
    for i in range(valid.shape[0]):
        if valid[i]:
            depth_out[m] = depth[i]
            for j in range(feat.shape[1]):
                feat_out[m, j] = feat[i, j]
            for j in range(4):
                box_out[m, j] = box[i, j]
            m += 1
    return m


def _shrink_rows(a: np.ndarray, m: int) -> np.ndarray:
    """``a[:m]`` without a copy: the buffer is reallocated to ``m`` rows (``ndarray.resize``; a large
    buffer gives back its tail pages), so a capacity of N rows of which M were written costs M."""
    a.resize((m,) + a.shape[1:], refcheck=False)
    return a


def project_visible(
    positions: np.ndarray,  # [N, 3]
    scales: np.ndarray,  # [N, 3]
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3] (float32, or uint8: converted per row)
    opacities: np.ndarray,  # [N]
    view: PinholeView,
    near_m: float = NEAR_M,
    chunk: int = PROJECT_CHUNK,
) -> VisibleSplats:
    """Stage 3 in bounded memory: ``project_gaussians`` on ``chunk`` Gaussians at a time, keeping the
    drawn rows only (input order). The rows equal ``project_gaussians``'s valid rows bit for bit.

    Memory: the outputs are allocated for N rows but only the M drawn ones are written and kept
    (64 bytes per drawn Gaussian: ``N_FEAT`` float32, 4 int32, a float64 depth), plus the per-chunk
    buffers (65 bytes per chunk row).
    """
    n = positions.shape[0]
    feat = np.empty((n, N_FEAT), np.float32)
    box = np.empty((n, 4), np.int32)
    depth = np.empty(n, np.float64)
    no_aux = np.empty((0, N_AUX))
    m = 0
    for i in range(0, n, max(1, int(chunk))):
        c = slice(i, i + chunk)
        valid, d, f, b, _ = _project_kernel(
            positions[c], scales[c], rotations_xyzw[c], colors[c], opacities[c], view.R_cam_world,
            view.centre_world, view.fx, view.fy, view.cx, view.cy, view.width, view.height, near_m, no_aux)
        m = _compact_rows(valid, d, f, b, depth, feat, box, m)
    return VisibleSplats(_shrink_rows(feat, m), _shrink_rows(box, m), _shrink_rows(depth, m))


@njit(cache=True)
def _permute_rows_inplace(order, feat, box, depth):
    """``feat[:] = feat[order]``, ``box[:] = box[order]``, ``depth[:] = depth[order]`` in place,
    cycle by cycle (``order`` ``[M]`` int32, a permutation, is used as the visited mark and
    restored)."""
    m = order.shape[0]
    nf = feat.shape[1]
    ftmp = np.empty(nf, feat.dtype)
    btmp = np.empty(4, box.dtype)
    for start in range(m):
        if order[start] < 0 or order[start] == start:
            continue
        for j in range(nf):
            ftmp[j] = feat[start, j]
        for j in range(4):
            btmp[j] = box[start, j]
        dtmp = depth[start]
        k = start
        while True:
            src = order[k]
            order[k] = -1 - src  # visited
            if src == start:
                for j in range(nf):
                    feat[k, j] = ftmp[j]
                for j in range(4):
                    box[k, j] = btmp[j]
                depth[k] = dtmp
                break
            for j in range(nf):
                feat[k, j] = feat[src, j]
            for j in range(4):
                box[k, j] = box[src, j]
            depth[k] = depth[src]
            k = src
    for k in range(m):
        if order[k] < 0:
            order[k] = -1 - order[k]


def sort_visible(vis: VisibleSplats) -> np.ndarray:
    """Stage 4 in place: rows of ``vis`` front to back, ties in input order (the order of
    ``sort_by_depth``); returns that order ``[M]`` int32 (rows of the unsorted ``vis``). No sorted
    copy: 8 bytes per drawn Gaussian for the radix sort."""
    if len(vis.depth) == 0:
        return np.zeros(0, np.int32)
    order = _radix_argsort_positive(vis.depth)
    _permute_rows_inplace(order, vis.feat, vis.box, vis.depth)
    return order


@njit(cache=True)
def _tile_pair_counts_kernel(box, tiles_x, tiles_y):
    """Pairs per tile ``[tiles_y, tiles_x]`` int64 of ``box`` ``[M, 4]`` (2D difference array: O(M)
    work whatever the footprints)."""
    diff = np.zeros((tiles_y + 1, tiles_x + 1), dtype=np.int64)
    for k in range(box.shape[0]):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE + 1
        ty0 = box[k, 2] // TILE_SIZE
        ty1 = box[k, 3] // TILE_SIZE + 1
        diff[ty0, tx0] += 1
        diff[ty0, tx1] -= 1
        diff[ty1, tx0] -= 1
        diff[ty1, tx1] += 1
    for ty in range(tiles_y + 1):
        for tx in range(1, tiles_x + 1):
            diff[ty, tx] += diff[ty, tx - 1]
    for ty in range(1, tiles_y + 1):
        for tx in range(tiles_x + 1):
            diff[ty, tx] += diff[ty - 1, tx]
    return diff[:tiles_y, :tiles_x].copy()


def tile_pair_counts(
    box: np.ndarray,  # [M, 4] int32 boxes (x0, x1, y0, y1)
    width: int,
    height: int,
) -> np.ndarray:
    """Stage 5a: ``[n_tiles]`` int64 number of boxes touching each tile (row major), the lengths of
    ``bin_tiles``'s lists, without listing them."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    return _tile_pair_counts_kernel(box, tiles_x, tiles_y).reshape(-1)


def tile_batches(
    counts: np.ndarray,  # [n_tiles] pairs per tile
    max_tile_pairs: int | None = MAX_TILE_PAIRS,
) -> list[tuple[int, int]]:
    """Stage 5b: runs ``[(t0, t1)]`` of consecutive tiles (row major) covering every tile, each with at
    most ``max_tile_pairs`` pairs (a run of one tile may hold more: a tile is never split). None:
    one run."""
    n_tiles = len(counts)
    if max_tile_pairs is None or n_tiles == 0:
        return [(0, n_tiles)]
    cum = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])  # [n_tiles + 1]
    out = []
    t0 = 0
    while t0 < n_tiles:
        # the last tile whose run from t0 stays within the budget; at least one tile
        t1 = int(np.searchsorted(cum, cum[t0] + int(max_tile_pairs), side="right")) - 1
        t1 = min(n_tiles, max(t1, t0 + 1))
        out.append((t0, t1))
        t0 = t1
    return out


@njit(cache=True)
def _bin_tile_batch_kernel(box, tiles_x, t0, t1, tile_start, tile_ids):
    """Fill ``tile_ids`` with the rows of ``box`` ``[M, 4]`` touching tiles ``t0 .. t1 - 1``, per tile
    in row order (``tile_start`` ``[t1 - t0 + 1]``: the run's offsets)."""
    fill = tile_start[:-1].copy()
    ty_a = t0 // tiles_x
    ty_b = (t1 - 1) // tiles_x
    for k in range(box.shape[0]):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE
        for ty in range(max(box[k, 2] // TILE_SIZE, ty_a), min(box[k, 3] // TILE_SIZE, ty_b) + 1):
            row = ty * tiles_x
            for tx in range(max(tx0, t0 - row), min(tx1, t1 - 1 - row) + 1):
                t = row + tx - t0
                tile_ids[fill[t]] = k
                fill[t] += 1


def bin_tile_batch(
    box: np.ndarray,  # [M, 4] int32 boxes of the sorted Gaussians
    counts: np.ndarray,  # [n_tiles] from tile_pair_counts
    width: int,
    t0: int,
    t1: int,
    out: np.ndarray | None = None,  # [>= P] int32 buffer to fill (reused across runs)
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 5c: ``(tile_start [t1 - t0 + 1] int64, tile_ids [P] int32)`` of tiles ``t0 .. t1 - 1``:
    the slice of ``bin_tiles``'s lists for those tiles (same rows, same order)."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tile_start = np.zeros(t1 - t0 + 1, np.int64)
    np.cumsum(counts[t0:t1], out=tile_start[1:])
    p = int(tile_start[-1])
    tile_ids = np.empty(p, np.int32) if out is None else out[:p]
    _bin_tile_batch_kernel(box, tiles_x, t0, t1, tile_start, tile_ids)
    return tile_start, tile_ids


# --------------------------------------------------------------------------------------------
# Stage 6: compositing
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def exp_neg_fast(x):
    """``exp(x)`` for float32 ``x`` in ``[POWER_MIN, 0]`` to ~2e-6 relative error, plain arithmetic.

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
def _composite_worker(
    worker, n_workers, tile_start, tile_ids, feat, box, width, height, tiles_x, t0, n_tiles, bg,
    rgb, depth_out, alpha_out, median_out,
):
    """Composite tiles ``t0 + worker, t0 + worker + n_workers, ...`` (of ``t0 .. t0 + n_tiles - 1``)
    front to back into the output images.

    ``feat`` ``[M, N_FEAT]`` / ``box`` ``[M, 4]`` are the sorted Gaussians, ``tile_start`` /
    ``tile_ids`` from ``bin_tiles`` (``t0 = 0``) or ``bin_tile_batch`` (indexed from ``t0``); writes
    rgb ``[H, W, 3]`` uint8, depth, alpha and median depth ``[H, W]`` float32 in place.

    For each (tile, Gaussian) pair every touched tile row is processed as one 16-wide branch-free
    vector (lanes outside the Gaussian's box, below ``ALPHA_MIN`` or already terminated get alpha
    0): several times faster than a scalar loop over the box. Kept out of the ``prange`` body so the
    parallel transform cannot get in the way of that vectorisation.
    """
    t_min = np.float32(T_MIN)
    a_min = np.float32(ALPHA_MIN)
    a_max = np.float32(ALPHA_MAX)
    p_min = np.float32(POWER_MIN)  # lanes clamped here are rejected by the alpha test
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
    t_median = np.float32(MEDIAN_DEPTH_T)
    for t in range(worker, n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t0 + t, tiles_x, width, height)
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
            ux = feat[g, FEAT_U] - np.float32(px0)  # mean relative to the tile's left column
            v = feat[g, FEAT_V]
            nha = np.float32(-0.5) * feat[g, FEAT_CONIC_A]
            cb = feat[g, FEAT_CONIC_B]
            nhc = np.float32(-0.5) * feat[g, FEAT_CONIC_C]
            op = feat[g, FEAT_OPACITY]
            cr = feat[g, FEAT_RED]
            cgr = feat[g, FEAT_GREEN]
            cbl = feat[g, FEAT_BLUE]
            z = feat[g, FEAT_Z]
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
                    e = op * exp_neg_fast(power)
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
                    Dmv[j] = z if (Tl > t_median) & (Tn <= t_median) else Dmv[j]
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
def _composite_kernel(tile_start, tile_ids, feat, box, width, height, tiles_x, n_tiles, bg, n_workers):
    """All tiles, ``n_workers`` threads. Returns rgb ``[H, W, 3]`` uint8, depth, alpha and median
    depth ``[H, W]`` float32."""
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    depth_out = np.empty((height, width), dtype=np.float32)
    alpha_out = np.empty((height, width), dtype=np.float32)
    median_out = np.empty((height, width), dtype=np.float32)
    # Worker w takes tiles w, w + n_workers, ...: interleaving balances busy and empty regions.
    for w in prange(n_workers):
        _composite_worker(
            w, n_workers, tile_start, tile_ids, feat, box, width, height, tiles_x, 0, n_tiles, bg,
            rgb, depth_out, alpha_out, median_out,
        )
    return rgb, depth_out, alpha_out, median_out


@njit(cache=True, parallel=True)
def _composite_batch_kernel(tile_start, tile_ids, feat, box, width, height, tiles_x, t0, n_tiles, bg, n_workers,
                            rgb, depth_out, alpha_out, median_out):
    """Tiles ``t0 .. t0 + n_tiles - 1`` into the given output images, ``n_workers`` threads."""
    for w in prange(n_workers):
        _composite_worker(
            w, n_workers, tile_start, tile_ids, feat, box, width, height, tiles_x, t0, n_tiles, bg,
            rgb, depth_out, alpha_out, median_out,
        )


def composite_tiles(
    splats: SplatTiles,
    background: np.ndarray,  # [3] in [0, 255]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stage 6: ``(rgb [H, W, 3] uint8, depth_m, alpha, depth_median_m [H, W] float32)``, threaded
    over tiles (compiled)."""
    n_workers = min(splats.n_tiles, kernel_threads())
    return _composite_kernel(
        splats.tile_start, splats.tile_ids, splats.feat, splats.box, splats.width, splats.height,
        splats.tiles_x, splats.n_tiles, np.asarray(background, np.float32), n_workers,
    )


def composite_tile_batch(
    feat: np.ndarray,  # [M, N_FEAT] float32 sorted front to back
    box: np.ndarray,  # [M, 4] int32 in that order
    tile_start: np.ndarray,  # [t1 - t0 + 1] int64 from bin_tile_batch
    tile_ids: np.ndarray,  # [P] int32 from bin_tile_batch
    t0: int,
    background: np.ndarray,  # [3] in [0, 255]
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],  # rgb [H, W, 3] uint8, depth, alpha, median [H, W]
) -> None:
    """Stage 6 for one run of tiles (``bin_tile_batch``): writes those tiles' pixels of ``out``; every
    tile is drawn exactly as ``composite_tiles`` draws it."""
    rgb, depth_out, alpha_out, median_out = out
    height, width = rgb.shape[:2]
    n_tiles = len(tile_start) - 1
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    n_workers = max(1, min(n_tiles, kernel_threads()))
    _composite_batch_kernel(tile_start, tile_ids, feat, box, width, height, tiles_x, int(t0), n_tiles,
                            np.asarray(background, np.float32), n_workers, rgb, depth_out, alpha_out, median_out)

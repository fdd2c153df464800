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
6. compositing, in :mod:`atlas_pipeline.gaussian_world.composite`: the one tile-row kernel the
   renderer and the keyframe fit both run.

``prepare_splats`` runs stages 3-5 (what every caller needs before its own tile loop). The
renderer runs the same stages in bounded memory (:mod:`atlas_pipeline.gaussian_world.raster_bounded`;
same image bit for bit). Compiled kernels elsewhere (the fits' backward passes) build on the device
helpers ``world_to_camera``, ``rotmat_from_quat``, ``jacobian_clamp_limits``, ``projection_rows``,
``pixel_covariance``, ``pixel_alpha`` and ``tile_pixel_bounds``, so their forward model is this one
by construction.

Pixel centres are at integer pixel coordinates: a point at ``(u, v) = K p / z`` lands in the centre
of pixel ``(round(u), round(v))``, pixel ``i`` covers ``[i - 0.5, i + 0.5)``. ``scale_intrinsics`` /
``scale_camera`` (:mod:`atlas_pipeline.gaussian_world.intrinsics`, re-exported here) keep that
convention when an image is resampled. Skew in ``K`` is ignored.

Plain NumPy versions of every stage, used to check these, are in ``_raster_reference``.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.gaussian_world.intrinsics import scale_camera, scale_intrinsics, scaled_image_size

logger = logging.getLogger(__name__)

__all__ = [
    "TILE_SIZE", "ALPHA_MAX", "COLOR_LEVELS", "ALPHA_MIN", "T_MIN", "LOW_PASS_PX2", "FRUSTUM_MARGIN", "DEPTH_MIN_ALPHA",
    "SIGMA_EXTENT", "POWER_MIN", "BOX_SLACK_PX", "MEDIAN_DEPTH_T", "NEAR_M",
    "FEAT_U", "FEAT_V", "FEAT_CONIC_A", "FEAT_CONIC_B", "FEAT_CONIC_C", "FEAT_OPACITY", "FEAT_RED",
    "FEAT_GREEN", "FEAT_BLUE", "FEAT_Z", "N_FEAT", "AUX_X", "AUX_Y", "AUX_Z", "AUX_P", "AUX_A", "AUX_B",
    "AUX_CXX", "AUX_CXY", "AUX_CYY", "AUX_TXZ", "AUX_TYZ", "AUX_SLOPE_U", "AUX_SLOPE_V", "N_AUX",
    "PLANE_FLATNESS", "PLANE_MAX_SLOPE",
    "RasterInputs", "RasterView", "GaussianArrays", "Projection", "TileBins", "SplatTiles",
    "validate_inputs", "view_from_pose", "project_kernel", "project_gaussians", "radix_argsort_positive",
    "sort_by_depth", "gather_sorted", "bin_tiles",
    "pair_slots", "prepare_splats", "scale_intrinsics", "scaled_image_size", "scale_camera",
    "PROJECT_CHUNK", "MAX_TILE_PAIRS",
    "world_to_camera", "rotmat_from_quat", "jacobian_clamp_limits", "projection_rows", "pixel_covariance",
    "plane_depth_slopes", "pixel_alpha", "tile_pixel_bounds",
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
# Bounded-memory rendering (``raster_bounded``):
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


class RasterView(NamedTuple):
    """The camera as the compiled stages read it."""

    R_cam_world: np.ndarray  # [3, 3] float64, world -> camera rotation
    centre_world: np.ndarray  # [3] float64, camera centre (metres)
    fx: float
    fy: float
    cx: float
    cy: float
    width: int  # px
    height: int  # px


class GaussianArrays(NamedTuple):
    """The Gaussians as the compiled stages read them (all float32 or all float64; colours may be
    uint8)."""

    positions: np.ndarray  # [N, 3] world frame (metres)
    scales: np.ndarray  # [N, 3] standard deviations (metres)
    rotations_xyzw: np.ndarray  # [N, 4]
    colors: np.ndarray  # [N, 3]
    opacities: np.ndarray  # [N] in [0, 1]


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
) -> RasterView:
    """The camera of one raster pass (no checks: see ``validate_inputs``)."""
    T = np.asarray(T_world_cam, np.float64)
    Km = np.asarray(K, np.float64)
    return RasterView(
        np.ascontiguousarray(T[:3, :3].T), np.ascontiguousarray(T[:3, 3]),
        float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2]), int(width), int(height),
    )


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
def rows_times(P, M):
    """``(a0, a1, a2, b0, b1, b2)``: the two rows ``(p00, p01, p02, p10, p11, p12)`` of ``P`` times
    the 3 x 3 ``M`` ``(m00 .. m22)``, row major (each entry summed over k = 0, 1, 2 in order)."""
    p00, p01, p02, p10, p11, p12 = P
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = M
    return (p00 * m00 + p01 * m10 + p02 * m20, p00 * m01 + p01 * m11 + p02 * m21, p00 * m02 + p01 * m12 + p02 * m22,
            p10 * m00 + p11 * m10 + p12 * m20, p10 * m01 + p11 * m11 + p12 * m21, p10 * m02 + p11 * m12 + p12 * m22)


@njit(cache=True, inline="always")
def pixel_covariance(P, M):
    """``(a0, a1, a2, b0, b1, b2, cxx, cxy, cyy)``: rows ``a``, ``b`` of ``P M`` and the pixel
    covariance ``cov2d = (P M)(P M)^T + LOW_PASS_PX2 I`` (``[[cxx, cxy], [cxy, cyy]]``), with ``P``
    ``(p00, p01, p02, p10, p11, p12)`` from ``projection_rows`` and ``M`` ``(m00 .. m22)`` row major,
    the Gaussian's rotation times its scales ``R S``."""
    a0, a1, a2, b0, b1, b2 = rows_times(P, M)
    cxx = a0 * a0 + a1 * a1 + a2 * a2 + LOW_PASS_PX2
    cxy = a0 * b0 + a1 * b1 + a2 * b2
    cyy = b0 * b0 + b1 * b1 + b2 * b2 + LOW_PASS_PX2
    return a0, a1, a2, b0, b1, b2, cxx, cxy, cyy


@njit(cache=True, inline="always")
def plane_depth_slopes(R, sx, sy, sz, Rcw, x, y, z, fx, fy):
    """``(dz/du, dz/dv)``: how the depth of the plane through the camera-frame mean ``(x, y, z)``,
    normal to the Gaussian's shortest axis (rotation ``R`` ``(r00 .. r22)`` row major, scales ``s``,
    world -> camera ``Rcw`` ``[3, 3]``), changes along the pixel
    rays: ``z(u, v) ~ z + dz/du (u - u0) + dz/dv (v - v0)``. A Gaussian then reports the depth of its
    surface at a pixel, not of its centre (which on a slanted surface reads nearer for the front-most
    Gaussians). ``(0, 0)`` for Gaussians that are not flat (``PLANE_FLATNESS``) or seen edge-on;
    clamped at ``PLANE_MAX_SLOPE``."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
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
def project_kernel(gaussians, view, near, aux):
    """``Projection`` fields of ``gaussians`` (:class:`GaussianArrays`, float32 or float64) seen by
    ``view`` (:class:`RasterView`); the ``AUX_*`` intermediates of each drawn Gaussian into ``aux``
    ``[N, N_AUX]`` float64 when it has N rows (``[0, N_AUX]``: not kept).

    The box is the ``SIGMA_EXTENT``-sigma square cut to the bounding box of the ellipse
    ``d^T conic d <= 2 ln(opacity / ALPHA_MIN)``, outside of which ``alpha < ALPHA_MIN`` anyway, so
    the cut saves tiles without changing the image.
    """
    pos, scl, quat, col, opa = gaussians
    Rcw, tcw, fx, fy, cx, cy, width, height = view
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
            (p00, p01, p02, p10, p11, p12),
            (r00 * sx, r01 * sy, r02 * sz, r10 * sx, r11 * sy, r12 * sz, r20 * sx, r21 * sy, r22 * sz))
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
                (r00, r01, r02, r10, r11, r12, r20, r21, r22), sx, sy, sz, Rcw, x, y, z, fx, fy)
    return valid, depth, feat, box, aux


def project_gaussians(
    positions: np.ndarray,  # [N, 3] world (metres)
    scales: np.ndarray,  # [N, 3] standard deviations (metres)
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3] any range (copied to the feature rows)
    opacities: np.ndarray,  # [N] in [0, 1]
    view: RasterView,
    near_m: float = NEAR_M,
    keep_aux: bool = False,
) -> Projection:
    """Stage 3: project every Gaussian (compiled, threaded). Arrays all float32 or all float64.
    ``keep_aux``: also return each drawn Gaussian's ``AUX_*`` intermediates (for a backward pass)."""
    aux = np.empty((len(positions) if keep_aux else 0, N_AUX))
    gaussians = GaussianArrays(positions, scales, rotations_xyzw, colors, opacities)
    return Projection(*project_kernel(gaussians, view, near_m, aux))


# --------------------------------------------------------------------------------------------
# Stage 4: depth sort
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def radix_argsort_positive(keys):
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
    return ids[radix_argsort_positive(depth[ids])]


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
    view: RasterView,
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


"""View-dependent colour: real spherical harmonics up to degree 3, as 3D Gaussian Splatting has them.

A Gaussian seen along the unit direction ``d`` (world frame, from the camera centre to the
Gaussian's mean) has, per channel, the colour in [0, 1]::

    c(d) = max(0, 0.5 + C0 f_dc + sum_{k=1}^{K} Y_k(d) f_k)

with the basis ``Y_k`` and constants of the reference implementation (``utils/sh_utils.py``
``eval_sh``; gsplat's ``spherical_harmonics`` is the same): ``K = (degree + 1)^2 - 1``. No upper
clamp per Gaussian (as 3DGS: only the composited image is clipped). A :class:`GaussianField`
stores ``0.5 + C0 f_dc`` as its uint8 colour and ``f_1 .. f_K`` as ``sh_rest`` ``[N, K, 3]``, so in
colour levels::

    colour(d) = max(0, colors + COLOR_LEVELS sum_k Y_k(d) sh_rest[:, k - 1])

which at ``sh_rest == 0`` is the uint8 colour exactly. In a 3DGS PLY ``f_rest_*`` are channel-major:
``f_rest_{c K + k - 1}`` is coefficient ``k`` of channel ``c`` (``sh_rest[:, k - 1, c]``), the
``features_rest.transpose(1, 2).flatten(1)`` of the reference's ``save_ply``.

``view_colors`` is the compiled stage the renderer runs per view (threaded, float64 inside,
float32 out); ``view_colors_reference`` its NumPy transcription, term by term in the same order
(so the two agree bit for bit), and ``sh_basis_reference`` the basis itself.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from atlas_pipeline.gaussian_world.field import SH_MAX_DEGREE, sh_degree_of_rest_count, sh_rest_count

__all__ = ["SH_C0", "SH_C1", "SH_C2", "SH_C3", "SH_MAX_DEGREE", "COLOR_LEVELS", "sh_rest_count",
           "sh_basis_reference", "sh_basis_into", "unit_directions", "view_colors_reference", "view_colors", "check_sh_rest",
           "rest_to_channel_major"]

COLOR_LEVELS = 255.0  # uint8 colour levels (raster.COLOR_LEVELS; not imported: raster imports are heavy)
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)
_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = SH_C2  # scalars: numba folds them into the kernel
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = SH_C3


_CHECK_ROWS = 1 << 16  # rows checked at a time: the isfinite mask stays under 3 MB at degree 3


def check_sh_rest(sh_rest, n: int) -> np.ndarray:
    """``sh_rest`` as contiguous float32 ``[n, K, 3]`` (K = 3, 8 or 15; no copy when it already is);
    ``ValueError`` naming it otherwise."""
    a = np.ascontiguousarray(sh_rest, dtype=np.float32)
    if a.ndim != 3 or a.shape[0] != n or a.shape[2] != 3 or not sh_degree_of_rest_count(a.shape[1]):
        raise ValueError(f"sh_rest: expected shape [{n}, K, 3] with K in 3, 8, 15 (SH degree 1-{SH_MAX_DEGREE}), "
                         f"got {list(a.shape)}")
    if not all(np.isfinite(a[i:i + _CHECK_ROWS]).all() for i in range(0, n, _CHECK_ROWS)):
        raise ValueError("sh_rest: contains NaN or infinite values")
    return a


def rest_to_channel_major(sh_rest: np.ndarray) -> np.ndarray:
    """``[N, 3 K]`` columns ``f_rest_0 .. f_rest_{3K-1}`` of ``sh_rest`` ``[N, K, 3]`` (all R, then G, then B)."""
    return sh_rest.transpose(0, 2, 1).reshape(len(sh_rest), -1)


def unit_directions(positions: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``[N, 3]`` float64 unit vectors from ``centre`` ``[3]`` to ``positions`` ``[N, 3]`` (zero
    where they coincide: only the degree-0 colour is left)."""
    d = positions.astype(np.float64) - np.asarray(centre, np.float64)
    norm = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    safe = np.where(norm > 0.0, norm, 1.0)
    return np.where((norm > 0.0)[:, None], d / safe[:, None], 0.0)


def sh_basis_reference(dirs: np.ndarray, degree: int) -> np.ndarray:
    """``[N, (degree + 1)^2]`` float64: the 3DGS basis ``Y_0 .. Y_K`` at unit directions ``dirs`` ``[N, 3]``."""
    sh_rest_count(degree)  # checks the degree
    x, y, z = (np.asarray(dirs, np.float64)[:, i] for i in range(3))
    out = [np.full(len(x), SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2_0 * xy, _C2_1 * yz, _C2_2 * (2.0 * zz - xx - yy), _C2_3 * xz, _C2_4 * (xx - yy)]
    if degree >= 3:
        out += [_C3_0 * y * (3.0 * xx - yy), _C3_1 * xy * z, _C3_2 * y * (4.0 * zz - xx - yy),
                _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), _C3_4 * x * (4.0 * zz - xx - yy),
                _C3_5 * z * (xx - yy), _C3_6 * x * (xx - 3.0 * yy)]
    return np.stack(out, axis=1)


def view_colors_reference(
    positions: np.ndarray,  # [N, 3] world (metres)
    colors: np.ndarray,  # [N, 3] degree-0 colour in [0, 255]
    sh_rest: np.ndarray,  # [N, K, 3]
    centre: np.ndarray,  # [3] camera centre, world (metres)
) -> np.ndarray:
    """``[N, 3]`` float64 colour levels seen from ``centre``: ``max(0, colors + 255 sum_k Y_k sh_rest[:, k - 1])``."""
    k_rest = sh_rest.shape[1]
    degree = sh_degree_of_rest_count(k_rest)
    basis = sh_basis_reference(unit_directions(positions, centre), degree)  # [N, K + 1]
    acc = np.zeros((len(positions), 3))
    for k in range(k_rest):  # one term at a time, in the kernel's order
        acc = acc + basis[:, k + 1, None] * sh_rest[:, k, :].astype(np.float64)
    return np.maximum(0.0, colors.astype(np.float64) + COLOR_LEVELS * acc)


@njit(cache=True, inline="always")
def sh_basis_into(x, y, z, k_rest, out):
    """Fill ``out[0 .. k_rest - 1]`` with ``Y_1 .. Y_K`` at the unit direction ``(x, y, z)``."""
    out[0] = -SH_C1 * y
    out[1] = SH_C1 * z
    out[2] = -SH_C1 * x
    if k_rest > 3:
        xx = x * x
        yy = y * y
        zz = z * z
        xy = x * y
        yz = y * z
        xz = x * z
        out[3] = _C2_0 * xy
        out[4] = _C2_1 * yz
        out[5] = _C2_2 * (2.0 * zz - xx - yy)
        out[6] = _C2_3 * xz
        out[7] = _C2_4 * (xx - yy)
        if k_rest > 8:
            out[8] = _C3_0 * y * (3.0 * xx - yy)
            out[9] = _C3_1 * xy * z
            out[10] = _C3_2 * y * (4.0 * zz - xx - yy)
            out[11] = _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[12] = _C3_4 * x * (4.0 * zz - xx - yy)
            out[13] = _C3_5 * z * (xx - yy)
            out[14] = _C3_6 * x * (xx - 3.0 * yy)


@njit(cache=True, parallel=True)
def _view_colors_kernel(positions, colors, sh_rest, centre, out):
    n = positions.shape[0]
    k_rest = sh_rest.shape[1]
    for i in prange(n):
        basis = np.empty(15)
        dx = np.float64(positions[i, 0]) - centre[0]
        dy = np.float64(positions[i, 1]) - centre[1]
        dz = np.float64(positions[i, 2]) - centre[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm > 0.0:
            dx /= norm
            dy /= norm
            dz /= norm
        else:
            dx = dy = dz = 0.0
        sh_basis_into(dx, dy, dz, k_rest, basis)
        for c in range(3):
            acc = 0.0
            for k in range(k_rest):
                acc = acc + basis[k] * np.float64(sh_rest[i, k, c])
            out[i, c] = max(0.0, np.float64(colors[i, c]) + COLOR_LEVELS * acc)


def view_colors(
    positions: np.ndarray,  # [N, 3] float32 world (metres)
    colors: np.ndarray,  # [N, 3] uint8 or float32 degree-0 colour in [0, 255]
    sh_rest: np.ndarray,  # [N, K, 3] float32, K in 3, 8, 15
    centre: np.ndarray,  # [3] camera centre, world (metres)
) -> np.ndarray:
    """``[N, 3]`` float32 colour levels of each Gaussian seen from ``centre`` (compiled, threaded):
    the SH stage of the renderer. Equals ``view_colors_reference`` cast to float32."""
    out = np.empty((len(positions), 3), np.float32)
    if len(positions):
        _view_colors_kernel(positions, colors, sh_rest, np.ascontiguousarray(centre, np.float64), out)
    return out

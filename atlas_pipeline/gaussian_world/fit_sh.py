"""The keyframe fit's view-dependent colour stage: spherical harmonics per view, and their gradient.

Per step, before the projection, each Gaussian's colour in the view is (per channel, [0, 1]; the
fit's colours are ``GaussianField.colors / 255`` and its coefficients ``sh_rest`` as stored)::

    c(d) = max(0, col + sum_{k < K_a} Y_{k+1}(d) sh_rest[:, k])

with ``d`` the unit direction from the camera centre to the mean and ``K_a`` the coefficients of
the degree active at that step (grown during the fit, as 3DGS does): ``sh.view_colors`` divided by
``COLOR_LEVELS``. The rasterizer's backward pass gives ``d loss / d c`` in the colour rows of the
gradient; this stage turns them into::

    d loss / d col          = m d loss / d c
    d loss / d sh_rest[:, k] = m Y_{k+1}(d) d loss / d c      (k < K_a; 0 above)

``m`` = 1 where ``col + sum`` is >= 0, else 0 (the clamp; 3DGS's ``clamped`` mask). The dependence
of ``d`` on the mean is ignored (3DGS and gsplat keep it): it is at most ``|grad sh| / distance``,
small beside the depth and footprint terms that move the means.

``view_colors01`` / ``sh_backward`` are the compiled stages (threaded over Gaussians, float64
inside); ``view_colors01_reference`` / ``sh_backward_reference`` their NumPy transcriptions, term by
term in the same order, so the two agree bit for bit. The coefficient gradients go to rows
``P_SH + 3 k + c`` of the fit's gradient array (``[P_SH + 3 K, N]``), which the fit's Adam steps
like any other row.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from atlas_pipeline.gaussian_world.field import sh_degree_of_rest_count, sh_rest_count
from atlas_pipeline.gaussian_world.fit_kernels import P_COL, P_SH, render_loss_and_gradients
from atlas_pipeline.gaussian_world.raster import GaussianArrays
from atlas_pipeline.gaussian_world.sh import sh_basis_into, sh_basis_reference, unit_directions

__all__ = ["active_degree", "sh_grad_rows", "view_colors01", "view_colors01_reference", "sh_backward",
           "sh_backward_reference", "render_loss_and_sh_gradients"]


def active_degree(step: int, sh_degree: int, interval: int) -> int:
    """The SH degree the fit renders at ``step`` (0-based): 0 first, one more every ``interval``
    steps, up to ``sh_degree`` (3DGS: every 1000 of its 30,000 steps). ``interval`` 0: ``sh_degree``
    from the start."""
    if interval <= 0:
        return sh_degree
    return min(sh_degree, step // interval)


def sh_grad_rows(k_rest: int) -> int:
    """Rows of the fit's gradient and moment arrays with ``k_rest`` coefficients per channel."""
    return P_SH + 3 * k_rest


# --------------------------------------------------------------------------------------------
# NumPy references
# --------------------------------------------------------------------------------------------


def _rest_sum_reference(positions, sh_rest, k_active, centre):
    """``[N, 3]`` float64 ``sum_{k < k_active} Y_{k+1}(d) sh_rest[:, k]`` and the basis ``[N, 16]``."""
    degree = sh_degree_of_rest_count(k_active)
    basis = sh_basis_reference(unit_directions(positions, centre), degree)  # [N, k_active + 1]
    acc = np.zeros((len(positions), 3))
    for k in range(k_active):  # one term at a time, in the kernel's order
        acc = acc + basis[:, k + 1, None] * sh_rest[:, k, :].astype(np.float64)
    return acc, basis


def view_colors01_reference(positions: np.ndarray, col01: np.ndarray, sh_rest: np.ndarray, k_active: int,
                            centre: np.ndarray) -> np.ndarray:
    """``[N, 3]`` float32 view colours in [0, 1] units (no upper clamp): ``max(0, col01 + sum)``.
    ``positions [N, 3]``, ``col01 [N, 3]``, ``sh_rest [N, K, 3]`` (``k_active <= K`` used)."""
    acc, _ = _rest_sum_reference(positions, sh_rest, k_active, centre)
    return np.maximum(0.0, col01.astype(np.float64) + acc).astype(np.float32)


def sh_backward_reference(positions: np.ndarray, col01: np.ndarray, sh_rest: np.ndarray, k_active: int,
                          centre: np.ndarray, gparam: np.ndarray) -> None:
    """``gparam [P_SH + 3 K, N]`` in place: its colour rows (``d loss / d`` view colour) masked by
    the clamp, and ``d loss / d sh_rest[:, k, c]`` (float32) into rows ``P_SH + 3 k + c``."""
    acc, basis = _rest_sum_reference(positions, sh_rest, k_active, centre)
    live = col01.astype(np.float64) + acc >= 0.0  # [N, 3]
    g = np.where(live, gparam[P_COL:P_COL + 3].T.astype(np.float64), 0.0)  # [N, 3]
    gparam[P_COL:P_COL + 3] = g.T
    for k in range(k_active):
        gparam[P_SH + 3 * k:P_SH + 3 * k + 3] = (basis[:, k + 1, None] * g).T


# --------------------------------------------------------------------------------------------
# Compiled stages
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _direction(positions, i, centre):
    dx = np.float64(positions[i, 0]) - centre[0]
    dy = np.float64(positions[i, 1]) - centre[1]
    dz = np.float64(positions[i, 2]) - centre[2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    if norm > 0.0:
        return dx / norm, dy / norm, dz / norm
    return 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def _basis_of(positions, i, centre, k_active, basis):
    """``basis[:k_active]`` = the SH basis along Gaussian ``i``'s view direction (none at degree 0)."""
    if k_active > 0:
        x, y, z = _direction(positions, i, centre)
        sh_basis_into(x, y, z, k_active, basis)


@njit(cache=True, inline="always")
def _unclamped(col01, sh_rest, basis, k_active, i, c):
    """Gaussian ``i``'s colour channel ``c`` before the clamp at 0: DC plus the active SH terms."""
    acc = 0.0
    for k in range(k_active):
        acc = acc + basis[k] * np.float64(sh_rest[i, k, c])
    return np.float64(col01[i, c]) + acc


@njit(cache=True, parallel=True)
def _view_colors01_kernel(positions, col01, sh_rest, k_active, centre, out):
    for i in prange(positions.shape[0]):
        basis = np.empty(15)
        _basis_of(positions, i, centre, k_active, basis)
        for c in range(3):
            out[i, c] = max(0.0, _unclamped(col01, sh_rest, basis, k_active, i, c))


@njit(cache=True, parallel=True)
def _sh_backward_kernel(positions, col01, sh_rest, k_active, centre, gparam):
    for i in prange(positions.shape[0]):
        basis = np.empty(15)
        _basis_of(positions, i, centre, k_active, basis)
        for c in range(3):
            g = np.float64(gparam[P_COL + c, i]) if _unclamped(col01, sh_rest, basis, k_active, i, c) >= 0.0 else 0.0
            gparam[P_COL + c, i] = g
            for k in range(k_active):
                gparam[P_SH + 3 * k + c, i] = basis[k] * g


def _check(positions, sh_rest, k_active):
    if not 0 <= k_active <= sh_rest.shape[1] or sh_degree_of_rest_count(k_active) is None:
        raise ValueError(f"k_active must be 0, 3, 8 or 15 and at most sh_rest's {sh_rest.shape[1]}, got {k_active}")
    if sh_rest.shape[0] != len(positions):
        raise ValueError(f"sh_rest has {sh_rest.shape[0]} rows for {len(positions)} Gaussians")


def view_colors01(positions: np.ndarray, col01: np.ndarray, sh_rest: np.ndarray, k_active: int,
                  centre: np.ndarray) -> np.ndarray:
    """``[N, 3]`` float32 colour of each Gaussian seen from ``centre`` ``[3]`` (world), [0, 1] units
    (compiled, threaded). ``positions [N, 3]``, ``col01 [N, 3]`` float32; ``sh_rest [N, K, 3]``
    float32 of which the first ``k_active`` coefficients count. Equals ``view_colors01_reference``."""
    _check(positions, sh_rest, k_active)
    out = np.empty((len(positions), 3), np.float32)
    if len(positions):
        _view_colors01_kernel(positions, col01, sh_rest, k_active, np.ascontiguousarray(centre, np.float64), out)
    return out


def sh_backward(positions: np.ndarray, col01: np.ndarray, sh_rest: np.ndarray, k_active: int,
                centre: np.ndarray, gparam: np.ndarray) -> None:
    """The SH stage's backward pass into ``gparam`` ``[P_SH + 3 K, N]`` float32, in place (see the
    module docstring; rows of coefficients ``>= k_active`` are left as they are). Equals
    ``sh_backward_reference``."""
    _check(positions, sh_rest, k_active)
    if gparam.shape[0] < sh_grad_rows(k_active):
        raise ValueError(f"gparam has {gparam.shape[0]} rows, the SH stage needs {sh_grad_rows(k_active)}")
    if len(positions):
        _sh_backward_kernel(positions, col01, sh_rest, k_active, np.ascontiguousarray(centre, np.float64), gparam)


def render_loss_and_sh_gradients(gaussians: GaussianArrays, sh_rest: np.ndarray, T_world_cam: np.ndarray,
                                 K: np.ndarray, image01: np.ndarray, depth_m: np.ndarray, **kwargs):
    """``render_loss_and_gradients`` with view-dependent colour: ``gaussians`` as there (colours the
    degree-0 ``[N, 3]`` in [0, 1]), ``sh_rest [N, K, 3]`` all active. Returns ``(loss, grads)`` with
    grads as there (``color`` through the clamp) plus ``sh_rest [N, K, 3]`` float64."""
    f32 = GaussianArrays(*(np.ascontiguousarray(a, np.float32) for a in gaussians))
    sh = np.ascontiguousarray(sh_rest, np.float32)
    k = sh_rest_count(sh_degree_of_rest_count(sh.shape[1]))
    centre = np.asarray(T_world_cam, np.float64)[:3, 3]
    seen = f32._replace(colors=view_colors01(f32.positions, f32.colors, sh, k, centre))
    loss, g = render_loss_and_gradients(seen, T_world_cam, K, image01, depth_m, **kwargs)
    gparam = np.zeros((sh_grad_rows(k), len(sh)), np.float32)
    gparam[P_COL:P_COL + 3] = g["color"].T
    sh_backward(f32.positions, f32.colors, sh, k, centre, gparam)
    g["color"] = gparam[P_COL:P_COL + 3].T.astype(np.float64)
    g["sh_rest"] = gparam[P_SH:].reshape(k, 3, -1).transpose(2, 0, 1).astype(np.float64)
    return loss, g

"""The Kinect v1 structured-light depth model (see ``KINECT_V1_SENSOR``): axial noise (Nguyen et al.
2012), disparity quantisation, projector shadows, dropouts at edges, dark, shiny and grazing
surfaces.
"""

from __future__ import annotations

import math
from dataclasses import field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_spec import SyntheticSpec

__all__ = ["depth_noise_sigma_m", "apply_depth_sensor_model"]


_SENSOR_STREAM = 155921
_NGUYEN_Z0_M = 0.4  # Nguyen et al. 2012: sigma_z = a + b (z - 0.4 m)^2
_MAX_NOISE_ANGLE_RAD = math.radians(80.0)  # the angle term diverges at 90 deg: capped here
_EDGE_JUMP_REL = 0.04  # a neighbour farther by > 4 % of depth is a discontinuity (a slanted floor
#                        at 6 m changes < 1 % per pixel)
_CORRELATED_NOISE_FRACTION = 0.75  # of the noise variance, when correlated; the rest is per-pixel
#                                    flicker (an assumption: Nguyen et al. measured the total only)
_SHADOW_TOL_PX = 0.5  # projector-ordering tolerance: rounding on slanted planes is not a shadow
_SHINY_KINDS = ("sphere",)  # glossy objects: no depth where seen head-on


def _acos01(x: np.ndarray) -> np.ndarray:
    """arccos of ``x`` in [0, 1], Abramowitz & Stegun 4.4.45 (|error| < 7e-5 rad): only IEEE-exact
    operations, so noisy datasets stay bitwise reproducible across SIMD code paths."""
    x = np.clip(x, 0.0, 1.0)
    return np.sqrt(1.0 - x) * (1.5707288 + x * (-0.2121144 + x * (0.0742610 + x * -0.0187293)))


def depth_noise_sigma_m(
    spec: SyntheticSpec, z_m: np.ndarray, cos_incidence: np.ndarray | float = 1.0
) -> np.ndarray:
    """Axial depth noise std (metres) at depth ``z_m`` and incidence cosine (same shapes):
    ``a + b (z - 0.4)^2 + c / sqrt(z) * theta^2 / (pi/2 - theta)^2`` (Nguyen et al. 2012), with
    ``theta`` capped at 80 deg. Includes the disparity quantisation (the std that is written)."""
    z = np.asarray(z_m, dtype=np.float64)
    dz = z - _NGUYEN_Z0_M
    sigma = spec.depth_noise_a_m + spec.depth_noise_b_per_m * dz * dz
    if spec.depth_noise_angle_m > 0:
        theta = np.minimum(_acos01(np.asarray(cos_incidence, dtype=np.float64)), _MAX_NOISE_ANGLE_RAD)
        q = theta / (0.5 * math.pi - theta)
        sigma = sigma + spec.depth_noise_angle_m / np.sqrt(np.maximum(z, 1e-3)) * q * q
    return sigma


def _depth_edges(z: np.ndarray) -> np.ndarray:
    """Pixels ``[H, W]`` next to a depth discontinuity (relative jump > 4 %, or valid next to
    missing)."""
    edge = np.zeros(z.shape, dtype=bool)
    for a, b, sl_a, sl_b in (
        (z[:, :-1], z[:, 1:], (slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        (z[:-1, :], z[1:, :], (slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        jump = np.abs(a - b) > _EDGE_JUMP_REL * np.minimum(a, b)
        jump |= (a > 0) != (b > 0)
        edge[sl_a] |= jump
        edge[sl_b] |= jump
    return edge


def _dilate(mask: np.ndarray) -> np.ndarray:
    """3x3 binary dilation of ``mask`` ``[H, W]``."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    m = out.copy()
    out[:, 1:] |= m[:, :-1]
    out[:, :-1] |= m[:, 1:]
    return out


def _projector_shadow(z: np.ndarray, fx: float, baseline_m: float) -> np.ndarray:
    """Pixels ``[H, W]`` the projector (``baseline_m`` to the camera's +x) cannot light.

    A point at column ``u`` and depth ``z`` is lit from projector column ``u - fx b / z``; along a
    row a nearer surface to the right that reaches a smaller projector column hides it (the
    ordering test of stereo matching). Shadows fall left of foreground objects, ``fx b (1/z_near -
    1/z_far)`` pixels wide.
    """
    W = z.shape[1]
    u = np.arange(W, dtype=np.float64)[None, :]
    up = np.where(z > 0, u - fx * baseline_m / np.where(z > 0, z, 1.0), np.inf)
    suffix_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]  # min over q >= p
    right_min = np.full_like(up, np.inf)
    right_min[:, :-1] = suffix_min[:, 1:]  # min over q > p
    return (z > 0) & (up > right_min + _SHADOW_TOL_PX)


def _box_sum(a: np.ndarray, k: int) -> np.ndarray:
    """Sums over every k x k window of ``a`` ``[H + k - 1, W + k - 1]``: ``[H, W]`` (cumulative
    sums: exact order, deterministic)."""
    c = np.zeros((a.shape[0] + 1, a.shape[1]))
    np.cumsum(a, axis=0, out=c[1:])
    rows = c[k:] - c[:-k]
    c = np.zeros((rows.shape[0], rows.shape[1] + 1))
    np.cumsum(rows, axis=1, out=c[:, 1:])
    return c[:, k:] - c[:, :-k]


def _unit_noise(spec: SyntheticSpec, shape: tuple[int, int], frame_index: int) -> np.ndarray:
    """Zero-mean unit-variance noise ``[H, W]``: per pixel, or (``depth_noise_corr_px`` > 0) mostly a
    box-filtered field correlated over ``depth_noise_corr_px * W / 640`` pixels."""
    H, W = shape
    white = _effect_rng(spec, frame_index, 4).standard_normal((H, W))
    k = int(round(spec.depth_noise_corr_px * W / 640.0))
    if k <= 1:
        return white
    field = _effect_rng(spec, frame_index, 6).standard_normal((H + k - 1, W + k - 1))
    smooth = _box_sum(field, k) / k  # a sum of k^2 unit normals has std k
    f = _CORRELATED_NOISE_FRACTION
    return math.sqrt(f) * smooth + math.sqrt(1.0 - f) * white


def _effect_rng(spec: SyntheticSpec, frame_index: int, effect: int) -> np.random.Generator:
    # One stream per (frame, effect): switching one effect off leaves the others' noise unchanged.
    return np.random.default_rng([spec.seed, _SENSOR_STREAM, frame_index, effect])


def apply_depth_sensor_model(
    spec: SyntheticSpec,
    depth_m: np.ndarray,
    cos_incidence: np.ndarray,
    luma: np.ndarray,
    shiny: np.ndarray,
    frame_index: int = 0,
) -> np.ndarray:
    """The depth a structured-light sensor reports for an exact depth map.

    Args:
        depth_m: ``[H, W]`` exact camera z, 0 = no surface.
        cos_incidence: ``[H, W]`` cosine of the incidence angle at each pixel.
        luma: ``[H, W]`` surface brightness in [0, 1] (albedo x shading, a proxy of IR reflectance).
        shiny: ``[H, W]`` bool, glossy surface.
        frame_index: keys the random streams (with ``spec.seed``).

    Returns:
        ``[H, W]`` float64 depth in metres, 0 = no reading (not yet rounded to ``depth_scale``).
    """
    z0 = np.asarray(depth_m, dtype=np.float64)
    H, W = z0.shape
    z = z0.copy()
    cos_i = np.array(cos_incidence, dtype=np.float64)  # copies: the jitter below writes into them
    lum = np.array(luma, dtype=np.float64)
    shn = np.array(shiny, dtype=bool)
    edge = _depth_edges(z0)
    if spec.depth_lateral_noise_px > 0:
        # Jagged silhouettes: pixels near a discontinuity read a neighbour's depth.
        band = np.flatnonzero(_dilate(edge))
        rng = _effect_rng(spec, frame_index, 1)
        off = np.rint(rng.standard_normal((2, band.size)) * spec.depth_lateral_noise_px).astype(np.int64)
        v, u = np.divmod(band, W)
        src = np.clip(v + off[0], 0, H - 1) * W + np.clip(u + off[1], 0, W - 1)
        for arr in (z, cos_i, lum, shn):
            flat = arr.reshape(-1)
            flat[band] = flat[src] if arr is not z else z0.reshape(-1)[src]
    valid = z > 0
    if spec.edge_dropout_prob > 0:
        valid &= ~(edge & (_effect_rng(spec, frame_index, 2).random((H, W)) < spec.edge_dropout_prob))
    if spec.projector_baseline_m > 0:
        valid &= ~_projector_shadow(z0, spec.fx, spec.projector_baseline_m)
    if spec.dark_dropout_luma > 0:
        # Certain loss at black, none at or above the threshold, a linear ramp between.
        p_drop = np.clip(1.0 - lum / spec.dark_dropout_luma, 0.0, 1.0)
        valid &= ~(_effect_rng(spec, frame_index, 3).random((H, W)) < p_drop)
    if spec.shiny_dropout_deg > 0:
        valid &= ~(shn & (cos_i > math.cos(math.radians(spec.shiny_dropout_deg))))
    if spec.grazing_dropout_deg > 0:
        valid &= cos_i >= math.cos(math.radians(spec.grazing_dropout_deg))
    z = np.where(valid, z, 0.0)

    q = spec.inverse_depth_step_per_m
    if spec.depth_noise_a_m > 0 or spec.depth_noise_b_per_m > 0 or spec.depth_noise_angle_m > 0:
        sigma = depth_noise_sigma_m(spec, np.where(valid, z, 1.0), np.where(valid, cos_i, 1.0))
        # The model's std is the sensor's total: the Gaussian part leaves room for the
        # quantisation below (uniform steps of q z^2 have variance (q z^2)^2 / 12).
        step = q * z * z
        sd = np.sqrt(np.maximum(sigma * sigma - step * step / 12.0, 0.0))
        z = np.where(valid, z + sd * _unit_noise(spec, (H, W), frame_index), 0.0)
        valid &= z > 0
    if q > 0:
        inv_q = np.rint(1.0 / np.where(valid, z, 1.0) / q)
        z = np.where(valid & (inv_q > 0), 1.0 / (np.maximum(inv_q, 1.0) * q), 0.0)
    return np.where((z > 0) & (z <= spec.max_depth_m), z, 0.0)

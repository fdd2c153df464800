"""The colour camera model: motion blur, auto exposure and drift, white balance drift, noise and a
shift against depth; and one frame through the whole sensor model.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from atlas_pipeline.sensors.synthetic_kinect import _SENSOR_STREAM, _effect_rng, apply_depth_sensor_model
from atlas_pipeline.sensors.synthetic_path import camera_path
from atlas_pipeline.sensors.synthetic_raytrace import _render_colour, _render_layers

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_scene import SyntheticScene
    from atlas_pipeline.sensors.synthetic_spec import SyntheticSpec


_AE_TARGET_LUMA = 0.45  # auto exposure pulls the mean luma toward this (halfway, in log terms)
_AE_GAIN_RANGE = (0.7, 1.4)
_EXPOSURE_DRIFT_HZ = (0.11, 0.29)  # slow gain wander on top of auto exposure
_WHITE_BALANCE_HZ = (0.07, 0.05)  # red and blue gains drift independently (green is the reference)


def _shift_image(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` ``[H, W, C]`` moved by ``(dx, dy)`` pixels (bilinear, edges repeated):
    ``out[v, u] = img[v - dy, u - dx]``."""
    H, W = img.shape[:2]
    out = img
    for axis, shift, n in ((1, dx, W), (0, dy, H)):
        if shift == 0.0:
            continue
        i = math.floor(shift)
        f = np.float32(shift - i)
        idx = np.arange(n)
        a = np.take(out, np.clip(idx - i, 0, n - 1), axis=axis)  # weight 1 - f
        b = np.take(out, np.clip(idx - i - 1, 0, n - 1), axis=axis)  # weight f
        out = a * (np.float32(1.0) - f) + b * f
    return out


def _colour_gain(spec: SyntheticSpec, t: float, mean_luma: float) -> np.ndarray:
    """Per-channel gain ``[3]`` float32 at time ``t``: auto exposure, exposure and white-balance
    drift (slow sines with phases from the seed)."""
    ph = np.random.default_rng([spec.seed, _SENSOR_STREAM, 0xC0]).uniform(0.0, 2.0 * math.pi, size=4)
    gain = np.ones(3)
    if spec.exposure_drift > 0:
        # Auto exposure halves the log distance to the target brightness (no lag), then drifts.
        ae = math.sqrt(_AE_TARGET_LUMA / max(mean_luma, 1e-3))
        ae = min(max(ae, _AE_GAIN_RANGE[0]), _AE_GAIN_RANGE[1])
        f1, f2 = _EXPOSURE_DRIFT_HZ
        drift = 0.6 * math.sin(2 * math.pi * f1 * t + ph[0]) + 0.4 * math.sin(2 * math.pi * f2 * t + ph[1])
        gain *= ae * (1.0 + spec.exposure_drift * drift)
    if spec.white_balance_drift > 0:
        fr, fb = _WHITE_BALANCE_HZ
        gain[0] *= 1.0 + spec.white_balance_drift * math.sin(2 * math.pi * fr * t + ph[2])
        gain[2] *= 1.0 + spec.white_balance_drift * math.sin(2 * math.pi * fb * t + ph[3])
    return gain.astype(np.float32)


def _luma(col: np.ndarray) -> np.ndarray:
    """Rec. 601 luma ``[H, W]`` of a colour image ``[H, W, 3]``."""
    return (np.float32(0.299) * col[..., 0] + np.float32(0.587) * col[..., 1]
            + np.float32(0.114) * col[..., 2])


def _sensor_frame(
    spec: SyntheticSpec, scene: SyntheticScene, t: float, frame_index: int
) -> tuple[np.ndarray, np.ndarray]:
    """One frame through the sensor model: ``(rgb uint8 [H, W, 3], depth_m float64 [H, W])``.

    Depth is sensed at the pose of time ``t``; colour integrates the exposure around
    ``t + colour_delay_s``.
    """
    T = camera_path(spec, np.array([t]))[0]
    lay = _render_layers(spec, scene, T)
    luma = _luma(lay.col)
    depth = apply_depth_sensor_model(spec, lay.depth_m, lay.cos_incidence, luma, lay.shiny, frame_index)

    t_col = t + spec.colour_delay_s
    col = lay.col if t_col == t else _render_colour(spec, scene, camera_path(spec, np.array([t_col]))[0])
    n = spec.motion_blur_samples
    if n >= 2 and spec.exposure_time_s > 0:
        offsets = [spec.exposure_time_s * (k / (n - 1) - 0.5) for k in range(n)]
        sub = camera_path(spec, t_col + np.array(offsets))
        acc = np.zeros_like(col)
        for off, Tk in zip(offsets, sub):  # fixed order: deterministic float sums
            acc += col if off == 0.0 else _render_colour(spec, scene, Tk)
        col = acc * np.float32(1.0 / n)
    if spec.exposure_drift > 0 or spec.white_balance_drift > 0:
        col = col * _colour_gain(spec, t, float(_luma(col).mean()))
    if spec.rgb_shift_x_px or spec.rgb_shift_y_px:
        col = _shift_image(col, spec.rgb_shift_x_px, spec.rgb_shift_y_px)
    if spec.rgb_noise_std > 0:
        noise = _effect_rng(spec, frame_index, 5).standard_normal(col.shape, dtype=np.float32)
        col = col + noise * np.float32(spec.rgb_noise_std / 255.0)
    rgb = np.round(np.clip(col, 0.0, 1.0) * 255.0).astype(np.uint8)
    return rgb, depth

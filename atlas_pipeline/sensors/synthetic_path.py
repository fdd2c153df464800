"""The synthetic camera path and frame times: the ellipse walk, pans, shake, closed loops, dropped
frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from atlas_pipeline.geometry import look_at

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_spec import SyntheticSpec

__all__ = ["frame_times_s", "camera_path"]


# Camera path geometry (fixed; the seed only picks the starting phase and wobble phases).
_PATH_A_M = 2.2  # ellipse semi-axis along x: 0.8 m from the x walls
_PATH_B_M = 1.7  # ellipse semi-axis along y: 0.8 m from the y walls
_PATH_HEIGHT_M = 1.4
_PATH_BOB_M = 0.12
_PATH_RATE_RAD_S = math.radians(36.0)  # 72 deg of orbit over 2 s
_PAN_HALF_ANGLE_DEG = 40.0  # pans sweep 80 deg: from 40 deg one side of the room centre to the other
_PAN_RAMP_S = 0.15  # time to reach / leave the pan rate: a wrist starts a pan quickly (~400 deg/s^2)
_PAN_HOLD_S = 0.8  # looking to one side between two pans
_SHAKE_BAND_HZ = (5.0, 10.0)  # hand tremor and walking jitter frequencies
_LOOP_GAP_M = 0.003  # a loop ends this far from its start pose: a revisit, not the same frame
_LOOP_ENVELOPE_S = 1.0  # pans and shakes fade in/out over this long at the ends of a loop
_MOTION_STREAM = 104729  # rng stream ids: keep the streams of different effects independent
_DROP_STREAM = 130363
_MAX_DROP_BURST = 3  # a drop loses 1-3 consecutive sensor frames (USB hiccups come in bursts)


def _path_phases(seed: int) -> np.ndarray:
    """``[6]`` phases of the path: start angle, bob, target wobble x/y/z, roll."""
    # A separate stream from the scene's, so the path does not change if the scene code does.
    return np.random.default_rng([seed, 7919]).uniform(0.0, 2.0 * math.pi, size=6)


def _pose_at(t: float, ph: np.ndarray) -> np.ndarray:
    """``T_world_cam`` ``[4, 4]`` at time ``t`` seconds (scalar math: platform-independent)."""
    th = float(ph[0]) + _PATH_RATE_RAD_S * t
    eye = np.array(
        [
            _PATH_A_M * math.cos(th),
            _PATH_B_M * math.sin(th),
            _PATH_HEIGHT_M + _PATH_BOB_M * math.sin(2.0 * math.pi * 0.35 * t + float(ph[1])),
        ]
    )
    # Wobbling target: yaw +-~10 deg and pitch variation on top of the orbit.
    target = np.array(
        [
            0.35 * math.sin(2.0 * math.pi * 0.21 * t + float(ph[2])),
            0.30 * math.sin(2.0 * math.pi * 0.17 * t + float(ph[3])),
            0.55 + 0.10 * math.sin(2.0 * math.pi * 0.27 * t + float(ph[4])),
        ]
    )
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    # Small roll about the optical axis so all three rotation axes are exercised.
    roll = math.radians(3.0) * math.sin(2.0 * math.pi * 0.23 * t + float(ph[5]))
    c, s = math.cos(roll), math.sin(roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = T[:3, :3]
    # Explicit products instead of BLAS matmul: bitwise reproducible everywhere.
    T[:3, :3] = (R[:, :, None] * Rz[None, :, :]).sum(axis=1)
    return T


def frame_times_s(spec: SyntheticSpec) -> np.ndarray:
    """Capture times ``[n_frames]`` of the frames, seconds from the first.

    Frame ``i`` is at ``i / fps`` unless ``dropped_frame_rate`` > 0: then each sensor frame slot
    starts a drop burst of 1-3 slots with that probability (never before the first frame), and
    the frames that remain keep their slot times, so the timestamps have gaps.
    """
    n = spec.n_frames
    if spec.dropped_frame_rate <= 0.0:
        return np.arange(n, dtype=np.float64) / spec.fps
    rng = np.random.default_rng([spec.seed, _DROP_STREAM])
    slots = [0]
    k = 1
    while len(slots) < n:
        if rng.random() < spec.dropped_frame_rate:
            k += int(rng.integers(1, _MAX_DROP_BURST + 1))
        slots.append(k)
        k += 1
    return np.asarray(slots, dtype=np.float64) / spec.fps


def _orbit_rate_rad_s(spec: SyntheticSpec) -> float:
    """Angular speed along the ellipse: the spec's, or one that closes ``loop_revolutions`` turns
    exactly at the last frame."""
    if spec.loop_revolutions > 0:
        return 2.0 * math.pi * spec.loop_revolutions / float(frame_times_s(spec)[-1])
    return math.radians(spec.orbit_rate_deg_per_s)


@dataclass(frozen=True)
class _Motion:
    """Parameters of a non-default path (see :func:`_motion_of`)."""

    rate: float  # orbit, rad/s
    time_scale: float  # path-shape time per second: wobbles keep their shape at any orbit speed
    freqs: tuple[float, ...]  # bob, target x/y/z, roll (Hz of path-shape time)
    t_end: float  # loop: time of the last frame (0 otherwise)
    pan_up: float  # pan sweeps relative to the look-at direction, rad/s (0: no pans)
    pan_down: float
    pan_phase_s: float
    shake_m: float
    shake_rad: float
    shake_f: np.ndarray  # [6, 2] Hz: x, y, z, rx, ry, rz, two sines each
    shake_ph: np.ndarray  # [6, 2]
    look_at_height_m: float = 0.55  # the target's mean height


@lru_cache(maxsize=8)
def _motion_of(spec: SyntheticSpec) -> _Motion:
    """Path parameters of ``spec`` (cached: camera_path is called per frame and sub-frame)."""
    rate = _orbit_rate_rad_s(spec)
    scale = rate / _PATH_RATE_RAD_S
    freqs = (0.35, 0.21, 0.17, 0.27, 0.23)
    t_end = 0.0
    if spec.loop_revolutions > 0:
        t_end = float(frame_times_s(spec)[-1])
        # Whole cycles over the loop, so bob, wobble and roll return to their start values.
        tau_end = t_end * scale
        freqs = tuple(round(f * tau_end) / tau_end for f in freqs)
    rng = np.random.default_rng([spec.seed, _MOTION_STREAM])
    pan_phase = float(rng.uniform(0.0, 1.0))
    shake_f = rng.uniform(*_SHAKE_BAND_HZ, size=(6, 2))
    shake_ph = rng.uniform(0.0, 2.0 * math.pi, size=(6, 2))
    pan_up = pan_down = 0.0
    if spec.pan_rate_deg_per_s > 0:
        # The look-at direction itself turns with the orbit (+rate about z): sweeps against and
        # with it get different relative speeds, so the world yaw rate is the pan rate both ways.
        v = math.radians(spec.pan_rate_deg_per_s)
        pan_up, pan_down = v - rate, v + rate
    return _Motion(rate, scale, freqs, t_end, pan_up, pan_down, pan_phase, spec.shake_m,
                   math.radians(spec.shake_deg), shake_f, shake_ph, spec.look_at_height_m)


def _sweep_rad(tau: float, v: float, amp2: float) -> float:
    """Angle covered ``tau`` s into a sweep of ``amp2`` rad at top speed ``v`` rad/s, with linear
    speed ramps of ``_PAN_RAMP_S`` at both ends (trapezoidal velocity: C1 angle)."""
    r = _PAN_RAMP_S
    c = amp2 / v - r  # cruise time: v (r + c) = amp2
    if tau <= 0.0:
        return 0.0
    if tau < r:
        return v * tau * tau / (2.0 * r)
    if tau < r + c:
        return v * r / 2.0 + v * (tau - r)
    if tau < 2.0 * r + c:
        u = tau - r - c
        return v * r / 2.0 + v * c + v * u - v * u * u / (2.0 * r)
    return amp2


def _pan_rad(t: float, m: _Motion) -> float:
    """Pan yaw offset (rad) at time ``t``: sweep left, hold, sweep right, hold, periodically."""
    a = math.radians(_PAN_HALF_ANGLE_DEG)
    d_up = 2.0 * a / m.pan_up + _PAN_RAMP_S
    d_down = 2.0 * a / m.pan_down + _PAN_RAMP_S
    period = d_up + d_down + 2.0 * _PAN_HOLD_S
    tau = (t + m.pan_phase_s * period) % period  # Python's % is non-negative for period > 0
    if tau < d_up:
        return -a + _sweep_rad(tau, m.pan_up, 2.0 * a)
    tau -= d_up
    if tau < _PAN_HOLD_S:
        return a
    tau -= _PAN_HOLD_S
    if tau < d_down:
        return a - _sweep_rad(tau, m.pan_down, 2.0 * a)
    return -a


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _rot3(axis: int, ang: float) -> np.ndarray:
    """``[3, 3]`` rotation by ``ang`` rad about coordinate axis ``axis``."""
    c, s = math.cos(ang), math.sin(ang)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _mul3(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    # Explicit products instead of BLAS matmul: bitwise reproducible everywhere.
    return (A[:, :, None] * B[None, :, :]).sum(axis=1)


def _pose_at_motion(t: float, ph: np.ndarray, m: _Motion) -> np.ndarray:
    """``T_world_cam`` ``[4, 4]`` of a non-default path at time ``t`` (scalar math).

    The orbit of :func:`_pose_at` travelled at ``m.rate``, with the bob, wobble and roll on a time
    axis scaled to the same shape; then pans (yaw about the vertical through the eye), hand shake,
    and for loops a 3 mm linear offset and an envelope that keeps the ends free of pans and shake.
    """
    tau = t * m.time_scale
    f_bob, f_x, f_y, f_z, f_roll = m.freqs
    th = float(ph[0]) + m.rate * t
    eye = np.array(
        [
            _PATH_A_M * math.cos(th),
            _PATH_B_M * math.sin(th),
            _PATH_HEIGHT_M + _PATH_BOB_M * math.sin(2.0 * math.pi * f_bob * tau + float(ph[1])),
        ]
    )
    target = np.array(
        [
            0.35 * math.sin(2.0 * math.pi * f_x * tau + float(ph[2])),
            0.30 * math.sin(2.0 * math.pi * f_y * tau + float(ph[3])),
            m.look_at_height_m + 0.10 * math.sin(2.0 * math.pi * f_z * tau + float(ph[4])),
        ]
    )
    env = 1.0
    if m.t_end > 0.0:
        ramp = min(_LOOP_ENVELOPE_S, m.t_end / 4.0)
        env = _smoothstep(t / ramp) * _smoothstep((m.t_end - t) / ramp)
        frac = min(max(t / m.t_end, 0.0), 1.0)
        eye = eye + _LOOP_GAP_M * frac * np.array([0.6, 0.0, 0.8])
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    R = T[:3, :3]
    if m.pan_up > 0.0:
        R = _mul3(_rot3(2, env * _pan_rad(t, m)), R)  # world yaw about the eye
    roll = math.radians(3.0) * math.sin(2.0 * math.pi * f_roll * tau + float(ph[5]))
    R = _mul3(R, _rot3(2, roll))
    if m.shake_m > 0.0 or m.shake_rad > 0.0:
        w = [
            0.5 * env * sum(math.sin(2.0 * math.pi * float(m.shake_f[a, k]) * t + float(m.shake_ph[a, k]))
                            for k in range(2))
            for a in range(6)
        ]
        for a in range(3):
            R = _mul3(R, _rot3(a, m.shake_rad * w[3 + a]))
        T[:3, 3] = eye + m.shake_m * np.array(w[:3])
    T[:3, :3] = R
    return T


def camera_path(spec: SyntheticSpec, t_s: np.ndarray) -> np.ndarray:
    """Camera poses ``T_world_cam`` ``[N, 4, 4]`` at times ``t_s`` ``[N]`` (seconds from start).

    Smooth (C-infinity) in time for the default motion (pans are C1), defined for any real ``t``
    (negative included), and always more than 0.5 m from every wall and object of
    ``build_scene(spec.seed)``. A loop (``loop_revolutions``) returns to within 3 mm of its start
    pose at the last frame time.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    if spec.place == "suite":
        return _suite_camera_path(spec, t)
    ph = _path_phases(spec.seed)
    out = np.empty((t.shape[0], 4, 4), dtype=np.float64)
    if spec.custom_motion:
        m = _motion_of(spec)
        for i, ti in enumerate(t):
            out[i] = _pose_at_motion(float(ti), ph, m)
        return out
    for i, ti in enumerate(t):
        out[i] = _pose_at(float(ti), ph)
    return out


def _suite_camera_path(spec: SyntheticSpec, t: np.ndarray) -> np.ndarray:
    """Poses ``[N, 4, 4]`` along the suite route of ``spec`` (hand shake on top when set)."""
    from atlas_pipeline.sensors.synthetic_places import route_length_m, suite_path

    speed = spec.suite_speed_m_per_s
    if speed <= 0:  # the whole route over the recording
        speed = route_length_m(spec.route) / max(float(frame_times_s(spec)[-1]), 1.0 / spec.fps)
    out = suite_path(spec.route, speed, t)
    if spec.shake_m > 0.0 or spec.shake_deg > 0.0:
        m = _motion_of(spec)
        for i, ti in enumerate(t):
            w = [0.5 * sum(math.sin(2.0 * math.pi * float(m.shake_f[a, k]) * float(ti) + float(m.shake_ph[a, k]))
                           for k in range(2)) for a in range(6)]
            R = out[i, :3, :3]
            for a in range(3):
                R = _mul3(R, _rot3(a, m.shake_rad * w[3 + a]))
            out[i, :3, :3] = R
            out[i, :3, 3] += m.shake_m * np.array(w[:3])
    return out

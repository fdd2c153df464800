"""Colour taken at another time than depth, moved to the depth image's time.

Sensors whose colour and depth streams are not synchronised (Kinect v1: TUM fr1 stamps colour
about 15 ms after depth) see the camera move between the two exposures. A frame's pose is its
depth image's (``sensors/tum.py``), so its colour belongs a few pixels off the surface points it
is fused onto and compared with (TUM fr1 at 0.36 m/s: about 5 mm, 2 px at 1.5 m).

:func:`colour_at_depth_time` resamples the colour image onto the depth image's time given the
camera's motion between the two (``T_depth_colour``, the colour camera's pose in the depth
camera's frame): the tracker takes it from its constant-velocity motion model while it tracks;
the keyframe fit, and the render evaluation, from the whole trajectory once it is known
(:func:`pose_at_colour_time`, :func:`colour_motion_in_trajectory`). Each depth pixel's
point is projected into the colour camera and the colour read there (bilinear). Pixels without
depth are moved by the rotation alone (points at infinity). The flow is computed on the pinhole
(undistorted) rays and applied to the raw pixel grid, a first-order approximation for cameras
with lens distortion (TUM fr1: a few per cent of a 2 px flow).

Upper bound, measured in a ``/tmp`` harness with the motion between the two times taken from
ground truth: TUM fr1 (9 frames) ATE 0.296 -> 0.255 cm.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from atlas_pipeline.geometry import interpolate_pose, rotation_angle_rad
from atlas_pipeline.perception.rgbd import pixel_rays
from atlas_pipeline.sensors.camera import CameraIntrinsics

__all__ = ["colour_at_depth_time", "colour_motion_in_trajectory", "colour_time_poses", "max_flow_px",
           "pose_at_colour_time", "MIN_FLOW_PX", "MAX_COLOUR_DELAY_S"]

MIN_FLOW_PX = 0.1  # below this the colour is left as it is: resampling would only blur it
# Colour further than this from its depth image is not the same moment (TUM pairs within 20 ms);
# the motion model is not extrapolated that far.
MAX_COLOUR_DELAY_S = 0.05
NEAREST_DEPTH_M = 0.3  # the nearest surface assumed when bounding the flow from the translation
# A trajectory's poses are interpolated to a colour time only between frames this close in time
# (3 frames at 30 Hz): across a longer gap (dropped frames) the motion need not be even.
MAX_INTERPOLATION_GAP_S = 0.1


def pose_at_colour_time(T_world_cam: np.ndarray, timestamps_s: np.ndarray, i: int,
                        colour_delay_s: float) -> np.ndarray | None:
    """Frame ``i``'s camera pose ``[4, 4]`` when its colour image was taken, ``colour_delay_s``
    after its depth image (the frame's time), from a whole trajectory ``T_world_cam`` ``[N, 4, 4]``
    (NaN where unknown) at ``timestamps_s`` ``[N]``: interpolated between frame ``i`` and its
    neighbour on the delay's side (linear translation, slerp). None when there is nothing to
    compensate (no delay, or one beyond ``MAX_COLOUR_DELAY_S``), or frame ``i`` or that neighbour
    has no pose, or they are more than ``MAX_INTERPOLATION_GAP_S`` apart or do not bracket the
    colour time."""
    if not colour_delay_s or abs(colour_delay_s) > MAX_COLOUR_DELAY_S:
        return None
    j = i + 1 if colour_delay_s > 0 else i - 1
    if not 0 <= j < len(T_world_cam) or not (np.isfinite(T_world_cam[i]).all() and np.isfinite(T_world_cam[j]).all()):
        return None
    t_i, t_j = float(timestamps_s[i]), float(timestamps_s[j])
    t_colour = t_i + colour_delay_s
    if abs(t_j - t_i) > MAX_INTERPOLATION_GAP_S or not min(t_i, t_j) <= t_colour <= max(t_i, t_j):
        return None
    return interpolate_pose(t_i, T_world_cam[i], t_j, T_world_cam[j], t_colour)


def colour_motion_in_trajectory(T_world_cam: np.ndarray, timestamps_s: np.ndarray, i: int,
                                colour_delay_s: float) -> np.ndarray | None:
    """``T_depth_colour`` ``[4, 4]`` of frame ``i`` (the argument of :func:`colour_at_depth_time`)
    from a whole trajectory, or None (see :func:`pose_at_colour_time`)."""
    T_colour = pose_at_colour_time(T_world_cam, timestamps_s, i, colour_delay_s)
    return None if T_colour is None else np.linalg.solve(T_world_cam[i], T_colour)


def colour_time_poses(T_world_cam: np.ndarray, manifest, indices) -> dict[int, np.ndarray]:
    """Frame -> the pose ``[4, 4]`` at its colour image's time (:func:`pose_at_colour_time`), for
    each of ``indices`` whose colour was taken far enough from its depth image to move a pixel by
    ``MIN_FLOW_PX``; the others are left out (their colour belongs at ``T_world_cam[i]``). What a
    render compared with the colour images uses (the render evaluation, the demo's side-by-side)."""
    out = {}
    for i in map(int, indices):
        T = pose_at_colour_time(T_world_cam, manifest.timestamps_s, i, manifest.colour_delay_s(i))
        if T is not None and max_flow_px(np.linalg.solve(T_world_cam[i], T), manifest.camera) >= MIN_FLOW_PX:
            out[i] = T
    return out


def max_flow_px(T_depth_colour: np.ndarray, camera: CameraIntrinsics, nearest_m: float = NEAREST_DEPTH_M) -> float:
    """An upper bound of the pixel flow ``T_depth_colour`` ``[4, 4]`` causes: rotation angle times
    the focal length, plus the translation seen at ``nearest_m``."""
    angle = float(rotation_angle_rad(T_depth_colour[:3, :3]))
    f = max(camera.fx, camera.fy)
    return f * (angle + float(np.linalg.norm(T_depth_colour[:3, 3])) / nearest_m)


@njit(cache=True, parallel=True)
def _resample(rgb, depth_m, rays, R, t, fx, fy, cx, cy):  # pragma: no cover - compiled
    H, W = depth_m.shape
    out = rgb.copy()
    for v in prange(H):  # rows are independent
        for u in range(W):
            rx, ry = rays[v, u, 0], rays[v, u, 1]  # pixel_rays have z = 1
            z = depth_m[v, u]
            if z > 0:
                c0 = (R[0, 0] * rx + R[0, 1] * ry + R[0, 2]) * z + t[0]
                c1 = (R[1, 0] * rx + R[1, 1] * ry + R[1, 2]) * z + t[1]
                c2 = (R[2, 0] * rx + R[2, 1] * ry + R[2, 2]) * z + t[2]
            else:  # a point at infinity along the ray: the rotation alone moves it
                c0 = R[0, 0] * rx + R[0, 1] * ry + R[0, 2]
                c1 = R[1, 0] * rx + R[1, 1] * ry + R[1, 2]
                c2 = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
            if c2 <= 1e-6:  # behind the colour camera: keep the colour
                continue
            inv = np.float32(1.0) / c2
            x = u + fx * (c0 * inv - rx)
            y = v + fy * (c1 * inv - ry)
            if x < 0.0 or y < 0.0 or x > W - 1 or y > H - 1:
                continue
            x0 = min(int(x), W - 2)
            y0 = min(int(y), H - 2)
            ax = np.float32(x - x0)
            ay = np.float32(y - y0)
            one = np.float32(1.0)
            for k in range(3):
                top = rgb[y0, x0, k] * (one - ax) + rgb[y0, x0 + 1, k] * ax
                bottom = rgb[y0 + 1, x0, k] * (one - ax) + rgb[y0 + 1, x0 + 1, k] * ax
                out[v, u, k] = np.uint8(min(np.float32(255.0), top * (one - ay) + bottom * ay + np.float32(0.5)))
    return out


def colour_at_depth_time(rgb: np.ndarray, depth_m: np.ndarray, camera: CameraIntrinsics,
                         T_depth_colour: np.ndarray) -> np.ndarray:
    """Colour ``rgb`` ``[H, W, 3]`` uint8 taken at pose ``T_depth_colour`` ``[4, 4]`` (the colour
    camera in the depth camera's frame), resampled to the depth image ``depth_m`` ``[H, W]``
    (metres, 0 = none): ``[H, W, 3]`` uint8. Returns ``rgb`` itself when the motion moves no pixel
    by ``MIN_FLOW_PX``; pixels whose sample leaves the image keep their colour."""
    if max_flow_px(T_depth_colour, camera) < MIN_FLOW_PX:
        return rgb
    R_cd = T_depth_colour[:3, :3].T  # depth camera -> colour camera
    t_cd = -R_cd @ T_depth_colour[:3, 3]
    f32 = np.float32  # single precision throughout: a tenth of a pixel is all the resampling needs
    return _resample(np.ascontiguousarray(rgb), np.ascontiguousarray(depth_m, f32), pixel_rays(camera, 1),
                     np.ascontiguousarray(R_cd, f32), t_cd.astype(f32), f32(camera.fx), f32(camera.fy),
                     f32(camera.cx), f32(camera.cy))

"""One surface per surface: a keyframe's points that contradict the map are not merged into it.

Tracking drifts a few centimetres before a loop closes (or where no loop is found). A keyframe taken
on a return to a mapped place then sees the old surfaces a few centimetres off, and merging its
points would leave two copies of each wall in the tracking map. Whatever is later tracked against
that map, a frame of the same recording or a second visit, can then lock onto either copy, or slide
between them where the geometry leaves a direction free (a wall and the floor).

:func:`disagreeing_points` renders the map as it stands at the keyframe's pose and marks the
keyframe's points whose depth differs from the map's surface on their ray by more than the sensor
can explain (:func:`conflict_tolerance_m`). Those are left out; points where the map has no surface
(new surface) and points on the map's surface (a second look, which averages the noise) are merged.
A session extending a saved world merges only the first kind (:func:`point_relation`): the world
is its reference, and a second look from a pose a few cm off would thicken the world's surfaces.
"""

from __future__ import annotations

import numpy as np

from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.depth_noise import depth_sigma_m

__all__ = ["CONFLICT_LEVEL", "CONFLICT_MIN_M", "CONFLICT_SIGMAS", "conflict_tolerance_m", "disagreeing_points",
           "agreeing_points", "map_depth_on_rays", "point_relation"]

# The map is rendered at this pyramid level (half resolution): a view per keyframe costs
# milliseconds, and a keyframe's points are a stride-2 sample of its depth anyway.
CONFLICT_LEVEL = 1
# A point disagrees with the map when its depth and the map's surface on its ray differ by more
# than this many depth-noise sigmas (the sensor model of the mapper), and at least this much:
# twice the surfel disk's flatness error at a 2 cm voxel. Drift doubles a surface by several cm.
CONFLICT_SIGMAS = 3.0
CONFLICT_MIN_M = 0.03


def conflict_tolerance_m(depth_m: np.ndarray) -> np.ndarray:
    """How far (m) a reading at ``depth_m`` (any shape) may lie from the map's surface and still be
    the same surface: ``max(CONFLICT_MIN_M, CONFLICT_SIGMAS * sigma_z)``."""
    return np.maximum(CONFLICT_MIN_M, CONFLICT_SIGMAS * depth_sigma_m(depth_m))


def map_depth_on_rays(model, points_cam: np.ndarray, T_world_cam: np.ndarray,
                      camera: CameraIntrinsics) -> np.ndarray:
    """``[M]`` depth (m) of the map ``model``'s first surface (a
    :class:`~atlas_pipeline.localization.tracker.SurfelModel` rendered at ``T_world_cam [4, 4]``)
    on the ray of each camera-frame point ``[M, 3]``; NaN where the map has no surface there."""
    from atlas_pipeline.localization.tracker import _level_K

    pts = np.asarray(points_cam, np.float64)
    zm = np.full(len(pts), np.nan)
    if len(model) == 0 or len(pts) == 0:
        return zm
    view, _ = model.render(T_world_cam, camera, CONFLICT_LEVEL)
    z_map = view[..., 2]  # [h, w], NaN where the map has nothing
    h, w = z_map.shape
    fx, fy, cx, cy = _level_K(camera, CONFLICT_LEVEL)
    z = pts[:, 2]
    front = z > 0
    u = np.full(len(pts), -1, np.int64)
    v = np.full(len(pts), -1, np.int64)
    u[front] = np.floor(fx * pts[front, 0] / z[front] + cx + 0.5).astype(np.int64)
    v[front] = np.floor(fy * pts[front, 1] / z[front] + cy + 0.5).astype(np.int64)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    zm[inside] = z_map[v[inside], u[inside]]
    return zm


def point_relation(model, points_cam: np.ndarray, T_world_cam: np.ndarray,
                   camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """``(unmapped [M], conflicting [M])`` bool for the camera-frame points ``[M, 3]`` of a frame
    at ``T_world_cam [4, 4]`` against the map ``model`` (a
    :class:`~atlas_pipeline.localization.tracker.SurfelModel`): no surface of the map on the
    point's ray; a surface there, nearer or farther than :func:`conflict_tolerance_m` allows.
    Points in neither set lie on a surface the map holds."""
    z = np.asarray(points_cam, np.float64).reshape(-1, 3)[:, 2]
    zm = map_depth_on_rays(model, points_cam, T_world_cam, camera)
    unmapped = ~np.isfinite(zm)
    conflicting = np.zeros(len(z), bool)
    seen = ~unmapped
    conflicting[seen] = np.abs(z[seen] - zm[seen]) > conflict_tolerance_m(z[seen])
    return unmapped, conflicting


def disagreeing_points(model, points_cam: np.ndarray, T_world_cam: np.ndarray,
                       camera: CameraIntrinsics) -> np.ndarray:
    """``[M]`` bool: the camera-frame points ``[M, 3]`` of a frame at ``T_world_cam [4, 4]`` that the
    map ``model`` (a :class:`~atlas_pipeline.localization.tracker.SurfelModel`) contradicts: it has
    a surface on the point's ray, nearer or farther than :func:`conflict_tolerance_m` allows."""
    return point_relation(model, points_cam, T_world_cam, camera)[1]


def agreeing_points(model, points_cam: np.ndarray, colours: np.ndarray, T_world_cam: np.ndarray,
                    camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, int]:
    """``(points [K, 3], colours [K, 3], n_left_out)``: the keyframe's ``points_cam [M, 3]`` and
    ``colours [M, 3]`` that :func:`disagreeing_points` does not mark, the ones to merge."""
    agree = ~disagreeing_points(model, points_cam, T_world_cam, camera)
    return points_cam[agree], colours[agree], int(len(agree) - agree.sum())

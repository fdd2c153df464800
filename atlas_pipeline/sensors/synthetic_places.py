"""A larger synthetic place: a suite of three rooms joined by doors, and routes through it.

The room of :mod:`atlas_pipeline.sensors.synthetic` is small enough that every frame sees most of
the map. Persistence fails on places larger than a view: drift builds up between revisits, the
map outgrows the camera's frustum, and a second visit enters on another path. This module builds
that place for :class:`~atlas_pipeline.sensors.synthetic.SyntheticSpec` ``place="suite"``:

* the box ``[-6, 6] x [-2.5, 2.5] x [0, 3]`` split by two partition walls at ``x = -2`` and
  ``x = 2``, each with a full-height door ``DOOR_HALF_WIDTH_M`` either side of ``y = 0``: rooms
  A (west), B (middle) and C (east), 4 m x 5 m each, with a few objects per room;
* routes (``spec.route``) as closed or open Catmull-Rom curves through waypoints at walking
  height, travelled at constant speed (``spec.suite_speed_m_per_s``, or the whole route over the
  recording), the camera looking along the route with slow yaw sweeps and a slight downward
  pitch. Route 0 tours A, B, C and back through B into A, ending where it started (a loop
  closure after ~25 m); route 1 is a *second visit*: it enters at C and crosses the suite the
  other way, lower, so it sees the same surfaces from other viewpoints.

Everything is a pure function of the spec (scalar math and fixed-order NumPy), so datasets stay
byte-identical from run to run.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from atlas_pipeline.geometry import look_at

__all__ = ["SUITE_MIN", "SUITE_MAX", "SUITE_ROUTES", "build_suite_scene", "suite_path", "route_length_m"]

SUITE_MIN = np.array([-6.0, -2.5, 0.0])
SUITE_MAX = np.array([6.0, 2.5, 3.0])
PARTITION_X_M = (-2.0, 2.0)
PARTITION_HALF_THICKNESS_M = 0.06
DOOR_HALF_WIDTH_M = 0.7
ROOM_CENTRES_X_M = (-4.0, 0.0, 4.0)
OBJECTS_PER_ROOM = 3
# Objects keep this far (horizontally, beyond their footprint) from every route of the suite, so
# no route's camera comes closer than about half a metre to a surface.
ROUTE_CLEARANCE_M = 0.7

# Waypoints (x, y) m, heights m, closed or open. Route 0: A, along B's south side, around C, back
# along B's north side into A (closed: the recording ends where it began). Route 1: from C's
# north-east corner west through B, around A, and back into B (open), lower.
SUITE_ROUTES: dict[int, dict] = {
    0: {"closed": True, "height_m": 1.35, "points": (
        (-4.0, -1.2), (-5.0, 0.0), (-4.0, 1.3), (-3.0, 0.6), (-2.0, 0.0), (-1.0, -0.6), (0.0, -1.3),
        (1.0, -0.6), (2.0, 0.0), (3.0, 0.6), (4.0, 1.3), (5.0, 0.0), (4.0, -1.3), (3.0, -0.6), (2.0, 0.0),
        (1.0, 0.6), (0.0, 1.3), (-1.0, 0.6), (-2.0, 0.0), (-3.0, -0.6))},
    1: {"closed": False, "height_m": 1.15, "points": (
        (4.6, 1.4), (4.9, -0.2), (3.6, -1.2), (2.8, -0.3), (2.0, 0.0), (1.0, 0.2), (-1.0, -0.2), (-2.0, 0.0),
        (-3.0, 0.5), (-4.4, 1.3), (-5.1, -0.2), (-4.2, -1.4), (-3.0, -0.5), (-2.0, 0.0), (-0.8, 0.8),
        (0.6, 1.2))},
}

_SAMPLES_PER_SEGMENT = 64
_CENTRE_PULL_K = 1.5  # turn towards the room's middle by at most asin(1 / 1.5) = 42 deg
_CENTRE_PULL_FADE_M = 1.0
_ROOM_BLEND_M = 1.0  # width of the blend between two rooms' middles at a door
_YAW_SWEEP_DEG = 20.0  # the camera looks around while walking: left and right of the route
_YAW_SWEEP_PERIOD_S = 7.0
_PITCH_DEG = -10.0  # a held camera points slightly down
_PITCH_WOBBLE_DEG = 5.0
_PITCH_PERIOD_S = 5.3
_BOB_M = 0.03
_BOB_PERIOD_S = 1.1  # one step
_LOOK_AHEAD_M = 0.6  # the heading is the direction to the route point this far ahead (smooth turns)


def _catmull_rom(points: np.ndarray, closed: bool) -> np.ndarray:
    """Dense samples ``[S, 2]`` of the centripetal-free (uniform) Catmull-Rom curve through ``points [P, 2]``."""
    P = np.asarray(points, np.float64)
    if closed:
        ext = np.vstack([P[-1:], P, P[:2]])
        n_seg = len(P)
    else:
        ext = np.vstack([2 * P[0] - P[1], P, 2 * P[-1] - P[-2]])
        n_seg = len(P) - 1
    u = np.arange(_SAMPLES_PER_SEGMENT, dtype=np.float64) / _SAMPLES_PER_SEGMENT
    u2, u3 = u * u, u * u * u
    out = []
    for k in range(n_seg):
        p0, p1, p2, p3 = ext[k], ext[k + 1], ext[k + 2], ext[k + 3]
        seg = 0.5 * ((2 * p1)[None] + (p2 - p0)[None] * u[:, None]
                     + (2 * p0 - 5 * p1 + 4 * p2 - p3)[None] * u2[:, None]
                     + (-p0 + 3 * p1 - 3 * p2 + p3)[None] * u3[:, None])
        out.append(seg)
    out.append((P[0] if closed else P[-1])[None])
    return np.vstack(out)


@lru_cache(maxsize=8)
def _route_table(route: int) -> tuple[np.ndarray, np.ndarray, bool, float]:
    """``(samples [S, 2], cumulative arc length [S], closed, height_m)`` of a route."""
    if route not in SUITE_ROUTES:
        raise ValueError(f"suite route must be one of {sorted(SUITE_ROUTES)}, got {route}")
    r = SUITE_ROUTES[route]
    xy = _catmull_rom(np.array(r["points"]), r["closed"])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    xy.setflags(write=False)
    s.setflags(write=False)
    return xy, s, bool(r["closed"]), float(r["height_m"])


def route_length_m(route: int) -> float:
    """Length (m) of suite route ``route``."""
    return float(_route_table(route)[1][-1])


def _route_point(route: int, s_m: float) -> np.ndarray:
    """``[2]`` position ``s_m`` metres along the route (wrapped when closed, clamped when open)."""
    xy, s, closed, _ = _route_table(route)
    L = float(s[-1])
    s_m = s_m % L if closed else min(max(s_m, 0.0), L)
    return np.array([np.interp(s_m, s, xy[:, 0]), np.interp(s_m, s, xy[:, 1])])


def _room_centre_x(x_m: float) -> float:
    """The x of the middle of the room at ``x_m``, blended smoothly across the doors."""
    w = [math.exp(-((x_m - c) ** 2) / (2.0 * _ROOM_BLEND_M ** 2)) for c in ROOM_CENTRES_X_M]
    return sum(wi * c for wi, c in zip(w, ROOM_CENTRES_X_M)) / sum(w)


def suite_path(route: int, speed_m_per_s: float, t_s: np.ndarray) -> np.ndarray:
    """Camera poses ``T_world_cam [N, 4, 4]`` along suite route ``route`` at times ``t_s [N]``."""
    _, _, _, height = _route_table(route)
    t = np.atleast_1d(np.asarray(t_s, np.float64))
    out = np.empty((len(t), 4, 4))
    for i, ti in enumerate(t):
        ti = float(ti)
        s_m = speed_m_per_s * ti
        p = _route_point(route, s_m)
        ahead = _route_point(route, s_m + _LOOK_AHEAD_M) - _route_point(route, s_m - _LOOK_AHEAD_M)
        heading = math.atan2(ahead[1], ahead[0]) if np.hypot(*ahead) > 1e-9 else 0.0
        # Turned towards the middle of the room it is in (a bounded, smooth function of the
        # bearing d: at most asin(1 / k) off the route, 0 straight ahead or behind), so the
        # view holds the room, not one wall.
        centre = _room_centre_x(float(p[0])) - p[0], -p[1]
        d = math.atan2(centre[1], centre[0]) - heading
        r2 = centre[0] ** 2 + centre[1] ** 2  # the pull fades out near the middle (no bearing there)
        fade = r2 / (r2 + _CENTRE_PULL_FADE_M ** 2)
        yaw = (heading + fade * math.atan2(math.sin(d), math.cos(d) + _CENTRE_PULL_K)
               + math.radians(_YAW_SWEEP_DEG) * math.sin(2.0 * math.pi * ti / _YAW_SWEEP_PERIOD_S))
        pitch = math.radians(_PITCH_DEG + _PITCH_WOBBLE_DEG * math.sin(2.0 * math.pi * ti / _PITCH_PERIOD_S))
        eye = np.array([p[0], p[1], height + _BOB_M * math.sin(2.0 * math.pi * ti / _BOB_PERIOD_S)])
        fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
        out[i] = look_at(eye, eye + fwd, up=(0.0, 0.0, 1.0))
    return out


def _route_clearance_m(xy: np.ndarray) -> float:
    """Horizontal distance (m) from ``xy [2]`` to the nearest point of any suite route."""
    return min(float(np.min(np.hypot(*(_route_table(r)[0] - xy).T))) for r in SUITE_ROUTES)


def build_suite_scene(seed: int):
    """The suite (module docstring) with ``OBJECTS_PER_ROOM`` objects per room placed from ``seed``."""
    from atlas_pipeline.sensors.synthetic_scene import _N_ROOM_SURFACES, SceneObject, textured_scene

    rng = np.random.default_rng([seed, 0x5117E])
    objects: list[SceneObject] = []
    # Partition walls: two boxes per wall, either side of the door.
    half_len = (SUITE_MAX[1] - DOOR_HALF_WIDTH_M) / 2.0
    half_z = (SUITE_MAX[2] - SUITE_MIN[2]) / 2.0
    for x in PARTITION_X_M:
        for sgn in (-1.0, 1.0):
            centre = np.array([x, sgn * (DOOR_HALF_WIDTH_M + half_len), half_z])
            half = np.array([PARTITION_HALF_THICKNESS_M, half_len, half_z])
            objects.append(SceneObject("box", centre, half, _N_ROOM_SURFACES + len(objects)))
    walls = tuple(o.surface_id for o in objects)
    placed: list[tuple[np.ndarray, float]] = []
    for cx in ROOM_CENTRES_X_M:
        kinds = [str(k) for k in rng.permutation(["box", "sphere", "cylinder"])][:OBJECTS_PER_ROOM]
        for kind in kinds:
            for _attempt in range(500):
                if kind == "box":
                    half = np.array([rng.uniform(0.2, 0.4), rng.uniform(0.2, 0.35), rng.uniform(0.2, 0.6)])
                elif kind == "sphere":
                    r = rng.uniform(0.2, 0.35)
                    half = np.array([r, r, r])
                else:
                    r = rng.uniform(0.12, 0.25)
                    half = np.array([r, r, rng.uniform(0.3, 0.7)])
                xy = np.array([cx + rng.uniform(-1.5, 1.5), rng.uniform(-2.0, 2.0)])
                fr = float(np.hypot(half[0], half[1])) if kind == "box" else float(half[0])
                inside = (abs(xy[0] - cx) + fr < 1.85) and (abs(xy[1]) + fr < 2.4)
                if not inside or any(np.linalg.norm(xy - q) < fr + qr + 0.2 for q, qr in placed):
                    continue
                if _route_clearance_m(xy) < fr + ROUTE_CLEARANCE_M:
                    continue
                break
            else:
                continue  # no room left for this one: the scene has one object fewer
            placed.append((xy, fr))
            objects.append(SceneObject(kind, np.array([xy[0], xy[1], half[2]]), half,
                                       _N_ROOM_SURFACES + len(objects)))
    return textured_scene(seed, rng, objects, SUITE_MIN, SUITE_MAX, flat_ids=walls)

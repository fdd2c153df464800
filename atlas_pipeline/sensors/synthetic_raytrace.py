"""The synthetic ray tracer: per-pixel rays against the room box and its objects, colour and depth
of one view (and the layers the sensor model reads).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from atlas_pipeline.sensors.synthetic_kinect import _SHINY_KINDS
from atlas_pipeline.sensors.synthetic_scene import (
    _SID_CEILING, _SID_FLOOR, _SID_WALL_XMAX, _SID_WALL_XMIN, _SID_WALL_YMAX, _SID_WALL_YMIN,
)
from atlas_pipeline.sensors.synthetic_textures import _EPS_T, _albedo, _shade

if TYPE_CHECKING:
    from atlas_pipeline.sensors.synthetic_scene import SceneObject, SyntheticScene
    from atlas_pipeline.sensors.synthetic_spec import SyntheticSpec

__all__ = ["render_synthetic_frame"]


@lru_cache(maxsize=8)
def _pixel_rays(width: int, height: int, fx: float, fy: float, cx: float, cy: float):
    """Camera-frame ray directions with unit z: ``(x [H*W], y [H*W])`` float64.

    With ``d_cam = (x, y, 1)`` the ray parameter of a hit equals its camera z (depth).
    """
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    x = np.broadcast_to((u - cx) / fx, (height, width)).ravel()
    y = np.broadcast_to(((v - cy) / fy)[:, None], (height, width)).ravel()
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y


def _safe_inv(d: np.ndarray) -> np.ndarray:
    # Rays parallel to a slab: a huge finite inverse avoids 0 * inf = nan in the slab test.
    return 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)


def _slab(o: np.ndarray, inv: tuple, lo: np.ndarray, hi: np.ndarray):
    """Ray/AABB slab test: (t_near [N], t_far [N]) for rays ``o + t d``, ``inv = 1 / d``."""
    t_near = None
    t_far = None
    for a in range(3):
        t1 = (lo[a] - o[a]) * inv[a]
        t2 = (hi[a] - o[a]) * inv[a]
        lo_t = np.minimum(t1, t2)
        hi_t = np.maximum(t1, t2)
        t_near = lo_t if t_near is None else np.maximum(t_near, lo_t)
        t_far = hi_t if t_far is None else np.minimum(t_far, hi_t)
    return t_near, t_far


def _intersect_object(obj: SceneObject, o: np.ndarray, d: tuple, inv: tuple) -> np.ndarray:
    """Hit parameter ``t`` ``[N]`` of each ray with the object, ``inf`` where it misses."""
    c, h = obj.centre, obj.half_size
    if obj.kind == "box":
        t_near, t_far = _slab(o, inv, c - h, c + h)
        return np.where((t_near <= t_far) & (t_near > _EPS_T), t_near, np.inf)
    if obj.kind == "sphere":
        oc = o - c
        a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
        cc = float(oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2]) - h[0] * h[0]
        disc = b * b - a * cc
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        return np.where((disc > 0.0) & (t > _EPS_T), t, np.inf)
    # Vertical cylinder: side (quadratic in xy, z within range) and the two flat caps.
    oc = o - c
    a = d[0] * d[0] + d[1] * d[1]
    b = oc[0] * d[0] + oc[1] * d[1]
    cc = oc[0] * oc[0] + oc[1] * oc[1] - h[0] * h[0]
    disc = b * b - a * cc
    a_safe = np.where(a > 1e-12, a, 1.0)
    t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a_safe
    z_side = oc[2] + t_side * d[2]
    ok_side = (disc > 0.0) & (a > 1e-12) & (t_side > _EPS_T) & (np.abs(z_side) <= h[2])
    t = np.where(ok_side, t_side, np.inf)
    r2 = h[0] * h[0]
    for zc in (h[2], -h[2]):
        t_cap = (zc - oc[2]) * inv[2]
        px = oc[0] + t_cap * d[0]
        py = oc[1] + t_cap * d[1]
        ok = (t_cap > _EPS_T) & (px * px + py * py <= r2)
        t = np.minimum(t, np.where(ok, t_cap, np.inf))
    return t


def _surface_normals(
    scene: SyntheticScene, P: np.ndarray, prim: np.ndarray, room_axis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``[N, 3]`` (facing free space) and surface ids ``[N]`` of hit points ``[N, 3]``.

    Points on flat faces are snapped exactly onto their plane (in place), so rounding in
    ``o + t d`` cannot flip checker cells from pixel to pixel.
    """
    N = P.shape[0]
    nrm = np.zeros((N, 3), dtype=np.float64)
    sid = np.zeros(N, dtype=np.int64)

    m = np.flatnonzero(prim == 0)  # room interior; room_axis = 0..2 (min wall) or 3..5 (max wall)
    if m.size:
        k = room_axis[m]
        axis = k % 3
        is_min = k < 3
        nrm[m, axis] = np.where(is_min, 1.0, -1.0)
        P[m, axis] = np.where(is_min, scene.room_min[axis], scene.room_max[axis])
        sid_lut = np.array(
            [_SID_WALL_XMIN, _SID_WALL_YMIN, _SID_FLOOR,
             _SID_WALL_XMAX, _SID_WALL_YMAX, _SID_CEILING]
        )
        sid[m] = sid_lut[k]

    for j, obj in enumerate(scene.objects, start=1):
        m = np.flatnonzero(prim == j)
        if not m.size:
            continue
        c, h = obj.centre, obj.half_size
        Q = P[m] - c
        if obj.kind == "box":
            axis = np.argmax(np.abs(Q) / h, axis=1)  # the face hit: relatively farthest axis
            sgn = np.sign(Q[np.arange(m.size), axis])
            nrm[m, axis] = sgn
            P[m, axis] = c[axis] + sgn * h[axis]
        elif obj.kind == "sphere":
            nrm[m] = Q / np.sqrt(Q[:, 0] * Q[:, 0] + Q[:, 1] * Q[:, 1] + Q[:, 2] * Q[:, 2])[:, None]
        else:
            radial = np.sqrt(Q[:, 0] * Q[:, 0] + Q[:, 1] * Q[:, 1])
            cap = np.abs(np.abs(Q[:, 2]) - h[2]) < np.abs(radial - h[0])
            rs = np.where(radial > 1e-12, radial, 1.0)
            n_obj = np.zeros_like(Q)
            n_obj[:, 0] = np.where(cap, 0.0, Q[:, 0] / rs)
            n_obj[:, 1] = np.where(cap, 0.0, Q[:, 1] / rs)
            n_obj[:, 2] = np.where(cap, np.sign(Q[:, 2]), 0.0)
            nrm[m] = n_obj
            P[m, 2] = np.where(cap, c[2] + np.sign(Q[:, 2]) * h[2], P[m, 2])
        sid[m] = obj.surface_id
    return nrm, sid


def _screen_rect(
    obj: SceneObject, R: np.ndarray, o: np.ndarray, spec: SyntheticSpec
) -> tuple[slice, slice] | None:
    """Pixel rectangle ``(rows, cols)`` containing the object's image; None if it cannot be seen.

    The object lies inside its bounding box, so (with every corner in front of the camera) the
    projections of the 8 corners bound its image. A 2-pixel margin absorbs rounding.
    """
    H, W = spec.height, spec.width
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    rel = obj.centre + signs * obj.half_size - o  # [8, 3] corners relative to the camera
    # Camera coordinates p_cam = R^T (p - o), written out elementwise (no BLAS).
    pc = [rel[:, 0] * R[0, k] + rel[:, 1] * R[1, k] + rel[:, 2] * R[2, k] for k in range(3)]
    z = pc[2]
    if np.all(z <= 0.0):
        return None  # wholly behind the camera: hits need camera z = t > 0
    if np.any(z < 1e-3):
        return slice(0, H), slice(0, W)  # straddles the image plane: test every ray
    u = spec.fx * pc[0] / z + spec.cx
    v = spec.fy * pc[1] / z + spec.cy
    u0, u1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 3, W)
    v0, v1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 3, H)
    if u0 >= u1 or v0 >= v1:
        return None
    return slice(v0, v1), slice(u0, u1)


def _trace(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray):
    """Nearest hit of every pixel's ray.

    Returns ``(idx [M], t [M], d, nrm [M, 3], sid [M], col [M, 3])``: flat indices of the pixels
    with a hit, their ray parameter (= camera z), the world ray directions ``d`` (3 arrays
    ``[H*W]``, camera z = 1), unit normals, surface ids and shaded colour (float32, unclipped).
    """
    H, W = spec.height, spec.width
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_cam must be [4, 4], got {T.shape}")
    xc, yc = _pixel_rays(W, H, float(spec.fx), float(spec.fy), float(spec.cx), float(spec.cy))
    R = T[:3, :3]
    o = T[:3, 3].copy()
    # World directions of d_cam = (x, y, 1): elementwise so results are bitwise reproducible.
    d = tuple(xc * R[a, 0] + yc * R[a, 1] + R[a, 2] for a in range(3))
    inv = tuple(_safe_inv(da) for da in d)

    # The room box seen from inside: every ray leaves it through the nearest exit plane.
    t_best = None
    room_axis = None
    for a in range(3):
        pos = inv[a] > 0  # heading to the max wall (sign of the safe inverse: d = 0 counts as +)
        t_a = np.where(pos, scene.room_max[a] - o[a], scene.room_min[a] - o[a]) * inv[a]
        k_a = np.where(pos, a + 3, a)
        if t_best is None:
            t_best, room_axis = t_a, k_a
        else:
            nearer = t_a < t_best
            t_best = np.where(nearer, t_a, t_best)
            room_axis = np.where(nearer, k_a, room_axis)
    t_best = np.where(t_best > _EPS_T, t_best, np.inf)  # camera outside the room: no room hit
    prim = np.zeros(t_best.shape, dtype=np.int64)
    t2, prim2 = t_best.reshape(H, W), prim.reshape(H, W)  # views for per-object rectangles
    for j, obj in enumerate(scene.objects, start=1):
        rect = _screen_rect(obj, R, o, spec)
        if rect is None:
            continue
        # Only rays inside the object's image rectangle can hit it: same result, less work.
        d_r = tuple(da.reshape(H, W)[rect].ravel() for da in d)
        inv_r = tuple(ia.reshape(H, W)[rect].ravel() for ia in inv)
        tb = t2[rect]
        t = _intersect_object(obj, o, d_r, inv_r).reshape(tb.shape)
        closer = t < tb
        t2[rect] = np.where(closer, t, tb)
        prim2[rect][closer] = j

    hit = np.isfinite(t_best)
    idx = np.flatnonzero(hit)
    th = t_best[idx]
    P = np.stack([o[a] + th * d[a][idx] for a in range(3)], axis=1)  # [M, 3] world points
    nrm, sid = _surface_normals(scene, P, prim[idx], room_axis[idx])
    col = _albedo(scene, P, sid) * _shade(nrm)[:, None]
    if spec.light_level != 1.0:
        col = col * np.float32(spec.light_level)
    return idx, th, d, nrm, sid, col


def render_synthetic_frame(
    spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast one RGB-D frame from ``T_world_cam`` ``[4, 4]`` (camera inside the room).

    Returns:
        ``(rgb, depth_m)``: ``rgb`` uint8 ``[H, W, 3]``; ``depth_m`` float32 ``[H, W]``, the camera
        z of the hit (not the ray length), 0 where there is no hit or the hit is farther than
        ``spec.max_depth_m``. Colour and depth come from the same nearest hit per pixel, whose
        centre is at integer pixel coordinates. An ideal sensor: no noise, blur or dropouts.
    """
    H, W = spec.height, spec.width
    idx, th, _d, _nrm, _sid, col = _trace(spec, scene, T_world_cam)
    rgb = np.zeros((H * W, 3), dtype=np.uint8)
    depth = np.zeros(H * W, dtype=np.float32)
    if idx.size:
        rgb[idx] = np.round(np.clip(col, 0.0, 1.0) * 255.0).astype(np.uint8)
        # d_cam has z = 1, so t is the camera-frame depth directly.
        depth[idx] = np.where(th <= spec.max_depth_m, th, 0.0).astype(np.float32)
    return rgb.reshape(H, W, 3), depth.reshape(H, W)


@dataclass
class _Layers:
    """What the sensor model needs from one render (all ``[H, W]`` unless noted).

    Attributes:
        col: ``[H, W, 3]`` float32 shaded colour in [0, ~1.1] (unclipped), 0 where no hit.
        depth_m: float32 camera z, 0 where no hit or beyond ``max_depth_m``.
        cos_incidence: float32 cosine of the angle between the ray and the surface normal.
        shiny: bool, the pixel shows a glossy surface (:data:`_SHINY_KINDS`).
    """

    col: np.ndarray
    depth_m: np.ndarray
    cos_incidence: np.ndarray
    shiny: np.ndarray


def _render_colour(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray) -> np.ndarray:
    """Unclipped float32 colour ``[H, W, 3]`` (a motion-blur sub-frame)."""
    H, W = spec.height, spec.width
    idx, _th, _d, _nrm, _sid, col = _trace(spec, scene, T_world_cam)
    out = np.zeros((H * W, 3), dtype=np.float32)
    out[idx] = col
    return out.reshape(H, W, 3)


def _render_layers(spec: SyntheticSpec, scene: SyntheticScene, T_world_cam: np.ndarray) -> _Layers:
    H, W = spec.height, spec.width
    idx, th, d, nrm, sid, col = _trace(spec, scene, T_world_cam)
    out_col = np.zeros((H * W, 3), dtype=np.float32)
    depth = np.zeros(H * W, dtype=np.float32)
    cos_inc = np.zeros(H * W, dtype=np.float32)
    shiny = np.zeros(H * W, dtype=bool)
    if idx.size:
        out_col[idx] = col
        depth[idx] = np.where(th <= spec.max_depth_m, th, 0.0).astype(np.float32)
        dx, dy, dz = d[0][idx], d[1][idx], d[2][idx]
        dn = dx * nrm[:, 0] + dy * nrm[:, 1] + dz * nrm[:, 2]
        cos_inc[idx] = np.clip(-dn / np.sqrt(dx * dx + dy * dy + dz * dz), 0.0, 1.0)
        shiny_ids = [o.surface_id for o in scene.objects if o.kind in _SHINY_KINDS]
        shiny[idx] = np.isin(sid, shiny_ids)
    return _Layers(out_col.reshape(H, W, 3), depth.reshape(H, W), cos_inc.reshape(H, W),
                   shiny.reshape(H, W))

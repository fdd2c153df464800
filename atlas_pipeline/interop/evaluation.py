"""How close a mesh and an occupancy grid are to the synthetic room, whose geometry is known exactly
(``sensors.synthetic``: the room box, the boxes, spheres and vertical cylinders standing on the
floor).

* Mesh: the Chamfer distance between the mesh's vertices and the true surfaces the keyframes saw.
  *Accuracy*: the mean exact distance from each vertex to the nearest true surface (analytic).
  *Completeness*: the mean distance from points on the true surfaces, ray-cast from the keyframes'
  ground-truth poses (every ``TRUTH_STRIDE_PX``-th pixel), to the mesh's surface. The Chamfer
  distance is their mean. Surfaces no keyframe saw are no part of either.
* Occupancy: the true floor plan on the grid's cells: occupied where a cell touches an object's
  footprint or lies outside the room's walls, free elsewhere in the room; compared on the cells the
  keyframes observed (ray-cast from their ground-truth poses: a floor or obstacle hit in the cell,
  or a ray through the obstacle band over it). IoU per class and the share of cells whose state
  agrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["surface_distance_m", "visible_surface_points", "mesh_chamfer", "surface_samples", "MeshFigures", "floor_plan_truth",
           "occupancy_figures", "OccupancyFigures", "TRUTH_STRIDE_PX"]

SURFACE_SUBDIVISIONS = 4  # 15 points per triangle: ~3 mm apart on a 2 cm mesh
TRUTH_STRIDE_PX = 2  # truth points from every 2nd pixel in u and v: ~5 mm apart at 2 m, denser than the mesh


def _inside_distance(kind: str, c: np.ndarray, h: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Signed distance ``[N]`` of points ``[N, 3]`` to an object's surface: > 0 outside, < 0 inside."""
    d = p - c
    if kind == "box":
        q = np.abs(d) - h
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return outside + np.minimum(q.max(axis=1), 0.0)
    if kind == "sphere":
        return np.linalg.norm(d, axis=1) - h[0]
    radial = np.linalg.norm(d[:, :2], axis=1) - h[0]
    axial = np.abs(d[:, 2]) - h[2]
    q = np.stack([radial, axial], axis=1)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def surface_distance_m(scene, points: np.ndarray) -> np.ndarray:
    """Exact distance ``[N]`` from points ``[N, 3]`` to the nearest surface of ``scene`` (a
    ``SyntheticScene``): the room's walls, floor and ceiling, and every object's surface."""
    p = np.atleast_2d(np.asarray(points, np.float64))
    lo, hi = np.asarray(scene.room_min, np.float64), np.asarray(scene.room_max, np.float64)
    room = -_inside_distance("box", (lo + hi) / 2, (hi - lo) / 2, p)  # > 0 inside the room
    d = np.abs(room)
    for obj in scene.objects:
        d = np.minimum(d, np.abs(_inside_distance(obj.kind, np.asarray(obj.centre, np.float64),
                                                  np.asarray(obj.half_size, np.float64), p)))
    return d


def visible_surface_points(spec, scene, T_world_cam: np.ndarray, stride: int = TRUTH_STRIDE_PX) -> np.ndarray:
    """``[M, 3]`` world points of the true surfaces seen from each ``T_world_cam`` (``[K, 4, 4]``),
    ray-cast exactly (``render_synthetic_frame``: an ideal sensor), every ``stride``-th pixel."""
    from atlas_pipeline.sensors.synthetic import render_synthetic_frame

    out = []
    v, u = np.mgrid[0:spec.height:stride, 0:spec.width:stride]
    for T in np.asarray(T_world_cam, np.float64):
        _, depth = render_synthetic_frame(spec, scene, T)
        z = depth[v, u].astype(np.float64)
        ok = z > 0
        p_cam = np.stack([(u[ok] - spec.cx) / spec.fx * z[ok], (v[ok] - spec.cy) / spec.fy * z[ok], z[ok]], axis=1)
        out.append(p_cam @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


@dataclass
class MeshFigures:
    accuracy_m: float  # mean distance, mesh vertices -> true surfaces
    completeness_m: float  # mean distance, seen true surface points -> mesh
    chamfer_m: float  # their mean
    accuracy_p90_m: float
    completeness_p90_m: float
    n_vertices: int
    n_truth_points: int


def surface_samples(vertices: np.ndarray, triangles: np.ndarray, subdivisions: int = SURFACE_SUBDIVISIONS) -> np.ndarray:
    """``[T * (s+1)(s+2)/2, 3]`` points on a regular barycentric grid of every triangle (``s`` =
    ``subdivisions``): the mesh's surface, not only its vertices (at 2 cm voxels the vertices are
    ~1 cm apart, which alone would add ~5 mm to any completeness figure)."""
    s = subdivisions
    a, b = np.meshgrid(np.arange(s + 1), np.arange(s + 1), indexing="ij")
    keep = a + b <= s
    w = np.stack([a[keep], b[keep], s - a[keep] - b[keep]], axis=1) / s  # [S, 3] barycentric weights
    tri = np.asarray(vertices, np.float64)[np.asarray(triangles)]  # [T, 3, 3]
    return np.einsum("sk,tkd->tsd", w, tri).reshape(-1, 3)


def mesh_chamfer(vertices: np.ndarray, triangles: np.ndarray, scene, truth_points: np.ndarray) -> MeshFigures:
    """Accuracy, completeness and Chamfer distance of a mesh (``vertices`` ``[V, 3]``,
    ``triangles`` ``[T, 3]``) against ``scene``'s true surfaces and the seen ``truth_points``
    ``[M, 3]`` (accuracy from the vertices to the analytic surfaces; completeness from the truth
    points to the nearest point of the mesh's surface, sampled by :func:`surface_samples`)."""
    from scipy.spatial import cKDTree

    acc = surface_distance_m(scene, vertices)
    comp, _ = cKDTree(surface_samples(vertices, triangles)).query(truth_points, workers=-1)
    return MeshFigures(float(acc.mean()), float(comp.mean()), float((acc.mean() + comp.mean()) / 2),
                       float(np.percentile(acc, 90)), float(np.percentile(comp, 90)), len(vertices), len(truth_points))


def floor_plan_truth(scene, origin_xy: np.ndarray, resolution_m: float, shape: tuple[int, int],
                     band_m: tuple[float, float]) -> np.ndarray:
    """``[H, W]`` bool, True where the cell (row 0 at ``origin_xy[1]``, column 0 at ``origin_xy[0]``,
    ``resolution_m`` wide) touches an object's footprint within the height band ``band_m`` (above
    the floor at z = 0) or reaches outside the room's walls."""
    h, w = shape
    x0 = origin_xy[0] + np.arange(w) * resolution_m
    y0 = origin_xy[1] + np.arange(h) * resolution_m
    X0, Y0 = np.meshgrid(x0, y0)
    X1, Y1 = X0 + resolution_m, Y0 + resolution_m
    lo, hi = scene.room_min, scene.room_max
    occ = (X0 < lo[0]) | (X1 > hi[0]) | (Y0 < lo[1]) | (Y1 > hi[1])
    for obj in scene.objects:
        c, hs = np.asarray(obj.centre, np.float64), np.asarray(obj.half_size, np.float64)
        if obj.kind == "sphere":
            # the widest horizontal section within the band
            zc = np.clip(c[2], band_m[0], band_m[1])
            r = np.sqrt(max(hs[0] ** 2 - (zc - c[2]) ** 2, 0.0))
        else:
            if c[2] + hs[2] < band_m[0] or c[2] - hs[2] > band_m[1]:
                continue
            r = hs[0]
        # nearest point of each cell to the footprint's centre
        nx, ny = np.clip(c[0], X0, X1), np.clip(c[1], Y0, Y1)
        if obj.kind == "box":
            occ |= (np.abs(nx - c[0]) <= hs[0]) & (np.abs(ny - c[1]) <= hs[1])
        else:
            occ |= np.hypot(nx - c[0], ny - c[1]) <= r
    return occ


@dataclass
class OccupancyFigures:
    iou_free: float
    iou_occupied: float
    agreement: float  # share of the observed cells whose state (free / occupied) matches
    n_observed_cells: int
    unknown_share: float  # observed cells the map leaves unknown


def occupancy_figures(state: np.ndarray, truth_occupied: np.ndarray, observed: np.ndarray) -> OccupancyFigures:
    """Compare the map's ``state`` ``[H, W]`` (0 free, 100 occupied, -1 unknown: ROS's values) with
    ``truth_occupied`` ``[H, W]`` bool on the ``observed`` ``[H, W]`` cells."""
    pf, po = (state == 0) & observed, (state == 100) & observed
    tf, to = ~truth_occupied & observed, truth_occupied & observed

    def iou(a: np.ndarray, b: np.ndarray) -> float:
        union = (a | b).sum()
        return float((a & b).sum() / union) if union else 1.0

    n = int(observed.sum())
    agree = float(((pf & tf) | (po & to)).sum() / n) if n else 1.0
    return OccupancyFigures(iou(pf, tf), iou(po, to), agree, n,
                            float((observed & (state == -1)).sum() / n) if n else 0.0)


def observed_cells(spec, scene, T_world_cam: np.ndarray, grid, band_m: tuple[float, float]) -> np.ndarray:
    """``[H, W]`` bool: the cells of ``grid`` (map frame = world frame, floor at z = 0) that the
    cameras ``[K, 4, 4]`` saw, from exact ray-cast depth: the same evidence as the map's
    (:func:`atlas_pipeline.interop.occupancy.grid_evidence`), without the sensor."""
    from atlas_pipeline.interop.occupancy import HIT_STRIDE_PX, RAY_STRIDE_PX, grid_evidence
    from atlas_pipeline.sensors.synthetic import render_synthetic_frame

    def frames(stride: int) -> list[tuple[np.ndarray, np.ndarray]]:
        v, u = np.mgrid[0:spec.height:stride, 0:spec.width:stride]
        out = []
        for T, depth in zip(Ts, depths):
            z = depth[v, u].astype(np.float64)
            ok = z > 0
            p = np.stack([(u[ok] - spec.cx) / spec.fx * z[ok], (v[ok] - spec.cy) / spec.fy * z[ok], z[ok]], axis=1)
            out.append((T[:3, 3], p @ T[:3, :3].T + T[:3, 3]))
        return out

    Ts = np.asarray(T_world_cam, np.float64)
    depths = [render_synthetic_frame(spec, scene, T)[1] for T in Ts]
    hits, seen = grid_evidence(frames(HIT_STRIDE_PX), frames(RAY_STRIDE_PX), grid, band_m)
    return seen | (hits > 0)

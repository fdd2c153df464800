"""The camera-path planner's occupancy grid of a Gaussian world: ray casting and clearance."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from atlas_pipeline.viz.camera_path_settings import DEFAULT_SETTINGS, CameraPathSettings

__all__ = ["Occupancy", "build_occupancy"]


@dataclass
class Occupancy:
    """A boolean voxel grid of the map, with ray casting and clearance queries.

    Attributes:
        origin_world: ``[3]`` corner of voxel (0, 0, 0).
        voxel_m: edge length of a voxel (metres).
        occupied: ``[X, Y, Z]`` bool, dilated occupancy.
        box_min, box_max: ``[3]`` box a camera centre must stay in (map and keyframes).
        tree: KD-tree of the occupying means (clearance queries).
    """

    origin_world: np.ndarray
    voxel_m: float
    occupied: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    tree: cKDTree | None

    def is_occupied(self, points_world: np.ndarray) -> np.ndarray:
        """``[...]`` bool for points ``[..., 3]``; outside the grid counts as free."""
        p = np.asarray(points_world, dtype=np.float64)
        ijk = np.floor((p - self.origin_world) / self.voxel_m).astype(np.int64)
        shape = np.array(self.occupied.shape)
        inside = np.all((ijk >= 0) & (ijk < shape), axis=-1)
        ijk = np.where(inside[..., None], ijk, 0)
        flat = (ijk[..., 0] * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]
        return inside & self.occupied.ravel()[flat]

    def clearance_m(self, points_world: np.ndarray) -> np.ndarray:
        """``[N]`` distance from points ``[N, 3]`` to the nearest occupying mean (inf: empty map)."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if self.tree is None:
            return np.full(len(p), np.inf)
        d, _ = self.tree.query(p)
        return np.asarray(d, dtype=np.float64)

    def in_box(self, points_world: np.ndarray) -> np.ndarray:
        p = np.asarray(points_world, dtype=np.float64)
        return np.all((p >= self.box_min) & (p <= self.box_max), axis=-1)

    def first_hit_m(self, origins_world: np.ndarray, dirs_world: np.ndarray,
                    max_dist_m: np.ndarray | float) -> np.ndarray:
        """Distance ``[R]`` along unit rays (origins, dirs ``[R, 3]``) to the first occupied voxel
        within ``max_dist_m`` (scalar or ``[R]``); ``inf`` where the ray hits nothing.

        Marches at half a voxel; the first half voxel is skipped (the origin's own cell).
        """
        o = np.asarray(origins_world, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs_world, dtype=np.float64).reshape(-1, 3)
        dmax = np.broadcast_to(np.asarray(max_dist_m, dtype=np.float64), (len(o),))
        out = np.full(len(o), np.inf)
        if len(o) == 0:
            return out
        step = 0.5 * self.voxel_m
        n_steps = int(np.ceil(float(dmax.max()) / step)) if np.isfinite(dmax.max()) else 0
        if n_steps <= 0:
            return out
        t = step * np.arange(1, n_steps + 1)  # [S]
        # Chunks of rays keep the [R, S, 3] sample block to a few tens of MB.
        chunk = max(1, int(2_000_000 // n_steps))
        for a in range(0, len(o), chunk):
            b = min(len(o), a + chunk)
            pts = o[a:b, None, :] + t[None, :, None] * d[a:b, None, :]  # [r, S, 3]
            occ = self.is_occupied(pts) & (t[None, :] <= dmax[a:b, None])  # [r, S]
            hit = occ.any(axis=1)
            first = np.argmax(occ, axis=1)
            out[a:b] = np.where(hit, t[first], np.inf)
        return out


def build_occupancy(positions_world: np.ndarray, opacities: np.ndarray, voxel_size_m: float,
                    extra_points_world: np.ndarray | None = None,
                    cfg: CameraPathSettings = DEFAULT_SETTINGS) -> Occupancy:
    """Occupancy grid of the Gaussian means ``[N, 3]`` (opacities ``[N]``) at about the map voxel.

    ``extra_points_world`` ``[M, 3]`` (the keyframe centres) are kept inside the grid and the box.
    """
    pos = np.asarray(positions_world, dtype=np.float64).reshape(-1, 3)
    op = np.asarray(opacities, dtype=np.float64).reshape(-1)
    pos = pos[(op >= cfg.occ_min_opacity) & np.isfinite(pos).all(axis=1)]
    extra = np.zeros((0, 3)) if extra_points_world is None else np.asarray(extra_points_world, np.float64)
    extra = extra.reshape(-1, 3)
    voxel = float(voxel_size_m)
    if len(pos) == 0:
        lo = extra.min(axis=0) if len(extra) else np.zeros(3)
        hi = extra.max(axis=0) if len(extra) else np.zeros(3)
        return Occupancy(lo - 1.0, 1.0, np.zeros((1, 1, 1), bool), lo - cfg.box_margin_m, hi + cfg.box_margin_m, None)
    lo, hi = np.percentile(pos, cfg.occ_bounds_percentiles, axis=0)
    keep = np.all((pos >= lo) & (pos <= hi), axis=1)
    pos = pos[keep]
    if len(extra):
        lo, hi = np.minimum(lo, extra.min(axis=0)), np.maximum(hi, extra.max(axis=0))
    box_min, box_max = lo - cfg.box_margin_m, hi + cfg.box_margin_m
    if len(pos) > 1:
        rng = np.random.default_rng(0)
        sample = pos if len(pos) <= cfg.occ_spacing_sample else pos[rng.choice(len(pos), cfg.occ_spacing_sample, False)]
        nn, _ = cKDTree(pos).query(sample, k=2)
        voxel = max(voxel, float(np.percentile(nn[:, 1], cfg.occ_spacing_percentile)))
    pad = (cfg.occ_dilate_voxels + 2) * voxel
    origin = lo - pad
    extent = (hi + pad) - origin
    while np.prod(np.ceil(extent / voxel)) > cfg.occ_max_cells:
        voxel *= 1.25
        pad = (cfg.occ_dilate_voxels + 2) * voxel
        origin, extent = lo - pad, (hi + pad) - (lo - pad)
    shape = np.maximum(np.ceil(extent / voxel).astype(np.int64), 1)
    occ = np.zeros(tuple(shape), dtype=bool)
    ijk = np.clip(np.floor((pos - origin) / voxel).astype(np.int64), 0, shape - 1)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    if cfg.occ_dilate_voxels > 0:
        from scipy.ndimage import binary_dilation

        occ = binary_dilation(occ, structure=np.ones((3, 3, 3), bool), iterations=cfg.occ_dilate_voxels)
    return Occupancy(origin, voxel, occ, box_min, box_max, cKDTree(pos))

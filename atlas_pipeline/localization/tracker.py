"""Frame-to-model RGB-D tracking: hybrid geometric + photometric Gauss-Newton, coarse to fine.

Each frame is aligned to two references at once:

* the **model** (geometry): the world's voxel Gaussians as oriented disks (surfels: centre = voxel
  mean, normal = least-variance axis of the voxel's points), splatted into a view at the predicted
  pose. Residual: point-to-plane distance with projective association, as in KinectFusion /
  ElasticFusion. Because the model fuses every keyframe so far, this does not drift the way
  chained frame-to-frame odometry does.
* the **reference frame** (appearance): the last keyframe's intensity image. Residual: intensity
  difference at the point's projection (dense direct alignment, Kerl et al. 2013), which fixes the
  degrees of freedom geometry alone leaves weak (sliding along planes). In a saved world the
  reference is the world itself instead: the colours of its voxels rendered at the guess
  (:func:`map_reference_image`), which, unlike a keyframe of the same session, do not move with
  the camera's own error.

The initial guess comes from a constant-velocity motion model (falling back to the previous pose
when that aligns worse); the solve runs over an image pyramid (coarse levels first, wider
association distances). A frame whose alignment is poor (too few model correspondences, or a large
residual) is *lost*: its pose is a prediction and it is never merged into the map.

Each Gauss-Newton iteration is kiss-icp's ``Registration.cpp`` loop in named steps: ``associate``
and ``build_linear_system`` (Numba kernels, run together chunk by chunk on the process's share of
the cores by :func:`~atlas_pipeline.localization.normal_equations.normal_equations`), then
:func:`solve_update` (damped, trust-region-limited step), :func:`apply_update` and
:func:`converged`. Fixed tuning values are in :mod:`atlas_pipeline.localization.constants`;
per-run settings in ``LocalizationConfig``.

Shapes: ``T_*`` ``[4, 4]`` camera-to-world; ``depth_m`` ``[H, W]`` float32 metres (0 = none);
``rgb`` ``[H, W, 3]`` uint8.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from atlas_pipeline.config import LocalizationConfig
from atlas_pipeline.cores import kernel_threads
from atlas_pipeline.geometry import invert_se3, rotation_angle_rad, so3_exp, so3_log
from atlas_pipeline.localization import _kernels as kn
from atlas_pipeline.localization import _voxel_hash
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as C
from atlas_pipeline.localization.culling import CHUNK_M, MAX_CHUNKS, ChunkGrid, ChunkIndex
from atlas_pipeline.localization.noise_fit import fit_within_noise
from atlas_pipeline.localization.normal_equations import normal_equations
from atlas_pipeline.perception.rgbd import _undistort_normalized
from atlas_pipeline.sensors.camera import CameraIntrinsics

logger = logging.getLogger(__name__)

__all__ = ["FramePyramid", "SurfelModel", "TrackResult", "RGBDTracker", "surfels_from_voxels",
           "solve_update", "apply_update", "converged", "pyramid_levels", "splat_params"]


def pyramid_levels(cfg: LocalizationConfig) -> int:
    """Pyramid levels a tracker with settings ``cfg`` builds (finest level skipped included)."""
    return len(cfg.iterations) + cfg.finest_level


@functools.lru_cache(maxsize=32)
def _level_rays(camera: CameraIntrinsics, level: int) -> np.ndarray:
    """Undistorted rays (z = 1) through the centres of the level-``level`` pixels: ``[h, w, 3]``."""
    s = 2 ** level
    h, w = camera.height // s, camera.width // s
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u = s * u + (s - 1) / 2.0
    v = s * v + (s - 1) / 2.0
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    if camera.distortion:
        x, y = _undistort_normalized(x, y, camera.distortion)
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)
    rays.setflags(write=False)
    return rays


@functools.lru_cache(maxsize=8)
def _checkerboard(shape: tuple[int, int]) -> np.ndarray:
    """``[h, w]`` bool, True where ``u + v`` is even (read-only, shared)."""
    v, u = np.indices(shape)
    m = ((u + v) % 2) == 0
    m.setflags(write=False)
    return m


def _level_K(camera: CameraIntrinsics, level: int) -> tuple[float, float, float, float]:
    """Pinhole intrinsics ``(fx, fy, cx, cy)`` px of pyramid level ``level`` (block-centred pixel grid)."""
    s = 2 ** level
    return camera.fx / s, camera.fy / s, (camera.cx - (s - 1) / 2.0) / s, (camera.cy - (s - 1) / 2.0) / s


def _level_view(T_world_cam: np.ndarray, camera: CameraIntrinsics, level: int) -> kn.PinholeView:
    """The pinhole of pyramid level ``level`` posed at ``T_world_cam`` ``[4, 4]``."""
    s = 2 ** level
    return kn.PinholeView(np.ascontiguousarray(T_world_cam, np.float64), *_level_K(camera, level),
                          camera.width // s, camera.height // s)


def splat_params(radius_m: float, max_depth_m: float = math.inf) -> kn.SplatParams:
    """Splatting limits for disks of ``radius_m`` (``surfel_radius_voxels`` voxels), drawn up to
    ``max_depth_m`` from the camera (inf: all)."""
    voxel_m = radius_m / C.surfel_radius_voxels
    return kn.SplatParams(C.splat_max_radius_px, C.min_view_depth_m, C.splat_min_incidence_cos, C.splat_blend_sigmas,
                          C.splat_blend_floor_voxels * voxel_m, C.depth_noise_a_m, C.depth_noise_b_per_m,
                          C.depth_noise_z0_m, max_depth_m)


def _dist5(camera: CameraIntrinsics) -> np.ndarray:
    """Distortion ``(k1, k2, p1, p2, k3)`` ``[5]``, zero-padded (zeros: none)."""
    d = np.zeros(5)
    d[: len(camera.distortion)] = camera.distortion
    return d


@dataclass
class FramePyramid:
    """One RGB-D frame prepared for tracking.

    Attributes:
        depth: per level ``[h_l, w_l]`` float32 metres (0 = invalid), level 0 = full resolution.
        intensity: per level ``[h_l, w_l]`` float32 grey in [0, 1].
        grad: per level ``(gx, gy)`` of ``intensity``.
        rgb: ``[H, W, 3]`` uint8 colour image (kept for merging the frame into a map), or None.
    """

    camera: CameraIntrinsics
    depth: list[np.ndarray]
    intensity: list[np.ndarray]
    grad: list[tuple[np.ndarray, np.ndarray]]
    rgb: np.ndarray | None = None
    # points() per (level, checkerboard): relocalization aligns one frame from a dozen poses
    _points: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def build(cls, rgb: np.ndarray | None, depth_m: np.ndarray, camera: CameraIntrinsics, n_levels: int,
              depth_range_m: tuple[float, float]) -> "FramePyramid":
        d = np.where((depth_m > depth_range_m[0]) & (depth_m < depth_range_m[1]), depth_m, 0).astype(np.float32)
        if rgb is None:
            g = np.zeros(d.shape, np.float32)
        else:
            g = (rgb.astype(np.float32) @ np.array(C.luma_weights_rgb, np.float32)) / C.max_colour_value
        depths, intens, grads = [d], [g], [kn.image_gradients(g)]
        for _ in range(1, n_levels):
            depths.append(kn.downsample_depth(depths[-1], C.pyramid_max_depth_jump_m, C.pyramid_depth_jump_fraction))
            intens.append(kn.downsample_mean(intens[-1]))
            grads.append(kn.image_gradients(intens[-1]))
        return cls(camera, depths, intens, grads, rgb)

    def points(self, level: int, checkerboard: bool = False) -> kn.FramePoints:
        """Camera-frame points ``[M, 3]`` float64 and their intensities ``[M]`` at ``level``
        (a named tuple: unpacks as ``points, intensity``); with ``checkerboard``, only pixels
        whose ``u + v`` is even. Computed once per frame and read-only."""
        key = (level, checkerboard)
        if key not in self._points:
            z = self.depth[level]
            valid = z > 0
            if checkerboard:
                valid = valid & _checkerboard(z.shape)
            rays = _level_rays(self.camera, level)
            pts = kn.FramePoints(rays[valid] * z[valid][:, None].astype(np.float64),
                                 self.intensity[level][valid].astype(np.float64))
            for a in pts:
                a.flags.writeable = False
            self._points[key] = pts
        return self._points[key]

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.depth[0]))


def surfels_from_voxels(ids: np.ndarray, count: np.ndarray, sum_xyz: np.ndarray, sum_sq: np.ndarray,
                        min_points: int = C.surfel_min_points,
                        min_support: int = C.surfel_min_support) -> tuple[np.ndarray, np.ndarray]:
    """Surfel centres and normals from voxel statistics.

    Args:
        ids: ``[N]`` sorted uint64 voxel ids (:func:`pack_voxel_ids`); count ``[N]`` points per voxel;
            sum_xyz ``[N, 3]``; sum_sq ``[N, 6]`` (xx xy xz yy yz zz).
    Returns:
        ``(centres [M, 3], normals [M, 3])``: the voxel mean, and the least-variance axis of the
        points of the voxel *and its 26 neighbours* (a single voxel far from the camera holds a
        handful of noisy points, too few for a stable plane). Voxels with fewer than
        ``min_points`` points or a neighbourhood of fewer than ``min_support`` are left out.
    """
    from atlas_pipeline.gaussian_world._voxel_kernels import neighbourhood_surfels
    from atlas_pipeline.gaussian_world.builder import _BITS, _OFFSET, unpack_voxel_ids

    ids = np.ascontiguousarray(ids, np.uint64)
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    centres, normals, support = neighbourhood_surfels(
        ids, unpack_voxel_ids(ids), np.ascontiguousarray(count, np.float64), np.ascontiguousarray(sum_xyz, np.float64),
        np.ascontiguousarray(sum_sq, np.float64), _OFFSET, _BITS)
    keep = (count >= min_points) & (support >= min_support)
    return np.ascontiguousarray(centres[keep]), np.ascontiguousarray(normals[keep])


class SurfelCache:
    """The surfel map of a growing :class:`VoxelGaussianBuilder`, kept current incrementally.

    After each merge of statistics only the voxels it touched and their 26 neighbours are
    recomputed (a voxel's surfel depends on its neighbourhood alone), so a keyframe costs what it
    adds, not the size of the map; the result is bit-identical to :meth:`SurfelModel.from_builder`.
    A builder changed by more than one merge since the last call is recomputed whole.
    """

    def __init__(self, builder, min_points: int = C.surfel_min_points, min_support: int = C.surfel_min_support):
        self.builder = builder
        self.min_points, self.min_support = min_points, min_support
        self._version: int | None = None
        self._ids = self._centres = self._normals = self._support = None
        self._model: SurfelModel | None = None
        # The chunk of every voxel's surfel (culling), kept along with the surfels.
        self._chunks: ChunkIndex | None = None
        self._chunk_of: np.ndarray | None = None  # [N] int32

    def model(self) -> "SurfelModel":
        from atlas_pipeline.gaussian_world._voxel_kernels import insert_rows, neighbourhood_surfels_subset
        from atlas_pipeline.gaussian_world.builder import _BITS, _OFFSET, unpack_voxel_ids

        b = self.builder
        if self._model is not None and self._version == b.version:
            return self._model
        ids = np.ascontiguousarray(b.ids, np.uint64)
        n = len(ids)
        if n == 0:
            centres, normals, support = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
            self._chunks, chunk_of = ChunkIndex(), np.zeros(0, np.int32)
        else:
            count = np.ascontiguousarray(b.count, np.float64)
            sums = (np.ascontiguousarray(b.sum_xyz, np.float64), np.ascontiguousarray(b.sum_sq, np.float64), _OFFSET, _BITS)
            if self._ids is not None and self._version is not None and b.version == self._version + 1:
                # The last merge inserted new voxels among the old ones (numpy.insert positions):
                # the old surfels move along the same way. Redone: the voxels near the merge (the
                # touched ones and their neighbours), the new ones among them.
                at = b.last_inserted_at
                centres = insert_rows(self._centres, at, 0.0)
                normals = insert_rows(self._normals, at, 0.0)
                support = insert_rows(self._support, at, 0)
                chunk_of = insert_rows(self._chunk_of, at, 0)
                redo = _near(ids, np.ascontiguousarray(b.last_touched_ids, np.uint64))
                sub = np.flatnonzero(redo).astype(np.int64)
                centres[sub], normals[sub], support[sub] = neighbourhood_surfels_subset(
                    ids, unpack_voxel_ids(ids[sub]), count, *sums, sub)
                chunk_of[sub] = self._chunks.chunks_of(_as_stored(centres[sub]))
            else:
                centres, normals, support = neighbourhood_surfels_subset(
                    ids, unpack_voxel_ids(ids), count, *sums, np.arange(n, dtype=np.int64))
                chunk_of = None
            if chunk_of is None or len(self._chunks) > MAX_CHUNKS:
                self._chunks = ChunkIndex(CHUNK_M if chunk_of is None else 2.0 * self._chunks.chunk_m)
                chunk_of = self._chunks.chunks_of(_as_stored(centres))
        self._ids, self._centres, self._normals, self._support = ids, centres, normals, support
        self._chunk_of = chunk_of
        self._version = b.version
        keep = (np.asarray(b.count) >= self.min_points) & (support >= self.min_support)
        self._model = SurfelModel(np.ascontiguousarray(centres[keep]), np.ascontiguousarray(normals[keep]),
                                  C.surfel_radius_voxels * b.voxel_size_m, builder=b)
        self._model._chunks = self._chunks.grid(chunk_of[keep])
        return self._model


class FarLevel(NamedTuple):
    """A map's far part as fewer, larger disks, band by band of depth (:func:`far_level`)."""

    centres: np.ndarray  # [F, 3] float64
    normals: np.ndarray  # [F, 3] float64 unit
    radius_m: np.ndarray  # [F] float64
    depth_lo_m: np.ndarray  # [F] float64 each disk's band: drawn where its depth is in (lo, hi]
    depth_hi_m: np.ndarray  # [F] float64
    chunk_of: np.ndarray  # [F] int32 each disk's chunk, the bands' chunks numbered one after another
    bands: tuple[tuple[float, float, ChunkGrid], ...]  # (lo, hi, its disks' chunks) per band
    from_m: float  # the first band's lo


def far_level(centres: np.ndarray, normals: np.ndarray, radius_m: float, from_m: float) -> FarLevel:
    """The surfels ``centres``, ``normals`` ``[M, 3]`` (disks of ``radius_m``) coarsened for the
    part of a view beyond ``from_m`` (any frame point's reach), where a pixel spans several voxels.

    Band ``b`` of ``far_level_bands`` covers depths ``(from_m 2^b, from_m 2^(b+1)]`` (the last one
    unbounded). For each of its cell sizes, ``far_level_cell_voxels`` times ``2^b`` voxels halved
    down to 2, the surfels not merged yet are binned into cells of that many voxels. A cell of at
    least ``far_level_min_members`` of them whose normals agree (``far_level_min_coherence``)
    becomes one disk: the members' mean centre, their principal normal (largest eigenvector of the
    mean of ``n n^T``: a surfel normal's sign is arbitrary), and a radius that reaches the
    farthest member's disk, at most the cell's share (``cell voxels`` radii). The surfels left keep
    their disks. Deterministic: per band, the merged cells, coarse first, each size in ascending
    cell order, then the surfels left in map order."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)  # [M, 3]
    n = np.asarray(normals, np.float64).reshape(-1, 3)  # [M, 3]
    parts: list[tuple[np.ndarray, ...]] = []
    bands = []
    n_chunks = 0
    for b in range(C.far_level_bands):
        lo = from_m * 2.0 ** b
        hi = from_m * 2.0 ** (b + 1) if b + 1 < C.far_level_bands else math.inf
        left = np.arange(len(c))
        band: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        cell_voxels = C.far_level_cell_voxels * 2 ** b
        while cell_voxels >= 2:
            merged, left = _merge_cells(c, n, left, radius_m, cell_voxels)
            band.append(merged)
            cell_voxels //= 2
        band.append((c[left], n[left], np.full(len(left), float(radius_m))))
        bc, bn, br = (np.concatenate([p[i] for p in band]) for i in range(3))
        grid = ChunkGrid.build(bc)
        parts.append((bc, bn, br, np.full(len(bc), lo), np.full(len(bc), hi), grid.chunk_of + np.int32(n_chunks)))
        bands.append((lo, hi, grid))
        n_chunks += grid.n_chunks
    out = [np.concatenate([p[i] for p in parts]) for i in range(6)]
    return FarLevel(*out[:5], out[5].astype(np.int32), tuple(bands), float(from_m))


def _merge_cells(c: np.ndarray, n: np.ndarray, members: np.ndarray, radius_m: float,
                 cell_voxels: int) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """One cell size of :func:`far_level`: surfels ``members`` (indices into ``c``, ``n`` ``[M, 3]``)
    binned into cells of ``cell_voxels`` voxels. Returns ``((centres [G, 3], normals [G, 3],
    radius_m [G]) of the cells merged, the members left, ascending)``."""
    from atlas_pipeline.gaussian_world.builder import pack_voxel_ids

    if len(members) == 0:
        return (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), members
    cm, nm = c[members], n[members]
    cell_m = cell_voxels * radius_m / C.surfel_radius_voxels
    _, group, count = np.unique(pack_voxel_ids(np.floor(cm / cell_m).astype(np.int64)), return_inverse=True,
                                return_counts=True)
    group = group.reshape(-1)
    g = len(count)
    mean = np.stack([np.bincount(group, cm[:, a], g) for a in range(3)], axis=1) / count[:, None]  # [G, 3]
    scatter = np.empty((g, 3, 3))  # mean of n n^T per cell
    for a in range(3):
        for b in range(a, 3):
            scatter[:, a, b] = scatter[:, b, a] = np.bincount(group, nm[:, a] * nm[:, b], g) / count
    eigval, eigvec = np.linalg.eigh(scatter)  # ascending
    merged = (count >= C.far_level_min_members) & (eigval[:, 2] >= C.far_level_min_coherence)
    order = np.argsort(group, kind="stable")
    starts = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    reach = np.maximum.reduceat(np.linalg.norm(cm[order] - mean[group[order]], axis=1), starts) + radius_m
    radius = np.minimum(reach, cell_voxels * radius_m)
    return (mean[merged], eigvec[merged, :, 2], radius[merged]), members[~merged[group]]


def _as_stored(centres: np.ndarray) -> np.ndarray:
    """``centres [K, 3]`` rounded as :class:`SurfelModel` keeps them (float32), so their chunks are
    those of the model's centres."""
    return np.asarray(centres, np.float32).astype(np.float64)


def _near(ids: np.ndarray, touched: np.ndarray) -> np.ndarray:
    """``[N]`` bool: which of the sorted voxel ``ids`` ``[N]`` lie in the 3x3x3 neighbourhood of a
    ``touched`` id ``[T]`` (sorted uint64, :func:`pack_voxel_ids`).

    The three neighbours along the last axis are consecutive ids, so each of the nine (i, j)
    offsets is one shifted copy of ``touched`` (still sorted) searched in ``ids``: no sort of the
    27 T candidates. A shift that carries past the edge of the +-2^20 voxel range lands on some
    other id and at worst marks a voxel that did not need recomputing; the window's low end stops
    at id 0 instead of wrapping."""
    from atlas_pipeline.gaussian_world.builder import _BITS

    n = len(ids)
    out = np.zeros(n, bool)
    if n == 0 or len(touched) == 0:
        return out
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            base = touched + np.uint64(((di << (2 * _BITS)) + (dj << _BITS)) % (1 << 64))  # (i + di, j + dj, k)
            first = np.where(base > 0, base - np.uint64(1), base)  # (i + di, j + dj, k - 1)
            pos = np.searchsorted(ids, first)
            for dk in range(3):  # the ids in [first, first + 2] are the (up to) three from pos on
                p = np.minimum(pos + dk, n - 1)
                out[p[(ids[p] >= first) & (ids[p] - first <= np.uint64(2))]] = True
    return out


class VoxelAppearance:
    """Mean grey of every voxel of a map, to check a pose's appearance: ``ids [V]`` sorted uint64
    (:func:`pack_voxel_ids`), ``grey [V]`` float32 in [0, 1], the voxel size (m). Lookups go
    through a hash table of the ids (:mod:`._voxel_hash`), made on the first one."""

    def __init__(self, ids: np.ndarray, grey: np.ndarray, voxel_size_m: float):
        self.ids = ids
        self.grey = grey
        self.voxel_size_m = float(voxel_size_m)
        self._table: _voxel_hash.VoxelTable | None = None

    def voxel_index(self, points_world: np.ndarray) -> np.ndarray:
        """``[M]`` int64 index into ``ids`` of the voxel each of ``points_world [M, 3]`` falls in;
        -1 where the map has none."""
        if self._table is None:
            ids = np.ascontiguousarray(self.ids, np.uint64)
            bits = _voxel_hash.table_bits(len(ids))
            self._table = _voxel_hash.VoxelTable(ids, _voxel_hash.build_slots(ids, bits), bits, self.voxel_size_m)
        return _voxel_hash.lookup_points(self._table, np.ascontiguousarray(points_world, np.float64).reshape(-1, 3))

    @classmethod
    def from_builder(cls, builder) -> "VoxelAppearance":
        """The mean colour of each voxel of a :class:`VoxelGaussianBuilder`."""
        count = np.maximum(np.asarray(builder.count, np.float64), 1.0)
        rgb = np.asarray(builder.sum_rgb, np.float64) / count[:, None]
        grey = (rgb @ np.array(C.luma_weights_rgb)) / C.max_colour_value
        return cls(np.asarray(builder.ids, np.uint64), grey.astype(np.float32), float(builder.voxel_size_m))

    @classmethod
    def from_field(cls, field, voxel_size_m: float) -> "VoxelAppearance":
        """The mean colour of the solid Gaussians of a :class:`GaussianField` in each voxel: what a
        saved world shows, the same whether it is in memory or reloaded from its bundle."""
        from atlas_pipeline.gaussian_world.builder import pack_voxel_ids

        pos = np.asarray(field.positions, np.float64)
        rgb = np.asarray(field.colors, np.float64)
        solid = np.asarray(field.opacities) >= C.field_min_opacity
        if solid.sum() >= C.field_min_solid_fraction * len(pos):  # as SurfelModel.from_field
            pos, rgb = pos[solid], rgb[solid]
        if not len(pos):
            return cls(np.zeros(0, np.uint64), np.zeros(0, np.float32), float(voxel_size_m))
        ids = pack_voxel_ids(np.floor(pos / voxel_size_m).astype(np.int64))
        uniq, inv = np.unique(ids, return_inverse=True)
        grey = (rgb @ np.array(C.luma_weights_rgb)) / C.max_colour_value
        mean = np.bincount(inv, grey, len(uniq)) / np.bincount(inv, minlength=len(uniq))
        return cls(uniq, mean.astype(np.float32), float(voxel_size_m))

    def grey_at(self, points_world: np.ndarray) -> np.ndarray:
        """``[M]`` the grey of the voxel each of ``points_world [M, 3]`` falls in; NaN where the
        map has no voxel."""
        out = np.full(len(points_world), np.nan)
        if not len(self.ids) or not len(points_world):
            return out
        idx = self.voxel_index(points_world)
        hit = idx >= 0
        out[hit] = self.grey[idx[hit]]
        return out

    def correlation(self, points_world: np.ndarray, grey: np.ndarray) -> tuple[float, int]:
        """``(normalized cross-correlation, pairs)`` of ``grey [M]`` seen at ``points_world [M, 3]``
        with the map's grey of the voxels they fall in: invariant to exposure and gain, near 0 where
        the pose puts the frame on surfaces of other texture (a look-alike room)."""
        if not len(self.ids) or not len(points_world):
            return float("nan"), 0
        idx = self.voxel_index(points_world)
        hit = idx >= 0
        if hit.sum() < MIN_APPEARANCE_PAIRS:
            return float("nan"), int(hit.sum())
        a, b = np.asarray(grey, np.float64)[hit], self.grey[idx[hit]].astype(np.float64)
        a, b = a - a.mean(), b - b.mean()
        den = np.sqrt((a * a).sum() * (b * b).sum())
        return (float((a * b).sum() / den) if den > 0 else float("nan")), int(hit.sum())


# Fewer frame points in mapped voxels than this: no appearance check is possible.
MIN_APPEARANCE_PAIRS = 50
# The map's grey is matched to a frame's exposure by a gain within this factor either way
# (a second visit at another time of day); past it the fit says more about a wrong pose.
MAX_EXPOSURE_GAIN = 4.0


def map_reference_image(view: kn.ModelView, appearance: VoxelAppearance, frame: "FramePyramid",
                        level: int) -> kn.ReferenceImage | None:
    """The map as a photometric reference: the grey of the voxels under the model ``view``'s
    surface points (``[h, w]`` at pyramid ``level``, posed where the view was rendered), with
    the gain and offset that match it to ``frame``'s grey at the same pixels (exposure).

    Unlike a keyframe of the same session, the map does not move with the camera's own error,
    so where the surfaces leave a direction free (one textured wall in view) the texture the
    world was built with holds the pose. None when too few pixels see coloured map voxels."""
    pts = view.points_cam
    on_map = np.isfinite(pts[..., 2])
    T = view.T_world_cam
    grey_map = np.full(on_map.shape, np.nan)
    grey_map[on_map] = appearance.grey_at(pts[on_map] @ T[:3, :3].T + T[:3, 3])
    frame_grey, frame_depth = frame.intensity[level], frame.depth[level]
    pairs = np.isfinite(grey_map) & (frame_depth > 0)
    if pairs.sum() < MIN_APPEARANCE_PAIRS:
        return None
    m, f = grey_map[pairs], frame_grey[pairs].astype(np.float64)
    # Moments, not least squares: misregistration at the guess dilutes a regression's slope.
    spread = m.std()
    gain = float(np.clip(f.std() / spread, 1 / MAX_EXPOSURE_GAIN, MAX_EXPOSURE_GAIN)) if spread > 0 else 1.0
    offset = float(f.mean() - gain * m.mean())
    seen = np.isfinite(grey_map)
    intensity = np.where(seen, gain * grey_map + offset, f.mean()).astype(np.float32)  # holes: flat, no gradient
    depth = np.where(seen, pts[..., 2], 0.0).astype(np.float32)
    gx, gy = kn.image_gradients(intensity)
    return kn.ReferenceImage(intensity, gx, gy, depth, np.ascontiguousarray(T, np.float64), view.fx, view.fy,
                             view.cx, view.cy, np.zeros(5))


# surfels.npz members: (dtype kinds, ndim) -- centres [M, 3], normals [M, 3], radius_m scalar.
_SURFEL_MEMBERS = {"centres": ("f", 2), "normals": ("f", 2), "radius_m": ("f", 0)}


def frame_view(frame: FramePyramid, T_world_cam: np.ndarray, level: int) -> kn.ModelView:
    """A placed frame's own surface as a model view: its level-``level`` points and normals
    (from neighbouring pixels), moved onto the level's pinhole grid (a distorted sensor's pixels
    are not on it) with the nearest point kept per pixel. No surface behind (NaN).

    It is the geometric reference of the frame that follows: surfaces the map lacks (a floor
    the first visit never saw) still hold the camera relative to the last frame.
    """
    camera = frame.camera
    z = np.ascontiguousarray(frame.depth[level], np.float64)  # [h, w]
    h, w = z.shape
    fx, fy, cx, cy = _level_K(camera, level)
    out_p, out_n = kn.frame_surface(z, _level_rays(camera, level), (fx, fy, cx, cy), C.pyramid_max_depth_jump_m,
                                    C.pyramid_depth_jump_fraction)
    empty = np.full((h, w, 3), np.nan)
    return kn.ModelView(out_p, out_n, np.ascontiguousarray(T_world_cam, np.float64), fx, fy, cx, cy, empty, empty)


@dataclass
class SurfelModel:
    """The map as surfels: ``centres [M, 3]``, ``normals [M, 3]``, one disk radius (m)."""

    centres: np.ndarray
    normals: np.ndarray
    radius_m: float
    # What the map looks like, to check a relocalized pose (:meth:`appearance`), not saved: a
    # saved world's Gaussian colours (:meth:`VoxelAppearance.from_field`), or, while mapping, the
    # voxel statistics the surfels come from (computed when first needed).
    appearance_map: VoxelAppearance | None = field(default=None, repr=False, compare=False)
    builder: object = field(default=None, repr=False, compare=False)
    # A saved world's map, which never changes: a view's part beyond ``detail_m`` (see
    # :meth:`model_view`) is drawn from its :func:`far_level`, made once.
    fixed: bool = field(default=False, repr=False, compare=False)
    # The surfels binned by chunk of space, for culling what a view cannot see (made when first needed).
    _chunks: ChunkGrid | None = field(default=None, init=False, repr=False, compare=False)
    _far: FarLevel | None = field(default=None, init=False, repr=False, compare=False)  # for one detail_m

    def appearance(self) -> VoxelAppearance | None:
        """The map's voxel grey (:class:`VoxelAppearance`), or None when nothing is known of it."""
        if self.appearance_map is None and self.builder is not None:
            self.appearance_map = VoxelAppearance.from_builder(self.builder)
        return self.appearance_map

    def __post_init__(self) -> None:
        # The map is what surfels.npz stores (float32). Rounding here too makes a map used in
        # memory (the Dagster graph) and the same map reloaded from a bundle (the CLI) identical,
        # so both routes track to the same poses bit for bit. The kernels compute in float64.
        self.centres = np.asarray(self.centres, np.float32).astype(np.float64)
        self.normals = np.asarray(self.normals, np.float32).astype(np.float64)
        self.radius_m = float(self.radius_m)

    @classmethod
    def from_builder(cls, builder, min_points: int = C.surfel_min_points) -> "SurfelModel":
        c, n = surfels_from_voxels(builder.ids, builder.count, builder.sum_xyz, builder.sum_sq, min_points)
        return cls(c, n, C.surfel_radius_voxels * builder.voxel_size_m, builder=builder)

    @classmethod
    def from_field(cls, positions: np.ndarray, voxel_size_m: float, opacities: np.ndarray | None = None,
                   min_opacity: float = C.field_min_opacity) -> "SurfelModel":
        """Surfels from Gaussian centres ``[N, 3]`` alone (a bundle without ``surfels.npz``, e.g. an
        imported PLY): each centre is binned into its voxel, and normals come from the centres of
        the 3x3x3 voxel neighbourhood. With ``opacities [N]``, only Gaussians at least
        ``min_opacity`` opaque count: fitted fields park faint Gaussians off the surface."""
        from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder

        pts = np.asarray(positions, np.float64)
        if opacities is not None:
            solid = np.asarray(opacities) >= min_opacity
            if solid.sum() >= C.field_min_solid_fraction * len(pts):  # not a field of faint Gaussians only
                pts = pts[solid]
        b = VoxelGaussianBuilder(voxel_size_m)
        if len(pts):
            b.integrate(pts, np.zeros((len(pts), 3)))
        c, n = surfels_from_voxels(b.ids, b.count, b.sum_xyz, b.sum_sq, C.surfel_min_points, C.field_min_support)
        return cls(c, n, C.surfel_radius_voxels * voxel_size_m)

    def __len__(self) -> int:
        return len(self.centres)

    def save(self, path: Path) -> Path:
        """``surfels.npz``: centres and normals ``[M, 3]`` float32, radius_m (no pickled objects)."""
        from atlas_pipeline.io_utils import atomic_path
        from atlas_pipeline.safe_arrays import save_npz_deterministic

        with atomic_path(Path(path)) as tmp:
            with open(tmp, "wb") as fh:  # equal surfels, equal bytes (the bundle's hashes)
                save_npz_deterministic(fh, centres=np.asarray(self.centres, np.float32),
                                       normals=np.asarray(self.normals, np.float32),
                                       radius_m=np.float64(self.radius_m))
        return Path(path)

    @classmethod
    def load(cls, path: Path) -> "SurfelModel":
        """Read :meth:`save`'s file; a malformed one raises ``BundleFormatError`` naming it."""
        from atlas_pipeline.errors import BundleFormatError
        from atlas_pipeline.safe_arrays import load_npz_checked

        try:
            z = load_npz_checked(path, _SURFEL_MEMBERS)
        except BundleFormatError as exc:
            # keep one "<path>: " prefix: the inner message already names the file
            raise BundleFormatError(path, f"not a surfel map ({str(exc).removeprefix(f'{exc.path}: ')})") from exc
        c, n, r = z["centres"], z["normals"], float(z["radius_m"])
        if c.ndim != 2 or c.shape[1:] != (3,) or n.shape != c.shape:
            raise BundleFormatError(path, f"centres {list(c.shape)} and normals {list(n.shape)} must both be [M, 3]")
        if not (np.isfinite(c).all() and np.isfinite(n).all() and np.isfinite(r) and r > 0):
            raise BundleFormatError(path, "non-finite centres / normals or a non-positive radius_m")
        return cls(c.astype(np.float64), n.astype(np.float64), r)

    def render(self, T_world_cam: np.ndarray, camera: CameraIntrinsics, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Model view ``(points_cam [h, w, 3], normals_cam [h, w, 3])`` at pyramid ``level`` (NaN = empty)."""
        return self._splat(T_world_cam, camera, level, False)[:2]

    def _splat(self, T_world_cam: np.ndarray, camera: CameraIntrinsics, level: int,
               surface_behind: bool, max_depth_m: float = math.inf, detail_m: float = math.inf) -> tuple[np.ndarray, ...]:
        view, params = _level_view(T_world_cam, camera, level), splat_params(self.radius_m, max_depth_m)
        far = self._far_surfels(view, params, detail_m)
        near = params._replace(max_depth_m=min(max_depth_m, far.from_m))  # what the map's own surfels may reach
        return kn.splat_surfels(self.centres, self.normals, self.radius_m, view, params, surface_behind,
                                self.culling(view, near), far)

    def _far_surfels(self, view: kn.PinholeView, params: kn.SplatParams, detail_m: float) -> kn.FarSurfels:
        """The :func:`far_level` stand-ins a view of this map draws beyond ``detail_m``: none unless
        the map is :attr:`fixed`, large (``far_level_min_surfels``) and the view reaches past it."""
        far = self._far_level(detail_m) if detail_m < params.max_depth_m else None
        if far is None:
            return kn.NO_FAR
        seen = np.concatenate([grid.seen(view, params._replace(min_depth_m=max(params.min_depth_m, lo),
                                                              max_depth_m=min(params.max_depth_m, hi)))
                               for lo, hi, grid in far.bands])
        return kn.FarSurfels(far.centres, far.normals, far.radius_m, far.depth_lo_m, far.depth_hi_m,
                             kn.SplatCulling(far.chunk_of, seen), far.from_m)

    def _far_level(self, detail_m: float) -> FarLevel | None:
        """This map's :func:`far_level` beyond ``detail_m``, made at its first use; None unless the
        map is :attr:`fixed` and large (``far_level_min_surfels``)."""
        if not (self.fixed and len(self) >= C.far_level_min_surfels):
            return None
        if self._far is None or self._far.from_m != detail_m:
            self._far = far_level(self.centres, self.normals, self.radius_m, detail_m)
        return self._far

    def prepare_views(self, detail_m: float) -> None:
        """Make what the first views of this map would otherwise make: its culling chunks and, when
        :attr:`fixed`, its far level beyond ``detail_m``. A session calls it before its first
        frame, so a first frame that must be relocalized does not pay for them (a 1.8M-surfel
        map's far level takes seconds)."""
        if len(self.centres) >= C.min_surfels_to_cull and self._chunks is None:
            self._chunks = ChunkGrid.build(self.centres)
        self._far_level(detail_m)

    def culling(self, view: kn.PinholeView, params: kn.SplatParams) -> kn.SplatCulling:
        """What the splat of ``view`` may skip: the chunks of the map no surfel of which it can draw
        (:mod:`atlas_pipeline.localization.culling`); none for a map too small to be worth it."""
        if len(self.centres) < C.min_surfels_to_cull:
            return kn.NO_CULLING
        if self._chunks is None:
            self._chunks = ChunkGrid.build(self.centres)
        return kn.SplatCulling(self._chunks.chunk_of, self._chunks.seen(view, params))

    def model_view(self, T_world_cam: np.ndarray, camera: CameraIntrinsics, level: int,
                   surface_behind: bool = False, max_depth_m: float = math.inf,
                   detail_m: float = math.inf) -> kn.ModelView:
        """The map splatted at ``T_world_cam`` as the tracker's geometric reference: the first surface
        along each ray, with ``surface_behind`` the next one behind it too (else NaN), and the view's
        pinhole; surfels farther than ``max_depth_m`` from the camera are left out. In a
        :attr:`fixed` map, those farther than ``detail_m`` are drawn from its :func:`far_level`."""
        T = np.ascontiguousarray(T_world_cam, np.float64)
        pts, nrm, pts_behind, nrm_behind = self._splat(T, camera, level, surface_behind, max_depth_m, detail_m)
        return kn.ModelView(pts, nrm, T, *_level_K(camera, level), pts_behind, nrm_behind)


@dataclass
class TrackResult:
    """Outcome of aligning one frame.

    Attributes:
        T_world_cam: ``[4, 4]`` estimate.
        inlier_fraction: share of the frame's finest-level points with a model correspondence.
        agreement: share of the points that land on the model view that are correspondences
            (low: the frame overlaps the map but does not fit it, i.e. a wrong pose).
        residual_m: RMS point-to-plane residual of those correspondences.
        n_points: finest-level points used.
        ok: alignment judged good (see :meth:`RGBDTracker.judge`).
        overlap: share of the frame's points that land on the model view at all (covisibility
            with the map: 1 - overlap of the frame is surface the map does not have).
    """

    T_world_cam: np.ndarray
    inlier_fraction: float
    residual_m: float
    n_points: int
    ok: bool
    iterations: int = 0
    agreement: float = float("nan")
    overlap: float = float("nan")
    in_front: float = 0.0  # share of the frame's points in front of the map's surface (MATCH_IN_FRONT)
    # How well the geometry pins the position (translation_constraint): near 0 when the matched
    # surfaces leave a direction free, e.g. a wall and the floor seen through a door.
    translation_constraint: float = 1.0

    @property
    def strict_agreement(self) -> float:
        """Correspondences among the points that land on the map *including* those in front of
        it: what a pose with no motion prior (relocalization) must explain."""
        landed = self.overlap + self.in_front
        return self.inlier_fraction / landed if landed > 0 else 0.0


class RGBDTracker:
    """Aligns frames to a :class:`SurfelModel` and a reference frame (see the module docstring)."""

    def __init__(self, camera: CameraIntrinsics, cfg: LocalizationConfig, depth_range_m: tuple[float, float],
                 screening: bool = False):
        self.camera = camera
        self.cfg = cfg
        self.depth_range_m = depth_range_m
        self.n_levels = pyramid_levels(cfg)
        self.dist = _dist5(camera)
        coarser = cfg.finest_level + C.model_level_offset
        self.model_level = coarser if camera.width // 2 ** coarser >= C.model_min_width_px else cfg.finest_level
        # A screening tracker only ranks hypotheses (relocalization) for a full one to refine and
        # grade: it grades the result against the view it started from, without a second splat.
        self.screening = bool(screening)
        # Gates and weights of the kernel; the association gate and photometric weight vary per call.
        self._params = kn.Params(
            max_distance_m=cfg.min_correspondence_m, huber_depth_m=cfg.huber_depth_m, photometric_weight=0.0,
            huber_intensity=C.huber_intensity, occlusion_gate_m=C.occlusion_gate_m,
            min_view_depth_m=C.min_view_depth_m, noise_a_m=C.depth_noise_a_m, noise_b_per_m=C.depth_noise_b_per_m,
            noise_z0_m=C.depth_noise_z0_m, noise_reference_sigma_m=C.depth_noise_reference_sigma_m)
        # Stand-in for "no photometric reference" (the kernel skips it: photometric weight 0).
        empty = np.zeros((1, 1), np.float32)
        self._no_reference = kn.ReferenceImage(empty, empty, empty, empty, np.eye(4), 1.0, 1.0, 0.0, 0.0, self.dist)

    @property
    def tracking_far_m(self) -> float:
        """Far clip of a tracking view, m: the frame's farthest depth, the widest association gate
        and ``view_far_margin_m``; no frame point can match a surface beyond it."""
        return self.depth_range_m[1] + self.cfg.max_correspondence_m + C.view_far_margin_m

    def prepare(self, rgb: np.ndarray | None, depth_m: np.ndarray) -> FramePyramid:
        return FramePyramid.build(rgb, depth_m, self.camera, self.n_levels, self.depth_range_m)

    def _reference_image(self, frame: FramePyramid, T_world_cam: np.ndarray, level: int) -> kn.ReferenceImage:
        """``frame`` at ``level``, posed at ``T_world_cam``, as the kernel's photometric reference."""
        gx, gy = frame.grad[level]
        T = np.ascontiguousarray(T_world_cam, np.float64)
        return kn.ReferenceImage(frame.intensity[level], gx, gy, frame.depth[level], T, *_level_K(self.camera, level),
                                 self.dist)

    def _gate_m(self, li: int) -> float:
        """Association gate of the ``li``-th level run (coarsest first): it shrinks towards the
        finest level, a wide basin first and precision last, down to ``min_correspondence_m``."""
        cfg = self.cfg
        n_levels = len(cfg.iterations)
        max_dist = cfg.max_correspondence_m * (2.0 ** (n_levels - 1 - li)) / 2.0 ** (n_levels - 1)
        return max(max_dist, cfg.min_correspondence_m)

    def align(self, frame: FramePyramid, model: SurfelModel, T_init: np.ndarray,
              reference: tuple[FramePyramid, np.ndarray] | None = None, surface_behind: bool = False,
              motion_prior: np.ndarray | None = None, map_reference: bool = False,
              within_range: bool = False) -> TrackResult:
        """Coarse-to-fine Gauss-Newton from ``T_init``; ``reference`` = (frame, its pose) for the
        photometric term (None: geometry only). ``surface_behind``: points behind the map's first
        surface may match the one behind it (:class:`kn.ModelView`): for tracking along a fixed
        world, never for mapping, loop or relocalization checks, which must see a doubled surface
        as a disagreement. ``motion_prior``: ``[4, 4]`` the motion model's prediction, which holds
        the camera centre where the surfaces leave it free (:func:`add_motion_prior`).
        ``map_reference``: the photometric reference is the map's own colours rendered at the
        initial pose (:func:`map_reference_image`, weight ``map_photometric_weight``) instead
        of ``reference``, where the map has colours. ``within_range``: the model view holds only
        the map within reach of the frame's depth range (:meth:`tracking_far_m`), which changes
        no correspondence, only the count of points in front of the map beyond it
        (:attr:`TrackResult.in_front`): for tracking, not for checks that weigh free space.
        Ignored where the map's colours are the reference (their exposure fit spans the view)."""
        cfg = self.cfg
        T = np.array(T_init, np.float64)
        fin = cfg.finest_level
        kernel_threads()  # this process's share of the cores now (a pool of runs may change it)
        map_colours = map_reference and cfg.map_photometric_weight > 0 and model.appearance() is not None
        # The map's colours fit the exposure over every pixel of the view: the far ones stay in.
        far_m = self.tracking_far_m if within_range and not map_colours else math.inf
        # One model view per frame, at the initial pose; every level projects into it.
        view = model.model_view(T, self.camera, self.model_level, surface_behind, far_m, self.tracking_far_m)
        w_photo = cfg.photometric_weight * C.photometric_scale if reference is not None else 0.0
        map_ref = None
        if map_colours:
            map_ref = map_reference_image(view, model.appearance(), frame, self.model_level)
            if map_ref is not None:
                w_photo = cfg.map_photometric_weight * C.photometric_scale
        n_levels = len(cfg.iterations)
        total_it = 0
        for li, iters in enumerate(cfg.iterations):
            level = fin + (n_levels - 1 - li)  # coarse first
            points = frame.points(level, C.finest_checkerboard and level == fin)
            if len(points.points_cam) < C.min_points_per_level:
                continue
            params = self._params._replace(max_distance_m=self._gate_m(li), photometric_weight=w_photo)
            if map_ref is not None:
                ref = map_ref
            else:
                ref = self._no_reference if reference is None else self._reference_image(reference[0], reference[1], level)
            # Trust region, per level: coarse levels may step further (their basin is wider).
            max_step_m = C.max_step_m * 2 ** (level - fin)
            for _ in range(iters):
                H, g, stats = normal_equations(points, T, view, ref, params)
                total_it += 1
                if stats.n_geometric < C.min_geometric_inliers:
                    break
                if motion_prior is not None:
                    add_motion_prior(H, g, T, motion_prior[:3, 3], C.motion_prior_share)
                xi = solve_update(H, g, max_step_m, C.max_step_rad)
                if xi is None:
                    break
                T = apply_update(xi, T)
                if converged(xi, C.converged_step * C.converged_step_level_factor ** (level - fin)):
                    break
        # Quality at the final pose, finest level, geometry only; a view re-rendered there when
        # the pose travelled far from the one the model view was made at (relocalization).
        if not self.screening and poses_differ(view.T_world_cam, T, C.rerender_translation_m, C.rerender_rotation_deg):
            view = model.model_view(T, self.camera, self.model_level, surface_behind, far_m, self.tracking_far_m)
        H_final, stats = self.quality_stats(frame, view, T)
        agreement = stats.agreement
        ok = self.judge(stats.inlier_fraction, stats.rmse_m, agreement)
        if not ok and motion_prior is not None and model.fixed and self.judge(stats.inlier_fraction, stats.rmse_m):
            agreement = max(agreement, self.agreement_within_noise(frame, view, T))
            ok = self.judge(stats.inlier_fraction, stats.rmse_m, agreement)
        T = orthonormalize(T)
        overlap = stats.n_on_model / stats.n_points if stats.n_points else 0.0
        in_front = stats.n_in_front / stats.n_points if stats.n_points else 0.0
        return TrackResult(T, stats.inlier_fraction, stats.rmse_m, stats.n_points, ok, total_it, agreement,
                           overlap, in_front, translation_constraint(H_final))

    def agreement_within_noise(self, frame: FramePyramid, view: kn.ModelView, T_world_cam: np.ndarray) -> float:
        """The agreement of ``frame``'s finest-level points at ``T_world_cam`` with ``view``, each
        point judged within the depth noise at its range (:func:`fit_within_noise`): what loop
        verification grades, and what :meth:`align` grades a frame tracked in a saved world by when
        its fit and residual pass but its agreement at the fixed gate does not (at range the map's
        layers of one surface, fused from poses a few cm apart along the line of sight, disagree by
        the sensor's own noise). Only there with a motion prior and a fixed map: with no prior
        (relocalization, loops) a pose some cm off fits far surfaces nearly as well as the true
        one, and a frame SLAM accepts is fused into the map it is judged by."""
        points = frame.points(self.cfg.finest_level, C.finest_checkerboard)
        return fit_within_noise(points.points_cam, T_world_cam, view, self.cfg.min_correspondence_m,
                                C.min_view_depth_m).agreement

    def odometry(self, frame: FramePyramid, local_view: kn.ModelView, T_init: np.ndarray,
                 reference: tuple[FramePyramid, np.ndarray] | None = None,
                 motion_prior: np.ndarray | None = None) -> np.ndarray | None:
        """``T_world_cam [4, 4]`` of ``frame`` aligned to the previous frame's own surface
        (:func:`frame_view`) and, with ``reference`` (that frame and its pose), its intensities:
        frame-to-frame odometry, coarse levels only (a prediction, not a result). None when the
        two frames share too little surface. ``motion_prior``: ``[4, 4]`` holds the camera centre
        where the two frames' surfaces leave it free (:func:`add_motion_prior`), as in :meth:`align`."""
        cfg = self.cfg
        T = np.array(T_init, np.float64)
        fin = cfg.finest_level
        n_levels = len(cfg.iterations)
        w_photo = cfg.photometric_weight * C.photometric_scale if reference is not None else 0.0
        for li, iters in enumerate(cfg.iterations[:-1]):  # the finest level would only polish it
            level = fin + (n_levels - 1 - li)
            points = frame.points(level)
            params = self._params._replace(max_distance_m=self._gate_m(li), photometric_weight=w_photo)
            ref = self._no_reference if reference is None else self._reference_image(reference[0], reference[1], level)
            max_step_m = C.max_step_m * 2 ** (level - fin)
            for _ in range(iters):
                H, g, stats = normal_equations(points, T, local_view, ref, params)
                if stats.n_geometric < C.min_geometric_inliers:
                    return None
                if motion_prior is not None:
                    add_motion_prior(H, g, T, motion_prior[:3, 3], C.motion_prior_share)
                xi = solve_update(H, g, max_step_m, C.max_step_rad)
                if xi is None:
                    return None
                T = apply_update(xi, T)
                if converged(xi, C.converged_step * C.converged_step_level_factor ** (level - fin)):
                    break
        return T

    def quality_stats(self, frame: FramePyramid, view: kn.ModelView,
                      T_world_cam: np.ndarray) -> tuple[np.ndarray, kn.Stats]:
        """Geometric correspondences of ``frame``'s finest-level points at ``T_world_cam`` with the
        model ``view``, at the tightest gate (``min_correspondence_m``), no photometric term: what
        :meth:`judge` grades. Returns ``(H [6, 6] point-to-plane normal matrix, stats)``."""
        points = frame.points(self.cfg.finest_level, C.finest_checkerboard)
        T = np.ascontiguousarray(T_world_cam, np.float64)
        H, _, stats = normal_equations(points, T, view, self._no_reference, self._params)
        return H, stats

    def judge(self, inlier_fraction: float, residual_m: float, agreement: float = 1.0) -> bool:
        """Good alignment: enough of the frame explained by the map, the part of it that overlaps
        the map mostly agreeing with it, and a small residual."""
        return (inlier_fraction >= self.cfg.min_fitness and agreement >= self.cfg.min_agreement
                and np.isfinite(residual_m) and residual_m <= self.cfg.max_residual_m)


def translation_constraint(H: np.ndarray) -> float:
    """Smallest over largest eigenvalue of the translation block ``H[:3, :3]`` of point-to-plane
    normal equations ``[6, 6]``: 1 when matched normals span all directions evenly, near 0 when
    the surfaces let the camera slide (two planes constrain only two directions)."""
    ev = np.linalg.eigvalsh(0.5 * (H[:3, :3] + H[:3, :3].T))
    return float(ev[0] / ev[-1]) if ev[-1] > 0 else 0.0


def add_motion_prior(H: np.ndarray, g: np.ndarray, T_world_cam: np.ndarray, centre_pred: np.ndarray,
                     share: float) -> None:
    """Add a prior holding the camera centre of ``T_world_cam`` at ``centre_pred [3]`` to the
    normal equations ``H [6, 6]``, ``g [6]`` (in place, the left update of :func:`apply_update`).

    Its weight is ``share`` times the largest eigenvalue of the translation block: a direction the
    data constrain much more strongly than that keeps the data's answer; one they leave nearly
    free (sliding along a wall) stays at the prediction.
    """
    ev_max = float(np.linalg.eigvalsh(0.5 * (H[:3, :3] + H[:3, :3].T))[-1])
    if not ev_max > 0:
        return
    c = T_world_cam[:3, 3]
    # d(centre)/d(xi) of exp(xi) T: [I | -[c]x]
    J = np.zeros((3, 6))
    J[:, :3] = np.eye(3)
    J[:, 3:] = -np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    w = share * ev_max
    H += w * (J.T @ J)
    g += w * (J.T @ (c - centre_pred))


def solve_update(H: np.ndarray, g: np.ndarray, max_step_m: float, max_step_rad: float) -> np.ndarray | None:
    """The Gauss-Newton step ``xi = (v [3] m, omega [3] rad)`` of the normal equations
    ``H xi = -g`` (``H`` ``[6, 6]``, modified in place), or None when it cannot be solved.

    Levenberg damping keeps weakly constrained directions from jumping; the trust region scales the
    step down so it moves at most ``max_step_m`` and turns at most ``max_step_rad``, so an
    ill-conditioned early iterate cannot throw the pose out of the basin.
    """
    diag = np.diag_indices(6)
    H[diag] *= 1.0 + C.levenberg_damping
    H[diag] += C.diagonal_floor
    try:
        xi = -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(xi)):
        return None
    scale = max(np.linalg.norm(xi[:3]) / max_step_m, np.linalg.norm(xi[3:]) / max_step_rad, 1.0)
    return xi / scale


def apply_update(xi: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """``exp(xi) T_world_cam``: the left (world-frame) update the normal equations are built for,
    with the rotation ``so3_exp(omega)`` and the translation ``v`` taken as is."""
    dT = np.eye(4)
    dT[:3, :3] = so3_exp(xi[3:])
    dT[:3, 3] = xi[:3]
    return dT @ T_world_cam


def converged(xi: np.ndarray, tolerance: float = C.converged_step) -> bool:
    """The step ``xi`` ``[6]`` moved and turned less than ``tolerance`` (m, rad)."""
    return bool(np.linalg.norm(xi[:3]) < tolerance and np.linalg.norm(xi[3:]) < tolerance)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (SVD) in a pose ``[4, 4]``: round-off in chained products grows
    geometrically through a motion model's ``T_prev @ inv(T_prev2) @ T_prev``, so every
    estimate is snapped back onto SE(3)."""
    out = np.array(T, np.float64)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def predict_constant_velocity(T_prev: np.ndarray, T_prev2: np.ndarray | None, scale: float = 1.0) -> np.ndarray:
    """Constant-velocity prediction ``T_prev @ (T_prev2^-1 T_prev)^scale`` (camera-frame increment).

    ``scale`` = (time to this frame) / (time between the last two): a frame after a gap in the
    recording is predicted as far along as the camera's velocity carries it. The increment's
    rotation vector and translation are scaled apart: not the SE(3) power exactly, but within
    millimetres of it for the few-degree increments of consecutive frames."""
    if T_prev2 is None:
        return T_prev.copy()
    inc = invert_se3(T_prev2) @ T_prev
    if scale != 1.0:
        scaled = np.eye(4)
        scaled[:3, :3] = so3_exp(scale * so3_log(inc[:3, :3]))
        scaled[:3, 3] = scale * inc[:3, 3]
        inc = scaled
    return orthonormalize(T_prev @ inc)


def pose_change(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """``(translation m, rotation deg)`` between two poses."""
    rel = invert_se3(T_a) @ T_b
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle_rad(rel[:3, :3])))


def poses_differ(T_a: np.ndarray, T_b: np.ndarray, translation_m: float, rotation_deg: float) -> bool:
    """Whether two poses are more than ``translation_m`` or ``rotation_deg`` apart (:func:`pose_change`)."""
    moved_m, turned_deg = pose_change(T_a, T_b)
    return moved_m > translation_m or turned_deg > rotation_deg

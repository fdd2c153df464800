"""Voxel Gaussian merge (paper section 5.2), incremental per keyframe, with stable ids.

Points are binned into voxels of size ``v``. Each voxel keeps running sums (count, position,
colour, second moments), so merging a new keyframe only adds to sums: the result does not depend on
how keyframes are batched, and a voxel's id is derived from its integer coordinates, so the same
surface patch keeps the same id across merges, reruns and sessions.

Points may carry weights (the mapper gives each its inverse depth variance, so a far, noisy reading
moves a voxel's mean and shape less than a near one): positions and second moments are then
weighted sums over ``weight``, the sum of the weights; colours stay plain means over ``count``
(colour noise does not grow with depth). Unweighted points have weight 1 (``weight == count``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize, sh_degree_of_rest_count
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.safe_arrays import (
    is_finite_number,
    load_json_object_checked,
    load_npz_checked,
    save_npz_deterministic,
)

__all__ = ["pack_voxel_ids", "unpack_voxel_ids", "VoxelGaussianBuilder", "GaussianWorld"]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)  # voxel coordinates in [-2^20, 2^20): +-21 km at 2 cm voxels
_MASK = (1 << _BITS) - 1


def pack_voxel_ids(ijk: np.ndarray) -> np.ndarray:
    """Integer voxel coordinates ``[M, 3]`` to uint64 ids (21 bits per axis)."""
    ijk = np.asarray(ijk, dtype=np.int64)
    if ijk.size and (ijk.min() < -_OFFSET or ijk.max() >= _OFFSET):
        raise ValueError("point lies outside the addressable voxel range (+-2^20 voxels per axis)")
    u = (ijk + _OFFSET).astype(np.uint64)
    return (u[:, 0] << np.uint64(2 * _BITS)) | (u[:, 1] << np.uint64(_BITS)) | u[:, 2]


def unpack_voxel_ids(ids: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_voxel_ids`: ``[M]`` uint64 to ``[M, 3]`` int64."""
    ids = np.asarray(ids, dtype=np.uint64)
    m = np.uint64(_MASK)
    out = np.stack([(ids >> np.uint64(2 * _BITS)) & m, (ids >> np.uint64(_BITS)) & m, ids & m], axis=1)
    return out.astype(np.int64) - _OFFSET


# Order of the six second moments kept per voxel (xx xy xz yy yz zz).
_MOMENT_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _moments_to_matrices(sum_sq: np.ndarray) -> np.ndarray:
    """Six second moments per voxel ``[M, 6]`` to symmetric matrices ``[M, 3, 3]``."""
    Q = np.empty((len(sum_sq), 3, 3))
    for k, (a, b) in enumerate(_MOMENT_PAIRS):
        Q[:, a, b] = Q[:, b, a] = sum_sq[:, k]
    return Q


_MIN_POINTS_OWN_SHAPE = 5  # fewer points than this: the voxel's own covariance is too noisy
_MIN_SCALE = 0.05  # voxels: thickness floor along the normal (1 mm at 2 cm voxels)
_MAX_SCALE = 0.75  # voxels: no Gaussian spreads much past its voxel (or its merge cell)
# Widest merge cell (integrate's cell_voxels), in voxels a side: 16 cm at 2 cm voxels, the Kinect
# model's depth noise near 8 m (mapping/mapper.py noise_cell_voxels).
MAX_CELL_VOXELS = 8


def _opacity_from_support(count: np.ndarray) -> np.ndarray:
    """More observed points -> more confident surface. Saturates after a handful of samples."""
    return np.clip(1.0 - np.exp(-count / 3.0), 0.05, 0.99).astype(np.float32)


@dataclass
class VoxelGaussianBuilder:
    """Accumulates world-frame points into voxel statistics; one Gaussian per occupied voxel.

    State arrays (N occupied voxels, kept sorted by id):
        ids ``[N]`` uint64, count ``[N]`` int64 (points), sum_xyz ``[N, 3]`` float64 (weighted),
        sum_rgb ``[N, 3]`` float64 (unweighted), sum_sq ``[N, 6]`` float64 (weighted; xx xy xz yy yz
        zz, for covariances), n_keyframes ``[N]`` int32 (keyframes that observed the voxel),
        weight ``[N]`` float64 (sum of the point weights; ``count`` when no weights were given).
    """

    voxel_size_m: float
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    count: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sum_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sum_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sum_sq: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    n_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    weight: np.ndarray | None = None  # None: every point had weight 1 (weight = count)
    # Bookkeeping for incremental consumers (the tracker's surfel map), not state: bumped by every
    # merge of statistics, with the sorted ids that merge touched ...
    version: int = field(default=0, compare=False, repr=False)
    last_touched_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64), compare=False, repr=False)
    # ... and where its new voxels were inserted, as ``numpy.insert`` positions in the ids before it.
    last_inserted_at: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.weight is None:
            self.weight = self.count.astype(np.float64)

    def __len__(self) -> int:
        return len(self.ids)

    def integrate(self, points_world: np.ndarray, colors: np.ndarray, weights: np.ndarray | None = None,
                  cell_voxels: np.ndarray | None = None) -> int:
        """Merge one keyframe's points ``[M, 3]`` and colours ``[M, 3]``, with optional positive
        ``weights [M]`` for positions and shapes (None: 1 each); returns the new voxel count.

        ``cell_voxels [M]`` (powers of two up to ``MAX_CELL_VOXELS``, None: 1 each) merges a point into the cell of that many
        voxels a side that holds it, kept under the id of the cell's first voxel: noisy far points
        make one wider Gaussian per cell instead of a cloud of small ones (ids stay voxel ids).
        """
        if len(points_world) == 0:
            return 0
        p = np.asarray(points_world, dtype=np.float64)
        c = np.asarray(colors, dtype=np.float64)
        ijk = np.floor(p / self.voxel_size_m).astype(np.int64)
        if cell_voxels is not None:
            cell = np.asarray(cell_voxels, np.int64).reshape(-1, 1)
            if cell.shape != (len(p), 1) or (cell < 1).any() or (cell > MAX_CELL_VOXELS).any() or (cell & (cell - 1)).any():
                raise ValueError(f"integrate: cell_voxels must be [M] powers of two in [1, {MAX_CELL_VOXELS}]")
            ijk = np.floor_divide(ijk, cell) * cell  # the cell's first voxel (floor: also below zero)
        keys = pack_voxel_ids(ijk)
        uk, inv = np.unique(keys, return_inverse=True)
        nk = len(uk)

        def bsum(w: np.ndarray) -> np.ndarray:
            return np.bincount(inv, weights=w, minlength=nk)

        cnt = np.bincount(inv, minlength=nk).astype(np.int64)
        if weights is None:
            wsum, pw = cnt.astype(np.float64), p
        else:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != (len(p),) or not (np.isfinite(w).all() and (w > 0).all()):
                raise ValueError("integrate: weights must be [M] finite and > 0, one per point")
            wsum, pw = bsum(w), p * w[:, None]
        sxyz = np.stack([bsum(pw[:, k]) for k in range(3)], axis=1)
        srgb = np.stack([bsum(c[:, k]) for k in range(3)], axis=1)
        ssq = np.stack([bsum(pw[:, a] * p[:, b]) for a, b in _MOMENT_PAIRS], axis=1)
        return self._add(uk, cnt, sxyz, srgb, ssq, np.ones(nk, np.int32), wsum)

    def merge(self, other: "VoxelGaussianBuilder", T_self_other: np.ndarray) -> int:
        """Add ``other``'s statistics, moved by ``T_self_other [4, 4]`` (other's frame to this
        one's), as when two maps of one place are joined; returns the new voxel count.

        The sums move exactly (``sum p' = R sum p + n t``, and likewise the second moments), so a
        voxel's mean, colour and covariance are what integrating its points at the new pose gives;
        each moved voxel lands in the voxel holding its mean (two may share one).
        """
        if len(other) == 0:
            return 0
        T = np.asarray(T_self_other, np.float64)
        R, t = T[:3, :3], T[:3, 3]
        n = other.weight  # the weighted sums move with the sum of their weights
        s_old = other.sum_xyz
        s_new = s_old @ R.T + n[:, None] * t
        Q = _moments_to_matrices(other.sum_sq)  # [M, 3, 3] sum of p p^T
        Rs = s_old @ R.T  # [M, 3]
        Q_new = (R @ Q @ R.T + Rs[:, :, None] * t[None, None, :] + t[None, :, None] * Rs[:, None, :]
                 + n[:, None, None] * np.outer(t, t)[None])
        keys = pack_voxel_ids(np.floor(s_new / n[:, None] / self.voxel_size_m).astype(np.int64))
        uk, inv = np.unique(keys, return_inverse=True)
        nk = len(uk)

        def bsum(w: np.ndarray) -> np.ndarray:
            return np.bincount(inv, weights=w, minlength=nk)

        ssq6 = np.stack([Q_new[:, a, b] for a, b in _MOMENT_PAIRS], axis=1)
        return self._add(uk, bsum(other.count.astype(np.float64)).astype(np.int64),
                         np.stack([bsum(s_new[:, k]) for k in range(3)], axis=1),
                         np.stack([bsum(other.sum_rgb[:, k]) for k in range(3)], axis=1),
                         np.stack([bsum(ssq6[:, k]) for k in range(6)], axis=1),
                         bsum(other.n_keyframes.astype(np.float64)).astype(np.int32), bsum(n))

    def _add(self, uk: np.ndarray, cnt: np.ndarray, sxyz: np.ndarray, srgb: np.ndarray, ssq: np.ndarray,
             nkf: np.ndarray, wsum: np.ndarray) -> int:
        """Merge per-voxel sums for the sorted unique ids ``uk [M]`` into the state; returns new voxels.

        Both id sets are sorted, so the merge is a search of ``uk`` in ``ids`` and an insertion of
        the new ones (O(N + M log N)), not a sort of both."""
        from atlas_pipeline.gaussian_world._voxel_kernels import insert_rows

        n_old = len(self.ids)
        pos = np.searchsorted(self.ids, uk)
        exists = np.zeros(len(uk), bool)
        if n_old:
            exists = self.ids[np.minimum(pos, n_old - 1)] == uk
        at = pos[~exists]  # where each new id goes in the old order (before the voxel there)
        all_ids = insert_rows(self.ids, at, uk[~exists])
        new_idx = np.searchsorted(all_ids, uk)

        def merged(old: np.ndarray, new: np.ndarray) -> np.ndarray:
            out = insert_rows(old, at, 0)  # the new voxels start from zero sums
            out[new_idx] += new.astype(old.dtype)
            return out

        self.count = merged(self.count, cnt)
        self.sum_xyz = merged(self.sum_xyz, sxyz)
        self.sum_rgb = merged(self.sum_rgb, srgb)
        self.sum_sq = merged(self.sum_sq, ssq)
        self.n_keyframes = merged(self.n_keyframes, nkf)
        self.weight = merged(self.weight, wsum)
        self.ids = all_ids
        self.version += 1
        self.last_touched_ids = uk
        self.last_inserted_at = at
        return int(len(at))

    def to_field(self, min_points: int = 1) -> GaussianField:
        """The current Gaussians, one per voxel with at least ``min_points`` points.

        * mean: the mean of the voxel's points; colour: their mean colour;
        * covariance: the covariance of the voxel's points (a voxel with fewer than
          ``_MIN_POINTS_OWN_SHAPE`` points, or a degenerate one, takes the plane of its 3x3x3 voxel
          neighbourhood instead), as a rotation (local x, y = the surface directions, z = the
          normal) and three scales. The scales are the standard deviations times sqrt(3), so a
          voxel face evenly covered by points gives a Gaussian of about half a voxel that meets its
          neighbours without holes; they are clamped to [``_MIN_SCALE``, ``_MAX_SCALE``] voxels, so a
          Gaussian stays thin along the normal and never bleeds far past its voxel;
        * opacity: from support (points observed), saturating after a handful.

        Deterministic: the same statistics give the same field bit for bit (sorted ids, float64
        arithmetic, canonical eigenvector signs).
        """
        from atlas_pipeline.gaussian_world._voxel_kernels import neighbourhood_surfels
        from atlas_pipeline.geometry import rotmat_to_quat_xyzw

        keep = self.count >= min_points
        n = int(keep.sum())
        cnt = self.count[keep].astype(np.float64)
        wsum = self.weight[keep]  # positions and shapes are weighted means (== cnt without weights)
        pos = self.sum_xyz[keep] / wsum[:, None]
        rgb = np.clip(np.rint(self.sum_rgb[keep] / cnt[:, None]), 0, 255)
        v = self.voxel_size_m
        if n == 0:
            return GaussianField.empty()
        sq = self.sum_sq[keep] / wsum[:, None]
        cov = np.empty((n, 3, 3))
        for a, b, c in ((0, 0, 0), (0, 1, 1), (0, 2, 2), (1, 1, 3), (1, 2, 4), (2, 2, 5)):
            cov[:, a, b] = cov[:, b, a] = sq[:, c] - pos[:, a] * pos[:, b]
        w, vec = np.linalg.eigh(cov)  # ascending eigenvalues; columns are eigenvectors
        w = np.maximum(w, 0.0)
        # Local axes: x = largest spread, y = middle, z = smallest (the surface normal).
        R = vec[:, :, ::-1].copy()
        scales = np.sqrt(w[:, ::-1] * 3.0)
        # Sparse or line-like voxels: a disk in the plane of the voxel neighbourhood.
        _, nb_normal, support = neighbourhood_surfels(
            np.ascontiguousarray(self.ids[keep]), unpack_voxel_ids(self.ids[keep]), np.ascontiguousarray(wsum),
            np.ascontiguousarray(self.sum_xyz[keep]), np.ascontiguousarray(self.sum_sq[keep]), _OFFSET, _BITS)
        weak = (cnt < _MIN_POINTS_OWN_SHAPE) | (scales[:, 1] < _MIN_SCALE * v)
        if weak.any():
            nz = nb_normal[weak]
            # Any unit vector not parallel to the normal completes the frame.
            helper = np.where(np.abs(nz[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
            ax = np.cross(nz, helper)
            ax /= np.linalg.norm(ax, axis=1, keepdims=True)
            ay = np.cross(nz, ax)
            R[weak] = np.stack([ax, ay, nz], axis=2)
            scales[weak] = [0.5 * v, 0.5 * v, _MIN_SCALE * v]
        # Canonical signs: x and z axes point to their largest-magnitude component's positive side,
        # y completes a right-handed frame (det +1) -- independent of the eigen solver's choices.
        for k in (0, 2):
            col = R[:, :, k]
            big = np.take_along_axis(col, np.abs(col).argmax(axis=1)[:, None], axis=1)
            R[:, :, k] *= np.where(big < 0, -1.0, 1.0)
        R[:, :, 1] = np.cross(R[:, :, 2], R[:, :, 0])
        # A voxel's points lie inside it (or inside its merge cell), which bounds their spread; the
        # clamp is for degenerate moments, as wide as the widest cell.
        scales = np.clip(scales, _MIN_SCALE * v, _MAX_SCALE * v * MAX_CELL_VOXELS)
        # Canonical values survive the PLY's log/logit encoding bit for bit.
        return canonicalize(GaussianField(
            positions=pos, scales=scales.astype(np.float32), rotations_xyzw=rotmat_to_quat_xyzw(R).astype(np.float32),
            colors=rgb, opacities=_opacity_from_support(self.count[keep]), ids=self.ids[keep],
        ))


_POSE_SOURCES = ("ground_truth", "estimated")  # as mapping.keyframes.POSE_SOURCES (no import cycle)
# world.npz members: (dtype kinds or exact dtype, ndim); shapes in GaussianWorld / VoxelGaussianBuilder.
_WORLD_MEMBERS = {
    "positions": ("f", 2), "scales": ("f", 2), "rotations_xyzw": ("f", 2), "colors": (np.uint8, 2),
    "opacities": ("f", 1), "ids": (np.uint64, 1), "voxel_ids": (np.uint64, 1), "voxel_count": ("iu", 1),
    "voxel_sum_xyz": ("f", 2), "voxel_sum_rgb": ("f", 2), "voxel_sum_sq": ("f", 2),
    "voxel_n_keyframes": ("iu", 1), "keyframe_indices": ("iu", 1), "T_world_cam_keyframes": ("f", 3),
    "history": ("iu", 1),
}
_SH_MEMBER = "sh_rest"  # optional: [N, K, 3] SH coefficients of a field with view-dependent colour
# optional: [K] index of each keyframe's recording into world.json's ``recordings`` (worlds saved
# before keyframes named their recording lack it)
_RECORDING_MEMBER = "keyframe_recording"
# The mapping statistics (optional: worlds saved before mapping had its own depth range lack them).
_MAP_PREFIX = "map_voxel_"
_MAP_MEMBERS = {
    "map_voxel_ids": (np.uint64, 1), "map_voxel_count": ("iu", 1), "map_voxel_weight": ("f", 1),
    "map_voxel_sum_xyz": ("f", 2), "map_voxel_sum_rgb": ("f", 2), "map_voxel_sum_sq": ("f", 2),
    "map_voxel_n_keyframes": ("iu", 1),
}


@dataclass
class GaussianWorld:
    """A built world: the Gaussian field, the voxel statistics behind it, and how it was made.

    Attributes:
        field: the Gaussians.
        tracking_voxels: the voxel statistics of the tracking map (points within the tracking depth range,
            ``fusion``, unweighted): localization tracks against their surfels, and a later session
            keeps merging into them.
        map_voxels: the voxel statistics the field was made from (points within the mapping
            depth range, ``mapping.max_depth_m``, weighted by inverse depth variance), or None when
            they are ``tracking_voxels`` itself (a world saved before mapping had its own range).
        keyframe_indices: ``[K]`` frames merged, in merge order.
        T_world_cam_keyframes: ``[K, 4, 4]`` the poses they were merged with.
        pose_source: ``ground_truth`` or ``estimated``.
        history: ``[K]`` number of Gaussians after each merge.
        fit: how the field was fitted to the keyframe images (JSON-ready; empty when it was not):
            the keyframe fit's own record, ``optimize.OptimizationResult.record`` (steps and passes
            that ran, ``stop_reason``, ``final_loss``, the coarse level, Gaussians cloned, split and
            pruned). Content only: timings are run metadata, never part of the world.
        recordings: the recordings the keyframes come from, JSON records
            (:func:`atlas_pipeline.scene_memory.recordings.recording_record`: name, root,
            content_hash, n_frames, camera).
        keyframe_recording: ``[K]`` int64 index of each keyframe's recording into ``recordings``
            (``keyframe_indices[k]`` is a frame of that recording), or None when not recorded.
    """

    field: GaussianField
    tracking_voxels: VoxelGaussianBuilder
    keyframe_indices: np.ndarray
    T_world_cam_keyframes: np.ndarray
    pose_source: str
    history: np.ndarray
    fit: dict = field(default_factory=dict)
    map_voxels: VoxelGaussianBuilder | None = None
    recordings: list = field(default_factory=list)
    keyframe_recording: np.ndarray | None = None

    @property
    def map_id(self) -> str:
        return self.field.content_hash()[:16]

    @property
    def field_voxels(self) -> VoxelGaussianBuilder:
        """The statistics the field is made from: ``map_voxels``, else ``tracking_voxels``."""
        return self.tracking_voxels if self.map_voxels is None else self.map_voxels

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "world.npz"
        b = self.tracking_voxels
        with atomic_path(path) as tmp:
            save_npz_deterministic(
                tmp,
                positions=self.field.positions, scales=self.field.scales,
                rotations_xyzw=self.field.rotations_xyzw, colors=self.field.colors,
                opacities=self.field.opacities, ids=self.field.ids,
                voxel_ids=b.ids, voxel_count=b.count, voxel_sum_xyz=b.sum_xyz,
                voxel_sum_rgb=b.sum_rgb, voxel_sum_sq=b.sum_sq, voxel_n_keyframes=b.n_keyframes,
                keyframe_indices=self.keyframe_indices, T_world_cam_keyframes=self.T_world_cam_keyframes,
                history=self.history, **self._mapping_members(),
                # view-dependent colour only when the field has it: degree-0 worlds keep their bytes
                **({_SH_MEMBER: self.field.sh_rest} if self.field.sh_degree else {}),
                **({_RECORDING_MEMBER: np.asarray(self.keyframe_recording, np.int64)}
                   if self.keyframe_recording is not None else {}),
            )
        meta = write_json_atomic(directory / "world.json", {
            "map_id": self.map_id, "n_gaussians": len(self.field), "voxel_size_m": b.voxel_size_m,
            "n_keyframes": int(len(self.keyframe_indices)), "pose_source": self.pose_source,
            # timings are run metadata, not content (equal worlds give equal bytes)
            "fit": {k: v for k, v in self.fit.items() if k != "seconds"},
            **({"recordings": list(self.recordings)} if self.keyframe_recording is not None else {}),
        })
        return [path, meta]

    def _mapping_members(self) -> dict[str, np.ndarray]:
        m = self.map_voxels
        if m is None:
            return {}
        return {"map_voxel_ids": m.ids, "map_voxel_count": m.count, "map_voxel_weight": m.weight,
                "map_voxel_sum_xyz": m.sum_xyz, "map_voxel_sum_rgb": m.sum_rgb, "map_voxel_sum_sq": m.sum_sq,
                "map_voxel_n_keyframes": m.n_keyframes}

    @classmethod
    def load(cls, directory: Path) -> "GaussianWorld":
        """Read :meth:`save`'s folder. Every array is checked (dtype, shape, matching lengths,
        finite values, sorted voxel ids) before it is used; a malformed file raises
        ``ArtifactError`` naming it."""
        path, meta_path = directory / "world.npz", directory / "world.json"
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: Gaussian world missing world.npz or world.json")
        meta = load_json_object_checked(meta_path)
        voxel_size_m, pose_source, fit = meta.get("voxel_size_m"), meta.get("pose_source"), meta.get("fit", {})
        if not is_finite_number(voxel_size_m) or voxel_size_m <= 0:
            raise ArtifactError(f"{meta_path}: voxel_size_m must be a positive number, got {voxel_size_m!r}")
        if pose_source not in _POSE_SOURCES or not isinstance(fit, dict):
            raise ArtifactError(f"{meta_path}: pose_source must be one of {list(_POSE_SOURCES)} and fit an object, "
                                f"got {str(pose_source)[:40]!r} and {type(fit).__name__}")
        z = load_npz_checked(path, _WORLD_MEMBERS, error_type=ArtifactError)
        import zipfile

        with zipfile.ZipFile(path) as zf:  # already checked as an archive by load_npz_checked
            has_map = any(name.startswith(_MAP_PREFIX) for name in zf.namelist())
            has_sh = f"{_SH_MEMBER}.npy" in zf.namelist()
            has_rec = f"{_RECORDING_MEMBER}.npy" in zf.namelist()
        if has_map:
            z.update(load_npz_checked(path, _MAP_MEMBERS, error_type=ArtifactError))
        if has_sh:
            z.update(load_npz_checked(path, {_SH_MEMBER: ("f", 3)}, error_type=ArtifactError))
        if has_rec:
            z.update(load_npz_checked(path, {_RECORDING_MEMBER: ("iu", 1)}, error_type=ArtifactError))

        def bad(msg: str) -> ArtifactError:
            return ArtifactError(f"{path}: {msg}")

        n, m, k = len(z["positions"]), len(z["voxel_ids"]), len(z["keyframe_indices"])
        want = {"positions": (n, 3), "scales": (n, 3), "rotations_xyzw": (n, 4), "colors": (n, 3),
                "opacities": (n,), "ids": (n,), "voxel_count": (m,), "voxel_sum_xyz": (m, 3),
                "voxel_sum_rgb": (m, 3), "voxel_sum_sq": (m, 6), "voxel_n_keyframes": (m,),
                "T_world_cam_keyframes": (k, 4, 4)}
        if has_map:
            mm = len(z["map_voxel_ids"])
            want.update({"map_voxel_count": (mm,), "map_voxel_weight": (mm,), "map_voxel_sum_xyz": (mm, 3),
                         "map_voxel_sum_rgb": (mm, 3), "map_voxel_sum_sq": (mm, 6), "map_voxel_n_keyframes": (mm,)})
        for name, shape in want.items():
            if z[name].shape != shape:
                raise bad(f"{name} has shape {list(z[name].shape)}, expected {list(shape)}")
        recordings = meta.get("recordings", [])
        if has_rec:
            if not isinstance(recordings, list) or not all(isinstance(r, dict) for r in recordings):
                raise ArtifactError(f"{meta_path}: recordings must be a list of objects, one per recording")
            if z[_RECORDING_MEMBER].shape != (k,):
                raise bad(f"{_RECORDING_MEMBER} has shape {list(z[_RECORDING_MEMBER].shape)}, expected [{k}]")
            if k and (z[_RECORDING_MEMBER].min() < 0 or z[_RECORDING_MEMBER].max() >= len(recordings)):
                raise bad(f"{_RECORDING_MEMBER} must index the {len(recordings)} recordings of {meta_path.name}")
        if has_sh and not (z[_SH_MEMBER].shape[::2] == (n, 3) and sh_degree_of_rest_count(z[_SH_MEMBER].shape[1])):
            raise bad(f"{_SH_MEMBER} has shape {list(z[_SH_MEMBER].shape)}, expected [{n}, K, 3] with K in 3, 8, 15")
        finite = ["positions", "scales", "rotations_xyzw", "opacities", "voxel_sum_xyz", "voxel_sum_rgb",
                  "voxel_sum_sq", "T_world_cam_keyframes"] + ([_SH_MEMBER] if has_sh else [])
        for name in finite + (["map_voxel_weight", "map_voxel_sum_xyz", "map_voxel_sum_rgb", "map_voxel_sum_sq"]
                              if has_map else []):
            if not np.isfinite(z[name]).all():
                raise bad(f"{name} has NaN or infinite values")
        for name in ("voxel_ids", "map_voxel_ids") if has_map else ("voxel_ids",):
            # compared, not subtracted: a uint64 difference wraps, so a decreasing pair would pass
            if len(z[name]) and not (z[name][1:] > z[name][:-1]).all():
                raise bad(f"{name} must be strictly increasing (the merge relies on sorted ids)")
        if has_map and len(z["map_voxel_weight"]) and not (z["map_voxel_weight"] > 0).all():
            raise bad("map_voxel_weight must be > 0 (sums of positive point weights)")
        from atlas_pipeline.gaussian_world.field import ids_unique  # np.unique: ~1.5 s per million ids

        if not ids_unique(z["ids"]):
            raise bad("Gaussian ids are not unique")
        if (z["scales"] < 0).any() or (z["opacities"] < 0).any() or (z["opacities"] > 1).any():
            raise bad("scales must be >= 0 and opacities in [0, 1]")

        def counts(name: str, dtype) -> np.ndarray:
            # integers are cast to the builder's dtypes: refuse values that would wrap on the way
            a = z[name]
            if a.size and (a.min() < 0 or int(a.max()) > np.iinfo(dtype).max):
                raise bad(f"{name} must be in [0, {np.iinfo(dtype).max}]")
            return a.astype(dtype, copy=False)

        def f64(name: str) -> np.ndarray:  # no copy when the archive already holds native float64
            return np.asarray(z[name], dtype=np.float64)

        fld = GaussianField(z["positions"], z["scales"], z["rotations_xyzw"], z["colors"], z["opacities"], z["ids"],
                            z.get(_SH_MEMBER))
        builder = VoxelGaussianBuilder(
            float(voxel_size_m), np.asarray(z["voxel_ids"], np.uint64), counts("voxel_count", np.int64),
            f64("voxel_sum_xyz"), f64("voxel_sum_rgb"), f64("voxel_sum_sq"), counts("voxel_n_keyframes", np.int32))
        mapping = None
        if has_map:
            mapping = VoxelGaussianBuilder(
                float(voxel_size_m), np.asarray(z["map_voxel_ids"], np.uint64), counts("map_voxel_count", np.int64),
                f64("map_voxel_sum_xyz"), f64("map_voxel_sum_rgb"), f64("map_voxel_sum_sq"),
                counts("map_voxel_n_keyframes", np.int32), f64("map_voxel_weight"))
        return cls(fld, builder, counts("keyframe_indices", np.int64), f64("T_world_cam_keyframes"),
                   pose_source, counts("history", np.int64), dict(fit), mapping,
                   [dict(r) for r in recordings] if has_rec else [],
                   z[_RECORDING_MEMBER].astype(np.int64) if has_rec else None)

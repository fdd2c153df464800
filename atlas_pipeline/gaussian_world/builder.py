"""Voxel Gaussian merge (paper section 5.2), incremental per keyframe, with stable ids.

Points are binned into voxels of size ``v``. Each voxel keeps running sums (count, position,
colour, second moments), so merging a new keyframe only adds to sums: the result does not depend on
how keyframes are batched, and a voxel's id is derived from its integer coordinates, so the same
surface patch keeps the same id across merges, reruns and sessions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize
from atlas_pipeline.io_utils import atomic_path, write_json_atomic

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


def _opacity_from_support(count: np.ndarray) -> np.ndarray:
    """More observed points -> more confident surface. Saturates after a handful of samples."""
    return np.clip(1.0 - np.exp(-count / 3.0), 0.05, 0.99).astype(np.float32)


@dataclass
class VoxelGaussianBuilder:
    """Accumulates world-frame points into voxel statistics; one Gaussian per occupied voxel.

    State arrays (N occupied voxels, kept sorted by id):
        ids ``[N]`` uint64, count ``[N]`` int64, sum_xyz ``[N, 3]`` float64,
        sum_rgb ``[N, 3]`` float64, sum_sq ``[N, 6]`` float64 (xx xy xz yy yz zz, for covariances),
        n_keyframes ``[N]`` int32 (keyframes that observed the voxel).
    """

    voxel_size_m: float
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))
    count: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sum_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sum_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sum_sq: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    n_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    def __len__(self) -> int:
        return len(self.ids)

    def integrate(self, points_world: np.ndarray, colors: np.ndarray) -> int:
        """Merge one keyframe's points ``[M, 3]`` and colours ``[M, 3]``; returns new voxel count."""
        if len(points_world) == 0:
            return 0
        p = np.asarray(points_world, dtype=np.float64)
        c = np.asarray(colors, dtype=np.float64)
        keys = pack_voxel_ids(np.floor(p / self.voxel_size_m).astype(np.int64))
        uk, inv = np.unique(keys, return_inverse=True)
        nk = len(uk)

        def bsum(w: np.ndarray) -> np.ndarray:
            return np.bincount(inv, weights=w, minlength=nk)

        cnt = np.bincount(inv, minlength=nk).astype(np.int64)
        sxyz = np.stack([bsum(p[:, k]) for k in range(3)], axis=1)
        srgb = np.stack([bsum(c[:, k]) for k in range(3)], axis=1)
        pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        ssq = np.stack([bsum(p[:, a] * p[:, b]) for a, b in pairs], axis=1)

        # Merge sorted key sets: existing voxels accumulate, new ones are inserted in id order.
        all_ids, inv2 = np.unique(np.concatenate([self.ids, uk]), return_inverse=True)
        n_new = len(all_ids) - len(self.ids)
        old_idx, new_idx = inv2[: len(self.ids)], inv2[len(self.ids):]

        def merged(old: np.ndarray, new: np.ndarray) -> np.ndarray:
            out = np.zeros((len(all_ids),) + old.shape[1:], dtype=old.dtype)
            out[old_idx] = old
            out[new_idx] += new.astype(old.dtype)
            return out

        self.count = merged(self.count, cnt)
        self.sum_xyz = merged(self.sum_xyz, sxyz)
        self.sum_rgb = merged(self.sum_rgb, srgb)
        self.sum_sq = merged(self.sum_sq, ssq)
        self.n_keyframes = merged(self.n_keyframes, np.ones(nk, np.int32))
        self.ids = all_ids
        return n_new

    def to_field(self, min_points: int = 1) -> GaussianField:
        """The current Gaussians: mean position, mean colour, isotropic scale v/2, support opacity."""
        keep = self.count >= min_points
        cnt = self.count[keep].astype(np.float64)[:, None]
        n = int(keep.sum())
        pos = self.sum_xyz[keep] / cnt
        rgb = np.clip(np.rint(self.sum_rgb[keep] / cnt), 0, 255)
        rot = np.zeros((n, 4), np.float32)
        rot[:, 3] = 1.0
        # Canonical values survive the PLY's log/logit encoding bit for bit.
        return canonicalize(GaussianField(
            positions=pos, scales=np.full((n, 3), self.voxel_size_m / 2.0, np.float32),
            rotations_xyzw=rot, colors=rgb, opacities=_opacity_from_support(self.count[keep]),
            ids=self.ids[keep],
        ))


@dataclass
class GaussianWorld:
    """A built world: the Gaussian field, the voxel statistics behind it, and how it was made.

    Attributes:
        field: the Gaussians.
        builder: the voxel statistics, kept so a later session can keep merging into this world.
        keyframe_indices: ``[K]`` frames merged, in merge order.
        T_world_cam_keyframes: ``[K, 4, 4]`` the poses they were merged with.
        pose_source: ``ground_truth`` or ``estimated``.
        history: ``[K]`` number of Gaussians after each merge.
    """

    field: GaussianField
    builder: VoxelGaussianBuilder
    keyframe_indices: np.ndarray
    T_world_cam_keyframes: np.ndarray
    pose_source: str
    history: np.ndarray

    @property
    def map_id(self) -> str:
        return self.field.content_hash()[:16]

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "world.npz"
        b = self.builder
        with atomic_path(path) as tmp:
            np.savez(
                tmp,
                positions=self.field.positions, scales=self.field.scales,
                rotations_xyzw=self.field.rotations_xyzw, colors=self.field.colors,
                opacities=self.field.opacities, ids=self.field.ids,
                voxel_ids=b.ids, voxel_count=b.count, voxel_sum_xyz=b.sum_xyz,
                voxel_sum_rgb=b.sum_rgb, voxel_sum_sq=b.sum_sq, voxel_n_keyframes=b.n_keyframes,
                keyframe_indices=self.keyframe_indices, T_world_cam_keyframes=self.T_world_cam_keyframes,
                history=self.history,
            )
        meta = write_json_atomic(directory / "world.json", {
            "map_id": self.map_id, "n_gaussians": len(self.field), "voxel_size_m": b.voxel_size_m,
            "n_keyframes": int(len(self.keyframe_indices)), "pose_source": self.pose_source,
        })
        return [path, meta]

    @classmethod
    def load(cls, directory: Path) -> "GaussianWorld":
        path, meta_path = directory / "world.npz", directory / "world.json"
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: Gaussian world missing world.npz or world.json")
        meta = json.loads(meta_path.read_text())
        with np.load(path, allow_pickle=False) as z:
            fld = GaussianField(z["positions"], z["scales"], z["rotations_xyzw"], z["colors"],
                                z["opacities"], z["ids"])
            builder = VoxelGaussianBuilder(float(meta["voxel_size_m"]), z["voxel_ids"], z["voxel_count"],
                                           z["voxel_sum_xyz"], z["voxel_sum_rgb"], z["voxel_sum_sq"],
                                           z["voxel_n_keyframes"])
            return cls(fld, builder, z["keyframe_indices"], z["T_world_cam_keyframes"],
                       str(meta["pose_source"]), z["history"])

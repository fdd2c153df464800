"""Mapping poses and keyframe selection by pose change (paper section 5.3)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.config import MappingConfig
from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.geometry import invert_se3, rotation_angle_rad
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.localization.icp import PointModel, estimate_normals, icp_point_to_plane, voxel_downsample
from atlas_pipeline.perception.rgbd import FusedFrames
from atlas_pipeline.progress import Progress
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["KeyframeSet", "select_keyframes", "odometry_poses", "mapping_poses", "build_keyframes"]


def select_keyframes(T_world_cam: np.ndarray, valid: np.ndarray, translation_m: float,
                     rotation_deg: float) -> np.ndarray:
    """Indices of keyframes: the first valid frame, then every frame that moved more than
    ``translation_m`` or turned more than ``rotation_deg`` from the previous keyframe.

    Args:
        T_world_cam: ``[N, 4, 4]`` poses (rows where ``valid`` is False are ignored).
        valid: ``[N]`` bool, frames that have a pose.
    """
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return idx
    keys = [int(idx[0])]
    for i in idx[1:]:
        rel = invert_se3(T_world_cam[keys[-1]]) @ T_world_cam[i]
        moved = np.linalg.norm(rel[:3, 3])
        turned = np.degrees(rotation_angle_rad(rel[:3, :3]))
        if moved > translation_m or turned > rotation_deg:
            keys.append(int(i))
    return np.asarray(keys, dtype=np.int64)


def odometry_poses(fused: FusedFrames, voxel_m: float, max_corr_m: float = 0.05,
                   iterations: int = 30, log: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frame-to-frame point-to-plane ICP, chained from the first frame (which defines the world).

    Used for mapping when a dataset has no ground truth. Returns ``(T_world_cam [N, 4, 4],
    fitness [N])``; the first frame is the identity with fitness 1.
    """
    n = fused.n_frames
    poses = np.tile(np.eye(4), (n, 1, 1))
    fitness = np.ones(n)
    progress = Progress("odometry", n - 1, log)
    prev_model = None
    velocity = np.eye(4)
    for i in range(n):
        pts = voxel_downsample(fused.frame(i)[0].astype(np.float64), voxel_m)
        if len(pts) < 10:
            raise DatasetError(f"frame {i}", "too few valid depth points for odometry")
        if prev_model is not None:
            res = icp_point_to_plane(prev_model, pts, velocity, max_corr_m, iterations)
            velocity = res.T  # constant-velocity guess for the next frame
            poses[i] = poses[i - 1] @ res.T
            fitness[i] = res.fitness
            progress.update()
        prev_model = PointModel(pts, estimate_normals(pts, 3 * voxel_m, viewpoint=np.zeros(3)))
    return poses, fitness


def mapping_poses(manifest: FrameManifest, fused: FusedFrames, cfg: MappingConfig,
                  log: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """Poses the mapper places frames with: ``(T_world_cam [N, 4, 4], valid [N], source)``.

    ``auto`` uses ground truth when at least half the frames have it (as the paper does) and
    estimated odometry otherwise; ``ground_truth`` requires it.
    """
    n_gt = int(manifest.has_gt.sum())
    use_gt = cfg.pose_source == "ground_truth" or (cfg.pose_source == "auto" and n_gt >= manifest.n_frames / 2)
    if use_gt:
        if n_gt == 0:
            raise DatasetError(manifest.root, "mapping.pose_source is ground_truth but the dataset has no ground truth")
        return manifest.T_world_cam_gt.copy(), manifest.has_gt.copy(), "ground_truth"
    poses, _ = odometry_poses(fused, voxel_m=max(cfg.voxel_size_m, 0.01), log=log)
    return poses, np.ones(manifest.n_frames, bool), "estimated"


@dataclass
class KeyframeSet:
    """Mapping poses of all frames and the chosen keyframes.

    Attributes:
        T_world_cam: ``[N, 4, 4]`` mapping pose per frame (NaN where unknown).
        valid: ``[N]`` bool, frames with a mapping pose.
        indices: ``[K]`` int64 keyframe indices, increasing.
        pose_source: ``ground_truth`` or ``estimated``.
    """

    T_world_cam: np.ndarray
    valid: np.ndarray
    indices: np.ndarray
    pose_source: str

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "keyframes.npz"
        with atomic_path(path) as tmp:
            np.savez(tmp, T_world_cam=self.T_world_cam, valid=self.valid, indices=self.indices)
        meta = write_json_atomic(directory / "keyframes.json", {
            "pose_source": self.pose_source, "n_frames": int(len(self.valid)),
            "n_keyframes": int(len(self.indices)), "indices": [int(i) for i in self.indices],
        })
        return [path, meta]

    @classmethod
    def load(cls, directory: Path) -> "KeyframeSet":
        path, meta_path = directory / "keyframes.npz", directory / "keyframes.json"
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: keyframes missing keyframes.npz or keyframes.json")
        meta = json.loads(meta_path.read_text())
        with np.load(path, allow_pickle=False) as z:
            return cls(z["T_world_cam"], z["valid"], z["indices"], str(meta["pose_source"]))


def build_keyframes(manifest: FrameManifest, fused: FusedFrames, cfg: MappingConfig,
                    log: Callable[[str], None] | None = None) -> KeyframeSet:
    poses, valid, source = mapping_poses(manifest, fused, cfg, log)
    idx = select_keyframes(poses, valid, cfg.keyframe_translation_m, cfg.keyframe_rotation_deg)
    if len(idx) == 0:
        raise DatasetError(manifest.root, "no frame has a pose to map with")
    return KeyframeSet(poses, valid, idx, source)

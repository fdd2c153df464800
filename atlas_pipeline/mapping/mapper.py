"""Incremental mapping: merge keyframes one by one into a voxel Gaussian world."""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from atlas_pipeline.config import MappingConfig
from atlas_pipeline.gaussian_world.builder import GaussianWorld, VoxelGaussianBuilder
from atlas_pipeline.mapping.keyframes import KeyframeSet
from atlas_pipeline.perception.rgbd import FusedFrames
from atlas_pipeline.progress import Progress

logger = logging.getLogger(__name__)

__all__ = ["build_world", "extend_world"]


def extend_world(world: GaussianWorld | None, fused: FusedFrames, keyframes: KeyframeSet,
                 cfg: MappingConfig, log: Callable[[str], None] | None = None) -> GaussianWorld:
    """Merge ``keyframes`` into ``world`` (a new world when None), one keyframe at a time.

    Each keyframe's camera-frame points are moved to the world with its mapping pose and added to
    the voxel statistics; ids of voxels seen before are kept.
    """
    if world is not None and abs(world.builder.voxel_size_m - cfg.voxel_size_m) > 1e-12:
        raise ValueError(
            f"cannot extend a world built with {world.builder.voxel_size_m} m voxels using {cfg.voxel_size_m} m"
        )
    builder = VoxelGaussianBuilder(cfg.voxel_size_m) if world is None else world.builder
    history = [] if world is None else list(world.history)
    progress = Progress("merging keyframes", len(keyframes.indices), log, unit="keyframes")
    for k in keyframes.indices:
        pts, cols = fused.frame(int(k))
        T = keyframes.T_world_cam[k]
        pw = pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        builder.integrate(pw, cols)
        history.append(len(builder))
        progress.update()
    prev_idx = np.zeros(0, np.int64) if world is None else world.keyframe_indices
    prev_T = np.zeros((0, 4, 4)) if world is None else world.T_world_cam_keyframes
    return GaussianWorld(
        field=builder.to_field(),
        builder=builder,
        keyframe_indices=np.concatenate([prev_idx, keyframes.indices]).astype(np.int64),
        T_world_cam_keyframes=np.concatenate([prev_T, keyframes.T_world_cam[keyframes.indices]]),
        pose_source=keyframes.pose_source,
        history=np.asarray(history, dtype=np.int64),
    )


def build_world(fused: FusedFrames, keyframes: KeyframeSet, cfg: MappingConfig,
                log: Callable[[str], None] | None = None) -> GaussianWorld:
    """A new world from the keyframes of one sequence."""
    world = extend_world(None, fused, keyframes, cfg, log)
    logger.info("built world: %d Gaussians from %d keyframes", len(world.field), len(keyframes.indices))
    return world

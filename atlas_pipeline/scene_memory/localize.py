"""A recording placed in a saved world (``atlas-gs localize``) and its transitions (``atlas-gs
log-transitions``), each written into the world's bundle. Whether the part may go into the bundle
(:func:`atlas_pipeline.scene_memory.bundle.check_bundle_update`) is decided before any frame is read."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import DatasetEntry

if TYPE_CHECKING:
    import pyarrow as pa

    from atlas_pipeline.localization.localizer import LocalizationReport

__all__ = ["tracking_voxel_m", "localize_into_bundle", "log_bundle_transitions"]


def tracking_voxel_m(bundle: Any, cfg: PipelineConfig) -> float:
    """The map resolution a world was built at (the profile's where the bundle does not say)."""
    return float(bundle.metadata.get("gaussians", {}).get("voxel_size_m", cfg.mapping.voxel_size_m))


def localize_into_bundle(world: str | Path, entry: DatasetEntry, cfg: PipelineConfig,
                         start_pose: np.ndarray | None = None, relocalize: bool = False,
                         drop_transitions: bool = False) -> LocalizationReport:
    """Track ``entry``'s frames through the world bundle at ``world`` and write the report into it
    (``drop_transitions``: the transitions of an earlier report leave with it). The start is
    :func:`atlas_pipeline.scene_memory.metadata.start_pose`'s (``start_pose``: a given
    ``T_world_cam``). The world's own recording is never a mismatch; another that stops matching
    the map ends early, and the report says so (``summary["outcome"]``)."""
    from atlas_pipeline.io_utils import check_writable
    from atlas_pipeline.localization.localizer import localize_sequence
    from atlas_pipeline.memory_estimate import check_localization_memory
    from atlas_pipeline.scene_memory.bundle import (
        bundle_keyframe_poses,
        check_bundle_update,
        load_world_bundle,
        update_world_bundle,
    )
    from atlas_pipeline.scene_memory.metadata import start_pose as anchor_pose
    from atlas_pipeline.sensors.registry import load_dataset

    bundle = load_world_bundle(world)  # verifies every file the bundle lists
    check_bundle_update(world, entry.name, bundle.map_id, drop_transitions=drop_transitions, meta=bundle.metadata)
    check_writable(Path(world).parent)
    manifest = load_dataset(entry, cfg)
    check_localization_memory(cfg, manifest, len(bundle.field))
    T0, anchor = anchor_pose(bundle.metadata, entry.name, start_pose, relocalize=relocalize)
    if anchor >= manifest.n_frames:
        raise ConfigError(f"anchor frame {anchor} is beyond the {manifest.n_frames} frames loaded")
    own = bundle.metadata.get("dataset", {}).get("name") == entry.name
    report = localize_sequence(manifest, bundle.tracking_model(tracking_voxel_m(bundle, cfg)), cfg.localization,
                               T0, anchor, bundle.map_id, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                               prior_poses=bundle_keyframe_poses(bundle.metadata), stop_on_mismatch=not own,
                               places=bundle.stored_places(manifest.camera))
    update_world_bundle(world, localization=report, drop_transitions=drop_transitions)
    return report


def log_bundle_transitions(world: str | Path, entry: DatasetEntry, cfg: PipelineConfig) -> pa.Table:
    """Write ``transitions.parquet`` into the world bundle at ``world`` from the localization of
    ``entry`` it holds (ground-truth poses read again from the dataset when
    ``transitions.pose_source`` is ``ground_truth``); returns the table."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import check_bundle_update, update_world_bundle, verify_bundle_files
    from atlas_pipeline.sensors.registry import load_dataset
    from atlas_pipeline.transition_log.transitions import log_transitions

    world = Path(world)
    meta = verify_bundle_files(world)
    if not (world / "localization.json").is_file():
        spec = entry.name if entry.source_file else entry.path
        raise ConfigError(f"{world}: no localization.json; run `atlas-gs localize --world {world} --input {spec}` first")
    report = LocalizationReport.load(world)
    if report.dataset != entry.name:
        raise ConfigError(f"{world}/localization.json is for dataset '{report.dataset}', not '{entry.name}'")
    check_bundle_update(world, transitions_of={"dataset": entry.name, "map_id": report.map_id}, meta=meta)
    if cfg.transitions.pose_source == "ground_truth":  # refresh GT from the dataset, not the report
        report.T_world_cam_gt = load_dataset(entry, cfg).T_world_cam_gt
    table = log_transitions(report, entry.name, int(meta.get("n_gaussians", 0)), cfg)
    update_world_bundle(world, transitions=table)
    return table

"""A world bundle from a recording (``atlas-gs build``): fused frames, keyframes, the Gaussian
world and the tracker's map, written as one bundle; or more of a recording mapped into an earlier
bundle (``extend``), whose copy records it as its parent."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.sensors.registry import DatasetEntry

__all__ = ["BuiltWorld", "build_world_bundle"]


@dataclass(frozen=True)
class BuiltWorld:
    """What :func:`build_world_bundle` wrote."""

    path: Path
    n_gaussians: int
    n_keyframes: int  # keyframes this recording added
    map_id: str
    parent: dict[str, Any] | None  # the extended bundle's reference, None for a new world


def build_world_bundle(entry: DatasetEntry, cfg: PipelineConfig, output: str | Path, extend: str | Path | None = None,
                       force: bool = False, overrides: dict[str, Any] | None = None,
                       command: str = "atlas-gs build") -> BuiltWorld:
    """Map the recording ``entry`` into a new bundle at ``output`` (or into a copy of the bundle
    ``extend``). The output policy (:func:`atlas_pipeline.io_utils.prepare_output_dir`) and every
    file of ``extend`` are checked before any frame is read; ``overrides`` and ``command`` go into
    the lineage."""
    from atlas_pipeline.io_utils import prepare_output_dir
    from atlas_pipeline.localization.localizer import bundle_tracking_files
    from atlas_pipeline.mapping.mapper import build_gaussian_world, extend_saved_world, fuse_and_select_keyframes
    from atlas_pipeline.scene_memory.bundle import BUNDLE_KIND, load_world_bundle, parent_reference, write_world_bundle
    from atlas_pipeline.scene_memory.metadata import bundle_lineage, bundle_metadata
    from atlas_pipeline.memory_estimate import check_entry_memory
    from atlas_pipeline.sensors.registry import load_dataset

    inputs = [entry.path, extend]
    out = prepare_output_dir(output, BUNDLE_KIND, inputs, force)  # creates nothing; an input is never an output
    check_entry_memory(cfg, entry)  # before any frame is read
    if extend:
        # every listed file verified (world.npz, surfels.npz ...) before any work
        _check_extension_voxel(load_world_bundle(extend).metadata, extend, cfg)
    manifest = load_dataset(entry, cfg)
    parent = None
    if extend:
        parent = parent_reference(extend)
        world, n_keyframes = extend_saved_world(extend, manifest, None, cfg)  # fuses only if it needs to
    else:
        fused, keyframes = fuse_and_select_keyframes(manifest, cfg)  # each frame decoded once
        world = build_gaussian_world(fused, keyframes, cfg, manifest=manifest)
        n_keyframes = len(keyframes.indices)
    lineage = bundle_lineage(command, partition=entry.name, run_id=None, profile=cfg.profile,
                             config_overrides=overrides or {}, parent=parent)
    meta = bundle_metadata(entry.name, entry.name, world, manifest, cfg, lineage)
    model, places = bundle_tracking_files(world, manifest.camera, cfg.localization)
    write_world_bundle(out, world.field, meta, extras=(world,), surfels=model, places=places, inputs=inputs)
    return BuiltWorld(out, len(world.field), int(n_keyframes), world.map_id, parent)


# Voxel sizes this close are the same setting (a profile's value read back from JSON).
VOXEL_MATCH_TOL_M = 1e-12


def _check_extension_voxel(metadata: dict[str, Any], extend: str | Path, cfg: PipelineConfig) -> None:
    """An extension maps at the voxel size its world was built with: a ConfigError naming
    ``mapping.voxel_size_m`` and both sizes otherwise, before any frame is read."""
    from atlas_pipeline.errors import ConfigError

    built_m = (metadata.get("gaussians") or {}).get("voxel_size_m")
    asked_m = cfg.mapping.voxel_size_m
    if built_m is not None and abs(float(built_m) - asked_m) > VOXEL_MATCH_TOL_M:
        raise ConfigError(f"--extend {extend}: the world was built with mapping.voxel_size_m={float(built_m):g} m; "
                          f"this build would map it at mapping.voxel_size_m={asked_m:g} m. An extended world keeps "
                          f"its voxel size: leave mapping.voxel_size_m at {float(built_m):g} (drop that --set, or "
                          "use the profile the world was built with)")

"""The pipeline's software-defined assets, one per phase of the paper, and what they are made from.

Each pipeline asset receives its upstream artifacts as typed inputs (loaded by
:class:`assets.io_managers.ArtifactIOManager`), calls one library function and returns the artifact
with its content hash as data version (:func:`assets.versioning.versioned`), unless
:func:`assets.versioning.reuse` finds the partition's latest materialization current. Besides its
upstream assets each one depends on ``settings/<asset>`` (exactly the config fields it reads) and
``raw_dataset`` on ``dataset_files`` (the dataset folder, an observable source asset), so Dagster
records every input that shapes an artifact.
"""


import hashlib
import json
from pathlib import Path
from typing import Any, Optional

import numpy as np
import pyarrow as pa
from dagster import (
    AssetExecutionContext,
    AssetIn,
    Failure,
    StaticPartitionMapping,
    AssetsDefinition,
    AssetSpec,
    DataVersion,
    DataVersionsByPartition,
    MetadataValue,
    PartitionsDefinition,
    asset,
    multi_asset,
    observable_source_asset,
)

from assets.checks import (
    ATE_BOUND,
    BUNDLE_ROUNDTRIP,
    GAUSSIANS_VALID,
    TRANSITIONS_SCHEMA_OK,
    check_ate,
    check_bundle_roundtrip,
    check_gaussians,
    check_transitions_schema,
)
from assets.io_managers import artifacts_root
from assets.resources import AtlasConfig, dataset_entry
from assets.storage import is_remote, local_scratch
from assets.versioning import (
    DATASET_FILES,
    FIRST_VISIT_WORLD,
    REVISIT_STAGE,
    STAGES,
    artifact,
    lineage,
    reuse,
    settings_key,
    settings_result,
    settings_version,
    stage_settings,
    versioned,
)
from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering
from atlas_pipeline.io_utils import discard_dir
from atlas_pipeline.localization.localizer import LocalizationReport, bundle_tracking_files, localize, localize_visit
from atlas_pipeline.mapping.keyframes import KeyframeSet
from atlas_pipeline.mapping.mapper import build_gaussian_world, extend_world_with_visit, select_keyframes_stage
from atlas_pipeline.memory_estimate import check_memory, shape_of_manifest
from atlas_pipeline.perception.rgbd import FusedFrames, fuse
from atlas_pipeline.scene_memory.metadata import WorldBundleArtifact, bundle_lineage, bundle_metadata
from atlas_pipeline.sensors.registry import ensure_dataset_files, load_dataset, load_registry, revisits
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.transition_log.transitions import log_transitions
from atlas_pipeline.versioning import dataset_signature
from atlas_pipeline.viz.demo import render_demo_videos
from atlas_pipeline.viz.plots import markdown_image, preview_size, render_preview_png

GROUP = "atlas_gs"
IO = "artifact_io"


METADATA_SIG_DIGITS = 4  # floats shown in the UI: 0.001118, 21.32, not 0.0011175289268451744


def _sig(x: float) -> float:
    """``x`` to :data:`METADATA_SIG_DIGITS` significant digits."""
    return float(f"{x:.{METADATA_SIG_DIGITS}g}")


def _num(x: float) -> float | None:
    return _sig(float(x)) if x is not None and np.isfinite(x) else None


def _rounded(v: Any) -> Any:
    """Floats (also inside lists and dicts, for JSON metadata) rounded for reading; NaN / inf kept."""
    if isinstance(v, (float, np.floating)):
        return _sig(float(v)) if np.isfinite(v) else float(v)
    if isinstance(v, dict):
        return {k: _rounded(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_rounded(x) for x in v]
    return v


def _md_table(df) -> str:
    """A small DataFrame as a Markdown table (no extra dependency)."""
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    rows = ["| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r) + " |"
            for r in df.itertuples(index=False)]
    return head + "\n".join(rows)


SIGNATURES_DIR = ".signatures"  # under a local artifacts root (else the machine's scratch): content-hash caches


def signature_cache_dir() -> Path:
    root = artifacts_root()
    return local_scratch() / SIGNATURES_DIR if is_remote(str(root)) else Path(root) / SIGNATURES_DIR


def dataset_version(name: str) -> str:
    """Data version of a dataset: its registry entry and the signature (names, sizes, content hashes)
    of its files (:func:`atlas_pipeline.versioning.dataset_signature`; hashes cached by file identity)."""
    entry = dataset_entry(name)
    text = json.dumps(entry.describe(), sort_keys=True, default=str) + dataset_signature(entry.path, signature_cache_dir())
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def build_pipeline_assets(partitions_def: PartitionsDefinition, cfg: PipelineConfig) -> list[AssetsDefinition]:
    """The asset graph for one partition set (the datasets of the registry). ``cfg``, the code
    location's profile, versions the ``settings/*`` code: after a profile is edited and the code
    location reloaded, the UI shows the settings it changes as stale."""

    def settings_code(stage: str) -> str:
        return f"1+{settings_version(stage_settings(cfg, stage))}"

    def stage(name: str, code_version: str, description: str, *, extra_deps=(), check=None):
        return asset(name=name, code_version=code_version, description=description, partitions_def=partitions_def,
                     io_manager_key=IO, group_name=GROUP, deps=[settings_key(name), *extra_deps],
                     check_specs=[check] if check else None)

    @observable_source_asset(key=DATASET_FILES, partitions_def=partitions_def, group_name=GROUP,
                             description="The dataset's folder (or bag file) as registered; data version: the registry "
                                         "entry and the names, sizes and content hashes of its files. A "
                                         "generated (synthetic) dataset is generated first.")
    def dataset_files(context):
        names = [context.partition_key] if context.has_partition_key else partitions_def.get_partition_keys()
        for name in names:
            entry = dataset_entry(name)
            if entry.kind == "synthetic":  # defined by its spec: make the files the version describes
                ensure_dataset_files(entry)
        return DataVersionsByPartition({n: DataVersion(dataset_version(n)) for n in names})

    @multi_asset(name="settings", can_subset=True, specs=[
        AssetSpec(settings_key(s), partitions_def=partitions_def, group_name="settings", code_version=settings_code(s),
                  description=f"The config fields {s} reads, from the run's atlas resource (data version: their hash).")
        for s in STAGES if s != "keyframes"])
    def settings(context: AssetExecutionContext, atlas: AtlasConfig):
        cfg = atlas.load()
        for key in sorted(context.selected_asset_keys, key=lambda k: k.path):
            yield settings_result(key, stage_settings(cfg, key.path[-1]))

    @asset(key=settings_key("keyframes"), partitions_def=partitions_def, group_name="settings",
           code_version=settings_code("keyframes"),
           description="The config fields keyframes reads: the tracker's settings too when the dataset is mapped "
                       "from tracked poses (no ground truth, or mapping.pose_source estimated).")
    def keyframes_settings(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest):
        return settings_result(context.asset_key, stage_settings(atlas.load(), "keyframes", raw_dataset))

    @stage("raw_dataset", "2", "Frame manifest of the dataset: files, frame (depth) and colour timestamps, intrinsics, "
                              "ground truth at the frame times, content hash.",
           extra_deps=[DATASET_FILES])
    def raw_dataset(context: AssetExecutionContext, atlas: AtlasConfig):
        cfg, name = atlas.load(), context.partition_key
        if (out := reuse(context, cfg, dataset=dataset_version(name))) is not None:
            return out
        manifest = load_dataset(dataset_entry(name), cfg, log=context.log.info)
        check_memory(cfg, shape_of_manifest(manifest), name)  # a run from the UI: before the heavy stages
        return versioned(context, manifest, {
            "n_frames": manifest.n_frames,
            "n_with_ground_truth": int(manifest.has_gt.sum()),
            "duration_s": _num(manifest.timestamps_s[-1] - manifest.timestamps_s[0]),
            "camera": MetadataValue.json(manifest.camera.to_dict()),
            "dataset_root": MetadataValue.path(str(manifest.root)),
            "raw_content_hash": manifest.content_hash[:16],
            "dataset_version": dataset_version(name),  # after generating or downloading it
        })

    @stage("fused_frames", "2", "Back-projected coloured points of every frame (camera frame), in chunks of 32 frames; depth range and stride from config.")
    def fused_frames(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is not None:
            return out
        fused = fuse(raw_dataset, cfg, log=context.log.info)
        return versioned(context, fused, {"n_points": fused.n_points,
                                          "mean_valid_fraction": _num(fused.valid_fraction.mean())})

    @stage("keyframes", "11", "Mapping poses and keyframes: ground truth selected by motion, or (pose_source estimated / "
                             "no ground truth) the RGB-D tracker's own trajectory and keyframes.")
    def keyframes(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                  fused_frames: FusedFrames):
        cfg = atlas.load()
        if (out := reuse(context, cfg, raw_dataset)) is not None:
            return out
        kf = select_keyframes_stage(raw_dataset, fused_frames, cfg, log=context.log.info)
        return versioned(context, kf, {"n_keyframes": int(len(kf.indices)), "pose_source": kf.pose_source,
                                       "keyframe_indices": MetadataValue.json([int(i) for i in kf.indices])})

    @stage("gaussian_world", "12", "Gaussian world: anisotropic Gaussians merged per voxel from the keyframes (stable uint64 "
                                  "ids), then fitted to the keyframe images and depths (positions, scales, rotations, "
                                  "opacities, colours).", check=GAUSSIANS_VALID)
    def gaussian_world(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                       fused_frames: FusedFrames, keyframes: KeyframeSet):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is None:
            world = build_gaussian_world(fused_frames, keyframes, cfg, log=context.log.info, manifest=raw_dataset)
            lo, hi = world.field.bounds()
            # the dataset's camera at a readable size (its own, halved while wide), not a thumbnail
            cam = raw_dataset.camera
            pw, ph = preview_size(cam.width, cam.height)
            K = np.diag([pw / cam.width, ph / cam.height, 1.0]) @ cam.K
            preview = render_preview_png(world.field, world.T_world_cam_keyframes[0], pw, ph, K=K)
            out = versioned(context, world, {
                "n_gaussians": len(world.field),
                "map_id": world.map_id,
                "voxel_size_m": _num(world.tracking_voxels.voxel_size_m),
                "extent_m": MetadataValue.json([round(float(v), 3) for v in hi - lo]),
                "gaussians_after_each_keyframe": MetadataValue.json([int(h) for h in world.history]),
                "fit": MetadataValue.json(_rounded(world.fit)),  # with its timing (world.json keeps the rest)
                "render_preview": MetadataValue.md(markdown_image(preview, "render from the first keyframe")),
            })
        yield out
        yield check_gaussians(artifact(context, out).field)

    @stage("localization_report", "9", "Per-frame pose tracked against the world (frame-to-model, no ground truth used): "
                                       "status, residual; ATE and RPE where ground truth exists; trajectory plot. Timings "
                                       "are metadata.", check=ATE_BOUND)
    def localization_report(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                            gaussian_world: GaussianWorld):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is None:
            report = localize(raw_dataset, gaussian_world, cfg, log=context.log.info)
            s = report.summary
            out = versioned(context, report, {
                "n_tracked": s["n_tracked"],
                "n_lost": s["n_lost"],
                "n_relocalized": s.get("n_relocalized", 0),
                "ate_rmse_m": _num(s.get("ate_rmse_m")),
                "ate_rot_rmse_deg": _num(s.get("ate_rot_rmse_deg")),
                "rpe_trans_rmse_m_per_s": _num(s.get("rpe_trans_rmse_m_per_s")),
                "rpe_rot_rmse_deg_per_s": _num(s.get("rpe_rot_rmse_deg_per_s")),
                "frames_per_s": _num(s.get("frames_per_s")),
                "mean_time_per_frame_s": _num(s.get("mean_time_per_frame_s")),
                "outcome": str(s.get("outcome", "complete")),
                "n_not_attempted": int(s.get("n_not_attempted", 0)),
                "stopped_reason": MetadataValue.text(str(s.get("stopped_reason") or "")),
                "trajectory_plot": MetadataValue.md(markdown_image(
                    report.trajectory_plot_png(f"{context.partition_key}: top view"), "trajectory, top view")),
            })
        yield out
        yield check_ate(artifact(context, out).summary, cfg.localization.max_ate_m)

    @stage("transitions", "4", "State-action-state transitions, one row per consecutive frame pair (Parquet).",
           check=TRANSITIONS_SCHEMA_OK)
    def transitions(context: AssetExecutionContext, atlas: AtlasConfig, localization_report: LocalizationReport,
                    gaussian_world: GaussianWorld):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is None:
            table = log_transitions(localization_report, context.partition_key, len(gaussian_world.field), cfg)
            preview = table.slice(0, 5).select(["step", "dt_s", "action_vx_mps", "action_vy_mps", "action_vz_mps",
                                                "delta_translation_m", "delta_rotation_deg"]).to_pandas()
            out = versioned(context, table, {"n_rows": table.num_rows, "pose_source": cfg.transitions.pose_source,
                                             "preview": MetadataValue.md(_md_table(preview))})
        yield out
        yield check_transitions_schema(artifact(context, out))

    @stage("demo_videos", "5", "Orbit, trajectory and side-by-side (real | render) MP4s (H.264, yuv420p) from the CPU "
                               "Gaussian rasterizer.")
    def demo_videos(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                    gaussian_world: GaussianWorld, localization_report: LocalizationReport):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is not None:
            return out
        cam = raw_dataset.camera
        # Render into a staging folder beside the artifacts; the IO manager moves the files into place.
        staging = context.resources.artifact_io.staging_folder("demo_videos", context.partition_key)
        try:
            videos = render_demo_videos(gaussian_world.field, localization_report.T_world_cam, cam.K, cam.width,
                                        cam.height, cfg, staging, context.partition_key, log=context.log.info,
                                        manifest=raw_dataset)
            return versioned(context, videos, {"orbit_frames": videos.n_orbit_frames,
                                               "trajectory_frames": videos.n_trajectory_frames,
                                               "size": MetadataValue.json(list(videos.size))})
        finally:
            discard_dir(staging)  # empty once the videos moved into the staged artifact

    @stage("render_evaluation", "3", "The world rendered at held-out (non-keyframe) frames from their estimated poses: "
                                     "PSNR, SSIM and depth L1 against the real images, and a preview (real | rendered | "
                                     "depth error).")
    def render_evaluation(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                          gaussian_world: GaussianWorld, localization_report: LocalizationReport):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is not None:
            return out
        rep = evaluate_rendering(raw_dataset, gaussian_world, localization_report, cfg, log=context.log.info)
        s = rep.summary
        md = {k: (_num(s[k]) if isinstance(s[k], (float, np.floating)) else s[k]) for k in
              ("n_views", "mean_psnr_db", "mean_psnr_masked_db", "mean_ssim", "mean_depth_l1_m", "mean_depth_coverage")}
        if rep.preview_png:
            md["preview"] = MetadataValue.md(markdown_image(rep.preview_png, "real | rendered | depth error (cm)"))
        return versioned(context, rep, md)

    @stage("world_bundle", "8", "World bundle (paper 8.3): metadata.json, gaussians.ply, gaussians.bin, surfels.npz "
                                "(tracking map), places.npz (place index), localization.json, transitions.parquet.",
           check=BUNDLE_ROUNDTRIP)
    def world_bundle(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                     gaussian_world: GaussianWorld, localization_report: LocalizationReport, transitions: pa.Table):
        cfg = atlas.load()
        if (out := reuse(context, cfg)) is None:
            lin = lineage(context)
            upstream = lin["upstream"]
            info = bundle_lineage(
                partition=context.partition_key,
                run_id=context.run.run_id,
                profile=cfg.profile,
                config_overrides=_run_overrides(context),
                raw_content_hash=raw_dataset.content_hash,
                **lin,
                code_versions={**{a: u["code_version"] for a, u in upstream.items()},
                               "world_bundle": context.assets_def.get_asset_spec(context.asset_key).code_version},
                parent=None,  # the pipeline builds every partition's world from scratch
            )
            meta = bundle_metadata(context.partition_key, context.partition_key, gaussian_world, raw_dataset, cfg, info)
            model, places = bundle_tracking_files(gaussian_world, raw_dataset.camera, cfg.localization)
            out = versioned(context, WorldBundleArtifact(gaussian_world.field, meta, localization_report, transitions,
                                                         model, places),
                             {"n_gaussians": len(gaussian_world.field), "map_id": gaussian_world.map_id,
                              "upstream_data_versions": MetadataValue.json(
                                  {a: u["data_version"] for a, u in upstream.items()})})
        yield out
        yield check_bundle_roundtrip(artifact(context, out).field)

    keys = set(partitions_def.get_partition_keys())
    first_visit_of = {second: first for second, first in revisits(load_registry()).items()
                      if first in keys and second in keys}
    seconds_of: dict[str, set[str]] = {}
    for second, first in first_visit_of.items():
        seconds_of.setdefault(first, set()).add(second)

    @asset(name=REVISIT_STAGE, code_version="3", partitions_def=partitions_def, io_manager_key=IO, group_name=GROUP,
           deps=[settings_key(REVISIT_STAGE)], output_required=False,
           ins={"first_visit_world": AssetIn(
               FIRST_VISIT_WORLD.path[-1], dagster_type=Optional[GaussianWorld],
               partition_mapping=StaticPartitionMapping(seconds_of))},
           description="A second visit (registry entry with `extends`): the first visit's world extended with this "
                       "recording (relocalized with no start pose, then tracked and mapped into it), the recording "
                       "localized in the extended world, its transitions, written as a world bundle whose lineage "
                       "names the first visit's world as parent. Skipped for a first visit.")
    def revisit_bundle(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                       fused_frames: FusedFrames, first_visit_world: Optional[GaussianWorld]):
        name = context.partition_key
        first = first_visit_of.get(name)
        if first is None:
            context.log.info(f"{name} is a first visit (no `extends` in the registry): nothing to extend")
            return
        if first_visit_world is None:
            raise Failure(f"{name} extends {first}, whose world is not materialized: run "
                          f"`atlas-gs run {first}` first")
        cfg = atlas.load()
        dep_partitions = {FIRST_VISIT_WORLD: first}
        if (out := reuse(context, cfg, dep_partitions=dep_partitions)) is None:
            if first_visit_world.keyframe_recording is None:  # cached before keyframes named their recording
                from dataclasses import replace

                from atlas_pipeline.scene_memory.recordings import world_keyframe_recordings

                recs, rec_idx = world_keyframe_recordings(first_visit_world, load_dataset(load_registry()[first], cfg))
                first_visit_world = replace(first_visit_world, recordings=recs, keyframe_recording=rec_idx)
            world, n_new = extend_world_with_visit(first_visit_world, raw_dataset, fused_frames, cfg, context.log.info)
            model, places = bundle_tracking_files(world, raw_dataset.camera, cfg.localization)
            report = localize_visit(raw_dataset, world, cfg, log=context.log.info, tracking=(model, places))
            table = log_transitions(report, name, len(world.field), cfg)
            lin = lineage(context, dep_partitions)
            parent = {"partition": first, "map_id": first_visit_world.map_id,
                      "world": lin["upstream"].get(f"{FIRST_VISIT_WORLD.path[-1]}[{first}]")}
            info = bundle_lineage(partition=name, run_id=context.run.run_id, profile=cfg.profile,
                                  config_overrides=_run_overrides(context), raw_content_hash=raw_dataset.content_hash,
                                  **lin, parent=parent)
            meta = bundle_metadata(name, name, world, raw_dataset, cfg, info)
            s = report.summary
            out = versioned(context, WorldBundleArtifact(world.field, meta, report, table, model, places), {
                "extends": first, "parent_map_id": first_visit_world.map_id, "map_id": world.map_id,
                "n_gaussians": len(world.field), "n_new_keyframes": int(n_new),
                "n_tracked": s["n_tracked"], "n_lost": s["n_lost"], "n_relocalized": s.get("n_relocalized", 0),
                "ate_rmse_m": _num(s.get("ate_rmse_m")), "frames_per_s": _num(s.get("frames_per_s")),
                "trajectory_plot": MetadataValue.md(markdown_image(
                    report.trajectory_plot_png(f"{name} in the world of {first}: top view"), "trajectory, top view")),
            })
        yield out

    return [dataset_files, settings, keyframes_settings, raw_dataset, fused_frames, keyframes, gaussian_world,
            localization_report, transitions, demo_videos, render_evaluation, world_bundle, revisit_bundle]


def _run_overrides(context: AssetExecutionContext) -> dict[str, Any]:
    """The run's ``--set`` values (its ``atlas/set/...`` tags)."""
    prefix = "atlas/set/"
    return {k[len(prefix):]: json.loads(v) for k, v in sorted(context.run.tags.items()) if k.startswith(prefix)}

"""The pipeline's software-defined assets, one per phase of the paper.

Each asset unpacks its inputs, calls one library function, and attaches metadata. All of them are
partitioned by dataset and stored by :class:`assets.io_managers.ArtifactIOManager`, and all are
declared with :func:`assets.versioning.atlas_asset`, which gives them code and data versions and
reuses an artifact whose inputs, config and code are unchanged (see ``assets/versioning.py``).
"""


import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa
from dagster import (
    AssetExecutionContext,
    AssetsDefinition,
    MetadataValue,
    Output,
    PartitionsDefinition,
)

from assets.checks import ATE_CHECK, BUNDLE_CHECK, GAUSSIANS_CHECK, TRANSITIONS_CHECK
from assets.resources import AtlasConfig
from assets.versioning import atlas_asset, current_asset_info, upstream_lineage
from atlas_pipeline import pipeline as lib
from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.gaussian_world.evaluation import PhotometricReport
from atlas_pipeline.io_utils import discard_dir
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.mapping.keyframes import KeyframeSet
from atlas_pipeline.perception.rgbd import FusedFrames
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.versioning import dataset_signature
from atlas_pipeline.viz.plots import markdown_image, render_preview_png

GROUP = "atlas_gs"
IO = "artifact_io"


def _num(x: float) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def _md_table(df) -> str:
    """A small DataFrame as a Markdown table (no extra dependency)."""
    head = "| " + " | ".join(df.columns) + " |\n|" + "---|" * len(df.columns) + "\n"
    rows = ["| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r) + " |"
            for r in df.itertuples(index=False)]
    return head + "\n".join(rows)


def _raw_identity(partition: str, atlas: AtlasConfig) -> dict:
    """What the raw dataset's fingerprint holds besides config: the registry entry and a cheap
    signature (names, sizes, mtimes) of the dataset's files, so edited frames are noticed."""
    entry = atlas.dataset(partition)
    return {"entry": entry.describe(), "files": dataset_signature(entry.path)}


def build_pipeline_assets(partitions_def: PartitionsDefinition,
                          cfg: PipelineConfig | None = None) -> list[AssetsDefinition]:
    """The asset graph for one partition set (the datasets of the registry).

    ``cfg`` is the config the definitions are built with; its section hashes are folded into the
    code versions Dagster compares, so a config change marks the shaped assets stale.
    """

    common = dict(partitions_def=partitions_def, io_manager_key=IO, group_name=GROUP, definition_config=cfg)

    @atlas_asset(description="Frame manifest of the dataset: files, timestamps, intrinsics, ground truth, content hash.",
                 code_version="1", identity=_raw_identity, **common)
    def raw_dataset(context: AssetExecutionContext, atlas: AtlasConfig) -> FrameManifest:
        cfg = atlas.load()
        entry = atlas.dataset(context.partition_key)
        manifest = lib.load_dataset(entry, cfg, log=context.log.info)
        context.add_output_metadata({
            "n_frames": manifest.n_frames,
            "n_with_ground_truth": int(manifest.has_gt.sum()),
            "duration_s": float(manifest.timestamps_s[-1] - manifest.timestamps_s[0]),
            "camera": MetadataValue.json(manifest.camera.to_dict()),
            "dataset_root": MetadataValue.path(str(manifest.root)),
            "raw_content_hash": manifest.content_hash[:16],
        })
        return manifest

    @atlas_asset(description="Back-projected coloured points of every frame (camera frame), depth range and stride from config.",
                 code_version="1", **common)
    def fused_frames(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest) -> FusedFrames:
        t0 = time.perf_counter()
        fused = lib.fuse(raw_dataset, atlas.load(), log=context.log.info)
        dt = time.perf_counter() - t0
        context.add_output_metadata({
            "n_points": int(len(fused.points_cam)),
            "mean_valid_fraction": float(fused.valid_fraction.mean()),
            "frames_per_s": fused.n_frames / dt if dt > 0 else 0.0,
        })
        return fused

    @atlas_asset(description="Mapping poses and keyframes: ground truth selected by motion, or (pose_source estimated / "
                             "no ground truth) the RGB-D tracker's own trajectory and keyframes.",
                 code_version="6", **common)
    def keyframes(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                  fused_frames: FusedFrames) -> KeyframeSet:
        kf = lib.select_keyframes_stage(raw_dataset, fused_frames, atlas.load(), log=context.log.info)
        context.add_output_metadata({
            "n_keyframes": int(len(kf.indices)),
            "pose_source": kf.pose_source,
            "keyframe_indices": MetadataValue.json([int(i) for i in kf.indices]),
        })
        return kf

    @atlas_asset(description="Gaussian world: anisotropic Gaussians merged per voxel from the keyframes (stable uint64 ids), "
                             "then fitted to the keyframe images and depths (positions, scales, rotations, opacities, colours).",
                 code_version="4", checks=[GAUSSIANS_CHECK], **common)
    def gaussian_world(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                       fused_frames: FusedFrames, keyframes: KeyframeSet) -> GaussianWorld:
        world = lib.build_gaussian_world(fused_frames, keyframes, atlas.load(), log=context.log.info,
                                         manifest=raw_dataset)
        lo, hi = world.field.bounds()
        preview = render_preview_png(world.field, world.T_world_cam_keyframes[0])
        return Output(world, metadata={
            "n_gaussians": len(world.field),
            "map_id": world.map_id,
            "voxel_size_m": world.builder.voxel_size_m,
            "extent_m": MetadataValue.json([round(float(v), 3) for v in hi - lo]),
            "gaussians_after_each_keyframe": MetadataValue.json([int(h) for h in world.history]),
            "fit": MetadataValue.json(world.fit),
            "render_preview": MetadataValue.md(markdown_image(preview, "render from the first keyframe")),
        })

    @atlas_asset(description="Per-frame pose tracked against the world (frame-to-model, no ground truth used): status, "
                             "residual, time; ATE and RPE where ground truth exists; trajectory plot.",
                 code_version="5", checks=[ATE_CHECK], **common)
    def localization_report(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                            gaussian_world: GaussianWorld) -> LocalizationReport:
        report = lib.localize(raw_dataset, gaussian_world, atlas.load(), log=context.log.info)
        s = report.summary
        context.add_output_metadata({
            "n_tracked": s["n_tracked"],
            "n_lost": s["n_lost"],
            "n_relocalized": s.get("n_relocalized", 0),
            "ate_rmse_m": _num(s.get("ate_rmse_m")),
            "ate_rot_rmse_deg": _num(s.get("ate_rot_rmse_deg")),
            "rpe_trans_rmse_m_per_s": _num(s.get("rpe_trans_rmse_m_per_s")),
            "rpe_rot_rmse_deg_per_s": _num(s.get("rpe_rot_rmse_deg_per_s")),
            "frames_per_s": _num(s.get("frames_per_s")),
            "outcome": str(s.get("outcome", "complete")),
            "n_not_attempted": int(s.get("n_not_attempted", 0)),
            "stopped_reason": MetadataValue.text(str(s.get("stopped_reason") or "")),
            "trajectory_plot": MetadataValue.md(markdown_image(
                report.trajectory_plot_png(f"{context.partition_key}: top view"), "trajectory, top view")),
        })
        return report

    @atlas_asset(description="State-action-state transitions, one row per consecutive frame pair (Parquet).",
                 code_version="2", checks=[TRANSITIONS_CHECK], **common)
    def transitions(context: AssetExecutionContext, atlas: AtlasConfig, localization_report: LocalizationReport,
                    gaussian_world: GaussianWorld) -> pa.Table:
        table = lib.log_transitions(localization_report, context.partition_key, len(gaussian_world.field), atlas.load())
        preview = table.slice(0, 5).select(
            ["step", "dt_s", "action_vx_mps", "action_vy_mps", "action_vz_mps", "delta_translation_m", "delta_rotation_deg"]
        ).to_pandas()
        context.add_output_metadata({
            "n_rows": table.num_rows,
            "pose_source": atlas.load().transitions.pose_source,
            "preview": MetadataValue.md(_md_table(preview)),
        })
        return table

    @atlas_asset(description="Orbit, trajectory and side-by-side (real | render) MP4s (H.264, yuv420p) from the CPU "
                             "Gaussian rasterizer.",
                 code_version="3", **common)
    def demo_videos(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                    gaussian_world: GaussianWorld, localization_report: LocalizationReport) -> lib.DemoVideos:
        cfg = atlas.load()
        cam = raw_dataset.camera
        # Render into a staging folder beside the artifacts; the IO manager moves the files into place.
        staging = context.resources.artifact_io.staging_folder("demo_videos", context.partition_key)
        try:
            videos = lib.render_demo_videos(gaussian_world.field, localization_report.T_world_cam, cam.K, cam.width,
                                            cam.height, cfg, staging, context.partition_key, log=context.log.info,
                                            manifest=raw_dataset)
        except BaseException:
            discard_dir(staging)
            raise
        context.add_output_metadata({
            "orbit_frames": videos.n_orbit_frames,
            "trajectory_frames": videos.n_trajectory_frames,
            "size": MetadataValue.json(list(videos.size)),
        })
        return videos

    @atlas_asset(description="The world rendered at held-out (non-keyframe) frames from their estimated poses: PSNR, "
                             "SSIM and depth L1 against the real images, and a preview (real | rendered | depth error).",
                 code_version="1", **common)
    def render_evaluation(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                          gaussian_world: GaussianWorld, localization_report: LocalizationReport) -> PhotometricReport:
        rep = lib.evaluate_rendering(raw_dataset, gaussian_world, localization_report, atlas.load(), log=context.log.info)
        s = rep.summary
        md = {k: (_num(s[k]) if isinstance(s[k], float) else s[k]) for k in
              ("n_views", "mean_psnr_db", "mean_psnr_masked_db", "mean_ssim", "mean_depth_l1_m", "mean_depth_coverage")}
        if rep.preview_png:
            md["preview"] = MetadataValue.md(markdown_image(rep.preview_png, "real | rendered | depth error"))
        context.add_output_metadata(md)
        return rep

    @atlas_asset(description="World bundle (paper 8.3): metadata.json, gaussians.ply, gaussians.bin, surfels.npz (tracking map), localization.json, transitions.parquet.",
                 code_version="6", checks=[BUNDLE_CHECK], **common)
    def world_bundle(context: AssetExecutionContext, atlas: AtlasConfig, raw_dataset: FrameManifest,
                     gaussian_world: GaussianWorld, localization_report: LocalizationReport,
                     transitions: pa.Table):
        cfg = atlas.load()
        info = current_asset_info()
        upstream = upstream_lineage(context)
        lineage = {
            "partition": context.partition_key,
            "run_id": context.run.run_id,
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "profile": atlas.profile,
            "config_overrides": dict(atlas.overrides),
            "raw_content_hash": raw_dataset.content_hash,
            "upstream": upstream,
            "code_versions": {**{a: u["code_version"] for a, u in upstream.items()},
                              "world_bundle": info.code_version if info else None},
            "fingerprint": info.fingerprint if info else None,
            "parent": None,  # the pipeline builds every partition's world from scratch
        }
        meta = lib.bundle_metadata(context.partition_key, context.partition_key, gaussian_world, raw_dataset, cfg, lineage)
        return Output(lib.WorldBundleArtifact(gaussian_world.field, meta, localization_report, transitions,
                                              lib.tracking_map(gaussian_world)),
                      metadata={"n_gaussians": len(gaussian_world.field), "map_id": gaussian_world.map_id,
                                "upstream_data_versions": MetadataValue.json(
                                    {a: u["data_version"] for a, u in upstream.items()})})

    return [raw_dataset, fused_frames, keyframes, gaussian_world, localization_report, transitions,
            demo_videos, render_evaluation, world_bundle]


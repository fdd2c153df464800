"""Commands that place recordings in a saved world: ``localize``, ``relocalize``,
``log-transitions``, and ``evaluate-trajectory`` for any TUM trajectory file."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from assets.cli import options
from assets.cli.output import EXIT_INCOMPLETE, json_document, out
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.geometry import tq_from_pose
from atlas_pipeline.io_utils import check_writable
from atlas_pipeline.sensors.registry import load_dataset
# Imported with the module: pandas then loads before logging is configured, so its import-time INFO
# lines stay out of the command's stderr.
from atlas_pipeline.transition_log.transitions import log_transitions

logger = logging.getLogger("atlas_gs.cli")

MIN_MATCHED_POSES = 3  # fewer estimated poses with a ground-truth match give no ATE or RPE


def _tracking_voxel_m(bundle, cfg) -> float:
    """The map resolution a world was built at (the profile's where the bundle does not say)."""
    return float(bundle.metadata.get("gaussians", {}).get("voxel_size_m", cfg.mapping.voxel_size_m))


def cmd_relocalize(args: argparse.Namespace) -> int:
    """Place single frames in a saved world with no initial pose; print pose, confidence and, where
    the dataset has ground truth, the error (meaningful when the world shares its frame)."""
    from atlas_pipeline.localization.relocalize import relocalize_frames
    from atlas_pipeline.localization.tracker import pose_change
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle

    cfg = options.config(args)
    bundle = load_world_bundle(args.world)
    manifest = load_dataset(options.dataset(args), cfg)
    frames = args.frame if args.frame else list(range(manifest.n_frames))
    bad = [i for i in frames if not 0 <= i < manifest.n_frames]
    if bad:
        raise ConfigError(f"--frame {bad[0]} is outside 0..{manifest.n_frames - 1}")
    model = bundle.tracking_model(_tracking_voxel_m(bundle, cfg))
    rows = []
    for i, r in relocalize_frames(manifest, model, bundle_keyframe_poses(bundle.metadata), cfg, frames):
        row: dict[str, Any] = {"frame": i, "timestamp_s": float(manifest.timestamps_s[i]), "ok": bool(r.ok),
                               "confidence": round(r.confidence, 4), "source": r.source,
                               "inlier_fraction": round(r.inlier_fraction, 4)}
        if np.isfinite(r.T_world_cam).all():
            t, q = tq_from_pose(r.T_world_cam)
            row.update({"position_xyz": [round(float(v), 6) for v in t], "quat_xyzw": [round(float(v), 6) for v in q]})
            if manifest.has_gt[i]:
                dt_m, dr_deg = pose_change(manifest.T_world_cam_gt[i], r.T_world_cam)
                row.update({"error_t_m": round(dt_m, 4), "error_rot_deg": round(dr_deg, 3)})
        rows.append(row)
        logger.info("frame %d: %s (confidence %.2f, from %s hypothesis)", i, "placed" if r.ok else "not placed",
                    r.confidence, r.source)
    out(json.dumps({"world": str(Path(args.world).resolve()), "frames": rows,
                    "n_placed": sum(r["ok"] for r in rows)}, indent=2))
    return 0


def cmd_evaluate_trajectory(args: argparse.Namespace) -> int:
    """ATE and RPE of a TUM-format trajectory against ground truth (TUM's conventions)."""
    from atlas_pipeline.localization.metrics import evaluate_trajectories, read_tum_trajectory

    t_e, P = read_tum_trajectory(Path(args.estimated))
    t_g, G = read_tum_trajectory(Path(args.groundtruth))
    res = evaluate_trajectories(t_e, P, t_g, G, max_dt_s=args.max_dt, rpe_delta_s=args.delta)
    if res["n_matched"] < MIN_MATCHED_POSES:
        raise ConfigError(f"only {res['n_matched']} poses of {args.estimated} have a ground-truth pose within "
                          f"{args.max_dt} s in {args.groundtruth}: nothing to evaluate")
    out(json_document(res))  # figures that cannot be computed (RPE of a short path) are null
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    """Track a recording's frames through a saved world; the report goes into the bundle."""
    from atlas_pipeline.localization.localizer import localize_sequence
    from atlas_pipeline.scene_memory.bundle import (
        bundle_keyframe_poses,
        check_bundle_update,
        load_world_bundle,
        update_world_bundle,
    )
    from atlas_pipeline.scene_memory.metadata import start_pose

    cfg = options.config(args)
    bundle = load_world_bundle(args.world)  # verifies every file the bundle lists
    entry = options.dataset(args)
    # Whether the report may go into this bundle is known now, not after every frame is localized.
    check_bundle_update(args.world, entry.name, bundle.map_id, drop_transitions=args.drop_transitions,
                        meta=bundle.metadata)
    check_writable(Path(args.world).parent)
    manifest = load_dataset(entry, cfg)
    T0, anchor = start_pose(bundle.metadata, entry.name, options.start_pose(args), relocalize=args.relocalize)
    if anchor >= manifest.n_frames:
        raise ConfigError(f"anchor frame {anchor} is beyond the {manifest.n_frames} frames loaded")
    # The world's own recording is never a mismatch (the world was built from it), as in the graph.
    own = bundle.metadata.get("dataset", {}).get("name") == entry.name
    report = localize_sequence(manifest, bundle.tracking_model(_tracking_voxel_m(bundle, cfg)), cfg.localization,
                               T0, anchor, bundle.map_id, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                               prior_poses=bundle_keyframe_poses(bundle.metadata), stop_on_mismatch=not own)
    update_world_bundle(args.world, localization=report, drop_transitions=args.drop_transitions)
    out(json.dumps({"world": str(Path(args.world).resolve()), **{  # to_json: unknown numbers are null
        k: (round(v, 6) if isinstance(v, float) else v) for k, v in report.to_json()["summary"].items()}}, indent=2))
    if report.summary.get("outcome", "complete") != "complete":
        # The report (what was tried, what failed) is in the bundle; the command itself failed.
        logger.error("%s", report.summary.get("stopped_reason") or "localization stopped early")
        return EXIT_INCOMPLETE
    return 0


def cmd_log_transitions(args: argparse.Namespace) -> int:
    """Write transitions.parquet into a world bundle from the localization report it holds."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import check_bundle_update, update_world_bundle, verify_bundle_files

    cfg = options.config(args)
    world = Path(args.world)
    meta = verify_bundle_files(world)
    if not (world / "localization.json").is_file():
        raise ConfigError(f"{world}: no localization.json; run `atlas-gs localize --world {world} --input {args.input}` first")
    report = LocalizationReport.load(world)
    entry = options.dataset(args)
    if report.dataset != entry.name:
        raise ConfigError(f"{world}/localization.json is for dataset '{report.dataset}', not '{entry.name}'")
    check_bundle_update(world, transitions_of={"dataset": entry.name, "map_id": report.map_id}, meta=meta)
    if cfg.transitions.pose_source == "ground_truth":  # refresh GT from the dataset, not the report
        manifest = load_dataset(entry, cfg)
        report.T_world_cam_gt = manifest.T_world_cam_gt
    table = log_transitions(report, entry.name, int(meta.get("n_gaussians", 0)), cfg)
    update_world_bundle(world, transitions=table)
    out(json.dumps({"transitions": str((world / "transitions.parquet").resolve()), "rows": table.num_rows}, indent=2))
    return 0

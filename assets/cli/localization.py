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
from atlas_pipeline.sensors.registry import load_dataset
# Imported with the module: pandas then loads before logging is configured, so its import-time INFO
# lines stay out of the command's stderr.
from atlas_pipeline.transition_log import transitions  # noqa: F401

logger = logging.getLogger("atlas_gs.cli")

MIN_MATCHED_POSES = 3  # fewer estimated poses with a ground-truth match give no ATE or RPE


def cmd_relocalize(args: argparse.Namespace) -> int:
    """Place single frames in a saved world with no initial pose; print pose, confidence and, where
    the dataset has ground truth, the error (meaningful when the world shares its frame)."""
    from atlas_pipeline.localization.relocalize import relocalize_frames
    from atlas_pipeline.localization.tracker import pose_change
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle
    from atlas_pipeline.scene_memory.localize import tracking_voxel_m

    cfg = options.config(args)
    bundle = load_world_bundle(args.world)
    manifest = load_dataset(options.dataset(args), cfg)
    frames = args.frame if args.frame else list(range(manifest.n_frames))
    bad = [i for i in frames if not 0 <= i < manifest.n_frames]
    if bad:
        raise ConfigError(f"--frame {bad[0]} is outside 0..{manifest.n_frames - 1}")
    model = bundle.tracking_model(tracking_voxel_m(bundle, cfg))
    rows = []
    for i, r in relocalize_frames(manifest, model, bundle_keyframe_poses(bundle.metadata), cfg, frames,
                                  places=bundle.stored_places(manifest.camera)):
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
    from atlas_pipeline.scene_memory.localize import localize_into_bundle

    cfg = options.config(args)
    report = localize_into_bundle(args.world, options.dataset(args), cfg, options.start_pose(args), args.relocalize,
                                  args.drop_transitions)
    out(json.dumps({"world": str(Path(args.world).resolve()), **{  # to_json: unknown numbers are null
        k: (round(v, 6) if isinstance(v, float) else v) for k, v in report.to_json()["summary"].items()}}, indent=2))
    if report.summary.get("outcome", "complete") != "complete":
        # The report (what was tried, what failed) is in the bundle; the command itself failed.
        logger.error("%s", report.summary.get("stopped_reason") or "localization stopped early")
        return EXIT_INCOMPLETE
    return 0


def cmd_log_transitions(args: argparse.Namespace) -> int:
    """Write transitions.parquet into a world bundle from the localization report it holds."""
    from atlas_pipeline.scene_memory.localize import log_bundle_transitions

    world = Path(args.world)
    cfg = options.config(args)
    table = log_bundle_transitions(world, options.dataset(args), cfg)
    out(json.dumps({"transitions": str((world / "transitions.parquet").resolve()), "rows": table.num_rows}, indent=2))
    return 0

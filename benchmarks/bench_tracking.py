"""Tracking, relocalization and memory benchmark, with Open3D's RGB-D odometry as the
reference measured in the same process on the same frames.

    python benchmarks/bench_tracking.py                      # synthetic + TUM teddy (when present)
    python benchmarks/bench_tracking.py --datasets teddy --json out.json

Per dataset:

* **SLAM** (``mapping.pose_source: estimated``): the camera tracked frame-to-model while keyframes
  are merged into the map; no ground truth is read. ATE (rigid alignment, TUM conventions) and RPE
  per second against ground truth.
* **Localization** of every frame against the world that SLAM built (the ``localization_report``).
* **Reference**: Open3D 0.20 tensor RGB-D odometry, hybrid term, multi-scale 10/5/3 iterations,
  depth cut at 3 m, frame-to-frame and chained (what ``../shared/data/README.md`` describes).
* **Speed**: frames per second of tracking on frames already in memory (decoding excluded, for
  both), and the ratio ours / Open3D.
* **Relocalization**: a world built from the first half of the sequence (ground-truth poses, so
  the world shares the ground truth's frame); every second-half frame is relocalized with no
  initial pose; success = within 5 cm and 5 degrees.
* **Memory**: peak resident memory of localizing the first 25 / 50 / 100 frames, each in a fresh
  process: bounded tracking keeps it flat as the sequence grows.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Shared with bench_robustness.py: frames in memory, grading, our SLAM loop, Open3D's odometry.
from benchmarks.common import grade as _grade  # noqa: E402
from benchmarks.common import load_frames as _frames  # noqa: E402
from benchmarks.common import run_open3d_odometry  # noqa: E402
from benchmarks.common import run_slam as bench_slam  # noqa: E402

TEDDY = ROOT.parent / "shared" / "data" / "tum_fr3_teddy_100"


def _load(name: str, n_frames: int | None = None, synthetic_frames: int | None = None):
    """``name``'s frames (the first ``n_frames``); ``synthetic_frames``: the synthetic room generated
    with that many frames instead of the built-in 60 (a longer path through the same room)."""
    import dataclasses

    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.tum import load_tum_sequence

    if name == "teddy":
        if not (TEDDY / "rgb.txt").is_file():
            return None
        return load_tum_sequence(TEDDY, TUM_CAMERAS["freiburg3"], "tum_fr3_teddy_100", n_frames)
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset

    spec = SyntheticSpec()  # the built-in default partition: 60 frames, 640x480
    suffix = ""
    if synthetic_frames:
        spec, suffix = dataclasses.replace(spec, n_frames=synthetic_frames), f"_{synthetic_frames}"
    # Reused when its marker holds this spec and generator version, else generated again (a folder
    # from an older generator once stood in: depth stamped 3 ms after the colour it was rendered with).
    root = generate_synthetic_dataset(Path(tempfile.gettempdir()) / f"atlas_bench_synthetic{suffix}", spec)
    return load_tum_sequence(root, spec.camera(), "synthetic" + suffix.replace("_", "-"), n_frames)


def bench_localization(manifest, frames, cfg, builder, keyframe_poses) -> dict:
    """Every frame tracked against the fixed SLAM world, from the first frame's pose in it."""
    from atlas_pipeline.localization.sequence import SequenceTracker
    from atlas_pipeline.localization.tracker import SurfelModel

    st = SequenceTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                         model=SurfelModel.from_builder(builder), prior_poses=keyframe_poses)
    poses = np.full((manifest.n_frames, 4, 4), np.nan)
    status = []
    t0 = time.perf_counter()
    for i, (rgb, depth) in enumerate(frames):
        e = st.process(i, rgb, depth, T_given=keyframe_poses[0] if i == 0 else None, timestamp_s=float(manifest.timestamps_s[i]),
                       colour_delay_s=manifest.colour_delay_s(i))
        poses[i] = e.T_world_cam
        status.append(e.status)
    dt = time.perf_counter() - t0
    out = _grade(manifest, poses)
    out.update({"frames_per_s": (len(frames) - 1) / dt, "n_lost": status.count("lost"),
                "n_relocalized": status.count("relocalized")})
    return out


def bench_open3d(manifest, frames) -> dict:
    """Open3D tensor RGB-D odometry, hybrid, frame to frame, chained, depth cut at 3 m."""
    return run_open3d_odometry(manifest, frames, depth_max_m=3.0)


def bench_relocalization(manifest, frames, cfg) -> dict:
    """World from the first half (ground-truth poses), second-half frames with no initial pose."""
    import dataclasses

    from atlas_pipeline.localization.relocalize import Relocalizer
    from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel, pose_change
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    half = manifest.n_frames // 2
    first = dataclasses.replace(
        manifest, timestamps_s=manifest.timestamps_s[:half], depth_timestamps_s=manifest.depth_timestamps_s[:half],
        rgb_files=manifest.rgb_files[:half], depth_files=manifest.depth_files[:half],
        T_world_cam_gt=manifest.T_world_cam_gt[:half], has_gt=manifest.has_gt[:half])
    gcfg = cfg.with_overrides({"mapping.pose_source": "ground_truth"})
    fused = fuse(first, gcfg)
    world = build_gaussian_world(fused, select_keyframes_stage(first, fused, gcfg), gcfg)
    # As a later session sees it: Gaussian centres from the bundle, keyframe poses from its metadata.
    model = SurfelModel.from_field(world.field.positions, world.tracking_voxels.voxel_size_m)
    tracker = RGBDTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m))
    reloc = Relocalizer(tracker, model, world.T_world_cam_keyframes)
    ok, errs, confs, times = [], [], [], []
    for i in range(half, manifest.n_frames):
        if not manifest.has_gt[i]:
            continue
        t0 = time.perf_counter()
        r = reloc.relocalize(tracker.prepare(*frames[i]))
        times.append(time.perf_counter() - t0)
        dt_m, dr_deg = pose_change(r.T_world_cam, manifest.T_world_cam_gt[i]) if np.isfinite(r.T_world_cam).all() else (np.inf, np.inf)
        ok.append(dt_m < 0.05 and dr_deg < 5.0)
        errs.append((dt_m, dr_deg))
        confs.append(r.confidence)
    e = np.array(errs)
    good = np.array(ok)
    return {"n_frames": int(len(ok)), "success_rate": float(good.mean()) if len(ok) else float("nan"),
            "median_error_m": float(np.median(e[good, 0])) if good.any() else float("nan"),
            "median_error_deg": float(np.median(e[good, 1])) if good.any() else float("nan"),
            "mean_confidence_success": float(np.mean(np.array(confs)[good])) if good.any() else float("nan"),
            "mean_confidence_failure": float(np.mean(np.array(confs)[~good])) if (~good).any() else float("nan"),
            "seconds_per_frame": float(np.mean(times)) if times else float("nan")}


def _memory_child(name: str, n: int) -> None:
    """In a fresh process: localize the first ``n`` frames against a small world; print peak RSS."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.localization.localizer import localize
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    m = _load(name, n)
    cfg = load_profile("default").with_overrides({"dataset.max_frames": 10})
    first = _load(name, 10)
    fused = fuse(first, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(first, fused, cfg), cfg)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rep = localize(m, world, cfg)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"n_frames": n, "peak_rss_mb": peak / 1024.0, "rss_before_localize_mb": base / 1024.0,
                      "n_tracked": rep.summary["n_tracked"]}))


def bench_memory(name: str, sizes: list[int]) -> list[dict]:
    out = []
    for n in sizes:
        res = subprocess.run([sys.executable, __file__, "--memory-child", name, str(n)], capture_output=True, text=True,
                             check=True, cwd=ROOT)
        out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def _fmt(x, spec=".4f"):
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["synthetic", "teddy"], choices=["synthetic", "teddy"])
    ap.add_argument("--no-memory", action="store_true", help="skip the per-length memory runs")
    ap.add_argument("--no-relocalization", action="store_true", help="skip the relocalization runs")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value (YAML syntax), e.g. --set localization.iterations=[8,5,3]")
    ap.add_argument("--json", default=None, help="also write the figures here")
    ap.add_argument("--memory-child", nargs=2, metavar=("DATASET", "N"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.memory_child:
        _memory_child(args.memory_child[0], int(args.memory_child[1]))
        return 0

    from atlas_pipeline.config import load_profile, parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    try:
        overrides = {"mapping.pose_source": "estimated", **parse_set_overrides(args.set)}
    except ConfigError as exc:
        ap.error(str(exc))
    cfg = load_profile("default").with_overrides(overrides)
    results: dict = {}
    for name in args.datasets:
        manifest = _load(name)
        if manifest is None:
            print(f"{name}: skipped (no data at {TEDDY})")
            continue
        frames = _frames(manifest)
        # Warm-up: compile the Numba kernels outside the timed loops.
        bench_slam(manifest, frames[:3], cfg)
        slam, st = bench_slam(manifest, frames, cfg)
        loc = bench_localization(manifest, frames, cfg, st.builder, np.array(st.keyframe_poses))
        ref = bench_open3d(manifest, frames)
        rel = bench_relocalization(manifest, frames, cfg) if not args.no_relocalization else None
        r = {"n_frames": manifest.n_frames, "slam": slam, "localization": loc, "open3d_hybrid_odometry": ref,
             "speed_ratio_slam_vs_open3d": slam["frames_per_s"] / ref["frames_per_s"],
             "speed_ratio_localization_vs_open3d": loc["frames_per_s"] / ref["frames_per_s"],
             "relocalization": rel}
        if not args.no_memory:
            r["memory"] = bench_memory(name, [25, 50, 100] if manifest.n_frames >= 100 else [15, 30, 60])
        results[name] = r

        print(f"\n== {name} ({manifest.n_frames} frames, {manifest.camera.width}x{manifest.camera.height})")
        print(f"{'':34}{'ATE RMSE m':>11}{'RPE m/s':>10}{'RPE deg/s':>10}{'frames/s':>10}{'lost':>6}")
        for label, d in (("ours: tracking + mapping (no GT)", slam), ("ours: localization in that world", loc),
                         ("Open3D hybrid odometry (F2F)", ref)):
            print(f"{label:34}{_fmt(d.get('ate_rmse_m')):>11}{_fmt(d.get('rpe_trans_rmse_m')):>10}"
                  f"{_fmt(d.get('rpe_rot_rmse_deg'), '.3f'):>10}{_fmt(d['frames_per_s'], '.1f'):>10}{d.get('n_lost', 0):>6}")
        print(f"speed ratio vs Open3D (same frames, decoding excluded): tracking+mapping "
              f"{r['speed_ratio_slam_vs_open3d']:.2f}x, localization {r['speed_ratio_localization_vs_open3d']:.2f}x")
        if rel is None:
            continue
        print(f"relocalization (world from first half, {rel['n_frames']} second-half frames, no initial pose): "
              f"{100 * rel['success_rate']:.0f}% within 5 cm / 5 deg; median error {_fmt(rel['median_error_m'], '.3f')} m "
              f"{_fmt(rel['median_error_deg'], '.2f')} deg; {rel['seconds_per_frame']:.2f} s/frame; mean confidence "
              f"{_fmt(rel['mean_confidence_success'], '.2f')} (success) / {_fmt(rel['mean_confidence_failure'], '.2f')} (failure)")
        if "memory" in r:
            print("peak RSS localizing N frames (fresh process each): " +
                  ", ".join(f"N={x['n_frames']}: {x['peak_rss_mb']:.0f} MB" for x in r["memory"]))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

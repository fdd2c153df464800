"""What bounds SLAM's frame rate on this machine: the tracker's own work, then reading the frames.

For each sequence (the first ``--frames`` frames of the synthetic suite, 640x480; the shared TUM
recordings where present), with no profiler, each step timed apart on the same frames:

1. **decode**: the frames' colour and depth PNGs decoded one after the other on one thread
   (milliseconds a frame): the reader thread's work while SLAM runs from disk.
2. **SLAM in memory**: ``slam_poses`` (tracking, keyframe integration, loop closure) on frames
   decoded beforehand: the tracker's work on both cores (its normal equations split over
   them), plus only loop closure's own reads of its keyframes. Faster reading cannot make SLAM
   faster than this row.
3. **SLAM from disk**: ``slam_poses`` as it runs by default, the reader thread decoding ahead on
   the core the tracker shares (the files are in the page cache by then: this is decoding, not
   the disk).
4. **build pass**: as ``atlas-gs build`` runs it (:func:`bench_persistence.build_first_world`'s
   pass): each frame also back-projected for the fused frames on the reader thread.

``needed`` is how many times faster a row's work would have to be for 30 frames/s (33.3 ms a
frame); 1.00x where it is already there.

    python benchmarks/bench_slam_floor.py [--frames 1000] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_persistence import WARM_UP_FRAMES, _slice, benchmark_config  # noqa: E402
from benchmarks.common import load_frames, shared_tum_manifest  # noqa: E402

DATASET = "synthetic-suite"
SHARED = (("tum_fr3_teddy_100", "freiburg3"), ("tum_fr1_xyz_10", "freiburg1"))
TARGET_FRAMES_PER_S = 30.0


def _sequences(n_frames: int, cfg) -> list[tuple[str, object]]:
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    full = load_dataset(load_registry()[DATASET], cfg)
    out = [(f"{DATASET} 0-{min(n_frames, full.n_frames) - 1}", _slice(full, 0, min(n_frames, full.n_frames), DATASET))]
    for folder, cam in SHARED:
        m = shared_tum_manifest(folder, cam)
        if m is not None:
            out.append((folder, m))
    return out


def _decode_s(manifest) -> float:
    t0 = time.perf_counter()
    for i in range(manifest.n_frames):
        manifest.read_rgb(i)
        manifest.read_depth_m(i, allow_empty=True)
    return time.perf_counter() - t0


def _slam_s(manifest, cfg, frames=None, fuse: bool = False) -> float:
    from atlas_pipeline.mapping.keyframes import slam_poses
    from atlas_pipeline.perception.rgbd import FrameFuser

    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    args = (cfg.mapping, cfg.localization, depth_range, cfg.fusion.stride)
    head = _slice(manifest, 0, min(WARM_UP_FRAMES, manifest.n_frames), "warm-up")
    slam_poses(head, *args, frames=None if frames is None else frames[:WARM_UP_FRAMES])
    t0 = time.perf_counter()
    if not fuse:
        slam_poses(manifest, *args, frames=frames)
        return time.perf_counter() - t0
    with FrameFuser(manifest, cfg.fusion) as fuser:  # its temporary chunk files go with the block
        slam_poses(manifest, *args, frames=frames, on_frame=fuser.add)
    return time.perf_counter() - t0


def run(label: str, manifest, cfg) -> dict:
    n = manifest.n_frames
    decode_s = _decode_s(manifest)
    frames = load_frames(manifest)
    return {"sequence": label, "frames": n, "decode_ms_per_frame": 1e3 * decode_s / n,
            "slam_memory_s": _slam_s(manifest, cfg, frames), "slam_disk_s": _slam_s(manifest, cfg),
            "build_pass_s": _slam_s(manifest, cfg, fuse=True)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000, help="first N frames of the synthetic suite")
    ap.add_argument("--json", type=Path, help="write the rows here too")
    args = ap.parse_args(argv)
    cfg = benchmark_config()
    rows = []
    for label, manifest in _sequences(args.frames, cfg):
        print(f"running {label} ...", flush=True)
        rows.append(run(label, manifest, cfg))
    budget_ms = 1e3 / TARGET_FRAMES_PER_S
    print(f"\nmachine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores; "
          f"profile default, mapping.pose_source=estimated; target {TARGET_FRAMES_PER_S:.0f} frames/s = {budget_ms:.1f} ms a frame")
    print("| sequence | frames | decode ms/frame (one thread) | SLAM in memory f/s (ms/frame, needed) "
          "| SLAM from disk f/s (ms/frame, needed) | build pass f/s (ms/frame, needed) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        cells = []
        for key in ("slam_memory_s", "slam_disk_s", "build_pass_s"):
            ms = 1e3 * r[key] / r["frames"]
            cells.append(f"{1e3 / ms:.1f} ({ms:.1f}, {max(ms / budget_ms, 1.0):.2f}x)")
        print(f"| {r['sequence']} | {r['frames']} | {r['decode_ms_per_frame']:.1f} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

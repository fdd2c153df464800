"""Reading frames while tracking: SLAM wall time with frames decoded by a reader thread
(``perception.rgbd.read_ahead``) against the same SLAM reading each frame inline before tracking
it (the reference), on the frames as they lie on disk; with the frames held in memory (decoded
before the clock starts: the floor reading can reach); and the two passes of fusion then SLAM
against the one pass of ``atlas-gs build`` that fuses each frame as SLAM reads it
(``mapper.fuse_and_select_keyframes``), on the reader thread and, as its reference, on the
tracker's thread.

Every run tracks the same frames with the same settings (no loop closure, so only the tracking
loop is timed), alternating, ``--repeats`` times each; the poses must be identical. Usage::

    python benchmarks/bench_read_ahead.py [--dataset synthetic-suite] [--frames 300] [--repeats 2]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _inline(manifest, indices, on_frame=None):
    """The reference reader: each frame read (and ``on_frame`` run) when the tracker asks for it."""
    for i in indices:
        rgb, depth = manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True)
        if on_frame is not None:
            on_frame(i, rgb, depth)
        yield i, rgb, depth


def _on_caller(read_ahead):
    """``read_ahead`` with ``on_frame`` run on the tracker's thread, not the reader's (the reference
    of the one pass)."""
    def reader(manifest, indices, on_frame=None):
        for i, rgb, depth in read_ahead(manifest, indices):
            if on_frame is not None:
                on_frame(i, rgb, depth)
            yield i, rgb, depth
    return reader


def main(argv: list[str] | None = None) -> int:
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping import keyframes as kf_module
    from atlas_pipeline.mapping.mapper import fuse_and_select_keyframes
    from atlas_pipeline.perception.rgbd import fuse_frames, read_ahead
    from atlas_pipeline.sensors.registry import load_dataset, load_registry
    from benchmarks.bench_persistence import _slice

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="synthetic-suite")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    cfg = load_profile("default")
    cfg = cfg.with_overrides({"mapping.pose_source": "estimated", "mapping.loop_closure": False})
    full = load_dataset(load_registry()[args.dataset], cfg)
    m = _slice(full, 0, min(args.frames, full.n_frames), args.dataset)
    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    in_memory = [(m.read_rgb(i), m.read_depth_m(i, allow_empty=True)) for i in range(m.n_frames)]

    def slam(reader, frames=None):
        kf_module.read_ahead = reader
        return kf_module.slam_poses(m, cfg.mapping, cfg.localization, depth_range, cfg.fusion.stride, frames=frames)

    def fuse_then_slam():
        fuse_frames(m, cfg.fusion)
        return slam(read_ahead)

    def one_pass(reader=read_ahead):
        kf_module.read_ahead = reader
        return fuse_and_select_keyframes(m, cfg)[1]  # its KeyframeSet holds SLAM's poses

    runs = {"inline (reference)": lambda: slam(_inline), "read ahead": lambda: slam(read_ahead),
            "held in memory (decoded before the clock)": lambda: slam(read_ahead, frames=in_memory),
            "fusion, then SLAM read ahead (two passes)": fuse_then_slam,
            "SLAM read ahead, each frame fused in the pass on the tracker's thread": lambda: one_pass(_on_caller(read_ahead)),
            "SLAM read ahead, each frame fused in the pass on the reader thread (atlas-gs build)": one_pass}
    times: dict[str, list[float]] = {label: [] for label in runs}
    poses: dict[str, np.ndarray] = {}
    for _ in range(args.repeats):
        for label, run in runs.items():
            t0 = time.perf_counter()
            poses[label] = run().T_world_cam
            times[label].append(time.perf_counter() - t0)
    kf_module.read_ahead = read_ahead
    one = "SLAM read ahead, each frame fused in the pass on the reader thread (atlas-gs build)"
    caller = "SLAM read ahead, each frame fused in the pass on the tracker's thread"
    same = all(np.array_equal(poses["inline (reference)"], p, equal_nan=True) for p in poses.values())
    print(f"{args.dataset}, frames 0-{m.n_frames - 1} ({m.camera.width}x{m.camera.height}), "
          f"{platform.processor() or platform.machine()}, best of {args.repeats}")
    print("| frames | s | frames/s |")
    print("|---|---|---|")
    for label, ts in times.items():
        print(f"| {label} | {min(ts):.1f} | {m.n_frames / min(ts):.1f} |")
    print(f"read ahead against inline: {min(times['inline (reference)']) / min(times['read ahead']):.2f}x; "
          f"one pass against two: {min(times['fusion, then SLAM read ahead (two passes)']) / min(times[one]):.2f}x; "
          f"fusion on the reader thread against the tracker's: {min(times[caller]) / min(times[one]):.2f}x; "
          f"poses identical: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())

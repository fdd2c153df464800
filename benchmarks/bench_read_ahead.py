"""Reading frames ahead while tracking: SLAM wall time with frames decoded by a reader thread
(``perception.rgbd.read_ahead``, what ``atlas-gs build`` does) against the same SLAM reading each
frame inline before tracking it (the reference), on the frames as they lie on disk.

Both runs track the same frames with the same settings (no loop closure, so only the tracking
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


def _inline(manifest, indices):
    """The reference reader: each frame read when the tracker asks for it."""
    for i in indices:
        yield i, manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True)


def main(argv: list[str] | None = None) -> int:
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping import keyframes as kf_module
    from atlas_pipeline.perception.rgbd import read_ahead
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
    times: dict[str, list[float]] = {"inline (reference)": [], "read ahead": []}
    poses: dict[str, np.ndarray] = {}
    for _ in range(args.repeats):
        for label, reader in (("inline (reference)", _inline), ("read ahead", read_ahead)):
            kf_module.read_ahead = reader
            t0 = time.perf_counter()
            slam = kf_module.slam_poses(m, cfg.mapping, cfg.localization, depth_range, cfg.fusion.stride)
            times[label].append(time.perf_counter() - t0)
            poses[label] = slam.T_world_cam
    kf_module.read_ahead = read_ahead
    same = np.array_equal(poses["inline (reference)"], poses["read ahead"], equal_nan=True)
    print(f"{args.dataset}, frames 0-{m.n_frames - 1} ({m.camera.width}x{m.camera.height}), "
          f"{platform.processor() or platform.machine()}, best of {args.repeats}")
    print("| reader | SLAM s | frames/s |")
    print("|---|---|---|")
    for label, ts in times.items():
        print(f"| {label} | {min(ts):.1f} | {m.n_frames / min(ts):.1f} |")
    print(f"speed-up {min(times['inline (reference)']) / min(times['read ahead']):.2f}x, poses identical: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())

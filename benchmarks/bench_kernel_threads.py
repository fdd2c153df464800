"""The tracker's normal equations split over threads against one: SLAM frames/s and time per call.

SLAM (``slam_poses`` as ``atlas-gs build --set mapping.pose_source=estimated`` runs it, loop
closure included) on the first ``--frames`` frames of a dataset, decoded before the clock starts,
with the normal equations split between the calling thread and worker threads, as many threads as
Numba's (:mod:`atlas_pipeline.localization.normal_equations`, the default; 2 on a 2-core machine) and, as the reference in the
same run, on the calling thread alone (every call below the split threshold). Runs alternate,
``--repeats`` times each, best of each reported; the poses should be identical (two runs of
one mode may differ in rounding where a sequence loses frames or closes a loop). Per call: the
median wall time of the calls in each size class of frame points, over the last run of each. ::

    python benchmarks/bench_kernel_threads.py [--dataset synthetic-suite] [--frames 1000] [--repeats 2]
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

from benchmarks.bench_persistence import SHARED_SPLITS, _slice, benchmark_config  # noqa: E402
from benchmarks.common import SHARED_DATA, grade, load_frames, shared_tum_manifest  # noqa: E402

WARM_UP_FRAMES = 5  # compiles the kernels and starts the worker thread before the clock
ONE_THREAD = 1 << 62  # a split threshold no call reaches: every call on the calling thread
POINT_CLASSES = ((0, 2_000), (2_000, 6_000), (6_000, 15_000), (15_000, 30_000), (30_000, 1 << 62))


def _dataset(name: str, cfg):
    """A registry dataset, or a TUM folder of ``../shared/data`` (camera from its name)."""
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    for folder, cam, _ in SHARED_SPLITS:
        if name == folder:
            manifest = shared_tum_manifest(folder, cam)
            if manifest is None:
                raise SystemExit(f"{SHARED_DATA / folder}: not found")
            return manifest
    return load_dataset(load_registry()[name], cfg)


def _slam(manifest, frames, cfg) -> dict:
    """SLAM on preloaded frames: frames/s, ATE, keyframes and the poses ``[N, 4, 4]``."""
    from atlas_pipeline.mapping.keyframes import slam_poses

    slam = slam_poses(manifest, cfg.mapping, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                      cfg.fusion.stride, frames=frames)
    return {"frames_per_s": (manifest.n_frames - 1) / slam.time_s, "poses": slam.T_world_cam.copy(),
            "ate_rmse_m": grade(manifest, slam.T_world_cam).get("ate_rmse_m", np.nan), "n_keyframes": len(slam.keyframe_indices)}


class _CallTimer:
    """While active, times every call of the tracker's normal equations: ``[(points, seconds)]``."""

    def __init__(self):
        self.calls: list[tuple[int, float]] = []

    def __enter__(self):
        from atlas_pipeline.localization import tracker

        self._orig = tracker.normal_equations

        def timed(frame, *args, **kwargs):
            t0 = time.perf_counter()
            out = self._orig(frame, *args, **kwargs)
            self.calls.append((frame.points_cam.shape[0], time.perf_counter() - t0))
            return out

        tracker.normal_equations = timed
        return self

    def __exit__(self, *exc):
        from atlas_pipeline.localization import tracker

        tracker.normal_equations = self._orig


def main(argv: list[str] | None = None) -> int:
    from atlas_pipeline.localization import normal_equations as ne
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="synthetic-suite",
                    help="a registry name, or a folder of ../shared/data: " + ", ".join(f for f, _, _ in SHARED_SPLITS))
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    cfg = benchmark_config()
    full = _dataset(args.dataset, cfg)
    m = _slice(full, 0, min(args.frames, full.n_frames), args.dataset)
    frames = load_frames(m)
    _slam(_slice(m, 0, WARM_UP_FRAMES, args.dataset), frames[:WARM_UP_FRAMES], cfg)
    from atlas_pipeline.cores import kernel_threads

    modes = {"one thread (reference)": ONE_THREAD, f"split over {kernel_threads()} threads": ne.SPLIT_MIN_POINTS}
    best: dict[str, dict] = {}
    calls: dict[str, list] = {}
    poses: dict[str, np.ndarray] = {}
    default_threshold = ne.SPLIT_MIN_POINTS
    try:
        for _ in range(args.repeats):
            for name, threshold in modes.items():
                ne.SPLIT_MIN_POINTS = threshold
                with _CallTimer() as timer:
                    figures = _slam(m, frames, cfg)
                calls[name] = timer.calls
                if name not in best or figures["frames_per_s"] > best[name]["frames_per_s"]:
                    best[name] = figures
                poses[name] = figures["poses"]
    finally:
        ne.SPLIT_MIN_POINTS = default_threshold
    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}; {args.dataset}, first {m.n_frames} "
          f"frames in memory, loop closure on, best of {args.repeats}")
    print("| normal equations | frames/s | ATE cm | keyframes |")
    print("|---|---|---|---|")
    for name, f in best.items():
        print(f"| {name} | {f['frames_per_s']:.1f} | {100 * f['ate_rmse_m']:.3f} | {f['n_keyframes']} |")
    ref, split = (best[n] for n in modes)
    a, b = (poses[n] for n in modes)
    apart_m = np.nanmax(np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1), initial=0.0)
    print(f"speed-up: {split['frames_per_s'] / ref['frames_per_s']:.2f}x; poses identical: {np.array_equal(a, b, equal_nan=True)}"
          f" (largest camera centre difference {apart_m:.1e} m)")
    print()
    print("| frame points | calls | ms a call: " + " / ".join(modes) + " |")
    print("|---|---|---|")
    for lo, hi in POINT_CLASSES:
        ms = [np.median([s for n, s in calls[name] if lo <= n < hi] or [np.nan]) * 1e3 for name in modes]
        count = sum(1 for n, _ in calls[next(iter(modes))] if lo <= n < hi)
        label = f"{lo:,}+" if hi == POINT_CLASSES[-1][1] else f"{lo:,}-{hi:,}"
        print(f"| {label} | {count} | " + " / ".join(f"{v:.2f}" for v in ms) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Where a SLAM frame's time goes, and which parts grow with the map.

SLAM (``slam_poses``: tracking, keyframe integration, loop closure; no ground truth read) on the
first ``N`` frames of the synthetic suite (640x480, frames decoded before the clock starts),
under cProfile, for each ``N`` given. Per stage: milliseconds per frame and share of the run,
plus milliseconds per call where the stage runs per view or per keyframe. Comparing two ``N``
shows what grows with the map (the splat of the model view, keyframe integration, loop closure)
and what does not (the Gauss-Newton normal equations, frame preparation).

cProfile adds its own cost to every Python call (about a third more wall time here); the shares,
not the absolute frame rate, are the result. ``bench_persistence.py`` gives the frame rate.

    python benchmarks/bench_slam_stages.py [--frames 400 1500] [--json out.json]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import platform
import pstats
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_persistence import _slice, benchmark_config  # noqa: E402
from benchmarks.common import load_frames, run_slam  # noqa: E402

DATASET = "synthetic-suite"
WARM_UP_FRAMES = 5  # compiles the kernels before the clock starts

# stage -> (module path suffix, function name, time taken: "own" (tottime) or "all" (cumulative))
STAGES = {
    "normal equations (both threads, wall)": ("localization/normal_equations.py", "normal_equations", "all"),
    "Gauss-Newton step (solve)": ("localization/tracker.py", "solve_update", "all"),
    "Gauss-Newton step (apply)": ("localization/tracker.py", "apply_update", "all"),
    "model view splat (kernel)": ("localization/_kernels.py", "splat_surfels", "all"),
    "view culling": ("localization/tracker.py", "culling", "all"),
    "frame preparation (pyramid)": ("localization/tracker.py", "prepare", "all"),
    "frame points per level": ("localization/tracker.py", "points", "own"),
    "keyframe integration (map + surfels)": ("localization/sequence.py", "_integrate", "all"),
}
LOOP_CLOSURE = "loop closure (wall, its own alignments included)"


def _stage_times(stats: pstats.Stats) -> dict[str, tuple[float, int]]:
    """``stage -> (seconds, calls)`` from a profile."""
    out = {}
    for stage, (suffix, name, kind) in STAGES.items():
        seconds, calls = 0.0, 0
        for (path, _, func), (_, ncalls, tottime, cumtime, _) in stats.stats.items():
            if func == name and path.replace("\\", "/").endswith(suffix):
                seconds += tottime if kind == "own" else cumtime
                calls += ncalls
        out[stage] = (seconds, calls)
    return out


class _LoopClosureApart:
    """While active, ``close_loops`` runs with ``profile`` off and is timed on its own: its
    alignments call the same kernels as tracking, which would otherwise be counted twice."""

    def __init__(self, profile: cProfile.Profile):
        self.profile, self.seconds, self.calls = profile, 0.0, 0

    def __enter__(self):
        from atlas_pipeline.mapping import loop_closure

        self._orig = loop_closure.close_loops

        def timed(*args, **kwargs):
            self.profile.disable()
            t0 = time.perf_counter()
            try:
                return self._orig(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t0
                self.calls += 1
                self.profile.enable()

        loop_closure.close_loops = timed
        return self

    def __exit__(self, *exc):
        from atlas_pipeline.mapping import loop_closure

        loop_closure.close_loops = self._orig


def run(n_frames: int) -> dict:
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    cfg = benchmark_config()
    full = load_dataset(load_registry()[DATASET], cfg)
    manifest = _slice(full, 0, min(n_frames, full.n_frames), DATASET)
    frames = load_frames(manifest)
    run_slam(_slice(manifest, 0, WARM_UP_FRAMES, DATASET), frames[:WARM_UP_FRAMES], cfg)
    profile = cProfile.Profile()
    with _LoopClosureApart(profile) as loops:
        t0 = time.perf_counter()
        profile.enable()
        figures, _ = run_slam(manifest, frames, cfg)
        profile.disable()
        wall_s = time.perf_counter() - t0
    stages = {**_stage_times(pstats.Stats(profile)), LOOP_CLOSURE: (loops.seconds, loops.calls)}
    n = manifest.n_frames
    rows = {k: {"ms_per_frame": 1e3 * s / n, "share": s / wall_s, "calls": c,
                "ms_per_call": 1e3 * s / c if c else float("nan")} for k, (s, c) in stages.items()}
    accounted = sum(s for s, _ in stages.values())
    rows["everything else"] = {"ms_per_frame": 1e3 * (wall_s - accounted) / n, "share": 1 - accounted / wall_s,
                               "calls": 0, "ms_per_call": float("nan")}
    return {"frames": n, "wall_s_profiled": wall_s, "frames_per_s_profiled": n / wall_s,
            "keyframes": figures["n_keyframes"], "ate_m": figures.get("ate_rmse_m"), "stages": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[400, 1500], help="first N frames of the suite, per run")
    ap.add_argument("--json", type=Path, help="write the figures here too")
    args = ap.parse_args()
    results = [run(n) for n in args.frames]
    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}; {DATASET} 640x480, under cProfile")
    head = " | ".join(f"{r['frames']} frames: ms/frame, share, ms/call" for r in results)
    print(f"| stage | {head} |")
    print("|---|" + "---|" * len(results))
    for stage in results[0]["stages"]:
        cells = []
        for r in results:
            s = r["stages"][stage]
            per_call = "-" if s["calls"] == 0 else f"{s['ms_per_call']:.2f} ({s['calls']})"
            cells.append(f"{s['ms_per_frame']:.1f}, {100 * s['share']:.0f} %, {per_call}")
        print(f"| {stage} | " + " | ".join(cells) + " |")
    for r in results:
        print(f"{r['frames']} frames: {r['wall_s_profiled']:.1f} s profiled ({r['frames_per_s_profiled']:.1f} frames/s), "
              f"{r['keyframes']} keyframes, ATE " + ("-" if r["ate_m"] is None else f"{100 * r['ate_m']:.2f} cm"))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()

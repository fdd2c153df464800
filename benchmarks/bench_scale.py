"""How the pipeline scales with sequence length: seconds, per-frame time and peak memory per stage.

For each frame count N the synthetic room (the registry's ``synthetic`` entry with ``n_frames``
set to N: the same scene, a longer path) is generated into a temporary data folder (not timed),
then every stage runs through the library in a fresh child process, in the order the Dagster graph
runs them: load, fuse, keyframes, gaussian_world, localization, transitions, render_evaluation.
A sampler thread reads the process's resident set (``/proc/self/statm``) every
``SAMPLE_INTERVAL_S``; a stage's peak is the largest sample taken while it ran (memory freed by
an earlier stage may still be resident, so a stage's peak is an upper bound on its own need).

    python benchmarks/bench_scale.py                       # N = 100 500 2000
    python benchmarks/bench_scale.py --frames 60 240 --json scale.json
    python benchmarks/bench_scale.py --graph --frames 1200   # atlas-gs run through Dagster: every asset
    python benchmarks/bench_scale.py --frames 1200 --set mapping.fit.epochs=0   # no fit

The table gives, per N: seconds and peak RSS (MB) per stage, the whole run's peak, seconds per
frame and its ratio to the smallest N (the linear-cost check: 1.0 = per-frame cost unchanged), the
Gaussians the keyframes merged into and those after the fit, and the held-out PSNR (full frame /
within mapped pixels). A longer path sees other parts of the room, so its held-out views differ
from a shorter one's: every N's world is therefore also rendered at the smallest N's held-out views
that are not its own keyframes ("first N's views": the path is a function of time, so those frames
are the same images), which compares the worlds on identical views. The Ns run smallest first.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_INTERVAL_S = 0.05  # RSS sampling period: short against every stage at these sizes
STAGES = ("load_dataset", "fuse", "keyframes", "gaussian_world", "localization", "transitions",
          "render_evaluation")
DEFAULT_FRAMES = (100, 500, 2000)  # short, long and very long


class RssSampler(threading.Thread):
    """Samples this process's resident set size; :meth:`peak_since` gives the largest since a mark."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.page = os.sysconf("SC_PAGE_SIZE")
        self.peak = 0
        self._stop = threading.Event()

    def rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self.page

    def mark(self) -> None:
        self.peak = self.rss()

    def run(self) -> None:
        while not self._stop.wait(SAMPLE_INTERVAL_S):
            self.peak = max(self.peak, self.rss())

    def stop(self) -> None:
        self._stop.set()


def child(n_frames: int, data_dir: str, profile: str, overrides: dict | None = None,
          common_frames: list[int] | None = None) -> dict:
    """Every stage once on the synthetic room at ``n_frames`` (run inside a fresh process);
    ``common_frames``: the first N's held-out views, rendered in this world too (not timed)."""
    sys.path.insert(0, str(ROOT))
    os.environ["ATLAS_DATA_DIR"] = data_dir
    import dataclasses
    import logging

    logging.basicConfig(level=logging.WARNING)
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering, evaluate_views
    from atlas_pipeline.localization.localizer import localize
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.sensors.registry import load_dataset, load_registry
    from atlas_pipeline.transition_log.transitions import log_transitions

    quiet = lambda *_: None  # noqa: E731
    cfg = load_profile(profile).with_overrides(overrides or {}, "--set")
    base = load_registry()["synthetic"]
    entry = dataclasses.replace(base, name=f"synthetic-{n_frames}", path=Path(data_dir) / f"synthetic-{n_frames}",
                                params={**base.params, "n_frames": n_frames})
    sampler = RssSampler()
    sampler.start()
    out: dict = {"n_frames": n_frames, "stages": {}}

    def timed(stage: str, fn, *args, **kwargs):
        sampler.mark()
        t0 = time.perf_counter()
        res = fn(*args, **kwargs)
        sec = time.perf_counter() - t0
        out["stages"][stage] = {"seconds": round(sec, 2), "peak_rss_mb": round(max(sampler.peak, sampler.rss()) / 2**20)}
        return res

    manifest = timed("load_dataset", load_dataset, entry, cfg, quiet)
    fused = timed("fuse", fuse, manifest, cfg, quiet)
    keyframes = timed("keyframes", select_keyframes_stage, manifest, fused, cfg, quiet)
    world = timed("gaussian_world", build_gaussian_world, fused, keyframes, cfg, quiet, manifest=manifest)
    report = timed("localization", localize, manifest, world, cfg, quiet)
    timed("transitions", log_transitions, report, entry.name, len(world.field), cfg)
    ev = timed("render_evaluation", evaluate_rendering, manifest, world, report, cfg, quiet)
    sampler.stop()
    import resource

    import numpy as np

    common = ev  # the first N's own held-out views
    if common_frames is not None:
        frames = np.setdiff1d(np.asarray(common_frames, np.int64), world.keyframe_indices)
        common = evaluate_views(world.field, manifest, report.T_world_cam, frames, "estimated", world.map_id,
                                (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m))

    out.update(n_keyframes=int(len(keyframes.indices)), n_gaussians=int(len(world.field)),
               n_merged=int(world.history[-1]) if len(world.history) else None,  # before the fit
               peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
               psnr_db=ev.summary.get("mean_psnr_db"), psnr_masked_db=ev.summary.get("mean_psnr_masked_db"),
               ate_m=report.summary.get("ate_rmse_m"), eval_frames=[int(i) for i in ev.frames],
               common_n_views=len(common.frames), common_psnr_db=common.summary.get("mean_psnr_db"),
               common_psnr_masked_db=common.summary.get("mean_psnr_masked_db"))
    return out


def generate(n_frames: int, data_dir: str) -> None:
    """The synthetic room at ``n_frames`` into ``data_dir`` (before any timing)."""
    sys.path.insert(0, str(ROOT))
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset
    from atlas_pipeline.sensors.registry import load_registry

    params = {**load_registry()["synthetic"].params, "n_frames": n_frames}
    generate_synthetic_dataset(Path(data_dir) / f"synthetic-{n_frames}", SyntheticSpec(**params))


def whole_graph(n_frames: int, data_dir: str) -> dict:
    """``atlas-gs run synthetic-N`` through Dagster (every asset: videos, bundle and checks included)
    in fresh artifacts and Dagster folders: wall and CPU seconds and the peak RSS of the run's
    process (the in-process executor runs every step in it)."""
    import resource
    import yaml

    sys.path.insert(0, str(ROOT))
    from atlas_pipeline.sensors.registry import load_registry

    name = f"synthetic-{n_frames}"
    with tempfile.TemporaryDirectory(prefix="atlas-bench-graph-") as tmp:
        t = Path(tmp)
        (t / "dagster_home").mkdir()
        reg = t / "datasets.local.yaml"
        reg.write_text(yaml.safe_dump({"datasets": {name: {"kind": "synthetic",
                                                          **{**load_registry()["synthetic"].params,
                                                             "n_frames": n_frames}}}}))
        env = {**os.environ, "ATLAS_DATA_DIR": data_dir, "ATLAS_ARTIFACTS_DIR": str(t / "artifacts"),
               "ATLAS_LOCAL_REGISTRY": str(reg), "DAGSTER_HOME": str(t / "dagster_home")}
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "assets.cli", "run", name], cwd=ROOT, env=env,
                              capture_output=True, text=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            raise SystemExit(f"atlas-gs run {name} failed:\n{proc.stderr[-3000:]}")
        ev = json.loads((t / "artifacts" / "render_evaluation" / name / "photometric.json").read_text())["summary"]
        return {"n_frames": n_frames, "wall_s": round(wall, 1),
                "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1),
                # ru_maxrss of children: the largest child, here the run's one process (kB on Linux)
                "peak_rss_mb": round(after.ru_maxrss / 1024), "psnr_db": ev.get("mean_psnr_db"),
                "psnr_masked_db": ev.get("mean_psnr_masked_db")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", nargs="+", type=int, default=list(DEFAULT_FRAMES))
    ap.add_argument("--profile", default="default")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for every N (as atlas-gs --set), e.g. mapping.fit.epochs=0")
    ap.add_argument("--overrides", help=argparse.SUPPRESS)  # the child's: --set as JSON
    ap.add_argument("--graph", action="store_true",
                    help="instead: atlas-gs run through Dagster (every asset) per N: wall, CPU, peak RSS")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--common-frames", help=argparse.SUPPRESS)  # the child's: the first N's views, JSON
    ap.add_argument("--data", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child(args.child, args.data, args.profile, json.loads(args.overrides or "{}"),
                               json.loads(args.common_frames) if args.common_frames else None)))
        return 0
    from atlas_pipeline.config import parse_set_overrides

    overrides = parse_set_overrides(args.set)
    if args.graph and overrides:
        raise SystemExit("--set applies to the library stages, not to --graph")

    if args.graph:
        with tempfile.TemporaryDirectory(prefix="atlas-bench-scale-") as data:
            out = []
            for n in args.frames:
                generate(n, data)
                out.append(whole_graph(n, data))
        print(f"atlas-gs run synthetic-N (every asset, Dagster in-process); load average {os.getloadavg()[0]:.2f}")
        print(f"{'frames':>7} {'wall s':>8} {'CPU s':>8} {'s/frame':>8} {'peak MB':>8} {'PSNR':>6} {'masked':>7}")
        for r in out:
            print(f"{r['n_frames']:>7} {r['wall_s']:>8} {r['cpu_s']:>8} {r['wall_s'] / r['n_frames']:>8.3f} "
                  f"{r['peak_rss_mb']:>8} {r['psnr_db']:>6.2f} {r['psnr_masked_db']:>7.2f}")
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=2))
        return 0

    rows = []
    with tempfile.TemporaryDirectory(prefix="atlas-bench-scale-") as data:
        for n in sorted(args.frames):  # the smallest first: its held-out views are rendered in every world
            generate(n, data)
            common = ["--common-frames", json.dumps(rows[0]["eval_frames"])] if rows else []
            proc = subprocess.run([sys.executable, __file__, "--child", str(n), "--data", data,
                                   "--profile", args.profile, "--overrides", json.dumps(overrides), *common],
                                  capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                print(f"N={n}: failed\n{proc.stderr[-2000:]}", file=sys.stderr)
                return 1
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    print(f"synthetic room, profile {args.profile}"
          + "".join(f", {k}={v}" for k, v in overrides.items())
          + f"; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    print("seconds / peak RSS MB per stage:")
    print(f"{'frames':>7} " + " ".join(f"{s[:14]:>16}" for s in STAGES))
    for r in rows:
        print(f"{r['n_frames']:>7} " + " ".join(
            f"{r['stages'][s]['seconds']:>8.1f}/{r['stages'][s]['peak_rss_mb']:<7d}" for s in STAGES))
    base = None
    print(f"\n{'frames':>7} {'keyframes':>9} {'merged':>8} {'Gaussians':>10} {'total s':>8} {'s/frame':>8} {'ratio':>6} "
          f"{'peak MB':>8} {'PSNR':>6} {'masked':>7} {'ATE cm':>7}  first N's views: {'n':>4} {'PSNR':>6} {'masked':>7}")
    for r in rows:
        total = sum(st["seconds"] for st in r["stages"].values())
        per = total / r["n_frames"]
        base = base or per
        f = lambda v, d=2: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
        print(f"{r['n_frames']:>7} {r['n_keyframes']:>9} {r.get('n_merged') or 'n/a':>8} {r['n_gaussians']:>10} {total:>8.1f} {per:>8.3f} "
              f"{per / base:>6.2f} {r['peak_rss_mb']:>8} {f(r['psnr_db']):>6} {f(r['psnr_masked_db']):>7} "
              f"{f(None if r['ate_m'] is None else r['ate_m'] * 100):>7}  {'':>16} {r['common_n_views']:>4} "
              f"{f(r['common_psnr_db']):>6} {f(r['common_psnr_masked_db']):>7}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The keyframe fit: its first version against today's, in the same run.

    python benchmarks/bench_fit.py                        # synthetic, and TUM teddy when present
    python benchmarks/bench_fit.py --datasets synthetic --variants legacy new
    python benchmarks/bench_fit.py --set mapping.fit.plateau_patience=3 --json fit.json
    python benchmarks/bench_fit.py --datasets synthetic --variants new --synthetic-frames 400   # a long path

For each dataset the default profile builds the world from ground-truth poses (fusion, keyframes,
voxel Gaussians, colour refinement: not timed), then fits it to the keyframes three ways:

* ``old``: the fit as committed in ``OLD_COMMIT`` (float64 per-pixel kernels, a serial-per-worker
  backward, 600 steps at half size), read from git; skipped with a message where git or the commit
  is missing;
* ``legacy``: that schedule (``first_schedule()``: 600 steps at the fit scale, no coarse level, no
  early stop, no densification, dense Adam) on today's kernels;
* ``new``: the default profile's schedule (``mapping.fit``) on today's kernels.

Each fitted world is rendered at every ``--view-stride``-th held-out frame (never a keyframe) from
its ground-truth pose and compared with the real image (``evaluation.evaluate_views``): PSNR over
the whole frame and over the pixels with a depth reading in the fusion range. Reported per variant:
steps, passes, why it stopped, steps/s (wall) and CPU seconds per step, CPU seconds per stage
(projection, forward, backward, Adam, densify), total CPU seconds, PSNR, Gaussians; then the ratio
old / new of the CPU seconds and the PSNR difference new - old. CPU seconds are
``time.process_time`` (every thread of the process), so a busy machine changes wall time far more
than them; the compiled kernels are warmed up before anything is timed.

The old code has no stage clock: its stages are timed by wrapping its functions (projection =
project, sort, bin and depth slopes; its one per-pixel kernel does forward and backward together and
is reported under backward; Adam = the rest of each step).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

OLD_COMMIT = "e4f823f"  # the last commit with the first fit
STAGES = ("projection", "forward", "backward", "adam", "densify")
VARIANTS = ("old", "legacy", "new")


def load_old_fit(commit: str = OLD_COMMIT):
    """The fit module as of ``commit`` (imported from a temporary file), or ``(None, why)``."""
    try:
        src = subprocess.run(["git", "show", f"{commit}:atlas_pipeline/gaussian_world/optimize.py"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"git show {commit} failed ({exc})"
    folder = Path(tempfile.mkdtemp(prefix="atlas_old_fit_"))
    path = folder / f"optimize_{commit}.py"
    path.write_text(src)
    name = f"atlas_old_fit_{commit}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod, ""


class _OldStageClock:
    """CPU seconds of the old fit's stages, by wrapping its module's functions."""

    def __init__(self, mod) -> None:
        self.cpu = dict.fromkeys(STAGES, 0.0)
        raster = mod.raster

        def timed(fn, stage):
            def run(*a, **k):
                t = time.process_time()
                try:
                    return fn(*a, **k)
                finally:
                    self.cpu[stage] += time.process_time() - t
            return run

        class _Raster:  # the raster module, its prepare_splats timed
            def __getattr__(self, item):
                return getattr(raster, item)

        proxy = _Raster()
        proxy.prepare_splats = timed(raster.prepare_splats, "projection")
        mod.raster = proxy
        mod._depth_slopes = timed(mod._depth_slopes, "projection")
        mod._backward = timed(mod._backward, "backward")
        mod._backward_params = timed(mod._backward_params, "backward")


def build_inputs(manifest, cfg) -> dict:
    """The world before its keyframe fit, and the fit's inputs (as ``pipeline.build_gaussian_world``)."""
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    base = cfg.with_overrides({"mapping.fit.epochs": 0})
    fused = fuse(manifest, base)
    kf = select_keyframes_stage(manifest, fused, base)
    world = build_gaussian_world(fused, kf, base, manifest=manifest)  # voxel Gaussians, colours fitted
    idx = [int(i) for i in world.keyframe_indices]
    lo, hi = cfg.fusion.min_depth_m, cfg.fusion.max_depth_m
    depths = []
    for i in idx:
        d = manifest.read_depth_m(i, allow_empty=True)
        depths.append(np.where((d >= lo) & (d <= hi), d, 0.0))
    return {"field": world.field, "images": [manifest.read_rgb(i) for i in idx], "depths": depths,
            "poses": list(world.T_world_cam_keyframes), "K": manifest.camera.K, "keyframes": idx}


def held_out_psnr(manifest, field, keyframes: list[int], cfg, stride: int) -> tuple[float, float, int]:
    from atlas_pipeline.gaussian_world.evaluation import evaluate_views

    kf = set(keyframes)
    frames = np.array([i for i in range(manifest.n_frames) if i not in kf][::stride])
    rep = evaluate_views(field, manifest, manifest.T_world_cam_gt, frames, "ground_truth",
                         depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), log=lambda _: None)
    s = rep.summary
    return s["mean_psnr_db"], s["mean_psnr_masked_db"], s["n_views"]


def first_schedule(**overrides):
    """The fit's first schedule: up to 30 passes and 600 steps, every one at half size, no early stop,
    no densification or pruning, dense Adam (``overrides`` replace any field)."""
    from atlas_pipeline.config import FitConfig

    return FitConfig(**{"epochs": 30, "max_steps": 600, "min_steps_per_keyframe": 0, "scale": 0.5,
                                   "coarse_factor": 1, "coarse_max_steps": 0, "plateau_patience": 0,
                                   "densify_interval": 0, "selective_adam": False, **overrides})


def run_variant(variant: str, inputs: dict, cfg, old_mod) -> dict:
    from atlas_pipeline.gaussian_world.optimize import optimize_gaussians

    args = (inputs["field"], inputs["images"], inputs["depths"], inputs["poses"], inputs["K"])
    quiet = {"log": lambda _: None}
    mc = cfg.mapping
    first = first_schedule(depth_weight=mc.fit.depth_weight)  # the first schedule
    if variant == "old":
        settings = old_mod.OptimizationSettings(epochs=first.epochs, max_steps=first.max_steps, scale=first.scale,
                                                depth_weight=first.depth_weight)
        old_mod.optimize_gaussians(*args, old_mod.OptimizationSettings(epochs=1, max_steps=1), **quiet)  # JIT
        clock = _OldStageClock(old_mod)
        c0, w0 = time.process_time(), time.perf_counter()
        res = old_mod.optimize_gaussians(*args, settings, **quiet)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        stages = dict(clock.cpu)
        stages["adam"] = cpu - sum(stages.values())
        steps = len(res.loss)
        stop = "step_cap" if steps < first.epochs * len(inputs["images"]) else "epochs"
        out = {"steps": steps, "epochs": -(-steps // len(inputs["images"])), "stop_reason": stop,
               "stage_cpu_s": stages, "n_gaussians": len(res.field)}
    else:
        settings = first if variant == "legacy" else mc.fit
        for warm in (1, settings.coarse_factor):  # JIT at both scales (the compiled code is cached on disk)
            optimize_gaussians(*args, first_schedule(max_steps=1, scale=settings.scale / warm), **quiet)
        c0, w0 = time.process_time(), time.perf_counter()
        res = optimize_gaussians(*args, settings, **quiet)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        rec = res.record
        out = {"steps": rec["steps"], "epochs": rec["epochs"], "stop_reason": rec["stop_reason"],
               "coarse_steps": (rec["coarse"] or {}).get("steps", 0), "stage_cpu_s": dict(res.stage_cpu_s),
               "n_gaussians": len(res.field), "n_cloned": rec["n_cloned"], "n_split": rec["n_split"],
               "n_pruned": rec["n_pruned"], "final_loss": rec["final_loss"]}
    out.update({"cpu_s": cpu, "wall_s": wall, "steps_per_s": out["steps"] / wall, "cpu_s_per_step": cpu / out["steps"],
                "field": res.field})
    return out


def _fmt_row(label: str, r: dict) -> str:
    st = r["stage_cpu_s"]
    stop = r["stop_reason"] + (f", {r['coarse_steps']} coarse" if r.get("coarse_steps") else "")
    return (f"  {label:8} {r['steps']:5d} {r['epochs']:4d}  {stop:22} {r['steps_per_s']:6.2f} {r['cpu_s_per_step']:7.3f}"
            + "".join(f" {st[k]:7.1f}" for k in STAGES)
            + f" {r['cpu_s']:8.1f} {r['psnr_db']:7.2f} {r['psnr_masked_db']:7.2f} {r['n_gaussians']:9,d}")


def main(argv: list[str] | None = None) -> int:
    import numba
    from bench_tracking import _load

    from atlas_pipeline.config import load_profile, parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["synthetic", "teddy"], choices=["synthetic", "teddy"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--view-stride", type=int, default=2, help="evaluate every n-th held-out frame")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every variant, e.g. mapping.fit.densify_interval=0")
    ap.add_argument("--synthetic-frames", type=int, default=None, metavar="N",
                    help="the synthetic room with N frames instead of the built-in 60 (a longer path "
                         "through the same room: more keyframes, more Gaussians per step)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    try:
        overrides = {"mapping.pose_source": "ground_truth", **parse_set_overrides(args.set)}
    except ConfigError as exc:
        ap.error(str(exc))
    cfg = load_profile("default").with_overrides(overrides)
    old_mod = None
    if "old" in args.variants:
        old_mod, why = load_old_fit()
        if old_mod is None:
            print(f"old: skipped ({why})")
    print(f"numba {numba.__version__}: {numba.get_num_threads()} threads, threading layer "
          f"{os.environ.get('NUMBA_THREADING_LAYER', 'default')}, OMP_WAIT_POLICY "
          f"{os.environ.get('OMP_WAIT_POLICY', 'unset')}; CPU seconds = process time, all threads")
    results: dict = {}
    for name in args.datasets:
        manifest = _load(name, synthetic_frames=args.synthetic_frames)
        if manifest is None:
            print(f"{name}: skipped (TUM frames not found at ../shared/data/tum_fr3_teddy_100)")
            continue
        inputs = build_inputs(manifest, cfg)
        rows = {}
        for variant in args.variants:
            if variant == "old" and old_mod is None:
                continue
            r = run_variant(variant, inputs, cfg, old_mod)
            r["psnr_db"], r["psnr_masked_db"], n_views = held_out_psnr(manifest, r.pop("field"), inputs["keyframes"],
                                                                       cfg, args.view_stride)
            rows[variant] = r
        print(f"\n{name}: {len(inputs['keyframes'])} keyframes, {len(inputs['field']):,} Gaussians before the fit, "
              f"{n_views} held-out views (ground-truth poses)")
        print(f"  {'variant':8} {'steps':>5} {'pass':>4}  {'stopped':22} {'step/s':>6} {'CPU-s/st':>7}"
              + "".join(f" {k[:7]:>7}" for k in STAGES) + f" {'CPU-s':>8} {'PSNR':>7} {'masked':>7} {'Gaussians':>9}")
        for variant, r in rows.items():
            print(_fmt_row(variant, r))
        base = rows.get("old") or rows.get("legacy")
        new = rows.get("new")
        if base is not None and new is not None and base is not new:
            label = "old" if "old" in rows else "legacy"
            print(f"  {label}/new CPU-s: {base['cpu_s'] / new['cpu_s']:.1f}x; PSNR new - {label}: "
                  f"{new['psnr_db'] - base['psnr_db']:+.2f} dB full frame, "
                  f"{new['psnr_masked_db'] - base['psnr_masked_db']:+.2f} dB pixels with depth")
        if "old" in rows and "legacy" in rows:
            print(f"  kernels alone (old/legacy CPU-s per step): "
                  f"{rows['old']['cpu_s_per_step'] / rows['legacy']['cpu_s_per_step']:.1f}x")
        results[name] = rows
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""View-dependent colour in the keyframe fit: held-out PSNR and the fit's CPU seconds at SH degree
0, 1 and 3, in one run.

    python benchmarks/bench_sh.py                               # teddy and fr1, degrees 0 1 3
    python benchmarks/bench_sh.py --datasets teddy --sh-degrees 0,1 --frames 60 --json sh.json
    python benchmarks/bench_sh.py --datasets teddy --sh-degrees 0,3 --set mapping.fit.lr_sh_rest=0.006

For each dataset the default profile builds the world from ground-truth poses (fusion, keyframes,
voxel Gaussians, colour refinement: not timed; ``bench_fit.build_inputs``), then fits it to the
keyframes once per degree with ``mapping.fit`` as the profile has it and only ``sh_degree`` changed
(the degree grown from 0 every ``sh_degree_interval`` steps). Each fitted world is rendered, its SH
included, at every ``--view-stride``-th held-out frame (never a keyframe) from its ground-truth pose
and compared with the real image (``evaluation.evaluate_views``): PSNR over the whole frame and over
the pixels with a depth reading in the fusion range. CPU seconds are the fit's ``time.process_time``
(every thread); the compiled kernels are warmed up at every degree and both fit scales first.
Reported per degree: steps, CPU seconds (and per step), PSNR, Gaussians, the gain over degree 0 and
the cost ratio, and whether it meets the bar for a new default (``GAIN_DB`` at most ``COST_RATIO``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

GAIN_DB = 0.5  # a degree > 0 becomes the default when it gains this much held-out full-frame PSNR ...
COST_RATIO = 1.5  # ... at most this times degree 0's fit CPU seconds


SHARED = ROOT.parent / "shared" / "data"
TUM = {"teddy": ("tum_fr3_teddy_100", "freiburg3"), "fr1": ("tum_fr1_xyz_10", "freiburg1")}


def load(name: str, n_frames: int | None):
    """The dataset's first ``n_frames`` (None: all), or None when its TUM frames are not present."""
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.tum import load_tum_sequence

    if name == "synthetic":
        from bench_tracking import _load as load_synthetic

        return load_synthetic(name, n_frames)
    folder, camera = TUM[name]
    if not (SHARED / folder / "rgb.txt").is_file():
        return None
    return load_tum_sequence(SHARED / folder, TUM_CAMERAS[camera], folder, n_frames)


def fit_at(inputs: dict, fit_cfg, degree: int) -> dict:
    from atlas_pipeline.gaussian_world.optimize import optimize_gaussians

    args = (inputs["field"], inputs["images"], inputs["depths"], inputs["poses"], inputs["K"])
    quiet = {"log": lambda _: None}
    settings = fit_cfg.model_copy(update={"sh_degree": degree})
    for f in (1, settings.coarse_factor):  # JIT at both scales and this degree (cached on disk after)
        optimize_gaussians(*args, settings.model_copy(update={"max_steps": 2, "min_steps_per_keyframe": 0,
                                                              "scale": settings.scale / f, "coarse_factor": 1,
                                                              "sh_degree_interval": 1}), **quiet)
    w0 = time.perf_counter()
    res = optimize_gaussians(*args, settings, **quiet)
    return {"field": res.field, "steps": res.record["steps"], "stop_reason": res.record["stop_reason"],
            "cpu_s": res.cpu_seconds, "wall_s": time.perf_counter() - w0, "stage_cpu_s": dict(res.stage_cpu_s),
            "n_gaussians": len(res.field)}


def main(argv: list[str] | None = None) -> int:
    import numba
    from bench_fit import build_inputs, held_out_psnr

    from atlas_pipeline.config import load_profile, parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["teddy", "fr1"], choices=["synthetic", "teddy", "fr1"])
    ap.add_argument("--sh-degrees", default="0,1,3", help="comma-separated SH degrees (0 first: the baseline)")
    ap.add_argument("--frames", type=int, default=None, metavar="N", help="only the first N frames of each dataset")
    ap.add_argument("--view-stride", type=int, default=2, help="evaluate every n-th held-out frame")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every degree, e.g. mapping.fit.lr_sh_rest=0.005")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    degrees = [int(d) for d in args.sh_degrees.split(",")]
    try:
        overrides = {"mapping.pose_source": "ground_truth", **parse_set_overrides(args.set)}
    except ConfigError as exc:
        ap.error(str(exc))
    cfg = load_profile("default").with_overrides(overrides)
    print(f"numba {numba.__version__}: {numba.get_num_threads()} threads; CPU seconds = process time of the fit, "
          f"all threads; sh_degree_interval {cfg.mapping.fit.sh_degree_interval}, lr_sh_rest "
          f"{cfg.mapping.fit.lr_sh_rest}")
    results: dict = {}
    for name in args.datasets:
        manifest = load(name, args.frames)
        if manifest is None:
            print(f"{name}: skipped (TUM frames not found in ../shared/data)")
            continue
        inputs = build_inputs(manifest, cfg)
        rows = {}
        for d in degrees:
            r = fit_at(inputs, cfg.mapping.fit, d)
            r["psnr_db"], r["psnr_masked_db"], n_views = held_out_psnr(manifest, r.pop("field"), inputs["keyframes"],
                                                                       cfg, args.view_stride)
            rows[d] = r
        print(f"\n{name}: {manifest.n_frames} frames, {len(inputs['keyframes'])} keyframes, "
              f"{len(inputs['field']):,} Gaussians before the fit, {n_views} held-out views (ground-truth poses)")
        print(f"  {'degree':>6} {'steps':>5} {'CPU-s':>7} {'CPU-s/st':>8} {'PSNR':>7} {'depth':>7} {'Gaussians':>9}"
              f" {'gain':>6} {'g depth':>7} {'cost':>5}")
        base = rows.get(0)
        for d, r in rows.items():
            gain = r["psnr_db"] - base["psnr_db"] if base else float("nan")
            gain_m = r["psnr_masked_db"] - base["psnr_masked_db"] if base else float("nan")
            cost = r["cpu_s"] / base["cpu_s"] if base else float("nan")
            r.update(gain_db=gain, gain_masked_db=gain_m, cost_ratio=cost)
            print(f"  {d:6d} {r['steps']:5d} {r['cpu_s']:7.1f} {r['cpu_s'] / r['steps']:8.3f} {r['psnr_db']:7.2f} "
                  f"{r['psnr_masked_db']:7.2f} {r['n_gaussians']:9,d} {gain:+6.2f} {gain_m:+7.2f} {cost:5.2f}")
        if base:
            win = [d for d, r in rows.items() if d and r["gain_db"] >= GAIN_DB and r["cost_ratio"] <= COST_RATIO]
            print(f"  meets the bar (>= {GAIN_DB} dB full frame at <= {COST_RATIO}x CPU): "
                  f"{', '.join(f'degree {d}' for d in win) or 'none'}")
        results[name] = rows
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

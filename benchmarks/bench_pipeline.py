"""Seconds and frames per second of every pipeline stage, run in-process through the library.

For each dataset the stages run in the order the Dagster graph runs them, each through the same
function of ``atlas_pipeline.pipeline`` the asset calls: load_dataset, fuse, keyframes,
gaussian_world, localization, transitions, demo_videos, then world_bundle (the bundle writer,
into a temporary folder). Throughput is frames of the sequence per stage second (for
demo_videos: rendered frames per second).

Datasets:
  synthetic  the registry entry ``synthetic``; when its frames are not in the data folder they
             are generated into a temporary ATLAS_DATA_DIR first (timed apart, not a stage).
  teddy      ../shared/data/tum_fr3_teddy_100 (freiburg3 calibration), if present.
  fr1xyz     ../shared/data/tum_fr1_xyz_10 (freiburg1 calibration), if present.

Not counted in any stage: the one-off compile (or cache load) of the numba rasteriser, measured
once before the first dataset and printed as "renderer warm-up".

Run: ``python benchmarks/bench_pipeline.py [--datasets synthetic teddy fr1xyz] [--profile default]
[--repeat 1] [--json PATH]``. With ``--repeat N`` every dataset's pipeline runs N times and the
table shows the median seconds per stage (the JSON keeps every run).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from atlas_pipeline.config import PipelineConfig, load_profile  # noqa: E402
from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering  # noqa: E402
from atlas_pipeline.localization.localizer import localize, tracking_map  # noqa: E402
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage  # noqa: E402
from atlas_pipeline.perception.rgbd import fuse  # noqa: E402
from atlas_pipeline.scene_memory.bundle import write_world_bundle  # noqa: E402
from atlas_pipeline.scene_memory.metadata import bundle_metadata  # noqa: E402
from atlas_pipeline.sensors.camera import TUM_CAMERAS  # noqa: E402
from atlas_pipeline.sensors.registry import DatasetEntry, ensure_dataset_files, load_dataset, load_registry  # noqa: E402
from atlas_pipeline.transition_log.transitions import log_transitions  # noqa: E402
from atlas_pipeline.viz.demo import render_demo_videos  # noqa: E402

SHARED_DATA = ROOT.parent / "shared" / "data"
TUM_SETS = {
    "teddy": ("tum-fr3-teddy-100", SHARED_DATA / "tum_fr3_teddy_100", "freiburg3"),
    "fr1xyz": ("tum-fr1-xyz-10", SHARED_DATA / "tum_fr1_xyz_10", "freiburg1"),
}
KNOWN = ["synthetic", *TUM_SETS]
STAGES = ["load_dataset", "fuse", "keyframes", "gaussian_world", "localization", "transitions",
          "demo_videos", "render_evaluation", "world_bundle"]


class Skip(Exception):
    """A dataset that cannot be benchmarked here (reason in the message)."""


def _quiet(msg: str) -> None:
    """Progress sink: the library's progress lines would break up the table."""


def machine_info() -> dict[str, Any]:
    info: dict[str, Any] = {
        "date": dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or "",
        "python": platform.python_version(),
    }
    try:
        info["cpu_affinity"] = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        pass
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import numba

        info["numba_threads"] = numba.get_num_threads()
    except Exception:  # noqa: BLE001 - informational only
        pass
    try:
        info["loadavg_1m"] = round(os.getloadavg()[0], 2)
    except OSError:
        pass
    return info


def _synthetic_complete(entry: DatasetEntry) -> bool:
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, spec_hash

    marker = entry.path / ".complete"
    try:
        return marker.is_file() and marker.read_text().strip() == spec_hash(SyntheticSpec(**entry.params))
    except OSError:
        return False


def resolve_entry(name: str, tmp_root: Path) -> tuple[DatasetEntry, dict[str, Any]]:
    """The DatasetEntry of a benchmark dataset and notes on where it came from."""
    if name == "synthetic":
        entry = load_registry().get("synthetic")
        if entry is None:
            raise Skip("no 'synthetic' entry in the dataset registry")
        notes: dict[str, Any] = {}
        if not _synthetic_complete(entry):
            # Not generated yet: generate into a temporary data folder, not the project's.
            os.environ["ATLAS_DATA_DIR"] = str(tmp_root / "data")
            entry = load_registry()["synthetic"]
            t0 = time.perf_counter()
            ensure_dataset_files(entry, _quiet)
            notes["generation_s"] = time.perf_counter() - t0
            notes["generated_into"] = str(entry.path)
        else:
            notes["generation_s"] = None
            notes["generated_into"] = f"{entry.path} (already present)"
        return entry, notes
    ds_name, path, cam = TUM_SETS[name]
    if not (path / "rgb.txt").is_file():
        why = "folder not found" if not path.exists() else "no rgb.txt in it"
        raise Skip(f"{path}: {why}")
    return DatasetEntry(name=ds_name, kind="tum", path=path.resolve(), camera=TUM_CAMERAS[cam]), {}


def warm_up_renderer() -> float:
    """Compile (or load from numba's cache) the rasteriser on a tiny scene; returns seconds."""
    from atlas_pipeline.gaussian_world.render import render_gaussians

    rng = np.random.default_rng(0)
    n = 64
    pos = (rng.normal(size=(n, 3)) * 0.2 + [0, 0, 2]).astype(np.float32)
    scl = np.full((n, 3), 0.02, np.float32)
    quat = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
    col = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    opa = np.full(n, 0.8, np.float32)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    t0 = time.perf_counter()
    render_gaussians(pos, scl, quat, col, opa, np.eye(4), K, 64, 48)
    return time.perf_counter() - t0


def _dir_bytes(directory: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(directory.iterdir()) if p.is_file()}


def run_once(entry: DatasetEntry, cfg: PipelineConfig, work: Path) -> dict[str, Any]:
    """Every stage once; returns seconds and frames per stage plus the results' figures."""
    sec: dict[str, float] = {}

    def timed(stage: str, fn, *args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        sec[stage] = time.perf_counter() - t0
        return out

    manifest = timed("load_dataset", load_dataset, entry, cfg, _quiet)
    n = manifest.n_frames
    fused = timed("fuse", fuse, manifest, cfg, _quiet)
    keyframes = timed("keyframes", select_keyframes_stage, manifest, fused, cfg, _quiet)
    world = timed("gaussian_world", build_gaussian_world, fused, keyframes, cfg, _quiet, manifest=manifest)
    report = timed("localization", localize, manifest, world, cfg, _quiet)
    table = timed("transitions", log_transitions, report, entry.name, len(world.field), cfg)
    cam = manifest.camera
    videos = timed("demo_videos", render_demo_videos, world.field, report.T_world_cam, cam.K, cam.width,
                   cam.height, cfg, work / "videos", entry.name, _quiet, manifest=manifest)
    evaluation = timed("render_evaluation", evaluate_rendering, manifest, world, report, cfg, _quiet)
    meta = bundle_metadata(entry.name, entry.name, world, manifest, cfg,
                           {"created_by": "benchmarks/bench_pipeline.py"})
    bundle_dir = timed("world_bundle", write_world_bundle, work / "bundle", world.field, meta, report, table,
                       surfels=tracking_map(world))

    frames = {s: n for s in STAGES}
    frames["demo_videos"] = videos.n_orbit_frames + 2 * videos.n_trajectory_frames  # orbit, trajectory, side by side
    frames["render_evaluation"] = max(int(evaluation.summary["n_views"]), 1)
    files = _dir_bytes(bundle_dir)
    n_g = len(world.field)
    s = report.summary

    def num(x: Any) -> float | None:
        return float(x) if x is not None and np.isfinite(x) else None

    return {
        "stages": {st: {"seconds": sec[st], "frames": frames[st]} for st in STAGES},
        "n_frames": n,
        "n_fused_points": fused.n_points,
        "n_keyframes": int(len(keyframes.indices)),
        "mapping_pose_source": keyframes.pose_source,
        "n_gaussians": n_g,
        "localization": {
            "rpe_trans_rmse_m_per_s": num(s.get("rpe_trans_rmse_m_per_s")),
            "ate_rmse_m": num(s.get("ate_rmse_m")),
            "n_relocalized": s.get("n_relocalized"),
            "n_tracked": int(s["n_tracked"]),
            "n_lost": int(s["n_lost"]),
            "n_graded": int(s.get("n_graded", 0)),
            "tracking_frames_per_s": num(s.get("frames_per_s")),
        },
        "transitions_rows": int(table.num_rows),
        "videos": {"orbit_frames": videos.n_orbit_frames, "trajectory_frames": videos.n_trajectory_frames,
                   "size": list(videos.size),
                   "bytes": {p.name: p.stat().st_size for p in (videos.orbit, videos.trajectory)}},
        "bundle": {"bytes": sum(files.values()), "files": files,
                   "gaussians_bin_bytes_per_gaussian": files.get("gaussians.bin", 0) / n_g if n_g else None},
    }


def _fmt(x: float | None, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def print_dataset(name: str, entry: DatasetEntry, notes: dict[str, Any], runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Print the table of one dataset and return its summary (median seconds over runs)."""
    last = runs[-1]
    med = {st: statistics.median(r["stages"][st]["seconds"] for r in runs) for st in STAGES}
    mins = {st: min(r["stages"][st]["seconds"] for r in runs) for st in STAGES}
    print(f"\n== {name}: {entry.name} ({entry.kind}) {entry.path}")
    cam = entry.camera.to_dict() if entry.camera is not None else entry.params
    print(f"   {last['n_frames']} frames, images {cam.get('width')}x{cam.get('height')}", end="")
    if "generation_s" in notes:
        gen = notes["generation_s"]
        print(f"; generation {'not needed' if gen is None else f'{gen:.2f} s (not a stage)'}", end="")
    print()
    rep = f" (median of {len(runs)})" if len(runs) > 1 else ""
    print(f"   {'stage':<16}{'seconds' + rep:>{max(12, len(rep) + 10)}}{'frames':>9}{'frames/s':>11}")
    total = 0.0
    for st in STAGES:
        f = last["stages"][st]["frames"]
        t = med[st]
        total += t
        print(f"   {st:<16}{t:>{max(12, len(rep) + 10)}.3f}{f:>9d}{(f / t if t > 0 else float('nan')):>11.1f}")
    print(f"   {'total':<16}{total:>{max(12, len(rep) + 10)}.3f}{last['n_frames']:>9d}"
          f"{last['n_frames'] / total:>11.2f}")
    loc = last["localization"]
    print(f"   localization: rpe_m_per_s {_fmt(loc['rpe_trans_rmse_m_per_s'], '.4f')}  ate_rmse_m {_fmt(loc['ate_rmse_m'], '.4f')}  "
          f"n_relocalized {loc['n_relocalized']}  n_tracked {loc['n_tracked']}  n_lost {loc['n_lost']}  "
          f"(tracking alone {_fmt(loc['tracking_frames_per_s'], '.1f')} frames/s)")
    b = last["bundle"]
    print(f"   world: {last['n_gaussians']} Gaussians from {last['n_keyframes']} keyframes "
          f"({last['mapping_pose_source']} poses, {last['n_fused_points']} fused points)")
    print(f"   bundle: {b['bytes']} bytes ({b['bytes'] / 1e6:.2f} MB); gaussians.bin {b['files'].get('gaussians.bin', 0)} "
          f"bytes = {_fmt(b['gaussians_bin_bytes_per_gaussian'], '.1f')} bytes/Gaussian; "
          f"gaussians.ply {b['files'].get('gaussians.ply', 0)} bytes")
    v = last["videos"]
    print(f"   videos: {v['orbit_frames']} orbit + {v['trajectory_frames']} trajectory frames at "
          f"{v['size'][0]}x{v['size'][1]}; {sum(v['bytes'].values())} bytes")
    return {
        "name": name, "entry": entry.describe(), "notes": notes, "repeat": len(runs),
        "median_seconds": med, "min_seconds": mins,
        "frames_per_s": {st: last["stages"][st]["frames"] / med[st] if med[st] > 0 else None for st in STAGES},
        "runs": runs,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", nargs="+", default=KNOWN, choices=KNOWN, metavar="NAME",
                    help=f"datasets to run, of {KNOWN} (default: all)")
    ap.add_argument("--profile", default="default", help="configuration profile (name or YAML path)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of every dataset's pipeline (median reported)")
    ap.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write the results as JSON")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("atlas_pipeline").setLevel(logging.WARNING)

    cfg = load_profile(args.profile)
    info = machine_info()
    print(f"Atlas-GS pipeline benchmark  {info['date']}")
    print(f"machine: {info['cpu_count']} CPUs (usable {info.get('cpu_affinity', '?')}), "
          f"{info.get('cpu_model', info['processor'])}, {info['platform']}, Python {info['python']}, "
          f"numba threads {info.get('numba_threads', '?')}, load avg (1 min) {info.get('loadavg_1m', '?')}")
    print(f"profile: {cfg.profile} ({args.profile}); repeat {args.repeat}")

    warm = warm_up_renderer()
    print(f"renderer warm-up (numba compile or cache load, not in any stage): {warm:.2f} s")

    results: dict[str, Any] = {"machine": info, "profile": cfg.profile, "config": cfg.to_dict(),
                               "repeat": args.repeat, "renderer_warmup_s": warm, "datasets": {}, "skipped": {}}
    with tempfile.TemporaryDirectory(prefix="atlas_bench.") as tmp:
        tmp_root = Path(tmp)
        for name in args.datasets:
            try:
                entry, notes = resolve_entry(name, tmp_root)
            except Skip as exc:
                print(f"\n== {name}: skipped ({exc})")
                results["skipped"][name] = str(exc)
                continue
            runs = []
            for r in range(args.repeat):
                work = tmp_root / f"{name}-run{r}"
                work.mkdir()
                runs.append(run_once(entry, cfg, work))
            results["datasets"][name] = print_dataset(name, entry, notes, runs)

    results["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"\npeak RSS of this process: {results['peak_rss_mb']:.0f} MB")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

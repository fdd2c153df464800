"""Robustness benchmark: every available RGB-D sequence, one table.

Sequences: every synthetic entry of the dataset registry (the clean ``synthetic`` and the
realistic-sensor presets ``synthetic-noisy``, ``synthetic-handheld``, ``synthetic-loop``, generated
on first use into the data folder), the real TUM frames in ``../shared/data`` when present
(``tum_fr1_xyz_10``: freiburg1, ``tum_fr3_teddy_100``: freiburg3), registered recordings that are
on disk (any layout the registry reads; nothing is downloaded), and any ``--sequence PATH[:camera]``.

Per sequence, on the same in-memory frames (decoding excluded from every timing) and the same
depth range (``fusion.min_depth_m`` .. ``fusion.max_depth_m`` of the profile):

* **ours**: tracking and mapping with no ground truth (``mapping.pose_source: estimated``:
  ``slam_poses`` itself, with multiple maps and loop closure, both inside the timing): ATE RMSE
  (rigid alignment, TUM conventions), RPE per second, the end-to-start error (estimated against
  true position of the last frame relative to the first: a loop's closing error), lost and
  relocalized frames, maps started (and merged), loops kept by the pose graph (``-``: loop closure
  off), frames/s. A sequence that exceeds ``--budget-s`` is stopped and graded on the frames
  reached ("of N (budget)" in the table).
* **Open3D F2F**: tensor RGB-D odometry, hybrid term, multi-scale 10/5/3, frame to frame, chained.
* **Open3D F2M**: Open3D's dense frame-to-model SLAM (``open3d.t.pipelines.slam.Model``: track
  against the ray-cast TSDF model, integrate, ray-cast; voxel 5.8 mm, on the CPU).

Ground truth is read only to grade (``atlas_pipeline.localization.metrics``). Ratios ours / Open3D:
ATE below 1 means we are more accurate, speed above 1 that we are faster.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import (  # noqa: E402
    O3D_MODEL_VOXEL_M,
    load_frames,
    run_open3d_model,
    run_open3d_odometry,
    run_slam,
)

SHARED_DATA = ROOT.parent / "shared" / "data"
SHARED_SEQUENCES = (("tum_fr1_xyz_10", "freiburg1"), ("tum_fr3_teddy_100", "freiburg3"))
QUICK_MAX_FRAMES = 30
# A safety net for unknown recordings (relocalization backs off, but a sequence may be long):
# past this budget the row reports the frames ours reached.
DEFAULT_BUDGET_S = 300.0

logger = logging.getLogger("bench_robustness")


@dataclass
class Sequence:
    name: str
    entry: object  # a registry DatasetEntry (built here for the shared frames and --sequence)
    source: str  # "synthetic", "shared", "registry" or "user"


def _synthetic_sequences(names: list[str] | None, sensor: dict | None = None,
                         variant_dir: Path | None = None) -> list[Sequence]:
    """Synthetic registry entries, generated (or reused) in the data folder; with ``sensor``
    (``SyntheticSpec`` fields), variants of them with those fields changed, generated into
    ``variant_dir`` (ablations: which part of the sensor model costs what)."""
    import dataclasses

    from atlas_pipeline.sensors.registry import ensure_dataset_files, load_registry
    from atlas_pipeline.sensors.synthetic import SyntheticSpec

    out = []
    for name, e in load_registry().items():
        if e.kind != "synthetic" or (names is not None and name not in names):
            continue
        if sensor:
            label = name + "[" + ",".join(f"{k}={v}" for k, v in sensor.items()) + "]"
            params = {**e.params, **sensor}
            try:
                SyntheticSpec(**params)
            except (TypeError, ValueError) as exc:
                raise SystemExit(f"--sensor: {exc}") from exc
            e = dataclasses.replace(e, name=label, path=variant_dir / f"{name}-variant", params=params)
            name = label
        t0 = time.perf_counter()
        root = ensure_dataset_files(e)
        logger.info("%s: dataset ready at %s (%.1f s)", name, root, time.perf_counter() - t0)
        out.append(Sequence(name, e, "synthetic"))
    return out


def _real_sequences(user: list[str], builtin: bool = True) -> list[Sequence]:
    """The shared TUM frames and registered recordings on disk (``builtin``), then ``user``'s."""
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.registry import (
        DatasetEntry,
        default_camera_spec,
        detect_kind,
        load_registry,
        resolve_camera,
    )
    from atlas_pipeline.sensors.layouts import recording_exists

    out: list[Sequence] = []
    seen: set[Path] = set()

    def add(seq: Sequence) -> None:
        key = Path(seq.entry.path).resolve()
        if key not in seen and recording_exists(seq.entry.kind, Path(seq.entry.path)):
            seen.add(key)
            out.append(seq)

    if builtin:
        for folder, cam in SHARED_SEQUENCES:
            add(Sequence(folder, DatasetEntry(folder, "tum", SHARED_DATA / folder, camera=TUM_CAMERAS[cam]), "shared"))
        for name, e in load_registry().items():
            if e.kind != "synthetic":  # downloaded or user-registered recordings; never downloads here
                add(Sequence(name, e, "registry"))
    for arg in user:
        path, sep, cam = arg.rpartition(":")
        if not sep or "/" in cam:  # no camera given (a ':' inside the path is not one)
            path, cam = arg, ""
        root = Path(path).expanduser()
        kind = detect_kind(root)
        if kind is None:
            raise SystemExit(f"--sequence {arg}: {root} is not a recording layout this project reads "
                             "(TUM, 7-Scenes, Replica, ScanNet, bag)")
        spec = cam or default_camera_spec(kind)  # None: the recording carries its camera
        camera = resolve_camera(spec, f"--sequence {arg}") if spec else None
        add(Sequence(root.name, DatasetEntry(root.name, kind, root, camera=camera), "user"))
    return out


def _maps_and_loops(ours: dict) -> tuple[str, str]:
    """'maps started (merged)' and 'loops closed' of our run."""
    maps = f"{ours['n_maps']}" + (f" ({ours['n_maps_merged']} merged)" if ours["n_maps_merged"] else "")
    return maps, "-" if ours["n_loops"] is None else str(ours["n_loops"])


def bench_sequence(seq: Sequence, cfg, max_frames: int | None, with_model: bool, budget_s: float | None) -> dict:
    from atlas_pipeline.sensors.registry import read_dataset_manifest

    manifest = read_dataset_manifest(seq.entry, max_frames)
    frames = load_frames(manifest)
    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    cam = manifest.camera
    row: dict = {"sequence": seq.name, "source": seq.source, "kind": seq.entry.kind, "n_frames": manifest.n_frames,
                 "size": f"{cam.width}x{cam.height}", "n_with_gt": int(manifest.has_gt.sum())}
    t0 = time.perf_counter()
    ours, st = run_slam(manifest, frames, cfg, budget_s)
    row["ours"] = ours
    row["maps"], row["loops"] = _maps_and_loops(ours)
    logger.info("%s: ours ATE %s m, %.1f frames/s (%.1f s)", seq.name, ours.get("ate_rmse_m"), ours["frames_per_s"],
                time.perf_counter() - t0)
    if ours["n_attempted"] < manifest.n_frames:  # stopped by the budget: the references get the same frames
        manifest = read_dataset_manifest(seq.entry, ours["n_attempted"])
        frames = frames[:ours["n_attempted"]]
    t0 = time.perf_counter()
    row["open3d_f2f"] = run_open3d_odometry(manifest, frames, depth_max_m=depth_range[1], depth_min_m=depth_range[0])
    logger.info("%s: Open3D F2F ATE %s m (%.1f s)", seq.name, row["open3d_f2f"].get("ate_rmse_m"),
                time.perf_counter() - t0)
    if with_model:
        t0 = time.perf_counter()
        row["open3d_f2m"] = run_open3d_model(manifest, frames, depth_range[0], depth_range[1])
        logger.info("%s: Open3D F2M ATE %s m (%.1f s)", seq.name, row["open3d_f2m"].get("ate_rmse_m"),
                    time.perf_counter() - t0)
    return row


def _num(x) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def _f(x, scale: float = 1.0, spec: str = ".2f") -> str:
    x = _num(x)
    return "n/a" if x is None else format(x * scale, spec)


def _ratio(a, b, spec: str = ".2f") -> str:
    a, b = _num(a), _num(b)
    return "n/a" if a is None or b is None or b == 0 else format(a / b, spec)


def format_table(rows: list[dict]) -> str:
    head = ["sequence", "frames", "ATE cm", "RPE cm/s", "end err cm", "lost", "reloc", "maps", "loops", "fps",
            "O3D F2F ATE cm", "F2F fps", "O3D F2M ATE cm", "F2M fps",
            "ATE ours/F2F", "ATE ours/F2M", "speed ours/F2F", "speed ours/F2M"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for r in rows:
        o, a = r["ours"], r["open3d_f2f"]
        m = r.get("open3d_f2m", {})
        cells = [
            r["sequence"], (f"{r['n_frames']}" if o["n_attempted"] == r["n_frames"]  # budget: all on the first k
                            else f"{o['n_attempted']} of {r['n_frames']} (budget)") + f" ({r['size']})",
            _f(o.get("ate_rmse_m"), 100), _f(o.get("rpe_trans_rmse_m"), 100), _f(o.get("end_to_start_error_m"), 100),
            str(o["n_lost"]),
            str(o["n_relocalized"]), r["maps"], r["loops"], _f(o["frames_per_s"], spec=".1f"),
            _f(a.get("ate_rmse_m"), 100), _f(a["frames_per_s"], spec=".1f"),
            _f(m.get("ate_rmse_m"), 100) if m else "skipped", _f(m.get("frames_per_s"), spec=".1f") if m else "-",
            _ratio(o.get("ate_rmse_m"), a.get("ate_rmse_m")), _ratio(o.get("ate_rmse_m"), m.get("ate_rmse_m")),
            _ratio(o["frames_per_s"], a["frames_per_s"]), _ratio(o["frames_per_s"], m.get("frames_per_s")),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _override_tracker_constants(changes: dict) -> dict:
    """Replace the :class:`TrackerConstants` instance every loaded tracking module reads (their
    module-level ``C``) by one with ``changes``; returns the changes. Only values read at call
    time change (not a function's default argument)."""
    import dataclasses

    import atlas_pipeline.localization.constants as constants_module
    import atlas_pipeline.localization.relocalize  # noqa: F401  (loaded, so its C is replaced too)
    import atlas_pipeline.localization.sequence  # noqa: F401
    import atlas_pipeline.localization.tracker  # noqa: F401

    if not changes:
        return {}
    fields = {f.name: f.type for f in dataclasses.fields(constants_module.TrackerConstants)}
    unknown = sorted(set(changes) - set(fields))
    if unknown:
        raise ValueError(f"--constant: no TrackerConstants field {', '.join(unknown)}")
    old = constants_module.TRACKER_CONSTANTS
    new = dataclasses.replace(old, **changes)
    for name, module in list(sys.modules.items()):
        if name.startswith("atlas_pipeline.") and getattr(module, "C", None) is old:
            module.C = new
    constants_module.TRACKER_CONSTANTS = new
    return changes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help=f"short run: the first {QUICK_MAX_FRAMES} frames of every sequence")
    ap.add_argument("--max-frames", type=int, default=None, help="track at most this many frames per sequence")
    ap.add_argument("--sequence", action="append", default=[], metavar="PATH[:camera]",
                    help="another recording (any layout `atlas-gs dataset add` reads); camera: a preset "
                         "(freiburg1/2/3, default, ...), else the layout's own (repeatable)")
    ap.add_argument("--synthetic", nargs="*", default=None, metavar="NAME",
                    help="only these synthetic registry entries (none: no synthetic sequence)")
    ap.add_argument("--no-real", action="store_true", help="skip the shared and registered TUM sequences")
    ap.add_argument("--no-model", action="store_true", help="skip Open3D's frame-to-model reference (slowest)")
    ap.add_argument("--budget-s", type=float, default=DEFAULT_BUDGET_S,
                    help="stop our tracker on a sequence after this many seconds (0: no limit; default "
                         "%(default)s); its figures then cover the frames it reached")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value (YAML syntax) for ours and the Open3D depth range")
    ap.add_argument("--sensor", action="append", default=[], metavar="KEY=VALUE",
                    help="run variants of the synthetic presets with this SyntheticSpec field changed "
                         "(YAML value; repeatable), generated into a temporary folder, e.g. "
                         "--sensor depth_noise_b_per_m=0 --sensor inverse_depth_step_per_m=0")
    ap.add_argument("--constant", action="append", default=[], metavar="NAME=VALUE",
                    help="run ours with a field of the tracker's TrackerConstants changed (YAML value; "
                         "repeatable), e.g. --constant splat_blend_sigmas=0")
    ap.add_argument("--json", default=None, help="also write every figure here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    max_frames = args.max_frames or (QUICK_MAX_FRAMES if args.quick else None)

    from atlas_pipeline._open3d import open3d
    from atlas_pipeline.config import load_profile, parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    try:
        overrides = {"mapping.pose_source": "estimated", **parse_set_overrides(args.set)}
    except ConfigError as exc:
        ap.error(str(exc))
    try:
        sensor = parse_set_overrides(args.sensor, "--sensor")
    except ConfigError as exc:
        ap.error(str(exc))
    cfg = load_profile("default").with_overrides(overrides)
    try:
        constants = _override_tracker_constants(parse_set_overrides(args.constant, "--constant"))
    except (ConfigError, TypeError, ValueError) as exc:
        ap.error(str(exc))
    cmd = " ".join(shlex.quote(a) for a in [sys.executable.split("/")[-1], "benchmarks/bench_robustness.py",
                                              *(argv if argv is not None else sys.argv[1:])])
    print("# Robustness benchmark")
    print(f"# reproduce: cd {ROOT} && . .venv/bin/activate && {cmd}")
    print(f"# machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"Open3D {open3d().__version__}; load average at start {os.getloadavg()[0]:.2f} "
          "(frames/s are measured on a shared machine: compare the ratios)")
    print(f"# ours: profile default + {overrides}; depth range {cfg.fusion.min_depth_m}-{cfg.fusion.max_depth_m} m "
          f"for every method; Open3D F2M voxel {O3D_MODEL_VOXEL_M} m on CPU")
    if constants:
        print(f"# tracker constants changed: {constants}")
    print(f"# frames per sequence: {max_frames or 'all'}; time budget of ours per sequence: "
          f"{args.budget_s or 'none'} s; timings exclude image decoding; "
          "ATE after rigid alignment; RPE over 1 s", flush=True)

    import tempfile

    variant_tmp = tempfile.TemporaryDirectory(prefix="atlas-sensor-variants-") if sensor else None
    sequences = (_synthetic_sequences(args.synthetic, sensor, Path(variant_tmp.name) if variant_tmp else None)
                 + _real_sequences(args.sequence, builtin=not args.no_real))
    if not sequences:
        print("no sequence to run")
        return 1
    # Warm-up: compile the Numba kernels outside the timed loops.
    from atlas_pipeline.sensors.registry import read_dataset_manifest

    warm = read_dataset_manifest(sequences[0].entry, 3)
    warm_frames = load_frames(warm)
    run_slam(warm, warm_frames, cfg)
    # the colour-delay resampling runs only on sequences with a delay (TUM fr1): warm it too
    from atlas_pipeline.perception.colour_timing import colour_at_depth_time

    shift = np.eye(4)
    shift[0, 3] = 0.01
    colour_at_depth_time(*warm_frames[0], warm.camera, shift)

    rows = []
    t_all = time.perf_counter()
    for seq in sequences:
        rows.append(bench_sequence(seq, cfg, max_frames, not args.no_model, args.budget_s or None))
    print()
    print(format_table(rows))
    print(f"\n# {len(rows)} sequences in {time.perf_counter() - t_all:.0f} s, load average at end "
          f"{os.getloadavg()[0]:.2f}. lost: frames tracking gave up on; reloc: frames placed by relocalization; "
          "fps: frames/s of tracking (+ mapping for ours and F2M); frames: tracked (image size); "
          "'k of N (budget)': ours ran out of --budget-s, every method is graded on the first k frames.")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": cmd, "rows": rows}, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Persistence benchmark: worlds a robot comes back to.

For every pair of visits of one place, on the frames as read from disk:

1. **build**: tracking and mapping of visit 1 with no ground truth (``slam_poses``: loop closure
   included), its frames fused in the same pass, then the world merged from its keyframes (no
   fit) and its place index made (what the bundle stores as ``places.npz``): what ``atlas-gs
   build --set mapping.pose_source=estimated`` does. SLAM ATE, keyframes, frames/s (the pass
   without the fusion work done in it), build seconds, the place index's share of them.
2. **own frames**: visit 1 localized in the world it built, from the world's first keyframe
   (``atlas-gs localize``): placed %, ATE, frames/s. Target: 100 % placed, ATE <= 1.1x SLAM's.
3. **second visit, no start pose**: visit 2 localized in world 1 with no initial pose (the first
   frame relocalized): placed %, placed % of the frames that see mapped surface (judged with
   ground truth: the visit's true pose moved into the world's frame by the rigid alignment of
   visit 1's estimates to its ground truth, and at least half of the frame's points landing on
   the map there), ATE, frames/s, mean seconds per relocalization attempt, the place index's
   fast one and the full search apart (every attempt timed, failed ones too), and the seconds
   spent loading world 1's stored place index (saved and read back as the bundle holds it) and
   rendering any viewpoint it lacks (the first attempt waits for both).
4. **extend**: visit 2 tracked and mapped into world 1 (``atlas-gs build --extend``, starting from
   world 1's stored index): placed %, ATE (the extension's own poses: a frame placed at a wrong pose
   maps its surfaces there), frames/s (the extended world's own index included); then visit 2
   localized in the extended world with no start pose: placed %, ATE.

Pairs: the synthetic suite (``synthetic-suite`` then ``synthetic-suite-visit2``, generated into
the data folder on first use), and the real TUM frames in ``../shared/data`` split in two halves
(teddy frames 0-49 / 50-99; fr1 xyz 0-4 / 5-9). ``--pair A B`` adds registered datasets.
Ground truth only grades. Usage::

    python benchmarks/bench_persistence.py [--quick] [--json out.json] [--pair NAME1 NAME2] [--variant KEY=VALUE]

``--variant localization.odometry_prediction=false`` adds a row per pair: the same world, its
sessions run again with that override (a reference in the same run).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SHARED_SPLITS = (("tum_fr3_teddy_100", "freiburg3", 50), ("tum_fr1_xyz_10", "freiburg1", 5))
SUITE_PAIR = ("synthetic-suite", "synthetic-suite-visit2")
QUICK_SUITE_FRAMES = (300, 200)  # --quick: the first frames of each suite visit
# A frame "sees mapped surface" when at least this share of its points lands on the map at its true pose.
SEES_MAP_MIN_OVERLAP = 0.5

logger = logging.getLogger("bench_persistence")


def _slice(manifest, start: int, stop: int, name: str):
    """Frames ``start..stop-1`` of ``manifest`` as a manifest of their own (a visit)."""
    sl = slice(start, stop)
    rgb_ts = None if manifest.rgb_timestamps_s is None else manifest.rgb_timestamps_s[sl].copy()
    return dataclasses.replace(
        manifest, dataset=name, timestamps_s=manifest.timestamps_s[sl].copy(),
        depth_timestamps_s=manifest.depth_timestamps_s[sl].copy(), rgb_files=manifest.rgb_files[sl],
        depth_files=manifest.depth_files[sl], T_world_cam_gt=manifest.T_world_cam_gt[sl].copy(),
        has_gt=manifest.has_gt[sl].copy(), rgb_timestamps_s=rgb_ts)


def _pairs(args, cfg) -> list[tuple[str, object, object]]:
    from atlas_pipeline.sensors.registry import load_dataset, load_registry
    from benchmarks.common import SHARED_DATA, shared_tum_manifest

    reg = load_registry()
    out = []
    names = ([] if args.no_suite else [SUITE_PAIR]) + [tuple(p) for p in args.pair]
    for a, b in names:
        ma, mb = load_dataset(reg[a], cfg), load_dataset(reg[b], cfg)
        if args.quick and (a, b) == SUITE_PAIR:
            ma = _slice(ma, 0, min(QUICK_SUITE_FRAMES[0], ma.n_frames), a)
            mb = _slice(mb, 0, min(QUICK_SUITE_FRAMES[1], mb.n_frames), b)
        out.append((f"{a} / {b}", ma, mb))
    for folder, cam, split in SHARED_SPLITS:
        m = shared_tum_manifest(folder, cam)
        if m is None:
            logger.warning("%s not found: skipped", SHARED_DATA / folder)
            continue
        out.append((f"{folder} [0,{split}) / [{split},{m.n_frames})", _slice(m, 0, split, f"{folder}-1"),
                    _slice(m, split, m.n_frames, f"{folder}-2")))
    return out


def _placed(status: list[str]) -> np.ndarray:
    from atlas_pipeline.localization.sequence import PLACED_STATUSES, STATUS_ANCHOR

    return np.array([s in PLACED_STATUSES or s == STATUS_ANCHOR for s in status])


def _sees_map(manifest, model, T_align: np.ndarray, cfg) -> np.ndarray:
    """``[N]`` bool: frames whose true pose (moved into the world's frame) sees mapped surface."""
    from atlas_pipeline.localization.tracker import RGBDTracker

    tracker = RGBDTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m))
    out = np.zeros(manifest.n_frames, bool)
    for i in range(manifest.n_frames):
        if not manifest.has_gt[i]:
            continue
        T = T_align @ manifest.T_world_cam_gt[i]
        fp = tracker.prepare(None, manifest.read_depth_m(i, allow_empty=True))
        _, stats = tracker.quality_stats(fp, model.model_view(T, manifest.camera, tracker.model_level), T)
        out[i] = stats.n_points > 0 and stats.n_on_model / stats.n_points >= SEES_MAP_MIN_OVERLAP
    return out


def _gt_to_world(slam_poses: np.ndarray, valid: np.ndarray, manifest) -> np.ndarray | None:
    """``[4, 4]`` moving ground-truth coordinates into the SLAM world's (rigid alignment)."""
    from atlas_pipeline.localization.metrics import align_rigid

    ok = valid & manifest.has_gt & np.isfinite(slam_poses).all(axis=(1, 2))
    if ok.sum() < 3:
        return None
    return np.linalg.inv(align_rigid(slam_poses[ok], manifest.T_world_cam_gt[ok]))


class _AttemptTimer:
    """Seconds of every relocalization attempt while active, by path: the place index's fast
    attempt (``fast``) and the full search (``full``), successful or not; of indexing each
    keyframe into the place index (``index``), which the first attempt of a session waits for;
    and of making the map's culling and far level when a session starts (``start``). Wraps
    those methods (timing only; results pass through unchanged)."""

    def __init__(self):
        from atlas_pipeline.localization.places import PlaceIndex
        from atlas_pipeline.localization.relocalize import Relocalizer
        from atlas_pipeline.localization.tracker import SurfelModel

        # kind -> (class, method) timed as that kind
        self._methods = {"fast": (Relocalizer, "relocalize_fast"), "full": (Relocalizer, "relocalize"),
                         "index": (PlaceIndex, "add_keyframe"), "start": (SurfelModel, "prepare_views")}
        self.seconds: dict[str, list[float]] = {kind: [] for kind in self._methods}

    def __enter__(self):
        self._orig = {kind: getattr(owner, name) for kind, (owner, name) in self._methods.items()}

        def timed(kind):
            orig = self._orig[kind]

            def run(*args, **kwargs):
                t0 = time.perf_counter()
                try:
                    return orig(*args, **kwargs)
                finally:
                    self.seconds[kind].append(time.perf_counter() - t0)
            return run

        for kind, (owner, name) in self._methods.items():
            setattr(owner, name, timed(kind))
        return self

    def __exit__(self, *exc):
        for kind, (owner, name) in self._methods.items():
            setattr(owner, name, self._orig[kind])

    def mean_s(self, kind: str) -> float:
        t = self.seconds[kind]
        return float(np.mean(t)) if t else float("nan")


MAX_FRAMES_LISTED = 20  # own frames not placed, listed by index after the table
WARM_UP_FRAMES = 5  # built and localized untimed first: the kernels load before any clock starts


def _progress(stage: str, row: dict) -> None:
    """The figures so far, to stderr: a long pair shows each stage as it ends."""
    print(f"  {stage}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
          file=sys.stderr, flush=True)


def benchmark_config():
    """The default profile as ``atlas-gs build --set mapping.pose_source=estimated`` with no fit."""
    from atlas_pipeline.config import load_profile

    return load_profile("default").with_overrides({"mapping.pose_source": "estimated", "mapping.fit.epochs": 0,
                                                   "mapping.colour_refinement.iterations": 0})


def build_first_world(v1, cfg) -> tuple[object, object, object, dict[str, float]]:
    """Visit 1 tracked and mapped (loop closure included) and fused in the same pass, as
    ``atlas-gs build`` runs it (:func:`fuse_and_select_keyframes`), then merged into a world from
    its keyframes, and its place index: ``(slam_poses result, world, place index, seconds per
    step: pass_s (tracking, mapping and loop closure, each frame back-projected for fusion on the
    reader thread meanwhile), fusion_finish_s (the fused frames finished after it, and the
    keyframes picked), world_s, places_s)``."""
    from atlas_pipeline.localization.localizer import bundle_tracking_files
    from atlas_pipeline.mapping.keyframes import slam_keyframes, slam_poses
    from atlas_pipeline.mapping.mapper import build_world
    from atlas_pipeline.perception.rgbd import FrameFuser

    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    t0 = time.perf_counter()
    with FrameFuser(v1, cfg.fusion) as fuser:  # the pass of fuse_and_select_keyframes
        slam = slam_poses(v1, cfg.mapping, cfg.localization, depth_range, cfg.fusion.stride, on_frame=fuser.add)
        t_pass = time.perf_counter()
        fused = fuser.finish()
    kf = slam_keyframes(slam)
    t1 = time.perf_counter()
    world = build_world(fused, kf, cfg.mapping, manifest=v1)
    t2 = time.perf_counter()
    _, places = bundle_tracking_files(world, v1.camera, cfg.localization)
    return slam, world, places, {"pass_s": t_pass - t0, "fusion_finish_s": t1 - t_pass, "world_s": t2 - t1,
                                 "places_s": time.perf_counter() - t2}


def _warm_up(v1, cfg) -> None:
    """A world of visit 1's first frames built, localized in from its start pose and relocalized
    in with none, untimed: the first pair's tracking and relocalization figures then do not carry
    the kernels' loading (or compiling, on a first run)."""
    from atlas_pipeline.localization.localizer import localize, localize_sequence, tracking_map

    head = _slice(v1, 0, min(WARM_UP_FRAMES, v1.n_frames), f"{v1.dataset}-warm-up")
    _, world, places, _ = build_first_world(head, cfg)
    localize(head, world, cfg)
    localize_sequence(head, tracking_map(world), cfg.localization, None, map_id=world.map_id,
                      depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                      prior_poses=world.T_world_cam_keyframes, places=places)


def run_pair(label: str, v1, v2, cfg, variants: list[tuple[str, object]]) -> list[dict]:
    """The pair's row, then one row per variant ``(its label, its config)``: the same world,
    its sessions (own frames, second visit, extension) run again with the variant's config."""
    from benchmarks.common import grade

    row: dict = {"pair": label, "visit1_frames": v1.n_frames, "visit2_frames": v2.n_frames}
    slam, world, places, seconds = build_first_world(v1, cfg)
    row.update({"fusion_finish_s": seconds["fusion_finish_s"], "world_s": seconds["world_s"],
                "places_s": seconds["places_s"]})
    g = grade(v1, np.where(slam.valid[:, None, None], slam.T_world_cam, np.nan))
    row.update({"slam_ate_m": g.get("ate_rmse_m"), "slam_frames_per_s": v1.n_frames / seconds["pass_s"],
                "build_s": sum(seconds.values()), "keyframes": len(slam.keyframe_indices), "gaussians": len(world.field),
                "loops": None if slam.loop_closure is None else slam.loop_closure.get("n_loops")})
    _progress("build", row)
    rows = [{**row, **sessions_in_world(slam, world, places, v1, v2, cfg)}]
    for variant, vcfg in variants:
        print(f"  ... with {variant}", flush=True)
        rows.append({**row, "pair": f"{label}, {variant}", **sessions_in_world(slam, world, places, v1, v2, vcfg)})
    return rows


def _stored(places, camera):
    """``places`` saved and read back as a bundle holds it (``places.npz``): ``(index, seconds to read)``."""
    import tempfile

    from atlas_pipeline.localization.places import PLACES_FILE, PlaceIndex

    with tempfile.TemporaryDirectory() as tmp:
        path = places.save(Path(tmp) / PLACES_FILE)
        t0 = time.perf_counter()
        index = PlaceIndex.load(path, camera)
        return index, time.perf_counter() - t0


def sessions_in_world(slam, world, places, v1, v2, cfg) -> dict:
    """Visit 1's own frames, then visit 2, localized in ``world`` (with ``places``, its stored
    place index); visit 2 mapped into it (extension) and localized in the extended world. The
    row's figures of these steps."""
    from atlas_pipeline.localization.localizer import bundle_tracking_files, localize, localize_sequence, tracking_map
    from atlas_pipeline.mapping.mapper import extend_world_by_tracking
    from benchmarks.common import grade

    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    row: dict = {}
    # Own frames in the world they built.
    own = localize(v1, world, cfg)
    row.update({"own_placed_pct": 100 * _placed(own.status).mean(), "own_ate_m": own.summary.get("ate_rmse_m"),
                "own_not_placed": [int(i) for i in np.flatnonzero(~_placed(own.status))],
                "own_frames_per_s": own.summary.get("frames_per_s"), "own_outcome": own.summary.get("outcome")})
    _progress("own frames", row)
    # Second visit, no start pose.
    model = tracking_map(world)
    T_align = _gt_to_world(slam.T_world_cam, slam.valid, v1)
    stored, load_s = _stored(places, v2.camera)
    with _AttemptTimer() as attempts:
        second = localize_sequence(v2, model, cfg.localization, None, map_id=world.map_id, depth_range_m=depth_range,
                                   prior_poses=world.T_world_cam_keyframes, places=stored)
    placed = _placed(second.status)
    row.update({"visit2_placed_pct": 100 * placed.mean(), "visit2_ate_m": second.summary.get("ate_rmse_m"),
                "visit2_frames_per_s": second.summary.get("frames_per_s"),
                "visit2_reloc_fast_s": attempts.mean_s("fast"), "visit2_reloc_fast_n": len(attempts.seconds["fast"]),
                "visit2_reloc_full_s": attempts.mean_s("full"), "visit2_reloc_full_n": len(attempts.seconds["full"]),
                "visit2_index_s": load_s + float(np.sum(attempts.seconds["index"])),
                "visit2_index_n": len(attempts.seconds["index"]),
                "visit2_start_s": float(np.sum(attempts.seconds["start"])),
                "visit2_outcome": second.summary.get("outcome")})
    if T_align is not None:
        sees = _sees_map(v2, model, T_align, cfg)
        row["visit2_seeing_map"] = int(sees.sum())
        row["visit2_placed_of_seeing_pct"] = 100 * placed[sees].mean() if sees.any() else float("nan")
    _progress("second visit", row)
    # Extend world 1 by visit 2, then localize visit 2 in the extended world.
    t0 = time.perf_counter()
    extended, ext_poses, status = extend_world_by_tracking(world, v2, cfg.mapping, cfg.localization, depth_range,
                                                           cfg.fusion.stride, places=_stored(places, v2.camera)[0])
    ext_model, ext_places = bundle_tracking_files(extended, v2.camera, cfg.localization)
    ext_placed = _placed(status)
    row.update({"extend_placed_pct": 100 * ext_placed.mean(),
                "extend_ate_m": grade(v2, np.where(ext_placed[:, None, None], ext_poses, np.nan)).get("ate_rmse_m"),
                "extend_frames_per_s": v2.n_frames / (time.perf_counter() - t0)})
    again = localize_sequence(v2, ext_model, cfg.localization, None, map_id=extended.map_id,
                              depth_range_m=depth_range, prior_poses=extended.T_world_cam_keyframes,
                              places=_stored(ext_places, v2.camera)[0])
    row.update({"extended_placed_pct": 100 * _placed(again.status).mean(),
                "extended_ate_m": again.summary.get("ate_rmse_m"),
                "extended_frames_per_s": again.summary.get("frames_per_s")})
    return row


def _fmt(v, scale: float = 1.0, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v * scale:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=f"the first {QUICK_SUITE_FRAMES} frames of the suite visits")
    ap.add_argument("--pair", nargs=2, action="append", default=[], metavar=("VISIT1", "VISIT2"),
                    help="two registered datasets of one place")
    ap.add_argument("--no-suite", action="store_true", help="leave out the synthetic suite pair")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                    help="also run the sessions in the same world with this config override (a row each)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    from atlas_pipeline.config import parse_set_overrides

    cfg = benchmark_config()
    variants = [(v, cfg.with_overrides(parse_set_overrides([v], "--variant"))) for v in args.variant]
    rows = []
    pairs = _pairs(args, cfg)
    if pairs:
        _warm_up(pairs[0][1], cfg)
    for label, v1, v2 in pairs:
        print(f"running {label} ...", flush=True)
        rows.extend(run_pair(label, v1, v2, cfg, variants))
    print(f"\nmachine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores; "
          f"profile default, mapping.pose_source=estimated, no fit")
    print("| pair | frames | SLAM ATE cm | SLAM f/s | build s (of it place index) | keyframes | own placed % | own ATE cm | own f/s "
          "| visit 2 placed % (of seeing map) | visit 2 ATE cm | visit 2 f/s | reloc s fast (n) / full (n) "
          "| session start s: place index (keyframes rendered) + culling and far level | extend placed % "
          "| extend ATE cm | extend f/s "
          "| in extended placed % | ATE cm |")
    print("|" + "---|" * 19)
    for r in rows:
        print(f"| {r['pair']} | {r['visit1_frames']} + {r['visit2_frames']} | {_fmt(r['slam_ate_m'], 100, 2)} "
              f"| {_fmt(r['slam_frames_per_s'])} | {_fmt(r['build_s'])} ({_fmt(r['places_s'])}) | {r['keyframes']} "
              f"| {_fmt(r['own_placed_pct'])} | {_fmt(r['own_ate_m'], 100, 2)} | {_fmt(r['own_frames_per_s'])} "
              f"| {_fmt(r['visit2_placed_pct'])} ({_fmt(r.get('visit2_placed_of_seeing_pct'))} of "
              f"{r.get('visit2_seeing_map', '-')}) | {_fmt(r['visit2_ate_m'], 100, 2)} "
              f"| {_fmt(r['visit2_frames_per_s'])} | {_fmt(r['visit2_reloc_fast_s'], 1, 3)} ({r['visit2_reloc_fast_n']}) / {_fmt(r['visit2_reloc_full_s'], 1, 2)} ({r['visit2_reloc_full_n']}) "
              f"| {_fmt(r['visit2_index_s'], 1, 2)} ({r['visit2_index_n']}) + {_fmt(r['visit2_start_s'], 1, 2)} "
              f"| {_fmt(r['extend_placed_pct'])} | {_fmt(r['extend_ate_m'], 100, 2)} | {_fmt(r['extend_frames_per_s'])} "
              f"| {_fmt(r['extended_placed_pct'])} | {_fmt(r['extended_ate_m'], 100, 2)} |")
    for r in rows:
        if r["own_not_placed"]:
            shown = ", ".join(map(str, r["own_not_placed"][:MAX_FRAMES_LISTED]))
            more = len(r["own_not_placed"]) > MAX_FRAMES_LISTED
            print(f"{r['pair']}: own frames not placed: {shown}{', ...' if more else ''}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Live-rate replay: a recording's frames handed to the tracker on their timestamps, as a camera would.

A wall clock starts with the first frame; frame ``i`` arrives at ``t_i - t_0`` (its timestamp
relative to the first). The tracker takes one frame at a time; a frame that arrives while it is
busy waits, and when the tracker becomes free it takes the newest frame that has arrived and
drops the older waiting ones (skipped: a real camera does not wait, and nothing is queued without
bound). When no frame is waiting, it sleeps until the next one arrives. Per sequence, two sessions:

* **SLAM**: tracking and mapping as ``atlas-gs build`` runs it (``slam_poses``'s
  :class:`SequenceTracker` with a growing map, the first frame with depth anchoring the world);
  the build's fusion (on its reader thread) and the loop closure after the pass are not in it.
* **localize**: localization in the saved world of the same frames, as ``atlas-gs localize``
  runs it (the world's tracking map and its place index as the bundle stores it, starting from
  the world's first keyframe at its pose). The world is built before the replay, untimed.

Each session runs twice: frames decoded from disk when the tracker takes them (decoding counts in
the frame's time), and frames decoded into memory beforehand (what a live camera hands over).
Reported: frames processed, frames skipped, p50 / p95 latency from a frame's arrival to its pose,
and the ATE of the processed frames' poses against ground truth (ground truth only grades).

Usage::

    python benchmarks/bench_replay.py [--only NAME ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from atlas_pipeline.errors import ConfigError  # noqa: E402

# (name, TUM intrinsics of a ../shared/data folder, or None for a registered dataset preset)
SEQUENCES = (("tum_fr3_teddy_100", "freiburg3"), ("tum_fr1_xyz_10", "freiburg1"), ("synthetic", None))
SOURCES = ("disk", "memory")  # frames decoded when taken / decoded beforehand
P_HIGH = 95  # the latency percentile reported beside the median

logger = logging.getLogger("bench_replay")


@dataclass
class ReplayResult:
    """One replay: ``latency_s`` ``[N]`` (NaN where not processed), ``poses`` ``[N, 4, 4]``
    (NaN where not processed or lost), frames processed and skipped, and the wall seconds."""

    latency_s: np.ndarray
    poses: np.ndarray
    n_processed: int
    n_skipped: int
    n_lost: int
    wall_s: float


def replay(timestamps_s: np.ndarray, start: int, take: Callable[[int], tuple[np.ndarray | None, np.ndarray]],
           track: Callable[[int, np.ndarray | None, np.ndarray], tuple[np.ndarray, bool]]) -> ReplayResult:
    """Frames ``start..N-1`` fed on ``timestamps_s`` ``[N]``: ``take(i)`` gives frame ``i``'s
    ``(rgb [H, W, 3] or None, depth_m [H, W])`` (decoding, when it decodes, counts in the frame's
    time), ``track(i, rgb, depth_m)`` its ``(T_world_cam [4, 4], lost)``. Latency is from the
    frame's arrival to the moment ``track`` returns its pose."""
    n = len(timestamps_s)
    arrival_s = timestamps_s - timestamps_s[start]
    latency = np.full(n, np.nan)
    poses = np.full((n, 4, 4), np.nan)
    n_processed = n_skipped = n_lost = 0
    nxt = start  # the oldest frame neither taken nor skipped
    t0 = time.perf_counter()
    while nxt < n:
        now = time.perf_counter() - t0
        if arrival_s[nxt] > now:  # tracker idle: wait for the camera
            time.sleep(arrival_s[nxt] - now)
            now = time.perf_counter() - t0
        newest = max(nxt, int(np.searchsorted(arrival_s, now, side="right")) - 1)
        n_skipped += newest - nxt
        rgb, depth_m = take(newest)
        T, lost = track(newest, rgb, depth_m)
        latency[newest] = time.perf_counter() - t0 - arrival_s[newest]
        n_processed += 1
        if lost:
            n_lost += 1
        else:
            poses[newest] = T
        nxt = newest + 1
    return ReplayResult(latency, poses, n_processed, n_skipped, n_lost, time.perf_counter() - t0)


def _manifest(name: str, camera: str | None, cfg):
    """The sequence's frames (a FrameManifest), or None when its shared data is not here."""
    if camera is not None:
        from benchmarks.common import shared_tum_manifest

        return shared_tum_manifest(name, camera)
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    reg = load_registry()
    if name not in reg:
        raise ConfigError(f"--only {name}: not a registered dataset (configs/datasets.yaml)")
    return load_dataset(reg[name], cfg)


def _slam_session(manifest, cfg):
    """``(start index, track)`` of tracking and mapping as ``slam_poses`` sets it up; poses are
    moved into the frame of the map they ended in (as ``slam_poses`` does) after the replay by
    the returned ``finish(poses, map_ids)``."""
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.localization.sequence import STATUS_LOST, SequenceTracker
    from atlas_pipeline.mapping.keyframes import _MIN_ANCHOR_DEPTH_PIXELS

    m = cfg.mapping
    st = SequenceTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                         builder=VoxelGaussianBuilder(m.voxel_size_m), keyframe_translation_m=m.keyframe_translation_m,
                         keyframe_rotation_deg=m.keyframe_rotation_deg, fusion_stride=cfg.fusion.stride,
                         new_map_after_lost_frames=m.new_map_after_lost_frames)
    started = [False]
    map_ids: dict[int, int] = {}

    def track(i, rgb, depth_m):
        # The first frame with depth anchors the world at the identity (as slam_poses).
        anchor = None if started[0] or np.count_nonzero(depth_m) < _MIN_ANCHOR_DEPTH_PIXELS else np.eye(4)
        est = st.process(i, rgb, depth_m, T_given=anchor, timestamp_s=float(manifest.timestamps_s[i]),
                         colour_delay_s=manifest.colour_delay_s(i))
        started[0] = started[0] or anchor is not None
        map_ids[i] = est.map_id
        return est.T_world_cam, est.status == STATUS_LOST

    def finish(poses: np.ndarray) -> np.ndarray:
        out = poses.copy()
        for i, mid in map_ids.items():
            if np.isfinite(out[i]).all():
                _, out[i] = st.to_root(mid, out[i])
        return out

    return 0, track, finish


def _localize_session(manifest, world, places, cfg):
    """``(start index, track, finish)`` of localization in ``world`` as ``atlas-gs localize``
    runs it: from the world's first keyframe at its pose."""
    from atlas_pipeline.localization.localizer import tracking_map
    from atlas_pipeline.localization.sequence import STATUS_LOST, SequenceTracker

    st = SequenceTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                         model=tracking_map(world), prior_poses=world.T_world_cam_keyframes, places=places)
    anchor = int(world.keyframe_indices[0])

    def track(i, rgb, depth_m):
        given = world.T_world_cam_keyframes[0] if i == anchor else None
        est = st.process(i, rgb, depth_m, T_given=given, timestamp_s=float(manifest.timestamps_s[i]),
                         colour_delay_s=manifest.colour_delay_s(i))
        return est.T_world_cam, est.status == STATUS_LOST

    return anchor, track, lambda poses: poses


def run_sequence(name: str, manifest, cfg) -> list[dict]:
    """The sequence's rows: SLAM and localize, each from disk and from memory."""
    from benchmarks.bench_persistence import _stored, build_first_world
    from benchmarks.common import grade, load_frames

    # The saved world (untimed); building it also loads the kernels before any replay.
    slam, world, places, _ = build_first_world(manifest, cfg)
    places, _ = _stored(places, manifest.camera)
    frames = load_frames(manifest)
    sources = {"disk": lambda i: (manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True)),
               "memory": lambda i: frames[i]}
    rows = []
    for session in ("slam", "localize"):
        for source in SOURCES:
            start, track, finish = (_slam_session(manifest, cfg) if session == "slam"
                                    else _localize_session(manifest, world, places, cfg))
            r = replay(manifest.timestamps_s, start, sources[source], track)
            lat = r.latency_s[np.isfinite(r.latency_s)]
            g = grade(manifest, finish(r.poses))
            rows.append({"sequence": name, "session": session, "source": source,
                         "frames": manifest.n_frames - start, "processed": r.n_processed, "skipped": r.n_skipped,
                         "lost": r.n_lost, "p50_ms": 1e3 * float(np.percentile(lat, 50)),
                         f"p{P_HIGH}_ms": 1e3 * float(np.percentile(lat, P_HIGH)),
                         "ate_m": g.get("ate_rmse_m"), "wall_s": r.wall_s})
            logger.info("%s", rows[-1])
    return rows


def _table(rows: list[dict]) -> str:
    """Markdown: one line per sequence and session, disk | memory side by side."""
    def fmt(v, spec):
        return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)

    head = ("| sequence | session | frames | processed (disk / mem) | skipped (disk / mem) | "
            f"p50 ms (disk / mem) | p{P_HIGH} ms (disk / mem) | ATE cm (disk / mem) |")
    out = [head, "|" + "---|" * 8]
    keyed = {(r["sequence"], r["session"], r["source"]): r for r in rows}
    for seq, session in dict.fromkeys((r["sequence"], r["session"]) for r in rows):
        d, m = keyed[(seq, session, "disk")], keyed[(seq, session, "memory")]

        def both(key, spec, scale=None):
            return " / ".join(fmt(x[key] if x[key] is None or scale is None else x[key] * scale, spec)
                              for x in (d, m))

        out.append(f"| {seq} | {session} | {d['frames']} | {both('processed', 'd')} | {both('skipped', 'd')} | "
                   f"{both('p50_ms', '.1f')} | {both(f'p{P_HIGH}_ms', '.1f')} | {both('ate_m', '.2f', 100.0)} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", metavar="NAME", help="only these sequences (default: all)")
    ap.add_argument("--json", type=Path, help="also write the rows here (never overwrites a file)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.json is not None and args.json.exists():
        raise ConfigError(f"--json {args.json}: file exists; not overwritten")
    wanted = list(args.only or [name for name, _ in SEQUENCES])  # a name not in SEQUENCES: a registered preset
    from benchmarks.bench_persistence import benchmark_config

    cfg = benchmark_config()
    cams = dict(SEQUENCES)
    rows: list[dict] = []
    t0 = time.perf_counter()
    for name in wanted:
        manifest = _manifest(name, cams.get(name), cfg)
        if manifest is None:
            logger.warning("%s: not in ../shared/data; skipped", name)
            continue
        rows += run_sequence(name, manifest, cfg)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"total {time.perf_counter() - t0:.0f} s")
    print(_table(rows))
    if args.json is not None:
        with args.json.open("x") as f:  # "x": a file made meanwhile is not overwritten either
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

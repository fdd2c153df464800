"""Frame-by-frame trace of a second visit in a saved world: where poses go wrong, and why.

Builds world 1 from visit 1 as :mod:`bench_persistence` does (SLAM poses, no ground truth, no
fit), then, for the first ``--frames`` frames of visit 2:

* **extension**: visit 2 tracked and mapped into world 1 (``build --extend``);
* **localization**: visit 2 localized in world 1 with no start pose;
* **in extended**: visit 2 localized in the extended world (its own place index) with no start
  pose, as a robot coming back a third time along the same path would;

and prints, per block of ``--block`` frames, each run's statuses and its position error in the
world's frame (ground truth moved there by the rigid alignment of visit 1's SLAM poses to its
ground truth; the world itself bends by a few cm, so a few cm is no error). Then, for every
``--block``-th frame, the frame aligned to world 1 from its true pose with no motion prior: how
far the solve moves it and the smallest translation eigenvalue over the largest
(``translation_constraint``): a slide of tens of cm where that share is under a few percent is
a view the surfaces leave free. Ground truth only grades. Usage::

    python benchmarks/bench_extension_trace.py [--pair VISIT1 VISIT2] [--frames 600] [--block 20] [--min-overlap 0.5]
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_persistence import (  # noqa: E402
    SUITE_PAIR, _gt_to_world, _placed, _slice, benchmark_config, build_first_world)


STATUS_LETTERS = {"tracked": "t", "relocalized": "r", "lost": "l", "anchor": "a", "new_map": "m", "not_attempted": "-"}


def _status_letters(status: list[str]) -> str:
    """One letter per frame (``STATUS_LETTERS``)."""
    return "".join(STATUS_LETTERS.get(s, "?") for s in status)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", nargs=2, default=list(SUITE_PAIR), metavar=("VISIT1", "VISIT2"))
    ap.add_argument("--frames", type=int, default=600, help="visit 2 frames traced (from its first)")
    ap.add_argument("--block", type=int, default=20, help="frames per printed row")
    ap.add_argument("--min-overlap", type=float, default=None, metavar="SHARE",
                    help="share of a frame landing on the saved world above which the extension places it by that "
                         "world alone (default: sequence.SAVED_WORLD_MIN_OVERLAP; above 1: never)")
    args = ap.parse_args(argv)
    if args.min_overlap is not None:
        from atlas_pipeline.localization import sequence

        sequence.SAVED_WORLD_MIN_OVERLAP = args.min_overlap
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    from atlas_pipeline.localization.localizer import bundle_tracking_files, localize_sequence, tracking_map
    from atlas_pipeline.localization.tracker import RGBDTracker, pose_change
    from atlas_pipeline.mapping.mapper import extend_world_by_tracking
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    cfg = benchmark_config()
    reg = load_registry()
    v1, v2 = load_dataset(reg[args.pair[0]], cfg), load_dataset(reg[args.pair[1]], cfg)
    v2 = _slice(v2, 0, min(args.frames, v2.n_frames), args.pair[1])
    depth_range = (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m)
    slam, world, places, _ = build_first_world(v1, cfg)  # places: the index its bundle would store
    T_align = _gt_to_world(slam.T_world_cam, slam.valid, v1)
    if T_align is None:
        raise SystemExit(f"{args.pair[0]}: too few ground-truth poses to move visit 2 into the world's frame")
    truth = T_align @ v2.T_world_cam_gt  # [N, 4, 4]
    extended, ext_poses, ext_status = extend_world_by_tracking(world, v2, cfg.mapping, cfg.localization,
                                                               depth_range, cfg.fusion.stride, places=places)
    model = tracking_map(world)
    loc = localize_sequence(v2, model, cfg.localization, None, map_id=world.map_id, depth_range_m=depth_range,
                            prior_poses=world.T_world_cam_keyframes, places=places)
    ext_model, ext_places = bundle_tracking_files(extended, v2.camera, cfg.localization)
    again = localize_sequence(v2, ext_model, cfg.localization, None, map_id=extended.map_id,
                              depth_range_m=depth_range, prior_poses=extended.T_world_cam_keyframes,
                              places=ext_places)

    def error_cm(poses: np.ndarray, status: list[str]) -> np.ndarray:
        e = 100 * np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
        return np.where(_placed(status), e, np.nan)

    ext_e, loc_e = error_cm(ext_poses, ext_status), error_cm(loc.T_world_cam, list(loc.status))
    again_e = error_cm(again.T_world_cam, list(again.status))
    tracker = RGBDTracker(v2.camera, cfg.localization, depth_range)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; {args.pair[0]} / {args.pair[1]}, "
          f"frames 0-{v2.n_frames - 1}; errors in cm in the world's frame (median over placed frames of the block)")
    print("| frames | extension status | extension err cm | localization status | localization err cm "
          "| in extended status | in extended err cm | from truth, no prior: moved cm | translation constraint % |")
    print("|---|---|---|---|---|---|---|---|---|")
    for a in range(0, v2.n_frames, args.block):
        b = min(a + args.block, v2.n_frames)
        fp = tracker.prepare(v2.read_rgb(a), v2.read_depth_m(a, allow_empty=True))
        r = tracker.align(fp, model, truth[a], None, surface_behind=True)
        moved = 100 * pose_change(truth[a], r.T_world_cam)[0]

        def med(e):
            return f"{np.nanmedian(e[a:b]):.1f}" if np.isfinite(e[a:b]).any() else "-"
        print(f"| {a}-{b - 1} | {_status_letters(ext_status[a:b])} | {med(ext_e)} "
              f"| {_status_letters(list(loc.status[a:b]))} | {med(loc_e)} "
              f"| {_status_letters(list(again.status[a:b]))} | {med(again_e)} | {moved:.1f} "
              f"| {100 * r.translation_constraint:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

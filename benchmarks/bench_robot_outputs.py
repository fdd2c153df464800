"""Mesh and occupancy grid on every sequence at hand: the synthetic presets (whose geometry is known
exactly) and the real TUM recordings of ``../shared/data``.

Each sequence's world is built as ``atlas-gs build`` builds it (default profile; keyframes at
ground-truth poses where the recording has them), without the keyframe fit (neither output uses
it; ``--fit`` turns it on), then the TSDF mesh (``interop.mesh``, 2 cm voxels) and the occupancy
grid (``interop.occupancy``, 5 cm cells) from the keyframes at the world's keyframe poses.

Printed for every sequence, against the mesh (the keyframes' depth fused: surfaces a single noisy
reading does not make), heights above the floor the grid fitted:

* *unsupported*: the share of occupied cells with no mesh surface more than
  :data:`SURFACE_ABOVE_FLOOR_M` above the floor around them (a floor cell marked as an obstacle, or
  a surface some keyframes put where the others see through); "around": within one cell, or within
  3 std of the depth noise model at the cell's range where that is more;
* *free floor*: the share of the floor's cells (mesh surface there, none more than
  :data:`SURFACE_ABOVE_FLOOR_M` above the floor around them) the grid marks free;
* *obstacles*: the share of cells with mesh surface between :data:`SURFACE_ABOVE_FLOOR_M` and the
  band's top with an occupied cell around them: low things far away stay below the band, whose
  bottom rises with the depth noise;
* the mesh's floor: the RMS height of its surface on the floor's cells above the grid's floor
  (how flat the depth noise leaves it);
* the floor: regions fitted, their height range off the floor plane;
* on the synthetic room (not the suite): the mesh's accuracy, completeness and Chamfer distance
  against the true surfaces, the grid's IoU of free and occupied cells with the true floor plan on
  the cells the keyframes observed (``interop.evaluation``), and the share of the observed open
  floor (farther than :data:`OPEN_FLOOR_MARGIN_M` from a wall or an object) marked occupied.

    python benchmarks/bench_robot_outputs.py                        # every sequence at hand
    python benchmarks/bench_robot_outputs.py --dataset synthetic-noisy --dataset tum_fr3_teddy_100
    python benchmarks/bench_robot_outputs.py --fit --voxel 0.01 --json
    python benchmarks/bench_robot_outputs.py --dataset synthetic-loop-far --tilt-deg 0.7   # pose error
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

TUM_SEQUENCES = {"tum_fr3_teddy_100": "freiburg3", "tum_fr1_xyz_10": "freiburg1"}  # ../shared/data folder: camera
SURFACE_ABOVE_FLOOR_M = 0.10  # a surface this far above the floor is something a robot drives around
NOISE_REACH_SIGMAS = 3.0  # how far the depth noise spreads one surface's readings, in its std
# The true open floor: farther than this from a wall or an object (a robot's radius: Nav2 inflates
# every obstacle by it, so nearer cells are not where a robot's centre goes anyway)
OPEN_FLOOR_MARGIN_M = 0.15


def _manifest(dataset: str, cfg):
    """``(manifest, registry entry or None)`` of a registered dataset or a ../shared/data folder."""
    from common import shared_tum_manifest

    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    if dataset in TUM_SEQUENCES:
        m = shared_tum_manifest(dataset, TUM_SEQUENCES[dataset])
        if m is None:
            raise FileNotFoundError(f"../shared/data/{dataset} is not on this machine")
        return m, None
    entry = load_registry()[dataset]
    return load_dataset(entry, cfg), entry


def surface_figures(occ, mesh, above_m: float = SURFACE_ABOVE_FLOOR_M) -> dict:
    """The grid ``occ`` (an ``OccupancyGrid``) against the ``mesh``'s surfaces: see the module
    docstring (unsupported, free floor, obstacles). "Around" a cell is within one cell, or within
    :data:`NOISE_REACH_SIGMAS` std of the depth noise model at the cell's distance from the nearest
    keyframe where that is more (a wall read at 5 m is spread over +-12 cm)."""
    import numpy as np
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    from atlas_pipeline.interop.evaluation import surface_samples
    from atlas_pipeline.interop.occupancy import FREE, OCCUPIED
    from atlas_pipeline.sensors.depth_noise import depth_sigma_m

    res = occ.grid.resolution_m
    T_map_world = np.linalg.inv(occ.T_world_map)
    p = surface_samples(mesh.vertices, mesh.triangles) if len(mesh.triangles) else np.zeros((0, 3))
    p = p @ T_map_world[:3, :3].T + T_map_world[:3, 3]
    h = p[:, 2] - occ.floor.height_at(p[:, :2])
    r, c, ok = occ.grid.cells(p[:, :2])
    ok &= h <= occ.band_m[1]
    present = np.zeros(occ.state.shape, bool)
    present[r[ok], c[ok]] = True
    above = np.zeros(occ.state.shape, bool)
    up = ok & (h > above_m)
    above[r[up], c[up]] = True
    rows, cols = np.mgrid[0:occ.state.shape[0], 0:occ.state.shape[1]]
    centres = occ.grid.origin_xy + (np.stack([cols.ravel(), rows.ravel()], axis=1) + 0.5) * res
    range_m = cKDTree(occ.cameras_xy).query(centres)[0].reshape(occ.state.shape)
    reach_m = np.maximum(res * np.sqrt(2), NOISE_REACH_SIGMAS * depth_sigma_m(range_m))
    to_above_m = distance_transform_edt(~above) * res if above.any() else np.full(above.shape, np.inf)
    near_above = to_above_m <= reach_m
    occupied, free = occ.state == OCCUPIED, occ.state == FREE
    floor_cells = present & ~near_above
    n_occ, n_floor, n_above = int(occupied.sum()), int(floor_cells.sum()), int(above.sum())
    to_occupied_m = distance_transform_edt(~occupied) * res if occupied.any() else np.full(above.shape, np.inf)
    on_floor = ok.copy()
    on_floor[ok] = floor_cells[r[ok], c[ok]]
    return {"mesh_floor_rms_mm": float(1e3 * np.sqrt(np.mean(h[on_floor] ** 2))) if on_floor.any() else 0.0,
            "occupied_cells": n_occ, "free_cells": int(free.sum()),
            "unsupported_share": float((occupied & ~near_above).sum() / n_occ) if n_occ else 0.0,
            "floor_cells": n_floor, "free_floor_share": float((floor_cells & free).sum() / n_floor) if n_floor else 0.0,
            "obstacle_cells": n_above,
            "obstacles_occupied_share": float((above & (to_occupied_m <= reach_m)).sum() / n_above) if n_above else 0.0}


def tilted_poses(T_world_cam, tilt_deg: float, seed: int = 0):
    """``T_world_cam`` ``[K, 4, 4]`` each turned about a random level axis through its camera by a
    normal angle of std ``tilt_deg``: the pose error a SLAM (or a ground truth a few ms off the
    frames' clock) leaves, which lifts the far floor by centimetres per metre."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = np.array(T_world_cam, np.float64)
    for T in out:
        a = rng.uniform(0, 2 * np.pi)
        axis = np.array([np.cos(a), np.sin(a), 0.0])
        th = np.radians(tilt_deg) * rng.standard_normal()
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        T[:3, :3] = (np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K) @ T[:3, :3]
    return out


def measure(dataset: str = "synthetic", fit: bool = False, voxel_m: float = 0.02, resolution_m: float = 0.05,
            tilt_deg: float = 0.0) -> dict:
    """Build, mesh, grid and grade one sequence (its keyframes' poses tilted by :func:`tilted_poses`
    when ``tilt_deg`` > 0); the figures as a dict."""
    import numpy as np

    from scipy.ndimage import distance_transform_edt

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.errors import AtlasError
    from atlas_pipeline.interop.evaluation import (floor_plan_truth, mesh_chamfer, observed_cells, occupancy_figures,
                                                   visible_surface_points)
    from atlas_pipeline.interop.exports import build_mesh, build_occupancy
    from atlas_pipeline.interop.frames import ExportSource
    from atlas_pipeline.interop.occupancy import OCCUPIED
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, build_scene

    cfg = load_profile("default")
    if not fit:
        cfg = cfg.with_overrides({"mapping.fit.epochs": 0, "mapping.colour_refinement.iterations": 0})
    manifest, entry = _manifest(dataset, cfg)
    fused = fuse(manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(manifest, fused, cfg), cfg, manifest=manifest)
    T_kf = tilted_poses(world.T_world_cam_keyframes, tilt_deg) if tilt_deg > 0 else world.T_world_cam_keyframes
    src = ExportSource(world.field, manifest, world.keyframe_indices, T_kf, "keyframes", world.map_id)

    t0 = time.perf_counter()
    mesh = build_mesh(src, voxel_m, log=lambda _: None).mesh
    t_mesh = time.perf_counter() - t0
    out = {
        "dataset": dataset, "n_frames": manifest.n_frames, "n_keyframes": int(len(world.keyframe_indices)), "fit": fit,
        "tilt_deg": tilt_deg,
        "mesh": {"voxel_m": voxel_m, "n_vertices": int(len(mesh.vertices)), "n_triangles": int(len(mesh.triangles)),
                 "seconds": t_mesh},
    }
    t0 = time.perf_counter()
    try:
        occ = build_occupancy(src, resolution_m, log=lambda _: None).grid
    except AtlasError as exc:  # a recording that shows no floor has no grid: the exporter says so
        out["occupancy"] = {"resolution_m": resolution_m, "no_grid": str(exc)}
        return out
    t_occ = time.perf_counter() - t0
    tilt = float(np.degrees(np.arccos(np.clip(occ.floor_normal[2], -1, 1))))
    fs = occ.floor.summary()
    out["occupancy"] = {"resolution_m": resolution_m, "floor_tilt_deg": tilt,
                        "floor_offset_mm": 1e3 * occ.floor_offset_m, "floor_regions": fs["tiles_fitted"],
                        "floor_height_range_m": fs["height_range_m"], "seconds": t_occ,
                        **surface_figures(occ, mesh)}
    spec = SyntheticSpec(**entry.params) if entry is not None and entry.kind == "synthetic" else None
    if spec is not None and spec.place == "room":  # the room's true geometry (the suite has no floor plan here)
        scene = build_scene(spec.seed)
        T_gt = manifest.T_world_cam_gt[world.keyframe_indices]
        m = mesh_chamfer(mesh.vertices, mesh.triangles, scene, visible_surface_points(spec, scene, T_gt))
        out["mesh"].update({"accuracy_mm": 1e3 * m.accuracy_m, "completeness_mm": 1e3 * m.completeness_m,
                            "chamfer_mm": 1e3 * m.chamfer_m, "accuracy_p90_mm": 1e3 * m.accuracy_p90_m,
                            "completeness_p90_mm": 1e3 * m.completeness_p90_m})
        truth = floor_plan_truth(scene, occ.grid.origin_xy, occ.grid.resolution_m, occ.state.shape, occ.band_m)
        seen = observed_cells(spec, scene, T_gt, occ.grid, occ.band_m)
        o = occupancy_figures(occ.state, truth, seen)
        open_floor = seen & (distance_transform_edt(~truth) > round(OPEN_FLOOR_MARGIN_M / resolution_m, 6))
        out["occupancy"].update({"open_floor_cells": int(open_floor.sum()),
                                 "open_floor_occupied_share": float((occ.state[open_floor] == OCCUPIED).mean())
                                 if open_floor.any() else 0.0})
        out["occupancy"].update({"iou_free": o.iou_free, "iou_occupied": o.iou_occupied,
                                 "mean_iou": (o.iou_free + o.iou_occupied) / 2, "agreement": o.agreement,
                                 "observed_cells": o.n_observed_cells, "unknown_share_of_observed": o.unknown_share})
    return out


def available_sequences() -> list[str]:
    """The default sequences: every registered synthetic dataset in the one room (ideal and
    Kinect-like; the three-room suite's 1,500 and 900 frames are left to ``--dataset``) and the TUM
    folders on this machine."""
    from common import SHARED_DATA

    from atlas_pipeline.sensors.registry import load_registry
    from atlas_pipeline.sensors.synthetic import SyntheticSpec

    rooms = [name for name, e in load_registry().items()
             if e.kind == "synthetic" and SyntheticSpec(**e.params).place == "room"]
    return [*rooms, *(d for d in TUM_SEQUENCES if (SHARED_DATA / d / "rgb.txt").is_file())]


def report_lines(r: dict) -> list[str]:
    m, o = r["mesh"], r["occupancy"]
    if "error" in r:
        return [f"{r['dataset']}: {r['error']}"]
    tilted = f", poses tilted {r['tilt_deg']:g} deg (std)" if r["tilt_deg"] else ""
    lines = [f"{r['dataset']}: {r['n_keyframes']} keyframes of {r['n_frames']} frames, keyframe fit "
             f"{'on' if r['fit'] else 'off'}{tilted}"]
    mesh = f"  mesh ({m['voxel_m'] * 100:g} cm voxels, {m['n_triangles']:,} triangles, {m['seconds']:.1f} s)"
    if "chamfer_mm" in m:
        mesh += (f": Chamfer {m['chamfer_mm']:.2f} mm (accuracy {m['accuracy_mm']:.2f} mm, completeness "
                 f"{m['completeness_mm']:.2f} mm; p90 {m['accuracy_p90_mm']:.2f} / {m['completeness_p90_mm']:.2f} mm)")
    if "no_grid" in o:
        return [*lines, mesh, f"  occupancy: no grid ({o['no_grid']})"]
    mesh += f"; its floor {o['mesh_floor_rms_mm']:.1f} mm RMS off the grid's floor"
    lines.append(mesh)
    lines.append(f"  occupancy ({o['resolution_m'] * 100:g} cm cells, {o['seconds']:.1f} s): {o['occupied_cells']:,} "
                 f"occupied, {o['unsupported_share']:.1%} of them with no surface > {SURFACE_ABOVE_FLOOR_M * 100:g} cm "
                 f"above the floor; free floor {o['free_floor_share']:.1%} of {o['floor_cells']:,} cells; obstacles "
                 f"occupied {o['obstacles_occupied_share']:.1%} of {o['obstacle_cells']:,} cells")
    lines.append(f"  floor: plane tilt {o['floor_tilt_deg']:.3f} deg, offset {o['floor_offset_mm']:.2f} mm; "
                 f"{o['floor_regions']} regions, {o['floor_height_range_m'][0] * 100:+.1f}.."
                 f"{o['floor_height_range_m'][1] * 100:+.1f} cm off the plane")
    if "mean_iou" in o:
        lines.append(f"  vs the true floor plan: IoU free {o['iou_free']:.3f}, occupied {o['iou_occupied']:.3f}, "
                     f"mean {o['mean_iou']:.3f}; {o['agreement']:.1%} of {o['observed_cells']:,} observed cells agree; "
                     f"{o['open_floor_occupied_share']:.2%} of {o['open_floor_cells']:,} open-floor cells occupied")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", action="append", help="a registered dataset or a ../shared/data TUM folder "
                    "(repeatable; default: every sequence at hand)")
    ap.add_argument("--fit", action="store_true", help="run the keyframe fit (default off: neither output uses it)")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--tilt-deg", type=float, default=0.0, help="turn each keyframe's pose about a random level "
                    "axis by this std (degrees): pose error on a sequence whose geometry is known")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    results = []
    for d in args.dataset or available_sequences():
        try:
            r = measure(d, args.fit, args.voxel, args.resolution, args.tilt_deg)
        except Exception as exc:  # one sequence's failure is its line, the others still run
            r = {"dataset": d, "error": f"{type(exc).__name__}: {exc}", "mesh": {}, "occupancy": {}}
        results.append(r)
        if not args.json:
            print("\n".join(report_lines(r)), flush=True)
    if args.json:
        print(json.dumps(results, indent=2))
    return 1 if any("error" in r for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())

"""Mesh and occupancy grid on every sequence at hand: the synthetic presets (whose geometry is known
exactly) and the real TUM recordings of ``../shared/data``.

Each sequence's world is built as ``atlas-gs build`` builds it (default profile; keyframes at
ground-truth poses where the recording has them), without the keyframe fit (neither output uses
it; ``--fit`` turns it on), then the TSDF mesh (``interop.mesh``, 2 cm voxels) and the occupancy
grid (``interop.occupancy``, 5 cm cells) from the keyframes at the world's keyframe poses.

Printed for every sequence, against the mesh (the keyframes' depth fused: surfaces a single noisy
reading does not make), heights above the floor the grid fitted:

* *unsupported*: the share of occupied cells with no mesh surface more than
  :data:`SURFACE_ABOVE_FLOOR_M` above the floor in the cell or the 8 around it (a floor cell marked
  as an obstacle);
* *free floor*: the share of the floor's cells (mesh surface there, none more than
  :data:`SURFACE_ABOVE_FLOOR_M` above the floor in the cell or the 8 around it) the grid marks free;
* *obstacles*: the share of cells with mesh surface between :data:`SURFACE_ABOVE_FLOOR_M` and the
  band's top that the grid marks occupied (itself or a neighbour): low things far away stay below
  the band, whose bottom rises with the depth noise;
* the floor: regions fitted, their height range off the floor plane;
* on the synthetic room (not the suite): the mesh's accuracy, completeness and Chamfer distance
  against the true surfaces, and the grid's IoU of free and occupied cells with the true floor
  plan on the cells the keyframes observed (``interop.evaluation``).

    python benchmarks/bench_robot_outputs.py                        # every sequence at hand
    python benchmarks/bench_robot_outputs.py --dataset synthetic-noisy --dataset tum_fr3_teddy_100
    python benchmarks/bench_robot_outputs.py --fit --voxel 0.01 --json
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

# The synthetic presets in one room, ideal and Kinect-like (configs/datasets.yaml); the suite's
# 1,500 + 900 frames are left to --dataset.
SYNTHETIC_SEQUENCES = ("synthetic", "synthetic-noisy", "synthetic-handheld", "synthetic-loop")
TUM_SEQUENCES = {"tum_fr3_teddy_100": "freiburg3", "tum_fr1_xyz_10": "freiburg1"}  # ../shared/data folder: camera
SURFACE_ABOVE_FLOOR_M = 0.10  # a surface this far above the floor is something a robot drives around


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
    docstring (unsupported, free floor, obstacles)."""
    import numpy as np

    from atlas_pipeline.interop.evaluation import surface_samples
    from atlas_pipeline.interop.occupancy import FREE, OCCUPIED

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

    def around(a: np.ndarray) -> np.ndarray:
        q = np.pad(a, 1)
        return np.any([q[i:i + a.shape[0], j:j + a.shape[1]] for i in range(3) for j in range(3)], axis=0)

    occupied, free = occ.state == OCCUPIED, occ.state == FREE
    floor_cells = present & ~around(above)
    n_occ, n_floor, n_above = int(occupied.sum()), int(floor_cells.sum()), int(above.sum())
    return {"occupied_cells": n_occ, "free_cells": int(free.sum()),
            "unsupported_share": float((occupied & ~around(above)).sum() / n_occ) if n_occ else 0.0,
            "floor_cells": n_floor, "free_floor_share": float((floor_cells & free).sum() / n_floor) if n_floor else 0.0,
            "obstacle_cells": n_above,
            "obstacles_occupied_share": float((above & around(occupied)).sum() / n_above) if n_above else 0.0}


def measure(dataset: str = "synthetic", fit: bool = False, voxel_m: float = 0.02, resolution_m: float = 0.05) -> dict:
    """Build, mesh, grid and grade one sequence; the figures as a dict."""
    import numpy as np

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.interop.evaluation import (floor_plan_truth, mesh_chamfer, observed_cells, occupancy_figures,
                                                   visible_surface_points)
    from atlas_pipeline.interop.exports import build_mesh, build_occupancy
    from atlas_pipeline.interop.frames import ExportSource
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, build_scene

    cfg = load_profile("default")
    if not fit:
        cfg = cfg.with_overrides({"mapping.fit.epochs": 0, "mapping.colour_refinement.iterations": 0})
    manifest, entry = _manifest(dataset, cfg)
    fused = fuse(manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(manifest, fused, cfg), cfg, manifest=manifest)
    src = ExportSource(world.field, manifest, world.keyframe_indices, world.T_world_cam_keyframes, "keyframes",
                       world.map_id)

    t0 = time.perf_counter()
    mesh = build_mesh(src, voxel_m, log=lambda _: None).mesh
    t_mesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    occ = build_occupancy(src, resolution_m, log=lambda _: None).grid
    t_occ = time.perf_counter() - t0
    tilt = float(np.degrees(np.arccos(np.clip(occ.floor_normal[2], -1, 1))))
    fs = occ.floor.summary()
    out = {
        "dataset": dataset, "n_frames": manifest.n_frames, "n_keyframes": int(len(world.keyframe_indices)), "fit": fit,
        "mesh": {"voxel_m": voxel_m, "n_vertices": int(len(mesh.vertices)), "n_triangles": int(len(mesh.triangles)),
                 "seconds": t_mesh},
        "occupancy": {"resolution_m": resolution_m, "floor_tilt_deg": tilt, "floor_offset_mm": 1e3 * occ.floor_offset_m,
                      "floor_regions": fs["tiles_fitted"], "floor_height_range_m": fs["height_range_m"],
                      "seconds": t_occ, **surface_figures(occ, mesh)},
    }
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
        out["occupancy"].update({"iou_free": o.iou_free, "iou_occupied": o.iou_occupied,
                                 "mean_iou": (o.iou_free + o.iou_occupied) / 2, "agreement": o.agreement,
                                 "observed_cells": o.n_observed_cells, "unknown_share_of_observed": o.unknown_share})
    return out


def available_sequences() -> list[str]:
    """The default sequences: the synthetic room's presets and the TUM folders on this machine."""
    from common import SHARED_DATA

    return [*SYNTHETIC_SEQUENCES, *(d for d in TUM_SEQUENCES if (SHARED_DATA / d / "rgb.txt").is_file())]


def report_lines(r: dict) -> list[str]:
    m, o = r["mesh"], r["occupancy"]
    if "error" in r:
        return [f"{r['dataset']}: {r['error']}"]
    lines = [f"{r['dataset']}: {r['n_keyframes']} keyframes of {r['n_frames']} frames, keyframe fit "
             f"{'on' if r['fit'] else 'off'}"]
    mesh = f"  mesh ({m['voxel_m'] * 100:g} cm voxels, {m['n_triangles']:,} triangles, {m['seconds']:.1f} s)"
    if "chamfer_mm" in m:
        mesh += (f": Chamfer {m['chamfer_mm']:.2f} mm (accuracy {m['accuracy_mm']:.2f} mm, completeness "
                 f"{m['completeness_mm']:.2f} mm; p90 {m['accuracy_p90_mm']:.2f} / {m['completeness_p90_mm']:.2f} mm)")
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
                     f"mean {o['mean_iou']:.3f}; {o['agreement']:.1%} of {o['observed_cells']:,} observed cells agree")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", action="append", help="a registered dataset or a ../shared/data TUM folder "
                    "(repeatable; default: every sequence at hand)")
    ap.add_argument("--fit", action="store_true", help="run the keyframe fit (default off: neither output uses it)")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    results = []
    for d in args.dataset or available_sequences():
        try:
            r = measure(d, args.fit, args.voxel, args.resolution)
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

"""Mesh and occupancy grid of the synthetic room against its exact geometry.

Builds the world of a synthetic dataset (default ``synthetic``: 60 frames, 640x480; keyframes at
ground-truth poses), then the TSDF mesh (``interop.mesh``, 2 cm voxels) and the occupancy grid
(``interop.occupancy``, 5 cm cells) from the keyframes at the world's keyframe poses, and prints:

* mesh: accuracy (vertices -> true surfaces), completeness (true surfaces the keyframes saw ->
  mesh surface), Chamfer distance (their mean), 90th percentiles, time;
* occupancy: IoU of the free and of the occupied cells with the true floor plan, their mean, the
  share of agreeing cells, on the cells the keyframes observed (``interop.evaluation``), time.

    python benchmarks/bench_robot_outputs.py                 # the keyframe fit off (the mesh does not use it)
    python benchmarks/bench_robot_outputs.py --fit --voxel 0.01
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def measure(dataset: str = "synthetic", fit: bool = False, voxel_m: float = 0.02, resolution_m: float = 0.05) -> dict:
    """Build, mesh, grid and grade; the figures as a dict."""
    import numpy as np

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.interop.evaluation import (floor_plan_truth, mesh_chamfer, observed_cells, occupancy_figures,
                                                   visible_surface_points)
    from atlas_pipeline.interop.exports import build_mesh, build_occupancy
    from atlas_pipeline.interop.frames import ExportSource
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.sensors.registry import load_dataset, load_registry
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, build_scene

    entry = load_registry()[dataset]
    if entry.kind != "synthetic":
        raise SystemExit(f"{dataset} is not a synthetic dataset: its true geometry is unknown")
    cfg = load_profile("default")
    if not fit:
        cfg = cfg.with_overrides({"mapping.fit.epochs": 0, "mapping.colour_refinement.iterations": 0})
    manifest = load_dataset(entry, cfg)
    fused = fuse(manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(manifest, fused, cfg), cfg, manifest=manifest)
    src = ExportSource(world.field, manifest, world.keyframe_indices, world.T_world_cam_keyframes, "keyframes",
                       world.map_id)
    spec = SyntheticSpec(**entry.params)
    scene = build_scene(spec.seed)
    T_gt = manifest.T_world_cam_gt[world.keyframe_indices]

    t0 = time.perf_counter()
    mesh = build_mesh(src, voxel_m).mesh
    t_mesh = time.perf_counter() - t0
    m = mesh_chamfer(mesh.vertices, mesh.triangles, scene, visible_surface_points(spec, scene, T_gt))

    t0 = time.perf_counter()
    occ = build_occupancy(src, resolution_m).grid
    t_occ = time.perf_counter() - t0
    truth = floor_plan_truth(scene, occ.grid.origin_xy, occ.grid.resolution_m, occ.state.shape, occ.band_m)
    seen = observed_cells(spec, scene, T_gt, occ.grid, occ.band_m)
    o = occupancy_figures(occ.state, truth, seen)
    tilt = float(np.degrees(np.arccos(np.clip(occ.floor_normal[2], -1, 1))))
    return {
        "dataset": dataset, "n_keyframes": int(len(world.keyframe_indices)), "fit": fit,
        "mesh": {"voxel_m": voxel_m, "n_vertices": m.n_vertices, "n_triangles": int(len(mesh.triangles)),
                 "accuracy_mm": 1e3 * m.accuracy_m, "completeness_mm": 1e3 * m.completeness_m,
                 "chamfer_mm": 1e3 * m.chamfer_m, "accuracy_p90_mm": 1e3 * m.accuracy_p90_m,
                 "completeness_p90_mm": 1e3 * m.completeness_p90_m, "seconds": t_mesh},
        "occupancy": {"resolution_m": resolution_m, "iou_free": o.iou_free, "iou_occupied": o.iou_occupied,
                      "mean_iou": (o.iou_free + o.iou_occupied) / 2, "agreement": o.agreement,
                      "observed_cells": o.n_observed_cells, "unknown_share_of_observed": o.unknown_share,
                      "floor_tilt_deg": tilt, "floor_offset_mm": 1e3 * occ.floor_offset_m, "seconds": t_occ},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="synthetic")
    ap.add_argument("--fit", action="store_true", help="run the keyframe fit (default off: the mesh does not use it)")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = measure(args.dataset, args.fit, args.voxel, args.resolution)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    m, o = r["mesh"], r["occupancy"]
    print(f"{r['dataset']}: {r['n_keyframes']} keyframes, keyframe fit {'on' if r['fit'] else 'off'}")
    print(f"mesh ({m['voxel_m'] * 100:g} cm voxels, {m['n_triangles']:,} triangles, {m['seconds']:.1f} s): "
          f"Chamfer {m['chamfer_mm']:.2f} mm (accuracy {m['accuracy_mm']:.2f} mm, completeness "
          f"{m['completeness_mm']:.2f} mm; p90 {m['accuracy_p90_mm']:.2f} / {m['completeness_p90_mm']:.2f} mm)")
    print(f"occupancy ({o['resolution_m'] * 100:g} cm cells, {o['seconds']:.1f} s): IoU free {o['iou_free']:.3f}, "
          f"occupied {o['iou_occupied']:.3f}, mean {o['mean_iou']:.3f}; {o['agreement']:.1%} of "
          f"{o['observed_cells']} observed cells agree; floor tilt {o['floor_tilt_deg']:.3f} deg, "
          f"offset {o['floor_offset_mm']:.2f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Per-frame tracking cost as the map grows: the model view and one frame's alignment, with the
map culled by chunk against the whole map splatted (the reference), and culled and clipped to the
frame's depth range (what the tracker does: ``RGBDTracker.align(within_range=True)``), in the same
run, on the same maps and frames.

Maps: a floor of ``R`` rooms (4 x 3 m, 2.6 m high, a grid), surfels on the floor, the ceiling and
every wall at a 4 cm voxel pitch with 3 mm of noise along the normal, as the voxel map makes them.
The camera stands in the first room, 1.2 m up, and looks across it; the frame is the map's own
depth at that pose (level 0, 640x480, Kinect-like intrinsics), and the alignment starts 2 cm and
1 degree away from it. Every figure is the median of ``--repeats`` calls after one warm-up (the
kernels compiled or loaded from numba's cache). Culled and whole renders are checked identical,
and so are the poses aligned within range, against the whole view, and against the same map as a
saved world holds it (``SurfelModel(fixed=True)``: its far part, beyond the frame's reach, drawn
from the coarser ``far_level``; the view and alignment timed as the other columns, and the far
level's making once). The tracker's
depth range is the default profile's (``fusion``).

Keyframe integration on the same maps: the map's surfels are integrated into a voxel map (the
tracker's ``VoxelGaussianBuilder`` and ``SurfelCache``), then ``KEYFRAMES`` keyframes seen from the
first room, the camera turning ``KEYFRAME_YAW_DEG`` further each time, are integrated as SLAM
integrates them (the frame's points at the default fusion stride, the voxel statistics merged,
the surfel map brought up to date, the model's chunks binned); the median over the keyframes,
after one warm-up. The reference in the same run is the surfel map made again from the whole
voxel map (``SurfelModel.from_builder``, its chunks binned), what a keyframe would cost if the
surfel map were not kept incrementally.

Run: ``python benchmarks/bench_map_cost.py [--rooms 1 4 16 64] [--repeats 20] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_pipeline.config import load_profile  # noqa: E402
from atlas_pipeline.geometry import so3_exp  # noqa: E402
from atlas_pipeline.localization import _kernels as kn  # noqa: E402
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as C  # noqa: E402
from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel, _level_view, far_level, splat_params  # noqa: E402
from atlas_pipeline.sensors.camera import CameraIntrinsics  # noqa: E402

CAMERA = CameraIntrinsics(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
ROOM_M = (4.0, 3.0, 2.6)  # x, y, height
VOXEL_M = 0.04
NOISE_M = 0.003
START_OFFSET_M = 0.02
START_OFFSET_DEG = 1.0
KEYFRAMES = 6
KEYFRAME_YAW_DEG = 4.0


class WholeMap(SurfelModel):
    """The reference: every surfel looked at for every view."""

    def culling(self, view, params):
        return kn.NO_CULLING


def rooms_map(n_rooms: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Surfel centres and normals ``[N, 3]`` of a near-square grid of ``n_rooms`` rooms."""
    rng = np.random.default_rng(seed)
    nx = int(np.ceil(np.sqrt(n_rooms)))
    ny = int(np.ceil(n_rooms / nx))
    wx, wy, h = ROOM_M
    centres, normals = [], []

    def plane(origin, u, v, lu, lv, normal):
        a, b = np.meshgrid(np.arange(0.0, lu, VOXEL_M), np.arange(0.0, lv, VOXEL_M), indexing="ij")
        p = origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
        centres.append(p + rng.normal(0.0, NOISE_M, (len(p), 1)) * normal)
        normals.append(np.broadcast_to(normal, p.shape))

    ex, ey, ez = np.eye(3)
    for i in range(nx + 1):  # walls x = const, the full floor's depth
        plane(np.array([i * wx, 0.0, 0.0]), ey, ez, ny * wy, h, ex)
    for j in range(ny + 1):
        plane(np.array([0.0, j * wy, 0.0]), ex, ez, nx * wx, h, ey)
    for z in (0.0, h):
        plane(np.array([0.0, 0.0, z]), ex, ey, nx * wx, ny * wy, ez)
    return np.ascontiguousarray(np.concatenate(centres)), np.ascontiguousarray(np.concatenate(normals))


def camera_pose() -> np.ndarray:
    """In the first room, 1.2 m up, looking along +x and a little down (camera z forward, y down)."""
    R_world_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # z -> +x, y -> -z
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.3, 0.0])) @ R_world_cam
    T[:3, 3] = [0.6, 1.5, 1.2]
    return T


def median_s(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def keyframe_ms(centres: np.ndarray, camera_poses: list[np.ndarray], whole: SurfelModel) -> dict[str, float]:
    """Median milliseconds per keyframe integrated into the voxel map of ``centres [N, 3]``:
    ``integrate`` (the frame's points merged into the voxel statistics), ``surfels`` (the surfel
    map and its chunks brought up to date) and ``rebuilt`` (the reference: the surfel map and its
    chunks made again from the whole voxel map). The first of ``camera_poses`` is the warm-up."""
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.perception.rgbd import backproject
    from atlas_pipeline.localization.tracker import SurfelCache

    fusion = load_profile("default").fusion
    builder = VoxelGaussianBuilder(VOXEL_M)
    builder.integrate(centres, np.zeros((len(centres), 3)))
    cache = SurfelCache(builder)
    cache.model()
    integrate, surfels = [], []
    for T in camera_poses:
        pts, _ = whole.render(T, CAMERA, 0)
        depth_m = np.nan_to_num(pts[..., 2], nan=0.0).astype(np.float32)
        t0 = time.perf_counter()
        pc, _ = backproject(depth_m, None, CAMERA, fusion.stride, fusion.min_depth_m, fusion.max_depth_m)
        builder.integrate(pc.astype(np.float64) @ T[:3, :3].T + T[:3, 3], np.full((len(pc), 3), 128.0))
        t1 = time.perf_counter()
        model = cache.model()
        model.culling(_level_view(T, CAMERA, 1), splat_params(model.radius_m))
        integrate.append(t1 - t0)
        surfels.append(time.perf_counter() - t1)

    def rebuilt() -> None:
        model = SurfelModel.from_builder(builder)
        model.culling(_level_view(camera_poses[0], CAMERA, 1), splat_params(model.radius_m))

    return {"integrate": 1e3 * float(np.median(integrate[1:])), "surfels": 1e3 * float(np.median(surfels[1:])),
            "rebuilt": 1e3 * median_s(rebuilt, 3)}


def turning(T: np.ndarray, n: int, step_deg: float) -> list[np.ndarray]:
    """``n`` poses at ``T``'s position, turned ``step_deg`` further about the world z axis each."""
    out = []
    for k in range(n):
        Tk = T.copy()
        Tk[:3, :3] = so3_exp(np.radians([0.0, 0.0, k * step_deg])) @ T[:3, :3]
        out.append(Tk)
    return out


def measure(n_rooms: int, repeats: int) -> dict:
    centres, normals = rooms_map(n_rooms)
    radius_m = C.surfel_radius_voxels * VOXEL_M
    culled, whole = SurfelModel(centres, normals, radius_m), WholeMap(centres, normals, radius_m)
    saved = SurfelModel(centres, normals, radius_m, fixed=True)  # a saved world's: a far level
    cfg = load_profile("default").localization
    fusion = load_profile("default").fusion
    tracker = RGBDTracker(CAMERA, cfg, (fusion.min_depth_m, fusion.max_depth_m))
    T = camera_pose()
    pts, _ = whole.render(T, CAMERA, 0)
    depth_m = np.nan_to_num(pts[..., 2], nan=0.0).astype(np.float32)
    frame = tracker.prepare(None, depth_m)
    T0 = T.copy()
    T0[:3, :3] = so3_exp(np.radians([START_OFFSET_DEG, 0.0, 0.0])) @ T[:3, :3]
    T0[:3, 3] += START_OFFSET_M / np.sqrt(3.0)
    level = tracker.model_level
    a, b = culled.model_view(T, CAMERA, level), whole.model_view(T, CAMERA, level)
    identical = all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a[:4], b[:4]))
    far_m = tracker.tracking_far_m
    ranged_pose = tracker.align(frame, culled, T0, within_range=True).T_world_cam
    aligned = tracker.align(frame, culled, T0).T_world_cam
    saved_pose = tracker.align(frame, saved, T0).T_world_cam
    identical = identical and np.array_equal(ranged_pose, aligned) and np.array_equal(saved_pose, aligned)
    row = {"rooms": n_rooms, "surfels": len(centres), "identical": identical}
    for name, model in (("culled", culled), ("whole", whole)):
        row[f"view_ms_{name}"] = 1e3 * median_s(lambda m=model: m.model_view(T, CAMERA, level), repeats)
        row[f"align_ms_{name}"] = 1e3 * median_s(lambda m=model: tracker.align(frame, m, T0), repeats)
    row["view_ms_range"] = 1e3 * median_s(lambda: culled.model_view(T, CAMERA, level, max_depth_m=far_m), repeats)
    row["align_ms_range"] = 1e3 * median_s(lambda: tracker.align(frame, culled, T0, within_range=True), repeats)
    row["view_ms_far_level"] = 1e3 * median_s(lambda: saved.model_view(T, CAMERA, level, False, np.inf, far_m), repeats)
    row["align_ms_far_level"] = 1e3 * median_s(lambda: tracker.align(frame, saved, T0), repeats)
    row["far_level_surfels"] = len(saved._far.centres) if saved._far is not None else 0
    t0 = time.perf_counter()  # made once per session, when it starts
    far_level(saved.centres, saved.normals, radius_m, far_m)
    row["far_level_s"] = time.perf_counter() - t0
    for name, far in (("", np.inf), ("_range", far_m)):
        seen = culled.culling(_level_view(T, CAMERA, level), splat_params(radius_m, far))
        row[f"looked_at_pct{name}"] = 100.0 * float(seen.chunk_seen[seen.chunk_of].mean()) if len(seen.chunk_of) else 100.0
    row["align_error_mm"] = 1e3 * float(np.linalg.norm(ranged_pose[:3, 3] - T[:3, 3]))
    row.update({f"keyframe_ms_{k}": v for k, v in keyframe_ms(
        centres, turning(T, KEYFRAMES + 1, KEYFRAME_YAW_DEG), whole).items()})
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rooms", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args(argv)
    rows = [measure(n, args.repeats) for n in args.rooms]
    print("| rooms | surfels (far level: disks, s to make) | looked at %: culled / within range "
          "| model view ms: whole / culled / far level / within range "
          "| align ms: whole / culled / far level / within range "
          "| keyframe ms: integrate / surfel map rebuilt / kept up to date | align error mm | identical |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['rooms']} | {r['surfels']:,} ({r['far_level_surfels']:,}, {r['far_level_s']:.2f}) "
              f"| {r['looked_at_pct']:.1f} / {r['looked_at_pct_range']:.1f} "
              f"| {r['view_ms_whole']:.2f} / {r['view_ms_culled']:.2f} / {r['view_ms_far_level']:.2f} / {r['view_ms_range']:.2f} "
              f"| {r['align_ms_whole']:.1f} / {r['align_ms_culled']:.1f} / {r['align_ms_far_level']:.1f} / {r['align_ms_range']:.1f} "
              f"| {r['keyframe_ms_integrate']:.0f} / {r['keyframe_ms_rebuilt']:.0f} / {r['keyframe_ms_surfels']:.0f} "
              f"| {r['align_error_mm']:.2f} | {r['identical']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())

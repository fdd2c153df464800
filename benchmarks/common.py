"""Helpers shared by the tracking benchmarks (``bench_tracking.py``, ``bench_robustness.py``).

Frames are decoded once into memory, so every tracker below is timed on the same in-memory frames
(decoding excluded). No tracker reads ground truth; :func:`grade` is the only place it is used.

* :func:`run_slam`: our tracking and mapping, ``atlas_pipeline.mapping.keyframes.slam_poses``
  (``mapping.pose_source: estimated``) on preloaded frames.
* :func:`run_open3d_odometry`: Open3D's tensor RGB-D odometry, hybrid term, multi-scale
  10/5/3 iterations, frame to frame, poses chained.
* :func:`run_open3d_model`: Open3D's dense frame-to-model SLAM (``open3d.t.pipelines.slam``, the
  loop of its ``dense_slam.py`` example: track against the ray-cast model, integrate, ray-cast).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"  # ../shared/data beside the project

# Open3D's reference settings (open3d/examples/python/t_reconstruction_system/default_config.yml).
O3D_ODOMETRY_ITERATIONS = (10, 5, 3)  # coarse to fine, as ../shared/data/README.md measured
O3D_DEPTH_SCALE = 1000.0  # depth handed to Open3D as uint16 millimetres
O3D_MODEL_VOXEL_M = 0.0058  # dense_slam.py default voxel (~3 m / 512)
O3D_MODEL_BLOCK_COUNT = 40000
O3D_MODEL_TRUNC_VOXELS = 8.0  # truncation distance = 8 voxels
O3D_MODEL_DISTANCE_THR_M = 0.07  # point-to-plane correspondence distance of frame-to-model tracking


def shared_tum_manifest(folder: str, camera: str):
    """The TUM recording ``folder`` of :data:`SHARED_DATA` with the TUM intrinsics ``camera``
    (``"freiburg1"``, ...); None when that folder is absent."""
    from atlas_pipeline.sensors.camera import TUM_CAMERAS
    from atlas_pipeline.sensors.registry import DatasetEntry, read_dataset_manifest

    root = SHARED_DATA / folder
    if not root.is_dir():
        return None
    return read_dataset_manifest(DatasetEntry(folder, "tum", root, camera=TUM_CAMERAS[camera]))


def load_frames(manifest) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(rgb uint8 [H, W, 3], depth_m float32 [H, W])]`` of every frame of the manifest."""
    return [(manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True)) for i in range(manifest.n_frames)]


def grade(manifest, poses: np.ndarray) -> dict:
    """ATE / RPE (TUM conventions, RPE per second) of ``poses`` ``[N, 4, 4]`` against ground truth."""
    from atlas_pipeline.localization.metrics import evaluate_trajectories

    return evaluate_trajectories(manifest.timestamps_s, poses, manifest.timestamps_s, manifest.T_world_cam_gt)


def end_to_start_error_m(manifest, poses: np.ndarray) -> float | None:
    """How far the estimated last frame is from where it should be relative to the first
    (translation of ``inv(T_0) T_last``, estimate against ground truth): a loop's closing error.
    None without ground truth or a pose at both ends."""
    gt, ok = manifest.T_world_cam_gt, manifest.has_gt
    placed = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if len(placed) < 2 or not (ok[placed[0]] and ok[placed[-1]]):
        return None
    a, b = placed[0], placed[-1]
    rel_est = np.linalg.solve(poses[a], poses[b])
    rel_gt = np.linalg.solve(gt[a], gt[b])
    return float(np.linalg.norm(rel_est[:3, 3] - rel_gt[:3, 3]))


def run_slam(manifest, frames, cfg, budget_s: float | None = None) -> tuple[dict, object]:
    """Our tracking and mapping on preloaded frames: ``slam_poses`` itself (multiple maps and loop
    closure included in the time; loop closure reads its keyframes from disk again). Returns
    ``(figures, SequenceTracker)``; the figures cover the ``n_attempted`` frames when ``budget_s``
    stopped the run."""
    from atlas_pipeline.localization.sequence import STATUS_LOST, STATUS_RELOCALIZED
    from atlas_pipeline.mapping.keyframes import slam_poses

    slam = slam_poses(manifest, cfg.mapping, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                      cfg.fusion.stride, frames=frames, budget_s=budget_s)
    n = slam.n_attempted
    poses = slam.T_world_cam.copy()
    poses[n:] = np.nan
    out = grade(manifest, poses)
    status = slam.status[:n]
    loops = slam.loop_closure
    out.update({"frames_per_s": (n - 1) / slam.time_s if n > 1 else float("nan"), "n_attempted": n,
                "n_keyframes": len(slam.keyframe_indices), "n_lost": status.count(STATUS_LOST),
                "n_relocalized": status.count(STATUS_RELOCALIZED), "n_maps": slam.maps["n_maps"],
                "n_maps_merged": slam.maps["n_merged"], "n_loops": None if loops is None else loops["n_loops"],
                "loop_max_change_m": None if loops is None else loops["max_translation_change_m"],
                "end_to_start_error_m": end_to_start_error_m(manifest, poses),
                "n_outside_main_map": int(sum(1 for i in range(n) if not slam.valid[i]
                                              and status[i] not in (STATUS_LOST,)))})
    return out, slam.tracker


def _o3d_depth(depth_m: np.ndarray, depth_min_m: float) -> np.ndarray:
    """uint16 millimetres ``[H, W]``; readings nearer than ``depth_min_m`` become 0 (no reading)."""
    return (np.where(depth_m >= depth_min_m, depth_m, 0.0) * O3D_DEPTH_SCALE).astype(np.uint16)


def run_open3d_odometry(manifest, frames, depth_max_m: float = 3.0, depth_min_m: float = 0.0) -> dict:
    """Open3D tensor RGB-D odometry, hybrid, frame to frame, chained; depth cut to
    ``[depth_min_m, depth_max_m]``."""
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    odo = o3d.t.pipelines.odometry
    K = o3d.core.Tensor(manifest.camera.K, o3d.core.Dtype.Float64)
    crit = [odo.OdometryConvergenceCriteria(n) for n in O3D_ODOMETRY_ITERATIONS]

    def rgbd(rgb, depth):
        return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(np.ascontiguousarray(rgb)),
                                        o3d.t.geometry.Image(_o3d_depth(depth, depth_min_m)))

    images = [rgbd(*f) for f in frames]
    poses = np.tile(np.eye(4), (len(frames), 1, 1))
    t0 = time.perf_counter()
    for i in range(1, len(frames)):
        r = odo.rgbd_odometry_multi_scale(images[i], images[i - 1], K, o3d.core.Tensor(np.eye(4)), O3D_DEPTH_SCALE,
                                          depth_max_m, crit, odo.Method.Hybrid)
        poses[i] = poses[i - 1] @ r.transformation.numpy()
    dt = time.perf_counter() - t0
    out = grade(manifest, poses)
    out["frames_per_s"] = (len(frames) - 1) / dt if len(frames) > 1 else float("nan")
    return out


def run_open3d_model(manifest, frames, depth_min_m: float, depth_max_m: float,
                     voxel_size_m: float = O3D_MODEL_VOXEL_M) -> dict:
    """Open3D dense frame-to-model SLAM on the CPU: ``track_frame_to_model`` against the model
    ray-cast at the previous pose, ``integrate``, ``synthesize_model_frame`` (point-to-plane,
    Open3D's defaults), poses chained from the first frame. A tracking exception (no valid
    correspondences) keeps the previous pose and counts the frame as lost."""
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # no per-frame warnings
    slam = o3d.t.pipelines.slam
    dev = o3d.core.Device("CPU:0")
    cam = manifest.camera
    K = o3d.core.Tensor(cam.K, o3d.core.Dtype.Float64)
    images = [(o3d.t.geometry.Image(np.ascontiguousarray(rgb)), o3d.t.geometry.Image(_o3d_depth(d, depth_min_m)))
              for rgb, d in frames]
    T = np.eye(4)
    poses = np.tile(np.eye(4), (len(frames), 1, 1))
    n_lost = 0
    t0 = time.perf_counter()
    model = slam.Model(voxel_size_m, 16, O3D_MODEL_BLOCK_COUNT, o3d.core.Tensor(T), dev)
    inp = slam.Frame(cam.height, cam.width, K, dev)
    ray = slam.Frame(cam.height, cam.width, K, dev)
    for i, (colour, depth) in enumerate(images):
        inp.set_data_from_image("depth", depth)
        inp.set_data_from_image("color", colour)
        if i > 0:
            try:
                r = model.track_frame_to_model(inp, ray, O3D_DEPTH_SCALE, depth_max_m, O3D_MODEL_DISTANCE_THR_M)
                T = T @ r.transformation.numpy()
            except RuntimeError as exc:  # e.g. too few correspondences
                n_lost += 1
                logger.debug("open3d frame-to-model: frame %d not tracked: %s", i, exc)
        poses[i] = T
        model.update_frame_pose(i, o3d.core.Tensor(T))
        model.integrate(inp, O3D_DEPTH_SCALE, depth_max_m, O3D_MODEL_TRUNC_VOXELS)
        model.synthesize_model_frame(ray, O3D_DEPTH_SCALE, depth_min_m, depth_max_m, O3D_MODEL_TRUNC_VOXELS, False)
    dt = time.perf_counter() - t0
    out = grade(manifest, poses)
    out.update({"frames_per_s": (len(frames) - 1) / dt if len(frames) > 1 else float("nan"), "n_lost": n_lost})
    return out

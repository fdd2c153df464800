"""Localize every frame of a sequence against a Gaussian world (paper section 5.4, without ground truth).

Tracking is frame-to-model: each frame's depth points are registered by point-to-plane ICP against
the world's Gaussian centres, starting from the previous frame's estimate. Ground truth is never read while estimating; it is used afterwards to grade.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.config import LocalizationConfig
from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.geometry import pose_from_tq, tq_from_pose
from atlas_pipeline.io_utils import write_json_atomic
from atlas_pipeline.localization.icp import PointModel, estimate_normals, icp_point_to_plane, voxel_downsample
from atlas_pipeline.localization.metrics import ate_rmse, error_stats, pose_errors, write_tum_trajectory
from atlas_pipeline.perception.rgbd import backproject
from atlas_pipeline.progress import Progress
from atlas_pipeline.sensors.images import read_depth_m
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["LocalizationReport", "map_model", "localize_sequence"]

STATUS_ANCHOR = "anchor"
STATUS_TRACKED = "tracked"
STATUS_LOST = "lost"


def map_model(gaussians: GaussianField, voxel_size_m: float) -> PointModel:
    """Registration target from the Gaussian centres, normals from their neighbourhoods."""
    pts = gaussians.positions.astype(np.float64)
    return PointModel(pts, estimate_normals(pts, radius_m=3.0 * voxel_size_m, max_nn=30))


@dataclass
class LocalizationReport:
    """Per-frame pose estimates of a sequence against a world, graded against ground truth.

    Attributes:
        timestamps_s: ``[N]``.
        T_world_cam: ``[N, 4, 4]`` estimates.
        status: ``N`` strings: ``anchor`` (the start pose), ``tracked``, ``lost``.
        fitness: ``[N]`` share of frame points with a map neighbour.
        inlier_rmse_m: ``[N]`` point-to-plane RMS residual.
        time_s: ``[N]`` seconds spent per frame (reading excluded).
        T_world_cam_gt: ``[N, 4, 4]`` ground truth, NaN where unknown.
        error_t_m, error_rot_deg: ``[N]`` per-frame errors, NaN without ground truth.
        summary: aggregate figures (RMSE, ATE, counts, rate).
    """

    dataset: str
    map_id: str
    timestamps_s: np.ndarray
    T_world_cam: np.ndarray
    status: list[str]
    fitness: np.ndarray
    inlier_rmse_m: np.ndarray
    time_s: np.ndarray
    T_world_cam_gt: np.ndarray
    error_t_m: np.ndarray
    error_rot_deg: np.ndarray
    summary: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.timestamps_s)

    def to_json(self) -> dict:
        t, q = tq_from_pose(self.T_world_cam)
        has_gt = np.isfinite(self.T_world_cam_gt).all(axis=(1, 2))

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        frames = []
        for i in range(self.n_frames):
            frames.append({
                "frame_id": i, "timestamp_s": float(self.timestamps_s[i]), "status": self.status[i],
                "position_xyz": [float(v) for v in t[i]], "quat_xyzw": [float(v) for v in q[i]],
                "fitness": num(self.fitness[i]), "inlier_rmse_m": num(self.inlier_rmse_m[i]),
                "time_s": num(self.time_s[i]), "has_ground_truth": bool(has_gt[i]),
                "error_t_m": num(self.error_t_m[i]), "error_rot_deg": num(self.error_rot_deg[i]),
            })
        return {"dataset": self.dataset, "map_id": self.map_id,
                "summary": {k: (num(v) if isinstance(v, float) else v) for k, v in self.summary.items()},
                "frames": frames}

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        js = write_json_atomic(directory / "localization.json", self.to_json())
        est = write_tum_trajectory(directory / "trajectory_estimated.tum", self.timestamps_s, self.T_world_cam)
        gt = write_tum_trajectory(directory / "trajectory_groundtruth.tum", self.timestamps_s, self.T_world_cam_gt)
        return [js, est, gt]

    @classmethod
    def load(cls, directory: Path) -> "LocalizationReport":
        path = directory / "localization.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: localization.json missing")
        d = json.loads(path.read_text())
        fr = d["frames"]
        T = pose_from_tq(np.array([f["position_xyz"] for f in fr]), np.array([f["quat_xyzw"] for f in fr]))
        gt_path = directory / "trajectory_groundtruth.tum"
        T_gt = np.full((len(fr), 4, 4), np.nan)
        if gt_path.is_file():
            rows = np.loadtxt(gt_path, comments="#", ndmin=2)
            if len(rows):
                ts = np.array([f["timestamp_s"] for f in fr])
                for r in rows:
                    k = int(np.argmin(np.abs(ts - r[0])))
                    T_gt[k] = pose_from_tq(r[1:4], r[4:8])

        def arr(key: str) -> np.ndarray:
            return np.array([np.nan if f[key] is None else f[key] for f in fr], dtype=np.float64)

        return cls(d["dataset"], d["map_id"], np.array([f["timestamp_s"] for f in fr]), T,
                   [f["status"] for f in fr], arr("fitness"), arr("inlier_rmse_m"), arr("time_s"), T_gt,
                   arr("error_t_m"), arr("error_rot_deg"), d.get("summary", {}))

    def pose_source_poses(self, source: str) -> np.ndarray:
        """``estimated`` or ``ground_truth`` poses ``[N, 4, 4]``."""
        return self.T_world_cam if source == "estimated" else self.T_world_cam_gt


def localize_sequence(
    manifest: FrameManifest,
    gaussians: GaussianField,
    voxel_size_m: float,
    cfg: LocalizationConfig,
    T_world_cam_start: np.ndarray,
    anchor_index: int = 0,
    map_id: str = "",
    depth_range_m: tuple[float, float] = (0.1, 4.0),
    log: Callable[[str], None] | None = None,
) -> LocalizationReport:
    """Track every frame of ``manifest`` against ``gaussians``.

    Args:
        T_world_cam_start: ``[4, 4]`` pose of frame ``anchor_index`` in the world, i.e. where this
            session starts (for a world built from this sequence, the first keyframe's mapping
            pose). Every other pose is estimated from the depth images and the map only.
        anchor_index: the frame whose pose is given.
        depth_range_m: depth readings used, ``(min, max)``; the fusion settings of the world.
    """
    model = map_model(gaussians, voxel_size_m)
    n = manifest.n_frames
    if not 0 <= anchor_index < n:
        raise ValueError(f"anchor_index {anchor_index} outside 0..{n - 1}")
    T_est = np.full((n, 4, 4), np.nan)
    fitness = np.full(n, np.nan)
    rmse = np.full(n, np.nan)
    times = np.full(n, np.nan)
    status: list[str] = [""] * n
    progress = Progress("localizing", n, log)
    down_m = max(voxel_size_m / 2.0, 0.005)
    # Forward from the anchor, then backward for frames before it (a sequence whose first frames
    # precede the map's first keyframe).
    order = [list(range(anchor_index, n)), list(range(anchor_index - 1, -1, -1))]
    for pass_idx, frames in enumerate(order):
        prev_i = anchor_index
        for i in frames:
            depth = read_depth_m(manifest.depth_path(i), manifest.camera, allow_empty=True)
            t0 = time.perf_counter()
            pts, _ = backproject(depth, None, manifest.camera, cfg.stride, *depth_range_m)
            pts = voxel_downsample(pts.astype(np.float64), down_m)
            if i == anchor_index and pass_idx == 0:
                T_est[i] = T_world_cam_start
                if len(pts) >= 10:
                    res = icp_point_to_plane(model, pts, T_world_cam_start, cfg.icp_max_correspondence_m,
                                             cfg.icp_iterations, levels=(1.0,))
                    fitness[i], rmse[i] = res.fitness, res.inlier_rmse_m
                status[i] = STATUS_ANCHOR
            else:
                # Initial guess: the previous estimate. A constant-velocity guess built from two
                # noisy estimates fed back into divergence on TUM teddy (measured), so it is not used.
                guess = T_est[prev_i]
                res = None
                if len(pts) >= 10:
                    res = icp_point_to_plane(model, pts, guess, cfg.icp_max_correspondence_m, cfg.icp_iterations)
                    fitness[i], rmse[i] = res.fitness, res.inlier_rmse_m
                if res is not None and res.fitness >= cfg.min_fitness:
                    T_est[i] = res.T
                    status[i] = STATUS_TRACKED
                else:
                    # No depth or poor overlap: keep the prediction rather than a bad alignment.
                    T_est[i] = guess
                    status[i] = STATUS_LOST
            times[i] = time.perf_counter() - t0
            prev_i = i
            progress.update()

    has_gt = manifest.has_gt.copy()
    err_t = np.full(n, np.nan)
    err_r = np.full(n, np.nan)
    if has_gt.any():
        err_t[has_gt], err_r[has_gt] = pose_errors(T_est[has_gt], manifest.T_world_cam_gt[has_gt])
    graded = has_gt.copy()
    graded[anchor_index] = False  # the anchor frame is given, not estimated
    summary: dict = {
        "n_frames": n,
        "n_tracked": status.count(STATUS_TRACKED),
        "n_lost": status.count(STATUS_LOST),
        "n_graded": int(graded.sum()),
        "anchor_index": int(anchor_index),
        "mean_time_per_frame_s": float(np.nanmean(np.delete(times, anchor_index))) if n > 1 else float("nan"),
    }
    summary["frames_per_s"] = 1.0 / summary["mean_time_per_frame_s"] if summary["mean_time_per_frame_s"] > 0 else float("nan")
    if graded.sum() >= 1:
        st = error_stats(err_t[graded])
        summary.update({"rmse_t_m": st["rmse"], "mean_t_m": st["mean"], "median_t_m": st["median"],
                        "max_t_m": st["max"], "rmse_rot_deg": error_stats(err_r[graded])["rmse"]})
    if graded.sum() >= 3:
        summary["ate_rmse_m"] = ate_rmse(T_est[graded, :3, 3], manifest.T_world_cam_gt[graded, :3, 3])
    logger.info("localized %s: %s", manifest.dataset, {k: round(v, 4) if isinstance(v, float) else v for k, v in summary.items()})
    if status.count(STATUS_LOST) == n - 1 and n > 1:
        logger.warning("%s: every frame after the first was lost; check the world and the dataset match", manifest.dataset)
    return LocalizationReport(manifest.dataset, map_id, manifest.timestamps_s.copy(), T_est, status,
                              fitness, rmse, times, manifest.T_world_cam_gt.copy(), err_t, err_r, summary)

"""Trajectory error metrics and the TUM trajectory text format.

Names follow evo: ``positions_xyz`` ``[N, 3]``, ``poses_se3`` ``[N, 4, 4]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from atlas_pipeline.geometry import invert_se3, rotation_angle_rad, tq_from_pose, umeyama_alignment
from atlas_pipeline.io_utils import write_text_atomic

__all__ = ["pose_errors", "ate_rmse", "write_tum_trajectory", "error_stats"]


def pose_errors(poses_est: np.ndarray, poses_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation error (m) and rotation error (deg), no alignment: ``([N], [N])``."""
    d = invert_se3(poses_gt) @ poses_est
    return np.linalg.norm(poses_est[:, :3, 3] - poses_gt[:, :3, 3], axis=1), np.degrees(rotation_angle_rad(d[:, :3, :3]))


def ate_rmse(positions_est: np.ndarray, positions_gt: np.ndarray, align: bool = True) -> float:
    """Absolute trajectory error: RMSE of positions after a rigid (SE(3)) Umeyama alignment.

    Args:
        positions_est, positions_gt: ``[N, 3]`` matched positions.
        align: align ``est`` onto ``gt`` first (TUM's ``evaluate_ate``); off gives the raw RMSE.
    """
    est = np.asarray(positions_est, np.float64)
    gt = np.asarray(positions_gt, np.float64)
    if align and len(est) >= 3:
        R, t, _ = umeyama_alignment(est, gt, with_scale=False)
        est = est @ R.T + t
    return float(np.sqrt(np.mean(np.sum((est - gt) ** 2, axis=1))))


def error_stats(errors: np.ndarray) -> dict[str, float]:
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return {"rmse": float("nan"), "mean": float("nan"), "median": float("nan"), "max": float("nan")}
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(e.mean()),
            "median": float(np.median(e)), "max": float(e.max())}


def write_tum_trajectory(path: Path, timestamps_s: np.ndarray, poses_se3: np.ndarray) -> Path:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (TUM format, readable by evo); NaN poses skipped."""
    ok = np.isfinite(poses_se3).all(axis=(1, 2))
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    if ok.any():
        t, q = tq_from_pose(poses_se3[ok])
        for ts, ti, qi in zip(np.asarray(timestamps_s)[ok], t, q):
            lines.append(f"{ts:.6f} " + " ".join(f"{v:.9f}" for v in (*ti, *qi)))
    return write_text_atomic(path, "\n".join(lines) + "\n")

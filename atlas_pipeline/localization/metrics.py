"""Trajectory error metrics and the TUM trajectory text format.

Names follow evo: ``positions_xyz`` ``[N, 3]``, ``poses_se3`` ``[N, 4, 4]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.geometry import invert_se3, pose_from_tq, rotation_angle_rad, tq_from_pose, umeyama_alignment
from atlas_pipeline.io_utils import write_text_atomic

__all__ = ["pose_errors", "ate_rmse", "write_tum_trajectory", "read_tum_trajectory", "error_stats",
           "align_rigid", "ate", "rpe", "match_trajectories", "evaluate_trajectories"]

TUM_MAX_DT_S = 0.02  # TUM's associate.py / evaluate_ate.py default


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


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``timestamp tx ty tz qx qy qz qw`` lines: ``(timestamps_s [N], poses_se3 [N, 4, 4])``.

    Comment lines (``#``) and blank lines are skipped; commas are accepted as separators (TUM's
    tools do the same). A path that is no regular file (a directory, a FIFO: never opened), a line
    that is malformed, not UTF-8 or endless, and timestamps that cannot be seconds (nanoseconds,
    microseconds, milliseconds: ``tum.check_timestamps_are_seconds``) raise :class:`DatasetError`
    naming the file (and line).
    """
    from atlas_pipeline.sensors.tum import _iter_lines, check_timestamps_are_seconds, file_problem

    path = Path(path)
    problem = file_problem(path)
    if problem is not None:
        raise DatasetError(path, f"trajectory file {problem}")
    rows, tq = [], []
    for lineno, line in _iter_lines(path):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(path, f"expected 8 values (timestamp tx ty tz qx qy qz qw), got {len(parts)}", lineno)
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise DatasetError(path, "non-numeric value", lineno) from None
        if not np.all(np.isfinite(vals)) or np.linalg.norm(vals[4:]) < 1e-9:
            raise DatasetError(path, "non-finite value or zero quaternion", lineno)
        rows.append((lineno, parts))
        tq.append(vals)
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    tq_a = np.asarray(tq)
    order = np.argsort(tq_a[:, 0], kind="stable")
    check_timestamps_are_seconds(path, [rows[i] for i in order], tq_a[order, 0])
    return tq_a[order, 0], pose_from_tq(tq_a[order, 1:4], tq_a[order, 4:])


def match_trajectories(ts_est: np.ndarray, poses_est: np.ndarray, ts_gt: np.ndarray, poses_gt: np.ndarray,
                       max_dt_s: float = TUM_MAX_DT_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of estimated and ground-truth poses whose timestamps differ by at most ``max_dt_s``
    (TUM's greedy one-to-one association); non-finite poses are dropped first.

    Returns ``(timestamps_s [M], est [M, 4, 4], gt [M, 4, 4])`` sorted by time.
    """
    from atlas_pipeline.sensors.tum import associate

    ke = np.flatnonzero(np.isfinite(poses_est).all(axis=(1, 2)))
    kg = np.flatnonzero(np.isfinite(poses_gt).all(axis=(1, 2)))
    pairs = associate(np.asarray(ts_est)[ke], np.asarray(ts_gt)[kg], max_dt_s)
    ie = np.array([ke[a] for a, _ in pairs], dtype=np.int64)
    ig = np.array([kg[b] for _, b in pairs], dtype=np.int64)
    return np.asarray(ts_est)[ie], np.asarray(poses_est)[ie], np.asarray(poses_gt)[ig]


def align_rigid(poses_est: np.ndarray, poses_gt: np.ndarray) -> np.ndarray:
    """``[4, 4]`` rigid transform S (Umeyama on positions, no scale) with ``S @ est ≈ gt``."""
    R, t, _ = umeyama_alignment(poses_est[:, :3, 3], poses_gt[:, :3, 3], with_scale=False)
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = R, t
    return S


# The alignment is fitted to positions, so its rotation about the path's own direction is fixed
# only by how far the positions lie off that line: about sqrt(3 / (n (s2^2 + s3^2))) * rmse radians
# for n positions spread s2, s3 across the path. On a near-straight path that is degrees or tens of
# degrees, and the rotation error after the alignment measures the alignment, not the tracking:
# beyond this bound it is not reported (NaN, with the reason in rot_note).
ALIGNMENT_MAX_ROT_UNCERTAINTY_DEG = 3.0


def alignment_rot_uncertainty_deg(positions_gt: np.ndarray, rmse_m: float) -> float:
    """How far (degrees) a rigid alignment fitted to ``positions_gt`` ``[M, 3]`` with residual
    ``rmse_m`` may be turned about the path's main direction (inf when the path is a line)."""
    xs = np.asarray(positions_gt, np.float64)
    xs = xs - xs.mean(axis=0)
    spread = np.linalg.svd(xs, compute_uv=False) / np.sqrt(len(xs))  # std along the principal axes
    across = float(np.hypot(spread[1], spread[2])) if len(spread) >= 3 else 0.0
    if across <= 0:
        return float("inf")
    return float(np.degrees(rmse_m / (np.sqrt(len(xs)) * across)))


def ate(poses_est: np.ndarray, poses_gt: np.ndarray, align: bool = True) -> dict:
    """Absolute trajectory error of matched poses ``[M, 4, 4]`` (TUM ``evaluate_ate``, evo ``ape``
    with the translation part): positions compared after a rigid alignment of est onto gt.

    Returns ``{"rmse_m", "mean_m", "median_m", "max_m", "rot_rmse_deg", "rot_note", "errors_t_m" [M],
    "errors_rot_deg" [M], "alignment" [4, 4], "alignment_rot_uncertainty_deg", "n"}``. The rotation
    figures are NaN, and ``rot_note`` says why, when the alignment's rotation is ill-posed (a
    near-straight path, :data:`ALIGNMENT_MAX_ROT_UNCERTAINTY_DEG`); ``rot_note`` is None otherwise.
    """
    est = np.asarray(poses_est, np.float64)
    gt = np.asarray(poses_gt, np.float64)
    aligning = align and len(est) >= 3
    S = align_rigid(est, gt) if aligning else np.eye(4)
    aligned = S @ est
    e_t, e_r = pose_errors(aligned, gt)
    st = error_stats(e_t)
    uncertainty = alignment_rot_uncertainty_deg(gt[:, :3, 3], st["rmse"]) if aligning else 0.0
    note = None
    if uncertainty > ALIGNMENT_MAX_ROT_UNCERTAINTY_DEG:
        by = (f"about {uncertainty:.3g} degrees" if uncertainty < 180 else  # no angle is more uncertain than 180
              "any angle (the positions do not fix it)")
        note = (f"not reported: the path is near straight, so the alignment's rotation about it is uncertain by "
                f"{by} (more than {ALIGNMENT_MAX_ROT_UNCERTAINTY_DEG:g} degrees); the unaligned rotation error "
                "(rmse_rot_unaligned_deg) is meaningful when the world shares the ground truth's frame")
        e_r = np.full_like(e_r, np.nan)
    return {"rmse_m": st["rmse"], "mean_m": st["mean"], "median_m": st["median"], "max_m": st["max"],
            "rot_rmse_deg": float("nan") if note else error_stats(e_r)["rmse"], "rot_note": note,
            "errors_t_m": e_t, "errors_rot_deg": e_r, "alignment": S,
            "alignment_rot_uncertainty_deg": uncertainty, "n": int(len(est))}


def rpe(timestamps_s: np.ndarray, poses_est: np.ndarray, poses_gt: np.ndarray, delta: float = 1.0,
        unit: str = "s") -> dict:
    """Relative pose error over a fixed interval (TUM ``evaluate_rpe`` with ``fixed_delta``).

    For each matched pose ``i``, ``j`` is the pose ``delta`` later (``unit="s"``: the one whose
    timestamp is closest to ``t_i + delta``, until that is the last pose, as TUM's script does;
    ``unit="frames"``: ``i + delta``, as evo's ``rpe``).
    Error ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)``; translational RMSE in metres (per ``delta``), and
    rotational RMSE in degrees. No alignment is needed: relative motions are frame-independent.
    """
    ts = np.asarray(timestamps_s, np.float64)
    P = np.asarray(poses_est, np.float64)
    G = np.asarray(poses_gt, np.float64)
    n = len(ts)
    pairs = []
    if unit == "frames":
        d = int(delta)
        if d < 1:
            raise ValueError("delta in frames must be >= 1")
        pairs = [(i, i + d) for i in range(n - d)]
    elif unit == "s":
        # TUM's evaluate_rpe (fixed delta): j is the pose closest in time to t_i + delta, and the
        # pairing stops once that is the last pose (the interval no longer fits in the sequence).
        for i in range(n):
            j = int(np.argmin(np.abs(ts - (ts[i] + delta))))
            if j == n - 1:
                break
            if j > i:
                pairs.append((i, j))
    else:
        raise ValueError(f"unit must be 's' or 'frames', got {unit!r}")
    if not pairs:
        return {"trans_rmse_m": float("nan"), "rot_rmse_deg": float("nan"), "n_pairs": 0,
                "delta": delta, "unit": unit}
    a = np.array([p[0] for p in pairs])
    b = np.array([p[1] for p in pairs])
    E = invert_se3(invert_se3(G[a]) @ G[b]) @ (invert_se3(P[a]) @ P[b])
    et = np.linalg.norm(E[:, :3, 3], axis=1)
    er = np.degrees(rotation_angle_rad(E[:, :3, :3]))
    return {"trans_rmse_m": float(np.sqrt(np.mean(et**2))), "trans_mean_m": float(et.mean()),
            "rot_rmse_deg": float(np.sqrt(np.mean(er**2))), "n_pairs": int(len(pairs)),
            "delta": delta, "unit": unit}


def evaluate_trajectories(ts_est: np.ndarray, poses_est: np.ndarray, ts_gt: np.ndarray, poses_gt: np.ndarray,
                          max_dt_s: float = TUM_MAX_DT_S, rpe_delta_s: float = 1.0) -> dict:
    """ATE and RPE (per ``rpe_delta_s`` seconds) of an estimated trajectory against ground truth,
    with TUM's conventions; figures only (no per-frame arrays)."""
    t, est, gt = match_trajectories(ts_est, poses_est, ts_gt, poses_gt, max_dt_s)
    out: dict = {"n_matched": int(len(t)), "n_estimated": int(np.isfinite(poses_est).all(axis=(1, 2)).sum())}
    if len(t) >= 3:
        a = ate(est, gt)
        out.update({"ate_rmse_m": a["rmse_m"], "ate_mean_m": a["mean_m"], "ate_median_m": a["median_m"],
                    "ate_max_m": a["max_m"], "ate_rot_rmse_deg": a["rot_rmse_deg"]})
        if a["rot_note"]:
            out["ate_rot_note"] = a["rot_note"]
        out["rmse_rot_unaligned_deg"] = error_stats(pose_errors(est, gt)[1])["rmse"]  # the note's fallback
        r = rpe(t, est, gt, rpe_delta_s, "s")
        out.update({"rpe_trans_rmse_m": r["trans_rmse_m"], "rpe_rot_rmse_deg": r["rot_rmse_deg"],
                    "rpe_n_pairs": r["n_pairs"], "rpe_delta_s": rpe_delta_s})
    return out

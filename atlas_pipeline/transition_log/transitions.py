"""State-action-state transitions (paper section 4.4) as a typed Parquet table.

One row per consecutive frame pair ``(t, t+1)``. The state is the camera pose in the world plus the
map it lives in; the action is the base velocity that moves state ``t`` to ``t+1`` (the paper's
v1 semantics), expressed in the camera frame of the state before (a body-frame twist, as a robot
base would command it): linear in m/s, angular in rad/s.

Rows are never dropped, but a row is only ``valid`` when both poses are real estimates that follow
each other: ``valid_reason`` says why not. An unknown quantity is NaN, never 0: the pose of a
``lost`` frame is only a prediction, so its pose columns are NaN, and the action and delta of every
invalid row are NaN.

Every column is a flat number or string, so ``pandas.read_parquet`` gives typed columns and no
JSON in cells. Units are in the column names.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from atlas_pipeline.config import TransitionsConfig
from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.geometry import invert_se3, so3_log, tq_from_pose
from atlas_pipeline.io_utils import atomic_path
from atlas_pipeline.localization.sequence import (
    STATUS_ANCHOR,
    STATUS_LOST,
    STATUS_NOT_ATTEMPTED,
    STATUS_RELOCALIZED,
    STATUS_TRACKED,
)

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.localization.localizer import LocalizationReport

__all__ = ["TRANSITIONS_SCHEMA", "VALID_REASONS", "REASON_OK", "STATUS_UNKNOWN", "build_transitions",
           "log_transitions", "write_transitions", "read_transitions"]

_POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]

POSE_SOURCES = ("estimated", "ground_truth")
STATUS_UNKNOWN = "unknown"  # ground-truth poses have no tracking status
_TRACKING_STATUSES = (STATUS_ANCHOR, STATUS_TRACKED, STATUS_RELOCALIZED, STATUS_LOST, STATUS_NOT_ATTEMPTED)

REASON_OK = "ok"
DEFAULT_MAX_GAP_S = TransitionsConfig().max_gap_s  # transitions.max_gap_s of the default profile
REASON_SEPARATOR = ";"
# Why a row is not valid, in the order they are listed in ``valid_reason`` (each is independent).
VALID_REASONS = {
    "before_lost": "the frame before is lost: its pose is only a prediction (pose columns NaN)",
    "after_lost": "the frame after is lost: its pose is only a prediction (pose columns NaN)",
    "no_depth": ("a frame of the pair has a depth image with no valid pixel (a sensor covered, too close, "
                 "facing a window): it was not tracked, so it is lost"),
    "after_relocalized": "the frame after was relocalized: a jump, not a motion from the frame before",
    "before_relocalized": ("the frame before precedes the anchor (tracked backwards from it) and was "
                           "relocalized: a jump, not a motion from the frame after"),
    "before_pose_unknown": "the pose before is unknown: not finite, or the frame was never processed (not_attempted)",
    "after_pose_unknown": "the pose after is unknown: not finite, or the frame was never processed (not_attempted)",
    "dt_not_positive": "dt_s <= 0 or not finite: no velocity can be derived",
    "gap": ("dt_s is longer than transitions.max_gap_s: the frames do not follow each other (frames missing "
            "in between, a paused recording), and a velocity averaged over the gap is no action; the row ends "
            "a run of transitions"),
}


def _reasons_doc() -> bytes:
    return "".join(f"\n{k}: {v}" for k, v in VALID_REASONS.items()).encode()  # one reason a line


TRANSITIONS_SCHEMA = pa.schema(
    [
        pa.field("partition", pa.string()),
        pa.field("map_id", pa.string()),
        pa.field("step", pa.int64()),
        pa.field("frame_id_before", pa.int64()),
        pa.field("frame_id_after", pa.int64()),
        pa.field("timestamp_before_s", pa.float64()),
        pa.field("timestamp_after_s", pa.float64()),
        pa.field("dt_s", pa.float64()),
        pa.field("pose_source", pa.string()),
        pa.field("status_before", pa.string()),
        pa.field("status_after", pa.string()),
        pa.field("valid", pa.bool_()),
        pa.field("valid_reason", pa.string()),
        *[pa.field(f"before_{c}", pa.float64()) for c in _POSE],
        *[pa.field(f"after_{c}", pa.float64()) for c in _POSE],
        *[pa.field(f"action_v{a}_mps", pa.float64()) for a in "xyz"],
        *[pa.field(f"action_w{a}_radps", pa.float64()) for a in "xyz"],
        *[pa.field(f"delta_{a}_m", pa.float64()) for a in "xyz"],
        *[pa.field(f"delta_q{a}", pa.float64()) for a in "xyzw"],
        pa.field("delta_translation_m", pa.float64()),
        pa.field("delta_rotation_deg", pa.float64()),
        pa.field("n_gaussians", pa.int64()),
    ],
    metadata={
        b"description": b"Atlas-GS state-action-state transitions, one row per consecutive frame pair",
        b"pose_frame": b"before_*/after_*: camera-to-world pose (T_world_cam), quaternion x y z w; "
                       b"NaN where the pose is unknown or the frame is lost (its pose is only a prediction)",
        b"action_frame": b"action_*: body-frame twist of the camera in the frame of state_before; NaN unless valid",
        b"delta_frame": b"delta_*: relative pose T_before^-1 T_after; NaN unless valid",
        b"status": ("status_before/after: tracking status of the frame (" + ", ".join(_TRACKING_STATUSES)
                    + f"); {STATUS_UNKNOWN} for pose_source ground_truth").encode(),
        b"valid": b"true when both poses are finite estimates that follow each other and 0 < dt_s <= max_gap_s; "
                  b"only valid rows carry an action and a delta",
        b"valid_reason": (f"'{REASON_OK}' or the reasons the row is not valid, joined by '{REASON_SEPARATOR}':"
                          ).encode() + _reasons_doc(),
    },
)


def _reason_strings(flags: dict[str, np.ndarray], n_rows: int) -> list[str]:
    """Per row: ``ok`` or the names of the raised flags, joined in :data:`VALID_REASONS` order."""
    names = [k for k in VALID_REASONS if k in flags]
    return [REASON_SEPARATOR.join(k for k in names if flags[k][r]) or REASON_OK for r in range(n_rows)]


def build_transitions(
    partition: str,
    map_id: str,
    n_gaussians: int,
    timestamps_s: np.ndarray,
    poses_se3: np.ndarray,
    pose_source: str,
    status: list[str] | None = None,
    anchor_index: int = 0,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    no_depth: list[int] | None = None,
) -> pa.Table:
    """Transitions table from a trajectory.

    Args:
        timestamps_s: ``[N]`` frame times.
        poses_se3: ``[N, 4, 4]`` T_world_cam (NaN where a pose is unknown).
        pose_source: ``estimated`` or ``ground_truth``.
        status: ``N`` tracking statuses (``anchor``, ``tracked``, ``relocalized``, ``lost``,
            ``not_attempted``) of an estimated trajectory; None: unknown. Ground-truth poses take
            none (they were not tracked).
        anchor_index: the frame tracking started from; frames before it were tracked backwards, so
            for them the jump of a relocalization lies between a frame and the one after it.
        max_gap_s: frames further apart (``dt_s``) do not follow each other (``transitions.max_gap_s``).
        no_depth: frames whose depth image had no valid pixel (lost for that reason: ``no_depth``).

    Returns:
        A table with :data:`TRANSITIONS_SCHEMA`, ``N - 1`` rows. ``valid`` is False (and
        ``valid_reason`` says why) when either frame is lost, the frame tracked second was
        relocalized, either pose is not finite, ``dt_s`` is not > 0 or exceeds ``max_gap_s``
        (reason ``gap``: the row ends a run of transitions); the action and delta
        columns of such a row are NaN, as are the pose columns of a lost frame.
    """
    ts = np.asarray(timestamps_s, np.float64)
    T = np.asarray(poses_se3, np.float64)
    n = len(ts)
    if T.shape != (n, 4, 4):
        raise ValueError(f"poses_se3 has shape {T.shape}, expected ({n}, 4, 4)")
    if n < 2:
        raise ValueError("need at least 2 frames for a transition")
    if not 0 <= anchor_index < n:
        raise ValueError(f"anchor_index {anchor_index} outside 0..{n - 1}")
    if not (np.isfinite(max_gap_s) and max_gap_s > 0):
        raise ValueError(f"max_gap_s must be a finite number > 0, got {max_gap_s!r}")
    if pose_source not in POSE_SOURCES:
        raise ValueError(f"pose_source must be one of {list(POSE_SOURCES)}, got {pose_source!r}")
    if status is not None and pose_source == "ground_truth":
        raise ValueError("ground-truth poses have no tracking status: pass status=None")
    if status is None:
        status = [STATUS_UNKNOWN] * n
    elif len(status) != n:
        raise ValueError(f"status has {len(status)} entries for {n} frames")
    else:
        odd = sorted({s for s in status if s not in _TRACKING_STATUSES})
        if odd:
            raise ValueError(f"unknown tracking status(es) {odd}; expected {list(_TRACKING_STATUSES)}")
    st = np.asarray(status, dtype=object)

    # [N] a pose exists: finite, and from a frame that was processed at all
    finite = np.isfinite(T).all(axis=(1, 2)) & (st != STATUS_NOT_ATTEMPTED)
    lost = st == STATUS_LOST  # [N]
    empty = np.zeros(n, bool)  # [N] no depth pixel at all
    empty[[i for i in (no_depth or []) if 0 <= i < n]] = True
    relocalized = st == STATUS_RELOCALIZED  # [N]
    known = finite & ~lost  # [N] a pose worth reporting: a lost frame's pose is a guess
    dt = np.diff(ts)  # [N-1]
    backward = np.arange(n - 1) < anchor_index  # [N-1] pair (i, i+1) tracked from i+1 to i
    flags = {
        "before_lost": lost[:-1],
        "after_lost": lost[1:],
        "no_depth": empty[:-1] | empty[1:],
        "after_relocalized": relocalized[1:] & ~backward,
        "before_relocalized": relocalized[:-1] & backward,
        "before_pose_unknown": ~finite[:-1],
        "after_pose_unknown": ~finite[1:],
        "dt_not_positive": ~(np.isfinite(dt) & (dt > 0)),
        "gap": np.isfinite(dt) & (dt > max_gap_s),
    }
    valid = ~np.logical_or.reduce(list(flags.values()))  # [N-1]

    T_safe = np.where(finite[:, None, None], T, np.eye(4))  # keep the math finite; unknowns are NaN-ed below
    t, q = tq_from_pose(T_safe)
    rel = invert_se3(T_safe[:-1]) @ T_safe[1:]  # [N-1, 4, 4] T_before^-1 T_after
    dt_safe = np.where(valid, dt, 1.0)  # avoids 0-division warnings; invalid rows are NaN-ed below
    omega = so3_log(rel[:, :3, :3])  # [N-1, 3] rad
    v = rel[:, :3, 3] / dt_safe[:, None]
    w = omega / dt_safe[:, None]
    dtq_t, dtq_q = tq_from_pose(rel)

    def masked(a: np.ndarray, m: np.ndarray) -> np.ndarray:
        a = a.astype(np.float64).copy()
        a[~m] = np.nan
        return a

    cols: dict[str, object] = {
        "partition": [partition] * (n - 1),
        "map_id": [map_id] * (n - 1),
        "step": np.arange(n - 1, dtype=np.int64),
        "frame_id_before": np.arange(n - 1, dtype=np.int64),
        "frame_id_after": np.arange(1, n, dtype=np.int64),
        "timestamp_before_s": ts[:-1],
        "timestamp_after_s": ts[1:],
        "dt_s": dt,  # as recorded, even when not > 0 (the row is then invalid)
        "pose_source": [pose_source] * (n - 1),
        "status_before": list(status[:-1]),
        "status_after": list(status[1:]),
        "valid": valid,
        "valid_reason": _reason_strings(flags, n - 1),
    }
    for prefix, sl, m in (("before", slice(0, n - 1), known[:-1]), ("after", slice(1, n), known[1:])):
        for k, c in enumerate(_POSE):
            src = t[sl, k] if k < 3 else q[sl, k - 3]
            cols[f"{prefix}_{c}"] = masked(src, m)
    for k, a in enumerate("xyz"):
        cols[f"action_v{a}_mps"] = masked(v[:, k], valid)
    for k, a in enumerate("xyz"):
        cols[f"action_w{a}_radps"] = masked(w[:, k], valid)
    for k, a in enumerate("xyz"):
        cols[f"delta_{a}_m"] = masked(dtq_t[:, k], valid)
    for k, a in enumerate("xyzw"):
        cols[f"delta_q{a}"] = masked(dtq_q[:, k], valid)
    cols["delta_translation_m"] = masked(np.linalg.norm(rel[:, :3, 3], axis=1), valid)
    cols["delta_rotation_deg"] = masked(np.degrees(np.linalg.norm(omega, axis=1)), valid)
    cols["n_gaussians"] = np.full(n - 1, n_gaussians, dtype=np.int64)
    return pa.table(cols, schema=TRANSITIONS_SCHEMA)


def write_transitions(table: pa.Table, path: Path) -> Path:
    """Write ``table`` to ``path`` as Parquet (atomically), checking its schema first."""
    if not table.schema.equals(TRANSITIONS_SCHEMA, check_metadata=False):
        raise ValueError("transitions table does not have the Atlas-GS transitions schema")
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path


def read_transitions(path: Path) -> pd.DataFrame:
    """Read a transitions Parquet file into a DataFrame, checking the schema."""
    if not Path(path).is_file():
        raise ArtifactError(f"{path}: transitions file not found")
    table = pq.read_table(path)
    missing = set(TRANSITIONS_SCHEMA.names) - set(table.schema.names)
    if missing:
        raise ArtifactError(f"{path}: not an Atlas-GS transitions table, missing columns {sorted(missing)}")
    return table.to_pandas()


def log_transitions(report: LocalizationReport, partition: str, n_gaussians: int,
                    cfg: PipelineConfig) -> pa.Table:
    """The transitions stage: transitions from the estimated (default) or ground-truth trajectory
    of ``report`` (``transitions.pose_source``).

    Estimated rows carry the tracking status of their frames (which decides ``valid``: lost frames
    and relocalization jumps are not motions); ground-truth rows have none (status ``unknown``,
    validity from pose finiteness and time only).
    """
    source, max_gap_s = cfg.transitions.pose_source, cfg.transitions.max_gap_s
    poses = report.pose_source_poses(source)  # [N, 4, 4] T_world_cam
    if source == "ground_truth" and not np.isfinite(poses).all(axis=(1, 2)).any():
        raise DatasetError(partition, "transitions.pose_source is ground_truth but the dataset has no ground truth")
    if source == "estimated":
        # Frames before the anchor were tracked backwards from it (see localize_sequence).
        return build_transitions(partition, report.map_id, n_gaussians, report.timestamps_s, poses, source,
                                 list(report.status), int(report.summary.get("anchor_index", 0)), max_gap_s,
                                 no_depth=list(report.summary.get("no_depth_frames") or []))
    return build_transitions(partition, report.map_id, n_gaussians, report.timestamps_s, poses, source,
                             max_gap_s=max_gap_s)

"""State-action-state transitions (paper section 4.4) as a typed Parquet table.

One row per consecutive frame pair ``(t, t+1)``. The state is the camera pose in the world plus the
map it lives in; the action is the base velocity that moves state ``t`` to ``t+1`` (the paper's
v1 semantics), expressed in the camera frame of the state before (a body-frame twist, as a robot
base would command it): linear in m/s, angular in rad/s.

Every column is a flat number or string, so ``pandas.read_parquet`` gives typed columns and no
JSON in cells. Units are in the column names.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.geometry import invert_se3, so3_log, tq_from_pose
from atlas_pipeline.io_utils import atomic_path

__all__ = ["TRANSITIONS_SCHEMA", "build_transitions", "write_transitions", "read_transitions"]

_POSE = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]

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
        b"pose_frame": b"before_*/after_*: camera-to-world pose (T_world_cam), quaternion x y z w",
        b"action_frame": b"action_*: body-frame twist of the camera in the frame of state_before",
        b"delta_frame": b"delta_*: relative pose T_before^-1 T_after",
    },
)


def build_transitions(
    partition: str,
    map_id: str,
    n_gaussians: int,
    timestamps_s: np.ndarray,
    poses_se3: np.ndarray,
    pose_source: str,
    status: list[str] | None = None,
) -> pa.Table:
    """Transitions table from a trajectory.

    Args:
        timestamps_s: ``[N]`` frame times.
        poses_se3: ``[N, 4, 4]`` T_world_cam (NaN rows where a pose is unknown: the rows that
            touch them get ``valid = False`` and NaN numbers).
        pose_source: ``estimated`` or ``ground_truth``.
        status: per-frame tracking status, or None.

    Returns:
        A table with :data:`TRANSITIONS_SCHEMA`, ``N - 1`` rows.
    """
    ts = np.asarray(timestamps_s, np.float64)
    T = np.asarray(poses_se3, np.float64)
    n = len(ts)
    if T.shape != (n, 4, 4):
        raise ValueError(f"poses_se3 has shape {T.shape}, expected ({n}, 4, 4)")
    if n < 2:
        raise ValueError("need at least 2 frames for a transition")
    status = status or ["unknown"] * n
    ok = np.isfinite(T).all(axis=(1, 2))
    valid = ok[:-1] & ok[1:]
    T_safe = np.where(ok[:, None, None], T, np.eye(4))  # keep the math finite; invalid rows are NaN-ed below
    t, q = tq_from_pose(T_safe)
    rel = invert_se3(T_safe[:-1]) @ T_safe[1:]  # [N-1, 4, 4] T_before^-1 T_after
    dt = np.diff(ts)
    dt_safe = np.where(dt > 0, dt, np.nan)
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
        "dt_s": dt,
        "pose_source": [pose_source] * (n - 1),
        "status_before": list(status[:-1]),
        "status_after": list(status[1:]),
        "valid": valid,
    }
    for prefix, sl, m in (("before", slice(0, n - 1), ok[:-1]), ("after", slice(1, n), ok[1:])):
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

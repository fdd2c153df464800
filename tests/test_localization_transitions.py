"""Tracking against a world, error metrics, and the transitions table."""

import numpy as np
import pandas as pd
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.geometry import pose_from_tq, so3_exp
from atlas_pipeline.localization.localizer import localize
from atlas_pipeline.localization.metrics import ate_rmse
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
from atlas_pipeline.perception.rgbd import fuse
from atlas_pipeline.transition_log.transitions import (
    TRANSITIONS_SCHEMA,
    build_transitions,
    log_transitions,
    read_transitions,
    write_transitions,
)


def test_tracker_recovers_a_known_offset(small_manifest):
    """Coarse to fine from 3 cm / 2 degrees off, against a map made of the same frame."""
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel, pose_change
    from atlas_pipeline.perception.rgbd import backproject
    from atlas_pipeline.sensors.images import read_depth_m, read_rgb

    m = small_manifest
    rgb, depth = read_rgb(m.rgb_path(0), m.camera), read_depth_m(m.depth_path(0), m.camera)
    b = VoxelGaussianBuilder(0.02)
    pts, cols = backproject(depth, rgb, m.camera, 1, 0.1, 4.0)
    b.integrate(pts.astype(np.float64), cols)
    tracker = RGBDTracker(m.camera, load_profile("default").localization, (0.1, 4.0))
    frame = tracker.prepare(rgb, depth)
    T0 = np.eye(4)
    T0[:3, :3] = so3_exp(np.radians([1.2, -1.0, 1.2]))
    T0[:3, 3] = [0.02, -0.015, 0.015]
    res = tracker.align(frame, SurfelModel.from_builder(b), T0, (frame, np.eye(4)))
    dt, dr = pose_change(res.T_world_cam, np.eye(4))
    assert res.ok and dt < 0.003 and dr < 0.2, (dt, dr)
    assert np.allclose(res.T_world_cam[:3, :3].T @ res.T_world_cam[:3, :3], np.eye(3), atol=1e-12)


def test_ate_is_invariant_to_a_rigid_offset():
    rng = np.random.default_rng(1)
    gt = rng.normal(size=(30, 3))
    R = so3_exp(np.array([0.1, 0.2, -0.3]))
    est = gt @ R.T + [1, 2, 3] + rng.normal(scale=0.01, size=gt.shape)
    assert ate_rmse(est, gt) < 0.02 < ate_rmse(est, gt, align=False)


@pytest.fixture(scope="module")
def small_run(small_manifest):
    cfg = load_profile("default")
    fused = fuse(small_manifest, cfg)
    kf = select_keyframes_stage(small_manifest, fused, cfg)
    world = build_gaussian_world(fused, kf, cfg)
    report = localize(small_manifest, world, cfg)
    return cfg, world, report


def test_localization_on_synthetic_is_millimetric(small_run):
    _, _, report = small_run
    s = report.summary
    assert s["n_lost"] == 0 and s["n_tracked"] == report.n_frames - 1
    assert s["rmse_t_unaligned_m"] < 0.005 and s["rmse_rot_unaligned_deg"] < 0.3 and s["ate_rmse_m"] < 0.003


def test_report_save_load(small_run, tmp_path):
    _, _, report = small_run
    report.save(tmp_path)
    r2 = type(report).load(tmp_path)
    assert np.allclose(r2.T_world_cam, report.T_world_cam, atol=1e-8)
    assert r2.status == report.status
    lines = (tmp_path / "trajectory_estimated.tum").read_text().splitlines()
    assert len(lines) == report.n_frames + 1 and len(lines[1].split()) == 8


def test_transitions_from_a_known_constant_motion(tmp_path):
    n, dt = 6, 0.1
    ts = 100.0 + dt * np.arange(n)
    # Camera moves +0.05 m along its own z (forward) and turns 0.02 rad about its y each step.
    T = [np.eye(4)]
    step = pose_from_tq(np.array([0, 0, 0.05]), np.array([0, np.sin(0.01), 0, np.cos(0.01)]))
    for _ in range(n - 1):
        T.append(T[-1] @ step)
    table = build_transitions("synth", "abc", 42, ts, np.array(T), "ground_truth")
    path = write_transitions(table, tmp_path / "t.parquet")
    df = pd.read_parquet(path)
    assert len(df) == n - 1
    assert np.allclose(df["action_vz_mps"], 0.5) and np.allclose(df["action_vx_mps"], 0, atol=1e-12)
    assert np.allclose(df["action_wy_radps"], 0.2)
    assert np.allclose(df["delta_rotation_deg"], np.degrees(0.02))
    assert (df["frame_id_after"] - df["frame_id_before"] == 1).all()
    # Typed columns, no JSON strings in cells.
    for c in df.columns:
        if c.startswith(("before_", "after_", "action_", "delta_")) or c in ("dt_s",):
            assert df[c].dtype == np.float64, c
    assert df["step"].dtype == np.int64 and df["valid"].dtype == bool
    assert read_transitions(path).shape == df.shape


def test_transitions_with_unknown_poses_are_marked_invalid():
    T = np.tile(np.eye(4), (4, 1, 1))
    T[2] = np.nan
    table = build_transitions("p", "m", 1, np.arange(4.0), T, "ground_truth")
    df = table.to_pandas()
    assert df["valid"].tolist() == [True, False, False]
    assert df["valid_reason"].tolist() == ["ok", "after_pose_unknown", "before_pose_unknown"]
    assert df.loc[1, ["action_vx_mps", "after_x_m"]].isna().all()
    assert table.schema.equals(TRANSITIONS_SCHEMA, check_metadata=False)


# ---- validity, table-driven ------------------------------------------------------------------------

STEP_M, STEP_RAD, DT_S = 0.05, 0.02, 0.1  # per frame: forward along camera z, turn about camera y
A, TR, RL, LO = "anchor", "tracked", "relocalized", "lost"
N_FRAMES = 4


def _trajectory(n: int = N_FRAMES) -> np.ndarray:
    """``[n, 4, 4]`` T_world_cam moving ``STEP_M`` along, and turning ``STEP_RAD`` about, its own axes each frame."""
    step = pose_from_tq(np.array([0, 0, STEP_M]), np.array([0, np.sin(STEP_RAD / 2), 0, np.cos(STEP_RAD / 2)]))
    T = [np.eye(4)]
    for _ in range(n - 1):
        T.append(T[-1] @ step)
    return np.array(T)


TIMES = DT_S * np.arange(N_FRAMES)
# name: (status, timestamps, frames with a NaN pose, anchor_index, expected valid_reason per row)
CASES = {
    "anchor_then_tracked": ([A, TR, TR, TR], TIMES, [], 0, ["ok", "ok", "ok"]),
    "lost_before": ([A, TR, LO, TR], TIMES, [], 0, ["ok", "after_lost", "before_lost"]),
    "lost_after": ([A, TR, TR, LO], TIMES, [], 0, ["ok", "ok", "after_lost"]),
    "lost_with_no_pose": ([A, LO, TR, TR], TIMES, [1], 0,
                          ["after_lost;after_pose_unknown", "before_lost;before_pose_unknown", "ok"]),
    "relocalized_after": ([A, TR, RL, TR], TIMES, [], 0, ["ok", "after_relocalized", "ok"]),
    # Before the anchor frames were tracked backwards: the jump is into the earlier frame.
    "relocalized_before_the_anchor": ([TR, RL, A, TR], TIMES, [], 2, ["ok", "before_relocalized", "ok"]),
    "relocalized_start": ([RL, TR, TR, TR], TIMES, [], 0, ["ok", "ok", "ok"]),
    "dt_negative": ([A, TR, TR, TR], np.array([0.0, 0.1, 0.05, 0.3]), [], 0, ["ok", "dt_not_positive", "ok"]),
    "dt_zero": ([A, TR, TR, TR], np.array([0.0, 0.1, 0.1, 0.2]), [], 0, ["ok", "dt_not_positive", "ok"]),
    "dt_nan": ([A, TR, TR, TR], np.array([0.0, 0.1, np.nan, 0.3]), [], 0,
               ["ok", "dt_not_positive", "dt_not_positive"]),
    "nan_pose": ([A, TR, TR, TR], TIMES, [2], 0, ["ok", "after_pose_unknown", "before_pose_unknown"]),
    "never_attempted": ([A, TR, TR, "not_attempted"], TIMES, [3], 0, ["ok", "ok", "after_pose_unknown"]),
    "several_reasons": ([A, TR, LO, TR], np.array([0.0, 0.1, 0.1, 0.3]), [], 0,
                        ["ok", "after_lost;dt_not_positive", "before_lost"]),
    "ground_truth_has_no_status": (None, np.array([0.0, 0.1, 0.2, 0.2]), [1], 0,
                                   ["after_pose_unknown", "before_pose_unknown", "dt_not_positive"]),
    # A long gap (transitions.max_gap_s, default 1 s) ends a run, never an averaged velocity.
    "gap_of_a_minute": ([A, TR, TR, TR], np.array([0.0, 0.1, 60.1, 60.2]), [], 0, ["ok", "gap", "ok"]),
    "gap_just_over_the_bound": ([A, TR, TR, TR], np.array([0.0, 1.0001, 1.1, 2.2]), [], 0, ["gap", "ok", "gap"]),
    "gap_at_the_bound_is_kept": ([A, TR, TR, TR], np.array([0.0, 1.0, 1.1, 1.2]), [], 0, ["ok", "ok", "ok"]),
    "gap_and_lost": ([A, TR, LO, TR], np.array([0.0, 0.1, 5.0, 5.1]), [], 0, ["ok", "after_lost;gap", "before_lost"]),
    "gap_in_ground_truth": (None, np.array([0.0, 30.0, 30.1, 30.2]), [], 0, ["gap", "ok", "ok"]),
    # A frame whose depth image has no valid pixel is lost, and its rows say why (the sixth item).
    "lost_without_depth": ([A, TR, LO, TR], TIMES, [], 0, ["ok", "after_lost;no_depth", "before_lost;no_depth"], [2]),
}
ACTION_DELTA = [c for c in TRANSITIONS_SCHEMA.names if c.startswith(("action_", "delta_"))]


@pytest.mark.parametrize("case", list(CASES))
def test_validity_reasons_and_nan_for_unknowns(case):
    status, ts, nan_frames, anchor, reasons, *no_depth = CASES[case]
    T = _trajectory()
    T[nan_frames] = np.nan
    source = "ground_truth" if status is None else "estimated"
    df = build_transitions("p", "m", 1, ts, T, source, status, anchor, no_depth=no_depth[0] if no_depth else None).to_pandas()

    assert len(df) == N_FRAMES - 1 and df["valid_reason"].tolist() == reasons
    assert df["valid"].tolist() == [r == "ok" for r in reasons]
    assert df["status_before"].tolist() + df["status_after"].tolist()[-1:] == (status or ["unknown"] * N_FRAMES)
    assert np.array_equal(df["dt_s"], np.diff(ts), equal_nan=True)  # recorded as is, even when invalid
    # Unknown is NaN, never 0: every action and delta of an invalid row ...
    assert df.loc[~df["valid"], ACTION_DELTA].isna().all().all()
    # ... and the pose of a lost frame (a prediction) or of a frame with no pose.
    unknown = set(nan_frames) | {i for i, s in enumerate(status or []) if s == LO}
    t_true = _trajectory()[:, :3, 3]
    for side, frames in (("before", df["frame_id_before"]), ("after", df["frame_id_after"])):
        for row, i in enumerate(frames):
            xyz = df.loc[row, [f"{side}_x_m", f"{side}_y_m", f"{side}_z_m"]].to_numpy(np.float64)
            assert np.isnan(xyz).all() if i in unknown else np.allclose(xyz, t_true[i], atol=1e-12), (side, i)
    # Valid rows are still exact.
    ok = df[df["valid"]]
    assert np.allclose(ok["action_vz_mps"], STEP_M / ok["dt_s"]) and np.allclose(ok["action_vx_mps"], 0, atol=1e-12)
    assert np.allclose(ok["action_wy_radps"], STEP_RAD / ok["dt_s"])
    assert np.allclose(ok["delta_translation_m"], STEP_M)
    assert np.allclose(ok["delta_rotation_deg"], np.degrees(STEP_RAD))
    assert np.isfinite(ok[ACTION_DELTA].to_numpy()).all()


def test_valid_reason_is_documented_and_follows_valid():
    from atlas_pipeline.transition_log.transitions import VALID_REASONS

    names = TRANSITIONS_SCHEMA.names
    assert names[names.index("valid") + 1] == "valid_reason"
    doc = TRANSITIONS_SCHEMA.metadata[b"valid_reason"].decode()
    assert all(f"{r}:" in doc for r in VALID_REASONS)
    reasons_seen = {r for case in CASES.values() for row in case[4] for r in row.split(";")} - {"ok"}
    assert reasons_seen == set(VALID_REASONS)  # the table above exercises every reason


def test_status_is_checked():
    T, ts = _trajectory(), TIMES
    with pytest.raises(ValueError, match="no tracking status"):
        build_transitions("p", "m", 1, ts, T, "ground_truth", [A, TR, TR, TR])
    with pytest.raises(ValueError, match="unknown tracking status"):
        build_transitions("p", "m", 1, ts, T, "estimated", [A, TR, "guessed", TR])
    with pytest.raises(ValueError, match="3 entries for 4 frames"):
        build_transitions("p", "m", 1, ts, T, "estimated", [A, TR, TR])
    with pytest.raises(ValueError, match="pose_source"):
        build_transitions("p", "m", 1, ts, T, "made_up")


def test_log_transitions_uses_status_only_for_estimated_poses():
    from types import SimpleNamespace

    T_est, T_gt = _trajectory(), _trajectory()
    T_est[2] = T_est[1]  # a lost frame's pose: the prediction, finite but only a guess
    report = SimpleNamespace(map_id="m", timestamps_s=TIMES, status=[A, TR, LO, TR], summary={"anchor_index": 0},
                             pose_source_poses=lambda s: T_est if s == "estimated" else T_gt)
    cfg = load_profile("default")
    est = log_transitions(report, "p", 1, cfg).to_pandas()
    assert est["valid_reason"].tolist() == ["ok", "after_lost", "before_lost"]
    assert est.loc[1, ["after_x_m", "action_vz_mps"]].isna().all()  # frame 2 is lost: its pose is a guess
    cfg_gt = cfg.with_overrides({"transitions.pose_source": "ground_truth"})
    gt = log_transitions(report, "p", 1, cfg_gt).to_pandas()
    assert gt["valid"].all() and set(gt["status_before"]) == {"unknown"}


def test_reading_a_table_without_valid_reason_is_refused(tmp_path):
    import pyarrow.parquet as pq

    from atlas_pipeline.errors import ArtifactError

    old = build_transitions("p", "m", 1, TIMES, _trajectory(), "ground_truth").drop_columns(["valid_reason"])
    pq.write_table(old, tmp_path / "old.parquet")
    with pytest.raises(ArtifactError, match="valid_reason"):
        read_transitions(tmp_path / "old.parquet")


@pytest.mark.parametrize("max_gap_s, reasons", [
    (0.5, ["ok", "gap", "gap"]),
    (3.0, ["ok", "ok", "gap"]),
    (10.0, ["ok", "ok", "ok"]),
])
def test_the_gap_bound_is_the_transitions_config(max_gap_s, reasons):
    cfg = load_profile("default").with_overrides({"transitions.pose_source": "ground_truth",
                                                  "transitions.max_gap_s": max_gap_s})
    ts = np.array([0.0, 0.1, 2.1, 7.1])
    df = build_transitions("p", "m", 1, ts, _trajectory(), "ground_truth",
                           max_gap_s=cfg.transitions.max_gap_s).to_pandas()
    assert df["valid_reason"].tolist() == reasons
    assert df.loc[~df["valid"], ACTION_DELTA].isna().all().all()


@pytest.mark.parametrize("value, message", [
    (0, "--set: transitions.max_gap_s must be greater than 0, got 0"),
    (-1.0, "--set: transitions.max_gap_s must be greater than 0, got -1.0"),
    ("1s", "--set: transitions.max_gap_s must be a valid number, got '1s'"),
])
def test_the_gap_bound_is_validated(value, message):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides({"transitions.max_gap_s": value}, "--set")
    assert str(err.value) == message

"""Tracking against a world, error metrics, and the transitions table."""

import numpy as np
import pandas as pd
import pytest

from atlas_pipeline import pipeline as lib
from atlas_pipeline.config import load_profile
from atlas_pipeline.geometry import pose_from_tq, so3_exp
from atlas_pipeline.localization.metrics import ate_rmse
from atlas_pipeline.transition_log.transitions import TRANSITIONS_SCHEMA, build_transitions, read_transitions, write_transitions


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
    fused = lib.fuse(small_manifest, cfg)
    kf = lib.select_keyframes_stage(small_manifest, fused, cfg)
    world = lib.build_gaussian_world(fused, kf, cfg)
    report = lib.localize(small_manifest, world, cfg)
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
    assert df.loc[1, ["action_vx_mps", "after_x_m"]].isna().all()
    assert table.schema.equals(TRANSITIONS_SCHEMA, check_metadata=False)

"""Fail fast and keep what was done: localizing frames a world does not contain stops early, returns
a report that says why, and the report (NaN poses included) saves as valid JSON and loads back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.localization.localizer import (
    MISMATCH_MAX_LOST_RUN_FRAMES,
    MISMATCH_WINDOW_FRAMES,
    OUTCOME_COMPLETE,
    OUTCOME_STOPPED_WORLD_MISMATCH,
    LocalizationReport,
    _MismatchGuard,
    grade,
    localize,
    localize_sequence,
    tracking_map,
)
from atlas_pipeline.localization.metrics import read_tum_trajectory
from atlas_pipeline.localization.sequence import (
    NOTE_NO_DEPTH,
    STATUS_ANCHOR,
    STATUS_LOST,
    STATUS_NOT_ATTEMPTED,
    STATUS_RELOCALIZED,
    STATUS_TRACKED,
    FrameEstimate,
)
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
from atlas_pipeline.perception.rgbd import fuse

from tests.conftest import SMALL_SYNTH


@pytest.fixture(scope="module")
def world(small_manifest):
    """The small synthetic world (seed 0), built as the pipeline builds it."""
    cfg = load_profile("default")
    fused = fuse(small_manifest, cfg)
    return cfg, build_gaussian_world(fused, select_keyframes_stage(small_manifest, fused, cfg), cfg)


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    """Another synthetic dataset (seed 1: other objects, textures and path phase), same camera.

    Its frames are not in the seed-0 world: measured, every one of them is lost against it."""
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset
    from atlas_pipeline.sensors.tum import load_tum_sequence

    spec = SyntheticSpec(**{**SMALL_SYNTH, "seed": 1})
    root = generate_synthetic_dataset(tmp_path_factory.mktemp("synth") / "synth-other", spec)
    return load_tum_sequence(root, spec.camera(), "synth-other")


def _localize(manifest, cfg, world, T0):
    return localize_sequence(manifest, tracking_map(world), cfg.localization, T0, 0, world.map_id,
                             (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), prior_poses=world.T_world_cam_keyframes)


def _assert_stopped(rep: LocalizationReport, n_given: int):
    s = rep.summary
    n = rep.n_frames
    assert n > MISMATCH_WINDOW_FRAMES + n_given  # something is left to skip
    assert s["outcome"] == OUTCOME_STOPPED_WORLD_MISMATCH
    # The cost bound: the window of tried frames (plus a given anchor), never the whole sequence.
    assert s["n_attempted"] == MISMATCH_WINDOW_FRAMES + n_given
    assert s["n_not_attempted"] == n - s["n_attempted"]
    assert rep.status[s["n_attempted"]:] == [STATUS_NOT_ATTEMPTED] * s["n_not_attempted"]
    skipped = np.array([st == STATUS_NOT_ATTEMPTED for st in rep.status])
    assert np.isnan(rep.T_world_cam[skipped]).all() and np.isnan(rep.time_s[skipped]).all()
    assert np.isnan(rep.fitness[skipped]).all() and np.isnan(rep.inlier_rmse_m[skipped]).all()
    assert s["n_tracked"] == s["n_relocalized"] == 0
    reason = s["stopped_reason"]
    assert rep.dataset in reason and rep.map_id in reason
    assert f"after {s['n_attempted']} of {n} frames" in reason


def _assert_round_trip(rep: LocalizationReport, directory):
    rep.save(directory)
    # Strict JSON (no NaN tokens): unknown poses and figures are null.
    d = json.loads((directory / "localization.json").read_text(),
                   parse_constant=lambda c: pytest.fail(f"non-JSON constant {c} in localization.json"))
    unknown = ~np.isfinite(rep.T_world_cam).all(axis=(1, 2))
    assert unknown.any()
    for f, u in zip(d["frames"], unknown):
        assert (f["position_xyz"] is None and f["quat_xyzw"] is None) == bool(u)
    assert d["summary"]["outcome"] == rep.summary["outcome"]
    r2 = LocalizationReport.load(directory)
    assert r2.status == rep.status
    assert np.array_equal(np.isnan(r2.T_world_cam), np.isnan(rep.T_world_cam))
    assert np.allclose(r2.T_world_cam[~unknown], rep.T_world_cam[~unknown], atol=1e-8)
    assert np.isnan(r2.time_s).all() and "time_s" not in d["frames"][0]  # timings are not content: not saved
    # The TUM file stays valid for evo / TUM tools: one line per known pose, none for unknown ones.
    ts, P = read_tum_trajectory(directory / "trajectory_estimated.tum")
    assert len(ts) == int((~unknown).sum()) and np.isfinite(P).all()


@pytest.mark.slow
def test_other_scene_without_start_pose_stops_after_the_window(world, other_scene, tmp_path):
    cfg, w = world
    rep = _localize(other_scene, cfg, w, None)
    _assert_stopped(rep, n_given=0)
    assert rep.summary["start"] == "relocalized" and "no start pose" in rep.summary["stopped_reason"]
    assert rep.status[:MISMATCH_WINDOW_FRAMES] == [STATUS_LOST] * MISMATCH_WINDOW_FRAMES
    _assert_round_trip(rep, tmp_path)


@pytest.mark.slow
def test_other_scene_with_a_wrong_start_pose_stops_after_the_window(world, other_scene, tmp_path):
    """The start pose is a real viewpoint of the world (its first keyframe), but the frames are of
    another scene: the anchor is not evidence that the world fits."""
    cfg, w = world
    rep = _localize(other_scene, cfg, w, w.T_world_cam_keyframes[0])
    _assert_stopped(rep, n_given=1)
    assert rep.status[0] == STATUS_ANCHOR and "given start pose" in rep.summary["stopped_reason"]
    _assert_round_trip(rep, tmp_path)


@pytest.mark.slow
def test_matching_world_is_unaffected(small_manifest, world):
    cfg, w = world
    rep = localize(small_manifest, w, cfg)
    s = rep.summary
    assert s["outcome"] == OUTCOME_COMPLETE and s["stopped_reason"] is None
    assert s["n_not_attempted"] == 0 and s["n_attempted"] == rep.n_frames and s["n_lost"] == 0
    # A wrong start pose (50 cm off) in the right world: relocalized, then tracked; not a mismatch.
    T0 = w.T_world_cam_keyframes[0].copy()
    T0[:3, 3] += [0.5, 0.3, 0.0]
    rep = _localize(small_manifest, cfg, w, T0)
    assert rep.summary["outcome"] == OUTCOME_COMPLETE and rep.summary["n_not_attempted"] == 0
    assert rep.summary["n_tracked"] + rep.summary["n_relocalized"] == rep.n_frames - 1


# ---- the rule, frame by frame (no images) ------------------------------------------------------


def _est(status: str, note: str = "", pose: bool = True) -> FrameEstimate:
    T = np.eye(4) if pose else np.full((4, 4), np.nan)
    return FrameEstimate(0, T, status, 0.0, float("nan"), 0.0, note=note)


def test_guard_counts_tried_frames_only():
    g = _MismatchGuard(MISMATCH_WINDOW_FRAMES, MISMATCH_MAX_LOST_RUN_FRAMES)
    g.add(_est(STATUS_ANCHOR))  # a given pose: not evidence either way
    for _ in range(MISMATCH_WINDOW_FRAMES - 1):
        g.add(_est(STATUS_LOST, "relocalization failed", pose=False))
        g.add(_est(STATUS_LOST, NOTE_NO_DEPTH, pose=False))  # nothing tried: not in the window
        assert g.stop_reason() is None
    g.add(_est(STATUS_LOST, "poor alignment"))
    assert f"first {MISMATCH_WINDOW_FRAMES} frames tried" in g.stop_reason()


def test_guard_stops_on_a_long_run_without_depth_and_never_after_a_placed_frame():
    g = _MismatchGuard(MISMATCH_WINDOW_FRAMES, MISMATCH_MAX_LOST_RUN_FRAMES)
    for _ in range(MISMATCH_MAX_LOST_RUN_FRAMES):
        g.add(_est(STATUS_LOST, NOTE_NO_DEPTH, pose=False))
    assert g.stop_reason() is None
    g.add(_est(STATUS_LOST, NOTE_NO_DEPTH, pose=False))
    assert "in a row were lost" in g.stop_reason()

    g = _MismatchGuard(MISMATCH_WINDOW_FRAMES, MISMATCH_MAX_LOST_RUN_FRAMES)
    g.add(_est(STATUS_RELOCALIZED))
    for _ in range(3 * MISMATCH_MAX_LOST_RUN_FRAMES):
        g.add(_est(STATUS_LOST, "poor alignment"))
    assert g.stop_reason() is None


def test_report_with_nan_rows_and_summary_round_trips(tmp_path):
    """Unknown poses and non-finite figures (NumPy scalars too, nested) are written as null."""
    n = 6
    ts = 1000.0 + np.arange(n) / 30.0
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * 0.1
    status = [STATUS_ANCHOR, STATUS_TRACKED, STATUS_LOST, STATUS_LOST, STATUS_NOT_ATTEMPTED, STATUS_NOT_ATTEMPTED]
    T[3:] = np.nan  # a lost frame without a prediction, and the frames never reached
    summary, err_t, err_r = grade(ts, T, status, np.full((n, 4, 4), np.nan))
    assert summary["n_not_attempted"] == 2 and summary["n_lost"] == 2 and summary["n_graded"] == 0
    summary.update({"outcome": OUTCOME_STOPPED_WORLD_MISMATCH, "stopped_reason": "because",
                    "frames_per_s": float("nan"), "f32": np.float32("nan"), "i64": np.int64(3),
                    "nested": {"x": [np.float64("inf"), 1.5]}})
    nan = np.full(n, np.nan)
    rep = LocalizationReport("d", "m", ts, T, status, nan.copy(), nan.copy(), np.where(np.arange(n) < 4, 0.01, np.nan),
                             np.full((n, 4, 4), np.nan), err_t, err_r, summary)
    rep.save(tmp_path)
    d = json.loads((tmp_path / "localization.json").read_text(),
                   parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert "frames_per_s" not in d["summary"] and d["summary"]["f32"] is None and d["summary"]["i64"] == 3
    assert d["summary"]["nested"] == {"x": [None, 1.5]}
    assert [f["position_xyz"] is None for f in d["frames"]] == [False] * 3 + [True] * 3
    r2 = LocalizationReport.load(tmp_path)
    assert r2.status == status
    assert np.isnan(r2.T_world_cam[3:]).all() and np.allclose(r2.T_world_cam[:3], T[:3])
    assert np.isnan(r2.time_s).all() and "time_s" not in d["frames"][0]  # timings are not content: not saved
    lines = [ln for ln in (tmp_path / "trajectory_estimated.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 3 and all(len(ln.split()) == 8 for ln in lines)

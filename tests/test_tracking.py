"""Tracking without ground truth, loss and relocalization, and trajectory metrics (checked against evo)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.errors import DatasetError
from atlas_pipeline.geometry import pose_from_tq, so3_exp, so3_log
from atlas_pipeline.localization.localizer import localize_sequence
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
from atlas_pipeline.perception.rgbd import fuse
from atlas_pipeline.localization.metrics import (
    ate,
    evaluate_trajectories,
    match_trajectories,
    read_tum_trajectory,
    rpe,
    write_tum_trajectory,
)
from atlas_pipeline.localization.relocalize import Relocalizer
from atlas_pipeline.localization.sequence import SequenceTracker
from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel, pose_change
from atlas_pipeline.sensors.images import read_depth_m, read_rgb

# Half-size synthetic sequence: enough pixels for relocalization, quick to generate.
MEDIUM_SYNTH = {"seed": 0, "n_frames": 24, "width": 320, "height": 240,
                "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}


@pytest.fixture(scope="module")
def medium_manifest(tmp_path_factory):
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset
    from atlas_pipeline.sensors.tum import load_tum_sequence

    spec = SyntheticSpec(**MEDIUM_SYNTH)
    root = generate_synthetic_dataset(tmp_path_factory.mktemp("synth") / "synth-medium", spec)
    return load_tum_sequence(root, spec.camera(), "synth-medium")


def _smooth_trajectory(n: int, rng: np.random.Generator) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n)
    pos = np.stack([np.cos(t), np.sin(t), 0.2 * np.sin(2 * t)], axis=1)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = so3_exp(np.array([0.1 * np.sin(t[i]), 0.2 * np.cos(t[i]), t[i]]))
        poses[i, :3, 3] = pos[i]
    return poses


# ---- metrics ------------------------------------------------------------------------------------


def test_ate_and_rpe_match_evo_on_the_same_tum_files(tmp_path):
    evo_sync = pytest.importorskip("evo.core.sync")
    from evo.core import metrics
    from evo.core.units import Unit
    from evo.tools import file_interface

    rng = np.random.default_rng(0)
    n = 60
    gt = _smooth_trajectory(n + 10, rng)
    ts_gt = np.arange(n + 10) / 30.0
    # Estimate: a rigidly moved copy with noise, 5 ms late, missing the first and last frames.
    S = pose_from_tq(np.array([0.3, -0.2, 1.0]), np.array([0.1, 0.2, 0.3, 0.9]))
    est = S @ gt[5:5 + n]
    est[:, :3, 3] += rng.normal(scale=0.01, size=(n, 3))
    for i in range(n):
        est[i, :3, :3] = est[i, :3, :3] @ so3_exp(rng.normal(scale=0.01, size=3))
    ts_est = ts_gt[5:5 + n] + 0.005
    f_est = write_tum_trajectory(tmp_path / "est.tum", ts_est, est)
    f_gt = write_tum_trajectory(tmp_path / "gt.tum", ts_gt, gt)

    t_e, P = read_tum_trajectory(f_est)
    t_g, G = read_tum_trajectory(f_gt)
    ours = evaluate_trajectories(t_e, P, t_g, G)
    assert ours["n_matched"] == n

    ref = file_interface.read_tum_trajectory_file(str(f_gt))
    tra = file_interface.read_tum_trajectory_file(str(f_est))
    ref, tra = evo_sync.associate_trajectories(ref, tra, max_diff=0.02)
    tra.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, tra))
    assert ours["ate_rmse_m"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)

    # RPE over a fixed number of frames, translation and rotation, against evo's.
    ts, Pm, Gm = match_trajectories(t_e, P, t_g, G)
    ref2 = file_interface.read_tum_trajectory_file(str(f_gt))
    tra2 = file_interface.read_tum_trajectory_file(str(f_est))
    ref2, tra2 = evo_sync.associate_trajectories(ref2, tra2, max_diff=0.02)
    for relation, key in ((metrics.PoseRelation.translation_part, "trans_rmse_m"),
                          (metrics.PoseRelation.rotation_angle_deg, "rot_rmse_deg")):
        r_evo = metrics.RPE(relation, delta=5, delta_unit=Unit.frames, all_pairs=True)  # every i, as ours
        r_evo.process_data((ref2, tra2))
        assert rpe(ts, Pm, Gm, 5, "frames")[key] == pytest.approx(r_evo.get_statistic(metrics.StatisticsType.rmse), rel=1e-6)


def test_ate_is_blind_to_a_rigid_change_of_frame_and_rpe_per_second_pairs_by_time():
    rng = np.random.default_rng(1)
    gt = _smooth_trajectory(90, rng)
    ts = np.arange(90) / 30.0
    S = pose_from_tq(np.array([1.0, 2.0, 3.0]), np.array([0.3, -0.1, 0.2, 0.9]))
    a = ate(S @ gt, gt)
    assert a["rmse_m"] < 1e-9 and a["rot_rmse_deg"] < 1e-6
    r = rpe(ts, S @ gt, gt, 1.0, "s")
    assert r["n_pairs"] == 59 and r["trans_rmse_m"] < 1e-9  # pairs (i, i + 30 frames) until j is the last


def test_read_tum_trajectory_names_file_and_line(tmp_path):
    p = tmp_path / "bad.tum"
    p.write_text("# timestamp tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.tum:3: expected 8 values"):
        read_tum_trajectory(p)


# ---- tracking -----------------------------------------------------------------------------------


@pytest.mark.slow
def test_slam_on_synthetic_without_ground_truth(small_manifest):
    cfg = load_profile("default").with_overrides({"mapping.pose_source": "estimated"})
    fused = fuse(small_manifest, cfg)
    kf = select_keyframes_stage(small_manifest, fused, cfg)
    assert kf.pose_source == "estimated" and kf.valid.all() and len(kf.indices) >= 2
    res = evaluate_trajectories(small_manifest.timestamps_s, kf.T_world_cam, small_manifest.timestamps_s,
                                small_manifest.T_world_cam_gt)
    assert res["ate_rmse_m"] < 0.003
    # Ground truth is never read while tracking: removing it changes nothing.
    blind = dataclasses.replace(small_manifest, T_world_cam_gt=np.full_like(small_manifest.T_world_cam_gt, np.nan),
                                has_gt=np.zeros_like(small_manifest.has_gt))
    kf_blind = select_keyframes_stage(blind, fused, cfg)
    assert np.array_equal(kf_blind.T_world_cam, kf.T_world_cam)


@pytest.fixture(scope="module")
def small_world(small_manifest):
    cfg = load_profile("default")
    fused = fuse(small_manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(small_manifest, fused, cfg), cfg)
    return cfg, world


def test_a_frame_with_no_depth_is_lost_and_tracking_recovers(small_manifest, small_world):
    cfg, world = small_world
    m = small_manifest
    st = SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), model=SurfelModel.from_builder(world.tracking_voxels))
    frames = [(read_rgb(m.rgb_path(i), m.camera), read_depth_m(m.depth_path(i), m.camera)) for i in range(4)]
    e0 = st.process(0, *frames[0], T_given=m.T_world_cam_gt[0])
    e1 = st.process(1, frames[1][0], np.zeros_like(frames[1][1]))
    e2 = st.process(2, *frames[2])
    assert (e0.status, e1.status) == ("anchor", "lost") and e1.note == "no valid depth"
    assert e2.status in ("tracked", "relocalized")
    assert pose_change(e2.T_world_cam, m.T_world_cam_gt[2])[0] < 0.01


def test_frames_of_another_scene_get_a_status_not_a_crash(small_manifest, small_world):
    cfg, world = small_world
    m = small_manifest
    rng = np.random.default_rng(0)
    st = SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), model=SurfelModel.from_builder(world.tracking_voxels),
                         prior_poses=world.T_world_cam_keyframes)
    statuses = []
    for i in range(3):  # speckle: depth with no surface at all, random colour
        depth = rng.uniform(0.5, 3.5, (m.camera.height, m.camera.width)).astype(np.float32)
        rgb = rng.integers(0, 255, (m.camera.height, m.camera.width, 3), dtype=np.uint8)
        e = st.process(i, rgb, depth)
        statuses.append(e.status)
        assert e.status == "lost" and e.note and not np.isfinite(e.T_world_cam).all()
    assert statuses == ["lost"] * 3


def test_motion_model_carries_the_velocity_over_short_gaps_only(small_manifest, small_world):
    cfg, world = small_world
    m = small_manifest
    st = SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), model=SurfelModel.from_builder(world.tracking_voxels))
    for i in range(2):
        st.process(i, read_rgb(m.rgb_path(i), m.camera), read_depth_m(m.depth_path(i), m.camera),
                   T_given=m.T_world_cam_gt[0] if i == 0 else None, timestamp_s=i / 30.0)
    last, first = st._last[1], st._prev[1]
    one_step = np.linalg.solve(first, last)  # the last increment (camera frame)
    # Even spacing: one increment on.
    np.testing.assert_allclose(st._predict(2, 2 / 30.0), last @ one_step, atol=1e-9)
    # Two frames dropped (three intervals): three increments on, as the velocity carries it.
    three = np.linalg.solve(last, st._predict(2, 4 / 30.0))
    np.testing.assert_allclose(three[:3, 3], 3 * one_step[:3, 3], atol=1e-6)
    np.testing.assert_allclose(so3_log(three[:3, :3]), 3 * so3_log(one_step[:3, :3]), atol=1e-9)
    assert np.allclose(st._predict(2, 1.0), last)  # a 1 s gap: no velocity to trust, the last pose


@pytest.mark.slow
def test_relocalization_of_unseen_frames_in_a_half_sequence_world(medium_manifest):
    """The issue's protocol at small scale: world from the first half, second-half frames placed
    with no initial pose."""
    from atlas_pipeline.sensors.tum import load_tum_sequence

    cfg = load_profile("default")
    first = load_tum_sequence(medium_manifest.root, medium_manifest.camera, "first-half", 12)
    fused = fuse(first, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(first, fused, cfg), cfg)
    model = SurfelModel.from_field(world.field.positions, world.tracking_voxels.voxel_size_m)
    tracker = RGBDTracker(medium_manifest.camera, cfg.localization, (0.1, 4.0))
    reloc = Relocalizer(tracker, model, world.T_world_cam_keyframes)
    m = medium_manifest
    good = []
    for i in range(12, 24, 2):
        fp = tracker.prepare(read_rgb(m.rgb_path(i), m.camera), read_depth_m(m.depth_path(i), m.camera))
        r = reloc.relocalize(fp)
        dt, dr = pose_change(r.T_world_cam, m.T_world_cam_gt[i])
        good.append(r.ok and dt < 0.05 and dr < 5.0)
        assert 0.0 <= r.confidence <= 1.0
    assert np.mean(good) >= 0.8, good


@pytest.mark.slow
def test_second_session_relocalizes_then_maps_into_the_saved_world(medium_manifest):
    from atlas_pipeline.mapping.mapper import extend_world_by_tracking
    from atlas_pipeline.sensors.tum import load_tum_sequence

    cfg = load_profile("default").with_overrides({"mapping.pose_source": "estimated"})
    first = load_tum_sequence(medium_manifest.root, medium_manifest.camera, "first-half", 12)
    fused = fuse(first, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(first, fused, cfg), cfg)
    n_before = len(world.field)
    ext, poses, status = extend_world_by_tracking(world, medium_manifest, cfg.mapping, cfg.localization,
                                                  (0.1, 4.0), cfg.fusion.stride)
    assert status[0] == "relocalized" and status.count("lost") == 0
    assert len(world.field) == n_before  # the parent world is untouched
    assert len(ext.field) > n_before and len(ext.keyframe_indices) > len(world.keyframe_indices)
    # The second session's trajectory lies in the first session's frame.
    S_first = world.T_world_cam_keyframes[0] @ np.linalg.inv(medium_manifest.T_world_cam_gt[0])
    a = ate(poses, S_first @ medium_manifest.T_world_cam_gt, align=False)
    assert a["rmse_m"] < 0.02


@pytest.mark.slow
def test_localize_sequence_without_start_pose_relocalizes_its_first_frame(small_manifest, small_world):
    cfg, world = small_world
    rep = localize_sequence(small_manifest, SurfelModel.from_builder(world.tracking_voxels), cfg.localization, None,
                            prior_poses=world.T_world_cam_keyframes)
    assert rep.status[0] == "relocalized" and rep.summary["start"] == "relocalized"
    assert rep.summary["rmse_t_unaligned_m"] < 0.01


def test_a_screening_alignment_renders_the_map_once_a_full_one_again_where_it_moved(small_manifest, small_world):
    """Relocalization screens many hypotheses only to rank them: a screening tracker grades the
    result against the view it started from (one splat); a full tracker re-renders the map at
    a pose that moved away from its start before it grades it."""
    cfg, world = small_world
    m = small_manifest

    class Counting(SurfelModel):
        views = 0

        def model_view(self, *args, **kwargs):
            type(self).views += 1
            return super().model_view(*args, **kwargs)

    base = SurfelModel.from_builder(world.tracking_voxels)
    model = Counting(base.centres, base.normals, base.radius_m)
    frame = RGBDTracker(m.camera, cfg.localization, (0.1, 4.0)).prepare(read_rgb(m.rgb_path(3), m.camera),
                                                                      read_depth_m(m.depth_path(3), m.camera))
    start = m.T_world_cam_gt[3].copy()
    start[:3, 3] += [0.08, 0.0, 0.0]  # past the re-render distance from the truth
    results = {}
    for screening in (True, False):
        Counting.views = 0
        results[screening] = RGBDTracker(m.camera, cfg.localization, (0.1, 4.0), screening=screening).align(
            frame, model, start)
        assert Counting.views == (1 if screening else 2)
    assert all(pose_change(r.T_world_cam, m.T_world_cam_gt[3])[0] < 0.02 for r in results.values())


# -- frame-to-frame odometry (the prediction along a saved world) -------------------------------

def test_a_frames_own_view_holds_its_surface_on_the_pinhole_grid():
    """A distorted sensor facing a flat wall with a step: the frame's own view holds the wall's
    points on the level's pinhole grid (each projects into the pixel it sits in), normals facing
    the camera, and no normal across the depth jump of the step."""
    from atlas_pipeline.localization.tracker import frame_view
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    cam = CameraIntrinsics(160, 120, 131.25, 131.25, 79.5, 59.5, distortion=(0.2, -0.3, 0.001, -0.001, 0.1))
    tracker = RGBDTracker(cam, load_profile("default").localization, (0.1, 4.0))
    depth_m = np.full((cam.height, cam.width), 1.5, np.float32)
    depth_m[:, 100:] = 2.5  # a step back: a depth jump, no surface joins the two
    level = tracker.model_level
    view = frame_view(tracker.prepare(None, depth_m), np.eye(4), level)
    ok = np.isfinite(view.points_cam).all(axis=-1)
    h, w = ok.shape
    assert ok.sum() > 0.5 * h * w
    p, n = view.points_cam[ok], view.normals_cam[ok]
    assert np.allclose(p[:, 2][p[:, 2] < 2.0], 1.5) and np.allclose(p[:, 2][p[:, 2] > 2.0], 2.5)
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (len(n), 1)), atol=1e-6)
    v, u = np.nonzero(ok)
    np.testing.assert_allclose(view.fx * p[:, 0] / p[:, 2] + view.cx, u, atol=0.5 + 1e-9)
    np.testing.assert_allclose(view.fy * p[:, 1] / p[:, 2] + view.cy, v, atol=0.5 + 1e-9)
    step_col = int(round(view.fx * (100 - cam.cx) / cam.fx + view.cx))  # the step, roughly, at this level
    assert not ok[:, step_col - 1:step_col + 1].any()  # on both sides of the jump: no normal
    assert np.isnan(view.points_behind_cam).all()


def _frame_view_reference(depth_m: np.ndarray, rays: np.ndarray, K4: tuple, jump_m: float, jump_fraction: float):
    """The frame's own surface (``kn.frame_surface``) in array operations, step by step: the
    reference the kernel must match bit for bit."""
    z = depth_m.astype(np.float64)
    h, w = z.shape
    P = rays * z[..., None]  # [h, w, 3]
    n = np.full((h, w, 3), np.nan)
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1, keepdims=True)
    zc = z[1:-1, 1:-1]
    nb = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    jump = jump_m + jump_fraction * zc
    ok = (zc > 0) & (nb > 0).all(axis=0) & (np.abs(nb - zc).max(axis=0) <= 2 * jump) & (norm[..., 0] > 0)
    c = c / np.where(norm > 0, norm, 1.0)
    c = np.where((np.einsum("ijk,ijk->ij", c, P[1:-1, 1:-1]) > 0)[..., None], -c, c)
    n[1:-1, 1:-1][ok] = c[ok]
    pts, nrm = P[1:-1, 1:-1][ok], n[1:-1, 1:-1][ok]
    fx, fy, cx, cy = K4
    u = np.rint(fx * pts[:, 0] / pts[:, 2] + cx).astype(np.int64)
    v = np.rint(fy * pts[:, 1] / pts[:, 2] + cy).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    order = np.argsort(-pts[inside, 2], kind="stable")  # far first: the nearest is written last
    u, v, pts, nrm = u[inside][order], v[inside][order], pts[inside][order], nrm[inside][order]
    out_p, out_n = np.full((h, w, 3), np.nan), np.full((h, w, 3), np.nan)
    out_p[v, u] = pts
    out_n[v, u] = nrm
    return out_p, out_n


@pytest.mark.parametrize("distortion", [(), (0.2, -0.3, 0.001, -0.001, 0.1)])
def test_the_frame_surface_kernel_matches_its_reference_bit_for_bit(distortion):
    """Noisy depth with holes, steps and a slanted floor, on a distorted sensor (pixels moving onto
    the pinhole grid collide there) and an undistorted one."""
    from atlas_pipeline.localization import _kernels as kn
    from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as TC
    from atlas_pipeline.localization.tracker import _level_K, _level_rays
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    cam = CameraIntrinsics(160, 120, 131.25, 131.25, 79.5, 59.5, distortion=distortion)
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    depth_m = 1.2 + 0.01 * v + rng.normal(0.0, 0.004, v.shape)
    depth_m[:, 90:] += 0.8  # a step back
    depth_m[rng.random(v.shape) < 0.05] = 0.0  # holes
    depth_m[40:60, 20:40] = np.round(depth_m[40:60, 20:40], 1)  # ties
    for level in (0, 1):
        z = np.ascontiguousarray(depth_m[::2 ** level, ::2 ** level], np.float64)
        rays, K4 = _level_rays(cam, level), _level_K(cam, level)
        got = kn.frame_surface(z, rays, K4, TC.pyramid_max_depth_jump_m, TC.pyramid_depth_jump_fraction)
        want = _frame_view_reference(z, rays, K4, TC.pyramid_max_depth_jump_m, TC.pyramid_depth_jump_fraction)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        assert np.isfinite(got[0]).all(axis=-1).mean() > 0.5


def test_odometry_follows_the_camera_from_the_last_frame_and_gives_up_without_overlap(small_manifest):
    """Frame 4 aligned to frame 3's own surface from frame 3's pose lands near its true pose (a
    prediction for the map alignment); from a pose that sees nothing of frame 3 it is None."""
    from atlas_pipeline.localization.tracker import frame_view

    m = small_manifest
    tracker = RGBDTracker(m.camera, load_profile("default").localization, (0.1, 4.0))
    frames = [tracker.prepare(read_rgb(m.rgb_path(i), m.camera), read_depth_m(m.depth_path(i), m.camera))
              for i in (3, 4)]
    T3, T4 = m.T_world_cam_gt[3], m.T_world_cam_gt[4]
    start_m, start_deg = pose_change(T3, T4)
    assert start_m > 0.01  # the camera moved: there is something to follow
    view = frame_view(frames[0], T3, tracker.model_level)
    T = tracker.odometry(frames[1], view, T3, reference=(frames[0], T3))
    moved_m, turned_deg = pose_change(T, T4)
    assert moved_m < 0.25 * start_m and moved_m < 0.01 and turned_deg < max(0.5, 0.5 * start_deg)
    away = T3.copy()
    away[:3, 3] += [0.0, 0.0, -20.0]  # 20 m behind frame 3: none of its surface in front
    assert tracker.odometry(frames[1], view, away) is None

"""Colour taken after its depth image is moved to the depth image's time (perception/colour_timing.py)."""

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.geometry import so3_exp
from atlas_pipeline.localization import sequence as seq
from atlas_pipeline.perception.colour_timing import MIN_FLOW_PX, colour_at_depth_time, max_flow_px
from atlas_pipeline.sensors.synthetic import SyntheticSpec, build_scene, camera_path, render_synthetic_frame
from tests.conftest import SMALL_SYNTH


def _motion(rot_rad, trans_m) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rot_rad, np.float64))
    T[:3, 3] = trans_m
    return T


def test_colour_taken_later_is_moved_back_onto_the_depth_image():
    """The colour camera 1.5 cm and 1 degree from the depth camera: the moved colour matches the
    render at the depth camera's pose far better than the colour as taken."""
    spec = SyntheticSpec(**SMALL_SYNTH)
    scene = build_scene(spec.seed)
    T_depth = camera_path(spec, np.array([0.1]))[0]
    dT = _motion([0.0, np.radians(1.0), 0.0], [0.015, 0.0, 0.0])  # colour camera in the depth camera's frame
    truth, depth = render_synthetic_frame(spec, scene, T_depth)
    taken, _ = render_synthetic_frame(spec, scene, T_depth @ dT)
    moved = colour_at_depth_time(taken, depth, spec.camera(), dT)
    assert moved.shape == taken.shape and moved.dtype == np.uint8

    def err(img):  # away from the border, where the moved samples may leave the image
        return np.abs(img.astype(float) - truth.astype(float))[8:-8, 8:-8].mean()

    assert max_flow_px(dT, spec.camera()) > 2.0
    assert err(moved) < 0.5 * err(taken), (err(moved), err(taken))


def test_no_motion_leaves_the_colour_as_it_is():
    spec = SyntheticSpec(**SMALL_SYNTH)
    rgb = np.random.default_rng(0).integers(0, 255, (spec.height, spec.width, 3), dtype=np.uint8)
    depth = np.full((spec.height, spec.width), 2.0, np.float32)
    assert colour_at_depth_time(rgb, depth, spec.camera(), np.eye(4)) is rgb
    tiny = _motion([0.0, 0.0, 0.0], [1e-5, 0.0, 0.0])
    assert max_flow_px(tiny, spec.camera()) < MIN_FLOW_PX
    assert colour_at_depth_time(rgb, depth, spec.camera(), tiny) is rgb


@pytest.mark.parametrize("compensate", [True, False])
def test_tracker_moves_the_colour_with_its_velocity(small_manifest, monkeypatch, compensate):
    """With a colour delay the tracker moves each frame's colour by its velocity over that delay,
    once it has a velocity (from the third frame), and only when compensation is on."""
    m = small_manifest
    cfg = load_profile("default").with_overrides({"localization.colour_delay_compensation": compensate})
    calls = []

    def record(rgb, depth_m, camera, T_depth_colour):
        calls.append(T_depth_colour)
        return rgb

    monkeypatch.setattr(seq, "colour_at_depth_time", record)
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder

    st = seq.SequenceTracker(m.camera, cfg.localization, (0.1, 4.0), builder=VoxelGaussianBuilder(0.02))
    st.process(0, m.read_rgb(0), m.read_depth_m(0), T_given=m.T_world_cam_gt[0], timestamp_s=float(m.timestamps_s[0]),
               colour_delay_s=0.015)
    for i in (1, 2):
        st.process(i, m.read_rgb(i), m.read_depth_m(i), timestamp_s=float(m.timestamps_s[i]), colour_delay_s=0.015)
    if not compensate:
        assert calls == []
        return
    assert len(calls) == 1  # frame 2: the first with two frames behind it
    # the velocity of frames 0 -> 1 over 15 ms: about 0.015 * fps of one frame's motion
    step = np.linalg.solve(m.T_world_cam_gt[0], m.T_world_cam_gt[1])
    assert np.linalg.norm(calls[0][:3, 3]) == pytest.approx(0.015 * 30.0 * np.linalg.norm(step[:3, 3]), rel=0.2)


def _moving_trajectory(n=5, fps=30.0, speed_m_s=1.0):
    """``n`` poses moving ``speed_m_s`` along x and turning 3 degrees a frame about y, at ``fps``."""
    t = np.arange(n) / fps
    T = np.stack([_motion([0.0, np.radians(3.0) * k, 0.0], [speed_m_s * tk, 0.0, 1.0]) for k, tk in enumerate(t)])
    return T, t


def test_pose_at_colour_time_interpolates_between_the_frames_around_it():
    from atlas_pipeline.perception.colour_timing import colour_motion_in_trajectory, pose_at_colour_time

    T, t = _moving_trajectory()
    T_c = pose_at_colour_time(T, t, 1, 0.015)  # halfway to frame 2 at 30 Hz
    assert T_c[0, 3] == pytest.approx(T[1, 0, 3] + 0.015)
    assert np.degrees(np.arccos(np.clip((np.trace(np.linalg.solve(T[1], T_c)[:3, :3]) - 1) / 2, -1, 1))) \
        == pytest.approx(1.35, abs=0.01)  # 3 degrees a frame, 0.45 of a frame
    before = pose_at_colour_time(T, t, 2, -0.010)  # colour taken before depth: towards frame 1
    assert before[0, 3] == pytest.approx(T[2, 0, 3] - 0.010)
    motion = colour_motion_in_trajectory(T, t, 1, 0.015)
    assert np.allclose(T[1] @ motion, T_c)

    assert pose_at_colour_time(T, t, 1, 0.0) is None  # nothing to compensate
    assert pose_at_colour_time(T, t, 1, 0.2) is None  # not the same moment
    assert pose_at_colour_time(T, t, 4, 0.015) is None  # the last frame: no frame after it
    lost = T.copy()
    lost[2] = np.nan
    assert pose_at_colour_time(lost, t, 1, 0.015) is None  # the neighbour has no pose
    gap = t.copy()
    gap[2:] += 0.5  # dropped frames between 1 and 2
    assert pose_at_colour_time(T, gap, 1, 0.015) is None
    assert pose_at_colour_time(T, t, 1, 0.040) is None  # past the next frame: not between them


@pytest.mark.parametrize("compensate", [True, False])
def test_keyframe_fit_and_evaluation_take_the_colour_at_its_own_time(small_manifest, monkeypatch, compensate):
    """With colour stamped 15 ms after depth, the keyframe fit moves each keyframe's colour to its
    depth time along the mapping trajectory (``mapping.colour_delay_compensation``), and the render
    evaluation compares each held-out colour image with a render at the trajectory's pose at the
    colour's time (``localization.colour_delay_compensation``); neither when they are off."""
    import dataclasses
    from types import SimpleNamespace

    from atlas_pipeline.gaussian_world import evaluation
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception import colour_timing
    from atlas_pipeline.perception.rgbd import fuse

    delay = 0.015
    m = dataclasses.replace(small_manifest, rgb_timestamps_s=small_manifest.timestamps_s + delay)
    cfg = load_profile("default").with_overrides({
        "localization.colour_delay_compensation": compensate, "mapping.colour_delay_compensation": compensate,
        "mapping.fit.epochs": 1,
        "mapping.colour_refinement.iterations": 0, "evaluation.view_stride": 1})
    moved = []

    def record(rgb, depth_m, camera, T_depth_colour):
        moved.append(T_depth_colour)
        return rgb

    monkeypatch.setattr(colour_timing, "colour_at_depth_time", record)
    fused = fuse(m, cfg)
    kf = select_keyframes_stage(m, fused, cfg)
    world = build_gaussian_world(fused, kf, cfg, manifest=m)
    gt = m.T_world_cam_gt
    expected = [colour_timing.colour_motion_in_trajectory(gt, m.timestamps_s, int(i), delay)
                for i in world.keyframe_indices]
    if compensate:
        assert len(moved) == sum(e is not None for e in expected) > 0
        assert all(np.allclose(a, b, atol=1e-9) for a, b in zip(moved, [e for e in expected if e is not None]))
    else:
        assert moved == []

    seen = {}
    monkeypatch.setattr(evaluation, "evaluate_views", lambda *a, **kw: seen.update(kw))
    report = SimpleNamespace(T_world_cam=gt)
    evaluation.evaluate_rendering(m, SimpleNamespace(keyframe_indices=world.keyframe_indices, field=world.field,
                                                     map_id="m"), report, cfg)
    poses = seen["colour_poses"]
    if not compensate:
        assert poses == {}
        return
    held = np.setdiff1d(np.arange(m.n_frames), world.keyframe_indices)
    assert set(poses) == {int(i) for i in held if i + 1 < m.n_frames}
    for i, T in poses.items():
        assert np.allclose(T, colour_timing.pose_at_colour_time(gt, m.timestamps_s, i, delay))


@pytest.mark.parametrize("compensate", [True, False])
def test_side_by_side_video_renders_the_colour_at_its_own_time(small_manifest, small_world, monkeypatch, tmp_path,
                                                               compensate):
    """The demo's real | render video puts beside each colour image a render at the trajectory's
    pose at that image's time (as the render evaluation), when compensation is on."""
    import dataclasses
    from types import SimpleNamespace

    from atlas_pipeline.gaussian_world import render
    from atlas_pipeline.perception.colour_timing import pose_at_colour_time
    from atlas_pipeline.viz.demo import render_side_by_side_video

    delay = 0.015
    m = dataclasses.replace(small_manifest, rgb_timestamps_s=small_manifest.timestamps_s + delay)
    cfg = load_profile("default").with_overrides({"localization.colour_delay_compensation": compensate})
    seen = []

    def fake_render(*args, **kwargs):
        seen.append(np.asarray(args[5]))  # T_world_cam
        return SimpleNamespace(rgb=np.zeros((m.camera.height, m.camera.width, 3), np.uint8))

    monkeypatch.setattr(render, "render_gaussians", fake_render)
    gt = m.T_world_cam_gt
    render_side_by_side_video(small_world, m, gt, cfg, tmp_path / "sbs.mp4")
    assert len(seen) == m.n_frames
    for i, T in enumerate(seen):
        at_colour = pose_at_colour_time(gt, m.timestamps_s, i, delay) if compensate else None
        assert np.allclose(T, gt[i] if at_colour is None else at_colour)
    assert compensate == (not np.allclose(seen[0], gt[0]))

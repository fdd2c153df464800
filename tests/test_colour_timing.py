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

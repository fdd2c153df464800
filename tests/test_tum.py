"""TUM layout loading: association, ground truth, bad input named by file and line."""

import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from atlas_pipeline.config import FusionConfig
from atlas_pipeline.errors import DatasetError
from atlas_pipeline.geometry import pose_from_tq
from atlas_pipeline.perception.rgbd import backproject, fuse_frames, pixel_rays
from atlas_pipeline.sensors.camera import TUM_CAMERAS
from atlas_pipeline.sensors.tum import FrameManifest, associate, load_tum_sequence, lookup_groundtruth
from tests.conftest import SMALL_SYNTH, tum_folder


def test_associate_nearest_within_20ms_one_to_one():
    a = np.array([0.000, 0.033, 0.066, 0.100])
    b = np.array([0.004, 0.030, 0.031, 0.200])
    pairs = associate(a, b, 0.02)
    # Closest pair first: 0.033 takes 0.031 (2 ms) over 0.030 (3 ms); 0.066 and 0.100 have nothing
    # within 20 ms once 0.031 is used.
    assert pairs == [(0, 0), (1, 2)]


def test_groundtruth_interpolated_between_samples():
    ts = np.array([0.0, 0.01, 0.02])
    T = pose_from_tq(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.tile([0, 0, 0, 1.0], (3, 1)))
    out, has = lookup_groundtruth(ts, T, np.array([0.005, 0.015, 0.5, -0.01]))
    assert has.tolist() == [True, True, False, True]
    assert np.allclose(out[0, :3, 3], [0.5, 0, 0]) and np.allclose(out[1, :3, 3], [1.5, 0, 0])
    assert np.allclose(out[3], T[0])  # before the first sample: nearest within 20 ms


def test_synthetic_manifest_roundtrip(small_manifest, tmp_path):
    m = small_manifest
    assert m.n_frames == SMALL_SYNTH["n_frames"] and m.has_gt.all()
    m.save(tmp_path)
    m2 = FrameManifest.load(tmp_path)
    assert m2.rgb_files == m.rgb_files and np.allclose(m2.T_world_cam_gt, m.T_world_cam_gt)
    assert m2.content_hash == m.content_hash and m2.camera == m.camera


def test_backprojection_inverts_projection():
    cam = TUM_CAMERAS["freiburg3"]
    depth = np.full((cam.height, cam.width), 2.0, np.float32)
    pts, _ = backproject(depth, None, cam, stride=8)
    uv = pts[:, :2] / pts[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    v, u = np.mgrid[0:cam.height:8, 0:cam.width:8]
    assert np.allclose(uv, np.stack([u.ravel(), v.ravel()], 1), atol=1e-3)


def test_undistortion_inverts_the_distortion_model():
    cam = TUM_CAMERAS["freiburg1"]
    rays = pixel_rays(cam, 16).reshape(-1, 3)
    x, y = rays[:, 0].astype(np.float64), rays[:, 1].astype(np.float64)
    k1, k2, p1, p2, k3 = cam.distortion
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    v, u = np.mgrid[0:cam.height:16, 0:cam.width:16]
    assert np.allclose(xd * cam.fx + cam.cx, u.ravel(), atol=0.05)
    assert np.allclose(yd * cam.fy + cam.cy, v.ravel(), atol=0.05)


# ---- bad input ----------------------------------------------------------------------------------

@pytest.fixture
def broken_copy(small_synthetic, tmp_path):
    dst = tmp_path / "seq"
    shutil.copytree(small_synthetic, dst)
    return dst


def _load(root):
    from atlas_pipeline.sensors.synthetic import SyntheticSpec

    return load_tum_sequence(root, SyntheticSpec(**SMALL_SYNTH).camera(), "x")


def test_missing_list_file(broken_copy):
    (broken_copy / "depth.txt").unlink()
    with pytest.raises(DatasetError, match=r"depth.txt: list file not found"):
        _load(broken_copy)


def test_malformed_line_names_file_and_line(broken_copy):
    lines = (broken_copy / "rgb.txt").read_text().splitlines()
    lines[5] = "1000.1 rgb/a.png extra-field"
    (broken_copy / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"rgb.txt:6: expected 2 fields"):
        _load(broken_copy)


def test_missing_image_names_list_line(broken_copy):
    first = (broken_copy / "rgb.txt").read_text().splitlines()[3].split()[1]
    (broken_copy / first).unlink()
    with pytest.raises(DatasetError, match=r"rgb.txt:4: rgb image .* not found"):
        _load(broken_copy)


def test_wrong_image_size(broken_copy):
    first = (broken_copy / "depth.txt").read_text().splitlines()[3].split()[1]
    iio.imwrite(broken_copy / first, np.ones((10, 10), np.uint16))
    with pytest.raises(DatasetError, match=r"image is 10x10, camera expects 160x120"):
        _load(broken_copy)


def test_depth_all_zero_is_a_lost_frame_unless_too_many(broken_copy):
    m = _load(broken_copy)
    iio.imwrite(m.depth_path(3), np.zeros((120, 160), np.uint16))
    fused = fuse_frames(m, FusionConfig())  # one frame without depth: fused with no points (tracking loses it)
    assert fused.valid_fraction[3] == 0 and (np.delete(fused.valid_fraction, 3) > 0).all()
    for i in range(m.n_frames):
        iio.imwrite(m.depth_path(i), np.zeros((120, 160), np.uint16))
    with pytest.raises(DatasetError, match=r"depth.*png: .*depth images have no valid pixel .* too few to map"):
        fuse_frames(m, FusionConfig())


def test_path_outside_dataset_refused(broken_copy):
    lines = (broken_copy / "rgb.txt").read_text().splitlines()
    lines[3] = lines[3].split()[0] + " ../../etc/passwd"
    (broken_copy / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="leaves the dataset folder"):
        _load(broken_copy)


def test_bad_groundtruth_line(broken_copy):
    with open(broken_copy / "groundtruth.txt", "a") as f:
        f.write("1000.5 1 2 3 0 0 0 nan-ish\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:\d+: non-numeric value"):
        _load(broken_copy)


# ---- real data ------------------------------------------------------------------------------------

def test_real_fr1_xyz_manifest():
    root = tum_folder("tum_fr1_xyz_10")
    m = load_tum_sequence(root, TUM_CAMERAS["freiburg1"], "tum-fr1-xyz-10")
    # 10 RGB frames, one of which has no depth image within 20 ms.
    assert m.n_frames == 9 and m.has_gt.all()
    assert np.all(np.abs(m.timestamps_s - m.depth_timestamps_s) <= 0.02)


def test_real_teddy_ground_truth_coverage():
    root = tum_folder("tum_fr3_teddy_100")
    m = load_tum_sequence(root, TUM_CAMERAS["freiburg3"], "tum-fr3-teddy-100")
    assert m.n_frames == 100 and int(m.has_gt.sum()) == 96


def test_frame_time_is_the_depth_time_and_ground_truth_is_looked_up_there(broken_copy, tmp_path):
    """Colour taken 15 ms after depth (TUM fr1): each frame's time, and its ground truth, are the
    depth image's (the pose a tracker estimates from it); the colour times are kept beside."""
    def rows(name):
        return [ln.split() for ln in (broken_copy / name).read_text().splitlines() if not ln.startswith("#")]

    t_rgb = np.array([float(r[0]) for r in rows("rgb.txt")])
    rows = rows("depth.txt")
    t_depth = t_rgb - 0.015
    (broken_copy / "depth.txt").write_text("".join(f"{t:.6f} {r[1]}\n" for t, r in zip(t_depth, rows)))
    # the camera moves 1 m/s along x, sampled at 100 Hz like TUM's motion capture
    ts = np.arange(t_rgb[0] - 0.1, t_rgb[-1] + 0.1, 0.01)
    (broken_copy / "groundtruth.txt").write_text("".join(f"{t:.6f} {t - 1000:.6f} 0 0 0 0 0 1\n" for t in ts))
    m = _load(broken_copy)
    np.testing.assert_allclose(m.timestamps_s, t_depth, atol=1e-6)
    np.testing.assert_allclose(m.rgb_timestamps_s, t_rgb, atol=1e-6)
    np.testing.assert_allclose(m.T_world_cam_gt[:, 0, 3], t_depth - 1000, atol=1e-5)  # not t_rgb - 1000
    m.save(tmp_path / "manifest")
    back = FrameManifest.load(tmp_path / "manifest")
    np.testing.assert_array_equal(back.rgb_timestamps_s, m.rgb_timestamps_s)
    np.testing.assert_array_equal(back.timestamps_s, m.timestamps_s)

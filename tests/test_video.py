"""Tests of camera orbits and MP4 writing (tiny frames, so ffmpeg runs in well under a second)."""

from __future__ import annotations

import subprocess

import imageio.v2 as imageio
import imageio_ffmpeg
import numpy as np
import pytest

from atlas_pipeline.viz.video import orbit_poses, side_by_side, write_mp4


def _frames(n, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    # smooth per-frame brightness change so frames differ but compress well
    return [np.clip(base.astype(int) // 2 + 20 * i, 0, 255).astype(np.uint8) for i in range(n)]


def _ffmpeg_info(path) -> str:
    proc = subprocess.run(
        [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)],
        capture_output=True, text=True,
    )
    return proc.stderr  # ffmpeg prints stream info on stderr (and exits 1: no output given)


def _read_all(path):
    with imageio.get_reader(path, format="FFMPEG") as reader:
        return [np.asarray(f) for f in reader]


def test_orbit_poses_circle_around_centre_looking_at_it():
    center = np.array([1.0, 2.0, 0.5])
    poses = orbit_poses(center, radius_m=2.0, height_m=1.0, n_frames=8)
    assert poses.shape == (8, 4, 4)
    eyes = poses[:, :3, 3]
    np.testing.assert_allclose(eyes[:, 2], 1.5)
    np.testing.assert_allclose(np.linalg.norm(eyes[:, :2] - center[:2], axis=1), 2.0)
    np.testing.assert_allclose(eyes[0], center + [2.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(eyes[2], center + [0.0, 2.0, 1.0], atol=1e-12)  # counter-clockwise
    for T in poses:
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        to_center = (center - T[:3, 3]) / np.linalg.norm(center - T[:3, 3])
        np.testing.assert_allclose(R[:, 2], to_center, atol=1e-12)  # camera z looks at the centre
        assert R[:, 1] @ [0.0, 0.0, 1.0] < 0  # image down is world down
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    # no duplicated end pose: a full turn in n steps
    angles = np.arctan2(eyes[:, 1] - center[1], eyes[:, 0] - center[0])
    np.testing.assert_allclose(np.diff(np.unwrap(angles)), 2 * np.pi / 8)


def test_orbit_poses_other_up_and_start_angle():
    poses = orbit_poses(np.zeros(3), 1.0, 0.0, 4, up=(0.0, -1.0, 0.0), start_angle_rad=np.pi / 2)
    eyes = poses[:, :3, 3]
    np.testing.assert_allclose(eyes[:, 1], 0.0, atol=1e-12)  # the circle is perpendicular to up
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 1.0)
    for T in poses:
        assert T[:3, 1] @ [0.0, -1.0, 0.0] < -0.99  # image down is against up


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(center=np.zeros(2), radius_m=1.0, height_m=0.0, n_frames=3),
        dict(center=np.zeros(3), radius_m=-1.0, height_m=0.0, n_frames=3),
        dict(center=np.zeros(3), radius_m=1.0, height_m=0.0, n_frames=0),
        dict(center=np.zeros(3), radius_m=0.0, height_m=0.0, n_frames=3),
        dict(center=np.zeros(3), radius_m=1.0, height_m=0.0, n_frames=3, up=(0, 0, 0)),
    ],
)
def test_orbit_poses_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        orbit_poses(**kwargs)


def test_write_mp4_h264_yuv420p_faststart(tmp_path):
    path = tmp_path / "orbit.mp4"
    frames = _frames(5)
    done = []
    n = write_mp4(iter(frames), path, fps=10, progress=done.append)
    assert n == 5
    assert done == [1, 2, 3, 4, 5]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["orbit.mp4"]  # no temporary left
    back = _read_all(path)
    assert len(back) == 5
    assert back[0].shape == (24, 32, 3)
    # lossy, but the mean brightness of each frame survives
    for a, b in zip(frames, back):
        assert abs(a.mean() - b.mean()) < 4
    info = _ffmpeg_info(path)
    assert "h264" in info and "yuv420p" in info
    data = path.read_bytes()
    assert data.index(b"moov") < data.index(b"mdat")  # +faststart: index before the media data


def test_write_mp4_pads_odd_sizes(tmp_path):
    path = tmp_path / "odd.mp4"
    frames = [np.full((25, 33, 3), 128, np.uint8) for _ in range(3)]
    assert write_mp4(frames, path, fps=5) == 3
    back = _read_all(path)
    assert len(back) == 3
    assert back[0].shape == (26, 34, 3)  # padded, not resized
    assert abs(back[0].astype(int) - 128).max() < 6  # edge padding keeps the content uniform


def test_write_mp4_replaces_existing_file_and_creates_folder(tmp_path):
    path = tmp_path / "sub" / "v.mp4"
    write_mp4(_frames(2), path)
    write_mp4(_frames(4, seed=1), path)
    assert len(_read_all(path)) == 4


def test_write_mp4_rejects_empty_sequence(tmp_path):
    path = tmp_path / "empty.mp4"
    with pytest.raises(ValueError, match="no frames"):
        write_mp4(iter([]), path)
    assert not path.exists()


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((24, 30, 3), np.uint8),  # different size
        np.zeros((24, 32, 3), np.float32),  # different dtype
        np.zeros((24, 32, 4), np.uint8),  # RGBA
    ],
)
def test_write_mp4_rejects_inconsistent_frames_and_leaves_nothing(tmp_path, bad):
    path = tmp_path / "bad.mp4"
    frames = _frames(3) + [bad]
    with pytest.raises(ValueError, match="frame 3"):
        write_mp4(frames, path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "first", [np.zeros((24, 32), np.uint8), np.zeros((24, 32, 3), np.float64)]
)
def test_write_mp4_rejects_non_rgb_uint8(tmp_path, first):
    with pytest.raises(ValueError, match="frame 0"):
        write_mp4([first], tmp_path / "x.mp4")
    assert list(tmp_path.iterdir()) == []


def test_side_by_side():
    a = np.zeros((4, 5, 3), np.uint8)
    b = np.full((4, 5, 3), 255, np.uint8)
    out = side_by_side(a, b)
    assert out.shape == (4, 10, 3)
    assert (out[:, :5] == 0).all() and (out[:, 5:] == 255).all()
    with pytest.raises(ValueError, match="height"):
        side_by_side(a, np.zeros((3, 5, 3), np.uint8))
    with pytest.raises(ValueError):
        side_by_side(a, np.zeros((4, 5, 3), np.float32))

"""Inputs checked for what they mean, not only their type: intrinsics of a camera of the image's
size, positive depth scales, ground truth that overlaps the frames and moves at a physical speed,
unit quaternions, one image file per list line, profile and section keys in ``--set``, a local
registry path that is a file. Each bad input is an error naming the file and line, the field or
the option, before any image is decoded or any work is done."""

from __future__ import annotations

import os
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from atlas_pipeline.config import load_profile, parse_set_overrides
from atlas_pipeline.errors import ConfigError, DatasetError
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.registry import intrinsics_camera, load_registry
from atlas_pipeline.sensors.tum import load_tum_sequence

# A tiny camera: 16x12 pixels, a 60 degree field of view.
W, H = 16, 12
CAM = CameraIntrinsics(W, H, 14.0, 14.0, 7.5, 5.5, 5000.0)
N_FRAMES = 6
FPS = 30.0
T0_S = 1305031100.0  # a TUM-like epoch stamp
GT_RATE_HZ = 100.0  # motion capture, as TUM's
SPEED_M_PER_S = 0.5  # the recording's camera: a slow hand-held pan along x


def _frame_times() -> np.ndarray:
    return T0_S + np.arange(N_FRAMES) / FPS


def _gt_rows(offset_s: float = 0.0) -> list[str]:
    """Ground truth at 100 Hz over the frames (and 50 ms either side), moving along x."""
    t = np.arange(T0_S - 0.05, _frame_times()[-1] + 0.05, 1.0 / GT_RATE_HZ)
    return [f"{tk + offset_s:.4f} {SPEED_M_PER_S * (tk - T0_S):.4f} 0 1 0 0 0 1" for tk in t]


def _write_tum(root: Path, gt: list[str] | None = None, rgb_names: list[str] | None = None,
               depth_names: list[str] | None = None) -> Path:
    """A TUM folder of ``N_FRAMES`` tiny frames; list lines 1-2 are comments, frame k is on line k + 3."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    for k in range(N_FRAMES):
        iio.imwrite(root / "rgb" / f"{k}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        iio.imwrite(root / "depth" / f"{k}.png", np.full((H, W), 5000 + 100 * k, np.uint16))
    rgb_names = rgb_names or [f"rgb/{k}.png" for k in range(N_FRAMES)]
    depth_names = depth_names or [f"depth/{k}.png" for k in range(N_FRAMES)]
    for name, names in (("rgb.txt", rgb_names), ("depth.txt", depth_names)):
        rows = [f"{t:.6f} {n}" for t, n in zip(_frame_times(), names)]
        (root / name).write_text("# TUM list\n# timestamp filename\n" + "\n".join(rows) + "\n")
    gt = _gt_rows() if gt is None else gt
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    return root


def _load(root: Path, max_frames: int | None = None):
    return load_tum_sequence(root, CAM, "x", max_frames)


def test_a_well_formed_recording_loads_with_ground_truth_at_every_frame(tmp_path):
    m = _load(_write_tum(tmp_path / "seq"))
    assert m.n_frames == N_FRAMES and m.has_gt.all()
    np.testing.assert_allclose(m.T_world_cam_gt[:, 0, 3], SPEED_M_PER_S * (_frame_times() - T0_S), atol=1e-3)


# ---- one image file per list line --------------------------------------------------------------

def _same_file_everywhere(root: Path) -> None:
    _write_tum(root, rgb_names=["rgb/0.png"] * N_FRAMES)


def _dot_alias_in_depth(root: Path) -> None:
    _write_tum(root, depth_names=["depth/0.png", "depth/1.png", "./depth/1.png", "depth/3.png", "depth/4.png",
                                  "depth/5.png"])


def _link_alias_in_rgb(root: Path) -> None:
    _write_tum(root)
    (root / "rgb" / "2.png").unlink()
    os.symlink("0.png", root / "rgb" / "2.png")


@pytest.mark.parametrize("make, message", [
    # line 4 (frame 1) repeats line 3's file
    (_same_file_everywhere, r"rgb\.txt:4: rgb image 'rgb/0\.png' is also named on line 3"),
    (_dot_alias_in_depth, r"depth\.txt:5: depth image '\./depth/1\.png' is also named on line 4"),
    (_link_alias_in_rgb, r"rgb\.txt:5: rgb image 'rgb/2\.png' is the file line 3 names"),
], ids=["one-image-for-every-time", "dot-path-alias", "symbolic-link-alias"])
def test_a_list_naming_one_image_file_twice_names_both_lines(tmp_path, make, message):
    root = tmp_path / "seq"
    make(root)
    with pytest.raises(DatasetError, match=message):
        _load(root)


# ---- ground truth: time overlap, speed, unit quaternions ---------------------------------------

def _gt_with_jump(jump_m: float, at: int = 10) -> list[str]:
    """Ground truth whose x leaps ``jump_m`` from row ``at`` on (file line ``at + 2``)."""
    rows = [r.split() for r in _gt_rows()]
    for r in rows[at:]:
        r[1] = f"{float(r[1]) + jump_m:.4f}"
    return [" ".join(r) for r in rows]


def _gt_with_glitch(jump_m: float, first: int, n_rows: int = 1, rows: list[str] | None = None) -> list[str]:
    """Ground truth (``rows``, else :func:`_gt_rows`) whose x leaps ``jump_m`` for rows
    ``first .. first + n_rows - 1`` only (a marker swap) and comes back."""
    rows = [r.split() for r in (rows or _gt_rows())]
    for r in rows[first:first + n_rows]:
        r[1] = f"{float(r[1]) + jump_m:.4f}"
    return [" ".join(r) for r in rows]


def _gt_sparse(rate_hz: float, lag_s: float) -> list[str]:
    """Ground truth at ``rate_hz``, ``lag_s`` after the frames' clock, over the frames (and one
    sample either side), moving along x as :func:`_gt_rows`."""
    t = T0_S + lag_s + np.arange(-1, round(N_FRAMES / FPS * rate_hz) + 2) / rate_hz
    return [f"{tk:.4f} {SPEED_M_PER_S * (tk - T0_S):.4f} 0 1 0 0 0 1" for tk in t]


def _gt_with_quaternion(q: str, at: int = 7) -> list[str]:
    rows = _gt_rows()
    rows[at] = " ".join(rows[at].split()[:4]) + " " + q
    return rows


@pytest.mark.parametrize("gt, message", [
    # 500 s off the frames' clock: both spans, the offset, never "0 frames with ground truth"
    (_gt_rows(offset_s=-500.0),
     r"groundtruth\.txt: ground truth matches none of the 6 frames: its poses span 1305030599\.950 - "
     r"1305030600\.\d+ s, the frames \(depth\.txt\) 1305031100\.000 - 1305031100\.167 s; the poses end "
     r"49\d\.\d+ s before the first frame"),
    (_gt_rows(offset_s=+500.0), r"groundtruth\.txt: .*the poses start 49\d\.\d+ s after the last frame"),
    # 5 m (and 5 mm of the pan) between two samples 10 ms apart: rows 10 and 11 on lines 11 and 12
    # the path goes on 5 m away: the frames on each side named, the scene would be there twice
    (_gt_with_jump(5.0), r"groundtruth\.txt:12: the camera moves 5\.01 m in 0\.01 s from line 11 \(t = "
                         r"1305031100\.0400\) to this line \(t = 1305031100\.0500\): 501 m/s, faster "
                         r"than the 20 m/s .*and the path goes on from there .*; frames 0-1 read poses before it, "
                         r"frames 2-5 after it: the scene would be mapped twice, 5\.01 m apart"),
    # away for 8 rows (80 ms) before coming back: longer than a glitch, refused like a jump
    (_gt_with_glitch(5.0, first=12, n_rows=8),
     r"groundtruth\.txt:14: the camera moves 5 m in 0\.01 s from line 13 .*does not come back within 5 rows\); "
     r"frames 0-1 read poses before it, frames 3-5 after it, frame 2 across it"),
    (_gt_with_quaternion("0 0 1e-6 1e-6"), r"groundtruth\.txt:9: quaternion qx qy qz qw \(0, 0, 1e-6, 1e-6\) has "
                                           r"norm 1\.41421e-06, not 1"),
    (_gt_with_quaternion("0 0 0 2"), r"groundtruth\.txt:9: quaternion .* has norm 2, not 1"),
], ids=["500-s-early", "500-s-late", "5-m-jump", "8-rows-away", "quaternion-norm-1e-6", "quaternion-norm-2"])
def test_ground_truth_that_cannot_be_this_cameras_path_names_file_and_line(tmp_path, gt, message):
    root = _write_tum(tmp_path / "seq", gt=gt)
    with pytest.raises(DatasetError, match=message):
        _load(root)


@pytest.mark.parametrize("gt", [
    _gt_with_quaternion("0 0 0.7071 0.7071"),  # printed to 4 digits: norm 0.99999, a 90 degree turn
    _gt_with_jump(0.04),  # 4 cm in 10 ms (4 m/s): motion capture noise, not a jump
    _gt_with_jump(0.15),  # 15 m/s: fast, still a camera a person can carry
], ids=["rounded-quaternion", "jitter", "fast-but-physical"])
def test_ground_truth_within_tolerance_loads(tmp_path, gt):
    assert _load(_write_tum(tmp_path / "seq", gt=gt)).has_gt.all()


# Row i of _gt_rows is at T0 - 0.05 + 0.01 i s on file line i + 2; frame k at T0 + k / 30 s. Frame 3
# (T0 + 0.1) is row 15's time: it reads rows 14 and 15 (lines 16-17); frame 5 reads rows 21 and 22.
@pytest.mark.parametrize("gt, max_frames, has_gt, message", [
    # one row 5 m away and back: dropped, frame 3 interpolated between the rows around it
    (_gt_with_glitch(5.0, first=15), None, [True] * 6,
     r"groundtruth\.txt: line 17 \(t = 1305031100\.1000\) jumps 5 m away from line 16 and back to line 18 "
     r"\(50\d m/s, faster than the 20 m/s a camera moves\): a motion-capture glitch .*left out; frame 3 reads it: "
     r"now 1 interpolated between the rows around it"),
    # three rows away (30 ms): a glitch still
    (_gt_with_glitch(5.0, first=14, n_rows=3), None, [True] * 6,
     r"groundtruth\.txt: lines 16-18 \(t = 1305031100\.0900 - 1305031100\.1100\) jump 5\.01 m away from line 15 "
     r"and back to line 19 .*frame 3 reads them: now 1 interpolated"),
    # the last row the last frame reads
    (_gt_with_glitch(-3.0, first=22), None, [True] * 6, r"groundtruth\.txt: line 24 .*frame 5 reads it"),
    # ground truth at 15 Hz, 10 ms after each frame: without the glitch row the rows around frames
    # 1-4 are 0.13 s apart (no interpolation); frame 4 takes the row 10 ms away, frames 1-3 none
    (_gt_with_glitch(5.0, first=2, rows=_gt_sparse(15.0, 0.01)), None, [True, False, False, False, True, True],
     r"groundtruth\.txt: line 4 .*frames 1-4 read it: now 1 from the nearest row left within 20 ms, 3 without "
     r"ground truth"),
    # rows no kept frame reads: a jump after dataset.max_frames, a jump before the frames' time
    (_gt_with_jump(5.0, at=20), 2, [True] * 2, None),
    (_gt_with_jump(5.0, at=2), None, [True] * 6, None),
], ids=["one-row-glitch", "three-row-glitch", "glitch-on-last-row-read", "sparse-ground-truth-loses-frames",
        "jump-after-max-frames", "jump-before-the-frames"])
def test_ground_truth_is_judged_where_the_frames_read_it_and_glitches_are_left_out(tmp_path, caplog, gt, max_frames,
                                                                                 has_gt, message):
    caplog.set_level("WARNING", logger="atlas_pipeline.sensors.tum")
    m = _load(_write_tum(tmp_path / "seq", gt=gt), max_frames=max_frames)
    assert m.has_gt.tolist() == has_gt
    # the frames with ground truth are on the camera's path, never on a glitch or the far side of a
    # jump (within the 5 mm a pose taken from a row 10 ms away is off at 0.5 m/s)
    x_m = m.T_world_cam_gt[m.has_gt, 0, 3]
    shift_m = 5.0 if gt == _gt_with_jump(5.0, at=2) else 0.0  # every frame reads the rows after that jump
    np.testing.assert_allclose(x_m, SPEED_M_PER_S * (_frame_times()[:m.n_frames][m.has_gt] - T0_S) + shift_m,
                               atol=6e-3)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    if message is None:
        assert not warned, warned
    else:
        assert len(warned) == 1 and re.search(message, warned[0]), warned


def test_many_ground_truth_glitches_are_named_once_each_up_to_five_then_summed_up(tmp_path, caplog):
    gt = _gt_rows()
    for row in (5, 8, 11, 14, 17, 20):  # every third row, lines 7 ... 22
        gt = _gt_with_glitch(1.0, first=row, rows=gt)
    caplog.set_level("WARNING", logger="atlas_pipeline.sensors.tum")
    m = _load(_write_tum(tmp_path / "seq", gt=gt))
    assert m.has_gt.all()
    np.testing.assert_allclose(m.T_world_cam_gt[:, 0, 3], SPEED_M_PER_S * (_frame_times() - T0_S), atol=2e-3)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 6 and all("motion-capture glitch" in w for w in warned[:5]), warned
    assert warned[5].endswith("groundtruth.txt: 1 more glitch(es) left out likewise (line 22)"), warned


def test_ground_truth_with_a_gap_over_the_whole_clip_names_the_gap_not_another_recording(tmp_path):
    """Poses before and after the frames but none within 0.1 s of any: the error names the gap's
    times and lines and the frames in it, not "another recording's ground truth"."""
    gap = [r for r in _gt_rows() if not T0_S - 0.025 < float(r.split()[0]) < T0_S + 0.195]
    with pytest.raises(DatasetError) as err:
        _load(_write_tum(tmp_path / "seq", gt=gap))
    msg = str(err.value)
    assert re.search(r"groundtruth\.txt: ground truth matches none of the 6 frames: .*the poses have gaps where the "
                     r"frames are: frames 0-5 in a gap from t = 1305031099\.970 \(line 4\) to 1305031100\.200 "
                     r"\(line 5\), 0\.23 s without a pose", msg), msg
    assert "another recording" not in msg and "clock" not in msg


def test_ground_truth_of_later_frames_is_no_error_when_only_earlier_frames_are_read(tmp_path):
    """The check is against the whole recording: ``max_frames`` keeping frames before the ground
    truth starts reads them without it (as before), never as a wrong file."""
    late = [r for r in _gt_rows() if float(r.split()[0]) > _frame_times()[3] - 0.01]
    m = _load(_write_tum(tmp_path / "seq", gt=late), max_frames=2)
    assert m.n_frames == 2 and not m.has_gt.any()


def test_a_ground_truth_path_that_is_a_folder_is_named(tmp_path):
    root = _write_tum(tmp_path / "seq")
    (root / "groundtruth.txt").unlink()
    (root / "groundtruth.txt").mkdir()
    with pytest.raises(DatasetError, match=r"groundtruth\.txt: ground-truth file is a directory"):
        _load(root)


def _pose_rows(jump_m: float, at: int = 3) -> list[np.ndarray]:
    """Camera-to-world poses of ``N_FRAMES`` frames at 30 Hz panning along x, leaping ``jump_m``
    from frame ``at`` on."""
    out = []
    for k in range(N_FRAMES):
        T = np.eye(4)
        T[0, 3] = SPEED_M_PER_S * k / FPS + (jump_m if k >= at else 0.0)
        out.append(T)
    return out


def _write_replica(root: Path, poses: list[np.ndarray]) -> Path:
    (root / "results").mkdir(parents=True)
    for k in range(N_FRAMES):
        iio.imwrite(root / "results" / f"frame{k:06d}.png", np.full((H, W, 3), 40 * k, np.uint8))
        iio.imwrite(root / "results" / f"depth{k:06d}.png", np.full((H, W), 6554, np.uint16))
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.6f}" for v in T.ravel()) + "\n" for T in poses))
    return root


def _write_7scenes(root: Path, poses: list[np.ndarray]) -> Path:
    root.mkdir(parents=True)
    for k in range(N_FRAMES):
        iio.imwrite(root / f"frame-{k:06d}.color.png", np.full((H, W, 3), 40 * k, np.uint8))
        iio.imwrite(root / f"frame-{k:06d}.depth.png", np.full((H, W), 1000, np.uint16))
        (root / f"frame-{k:06d}.pose.txt").write_text("\n".join(" ".join(f"{v:.6f}" for v in r) for r in poses[k]))
    return root


@pytest.mark.parametrize("layout", ["replica", "7scenes"])
def test_poses_of_other_layouts_moving_faster_than_a_camera_name_the_file(tmp_path, layout):
    from atlas_pipeline.sensors.layouts import load_7scenes_sequence, load_replica_sequence

    write, load = {"replica": (_write_replica, load_replica_sequence),
                   "7scenes": (_write_7scenes, load_7scenes_sequence)}[layout]
    assert load(write(tmp_path / "ok", _pose_rows(0.0)), CAM, "x").has_gt.all()
    # 2 m between frames 2 and 3, 1/30 s apart at the default 30 fps: 60 m/s
    root = write(tmp_path / "bad", _pose_rows(2.0))
    where = r"traj\.txt:4: .*from frame 2 \(line 3\)" if layout == "replica" else \
        r"frame-000003\.pose\.txt: .*from frame 2 \(frame-000002\.pose\.txt\)"
    with pytest.raises(DatasetError, match=rf"{where} to frame 3, 0\.0333 s later at 30 fps \(registry key fps\): "
                                           r"60\.\d m/s, faster than the 20 m/s"):
        load(root, CAM, "x")


@pytest.mark.parametrize("layout, glitch_frames, message", [
    ("replica", [3], r"the pose of frame 3 \(traj\.txt line 4\) jumps 2\.02 m away from frame 2 and back at frame 4 "
                     r"\(60\.\d m/s at 30 fps.*left out \(frame 3 without ground truth\)"),
    ("7scenes", [2, 3], r"the poses of frames 2-3 \(frame-000002\.pose\.txt - frame-000003\.pose\.txt\) jump 2\.03 m "
                        r"away from frame 1 and back at frame 4"),
], ids=["replica-one-frame", "7scenes-two-frames"])
def test_a_pose_that_jumps_away_and_back_leaves_that_frame_without_ground_truth(tmp_path, caplog, layout,
                                                                                glitch_frames, message):
    from atlas_pipeline.sensors.layouts import load_7scenes_sequence, load_replica_sequence

    write, load = {"replica": (_write_replica, load_replica_sequence),
                   "7scenes": (_write_7scenes, load_7scenes_sequence)}[layout]
    poses = _pose_rows(0.0)
    for k in glitch_frames:
        poses[k][0, 3] += 2.0
    caplog.set_level("WARNING", logger="atlas_pipeline.sensors.layouts")
    m = load(write(tmp_path / "seq", poses), CAM, "x")
    assert m.has_gt.tolist() == [k not in glitch_frames for k in range(N_FRAMES)]
    np.testing.assert_allclose(m.T_world_cam_gt[m.has_gt, 0, 3], SPEED_M_PER_S * np.flatnonzero(m.has_gt) / FPS,
                               atol=1e-5)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and re.search(message, warned[0]), warned


# ---- depth in range, judged on every pixel --------------------------------------------------------

STRIDE = 4  # the fusion grid: pixels (0, 0), (0, 4), ... (8, 12)
FAR_M = 13.107  # TUM's 65535 / 5000: a reading, beyond fusion.max_depth_m (4 m)


def _off_grid(value_m: float, base: np.ndarray | None = None) -> np.ndarray:
    """``[H, W]`` depth (``base``, else none) with ``value_m`` on a few pixels off the stride grid,
    as sparse depth (a projected lidar) has them."""
    d = np.zeros((H, W), np.float32) if base is None else base.copy()
    d[1::STRIDE, 2::STRIDE] = value_m
    return d


def _near_and_far_off_grid() -> np.ndarray:
    d = _off_grid(0.05)
    d[3, 3] = 9.0
    return d


@pytest.mark.parametrize("depth_m, message", [
    (_off_grid(2.0), None),  # readings in range, none on the grid: usable, not "out of range"
    (_off_grid(2.0, np.full((H, W), FAR_M, np.float32)), None),  # far on the grid, in range between
    (np.full((H, W), FAR_M, np.float32), r"6 of its 6 depth images have readings \(from 13\.1 to 13\.1 m\) but none "
                                         r"within the depth range 0\.1-4 m \(fusion\.min_depth_m"),
    # too near and too far, all off the grid: the range seen is the readings', outside 0.1-4 m
    (_near_and_far_off_grid(), r"6 of its 6 depth images have readings \(from 0\.05 to 9 m\) but none within"),
], ids=["sparse-in-range", "far-grid-in-range-between", "all-far", "sparse-near-and-far"])
def test_depth_in_range_is_judged_on_every_pixel_not_the_stride_grid(tmp_path, depth_m, message):
    from atlas_pipeline.config import FusionConfig
    from atlas_pipeline.perception.rgbd import FrameFuser

    m = _load(_write_tum(tmp_path / "seq"))
    rgb = np.zeros((H, W, 3), np.uint8)
    with FrameFuser(m, FusionConfig(stride=STRIDE)) as fuser:
        for i in range(m.n_frames):
            fuser.add(i, rgb, depth_m)
        if message is None:
            fuser.check_depth()
        else:
            with pytest.raises(DatasetError, match=message) as err:
                fuser.check_depth()
            assert str(m.root) in str(err.value) and "--depth-scale" in str(err.value)


# ---- intrinsics and scales -----------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, message", [
    (dict(intrinsics="517 516 900 255"), r"^--intrinsics '517 516 900 255' with a 640x480 image: principal point "
                                         r"cx=900 lies outside the image \(640 pixels wide: cx must be in \[0, 640\]\)"),
    (dict(intrinsics="517 516 318 -40"), r"--intrinsics .*principal point cy=-40 lies outside the image"),
    # divided by the image size (fx 517 / 640 = 0.81)
    (dict(intrinsics="0.81 0.81 0.5 0.5"), r"--intrinsics .*focal length fx=0\.81 gives a 179\.7 degree field of "
                                           r"view on 640 pixels \(at most 170\): focal lengths are in pixels"),
    # in millimetres (a RealSense D435's 1.93 mm)
    (dict(intrinsics="1.93 1.93 320 240"), r"--intrinsics .*focal length fx=1\.93 gives a 179\.3 degree field"),
    (dict(intrinsics="517 210 318 255"), r"--intrinsics .*fx=517 and fy=210 differ by a factor 2\.46"),
    (dict(intrinsics="517 516 318 255", depth_units_per_m=0.0), r"^--depth-scale must be a finite positive number"),
    (dict(intrinsics="517 516 318 255", depth_units_per_m=float("nan")), r"^--depth-scale must be"),
    (dict(intrinsics="517 516 318 255", width_px=0), r"^--width must be a positive whole number of pixels, got 0"),
    (dict(intrinsics="517 516 318 255", height_px=-480), r"^--height must be a positive whole number"),
], ids=["cx-outside", "cy-negative", "normalised", "millimetres", "swapped-order", "depth-scale-0", "depth-scale-nan",
        "width-0", "height-negative"])
def test_intrinsics_that_are_no_camera_of_the_image_name_the_option(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        intrinsics_camera("tum", **kwargs)


def test_given_sizes_and_scales_are_used_not_replaced_by_defaults():
    cam = intrinsics_camera("tum", "131.25 131.25 79.5 59.5", 160, 120, 1000.0)
    assert (cam["width"], cam["height"], cam["depth_scale"]) == (160, 120, 1000.0)


@pytest.mark.parametrize("camera, message", [
    ({"width": 640, "height": 480, "fx": 517, "fy": 516, "cx": 900, "cy": 255}, r"cx=900 lies outside"),
    ({"width": 640, "height": 480, "fx": 517, "fy": 516, "cx": 318, "cy": 255, "depth_scale": 0},
     r"depth_scale must be finite and positive, got 0"),
    ({"width": 0, "height": 480, "fx": 517, "fy": 516, "cx": 318, "cy": 255}, r"camera size must be positive"),
], ids=["cx-outside", "depth-scale-0", "width-0"])
def test_a_registry_camera_names_the_file_and_entry(tmp_path, camera, message):
    reg = tmp_path / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {"mine": {"kind": "tum", "path": str(tmp_path), "camera": camera}}}))
    with pytest.raises(ConfigError, match=rf"^{reg}: datasets\.mine\.camera: .*{message}"):
        load_registry([reg])


# ---- --set: profile, sections --------------------------------------------------------------------

@pytest.mark.parametrize("item, message", [
    ("profile=demo", r"^--set: profile must be chosen with --profile demo \(or \$ATLAS_PROFILE\), not set"),
    ("mapping=null", r"^--set: mapping is a section of settings, not a value: got null; set its keys "
                     r"\(mapping\.pose_source, "),
    ("mapping.fit=null", r"^--set: mapping\.fit is a section of settings, not a value: got null"),
    ("localization=3", r"^--set: localization is a section of settings, not a value: got 3"),
    ("mapping={fit: 0}", r"^--set: mapping\.fit is a section of settings, not a value: got 0"),
    ("mapping={voxel_sise_m: 0.04}", r"^--set: unknown config key 'mapping\.voxel_sise_m'"),
], ids=["profile", "section-null", "nested-section-null", "section-number", "nested-in-mapping", "typo-in-mapping"])
def test_set_of_a_profile_or_a_whole_section_names_the_key(item, message):
    with pytest.raises(ConfigError, match=message):
        load_profile("default").with_overrides(parse_set_overrides([item]), "--set")


def test_set_of_a_section_mapping_sets_those_keys_and_keeps_the_profiles_others():
    demo = load_profile("demo")
    cfg = demo.with_overrides(parse_set_overrides(["mapping={voxel_size_m: 0.05, fit: {epochs: 2}}"]), "--set")
    assert cfg.mapping.voxel_size_m == 0.05 and cfg.mapping.fit.epochs == 2
    assert cfg.mapping.fit.max_steps == demo.mapping.fit.max_steps and cfg.dataset == demo.dataset
    assert cfg.profile == "demo"


# ---- the local registry's path -------------------------------------------------------------------

@pytest.mark.parametrize("make, what", [
    (lambda p: p.mkdir(), "is a directory"),
    (lambda p: os.mkfifo(p), r"is not a regular file \(a FIFO\)"),
], ids=["directory", "fifo"])
def test_a_local_registry_that_is_no_file_names_the_variable_and_path(tmp_path, monkeypatch, make, what):
    reg = tmp_path / "registry"
    make(reg)
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(reg))
    with pytest.raises(ConfigError, match=rf"^ATLAS_LOCAL_REGISTRY={reg}: {what}"):
        load_registry()


def test_an_absent_local_registry_is_no_local_entries(tmp_path, monkeypatch):
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(tmp_path / "none.yaml"))
    assert "synthetic" in load_registry()


# ---- the command line: exit 2, one line naming the option, nothing registered -------------------

@pytest.mark.parametrize("extra, message", [
    (["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120", "--depth-scale", "0"],
     "--depth-scale must be a finite positive number"),
    (["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "0", "--height", "0"], "--width must be a positive"),
    (["--intrinsics", "517 516 900 255"], "principal point cx=900 lies outside the image"),
    (["--depth-scale", "1000"], "--depth-scale is used only with --intrinsics"),
], ids=["depth-scale-0", "size-0", "cx-outside", "depth-scale-without-intrinsics"])
def test_dataset_add_refuses_meaningless_camera_options(isolated, small_synthetic, capsys, extra, message):
    from assets.cli import main

    reg = Path(os.environ["ATLAS_LOCAL_REGISTRY"])
    before = reg.read_text()
    assert main(["dataset", "add", "mine", str(small_synthetic), *extra]) == 2
    assert message in capsys.readouterr().err
    assert reg.read_text() == before  # nothing registered


def test_commands_refuse_a_profile_override_and_a_registry_folder(isolated, monkeypatch, capsys):
    from assets.cli import main

    assert main(["build", "--input", "synth-small", "--output", str(isolated / "w"), "--set", "profile=demo"]) == 2
    assert "--set: profile must be chosen with --profile demo" in capsys.readouterr().err
    assert not (isolated / "w").exists() and not (isolated / "data").exists()  # nothing generated or written
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(isolated))
    for argv in (["dataset", "list"], ["status", "synth-small"]):
        assert main(argv) == 2
        assert f"ATLAS_LOCAL_REGISTRY={isolated}: is a directory" in capsys.readouterr().err

"""Inputs checked for what they mean, not only their type: intrinsics of a camera of the image's
size, positive depth scales, ground truth that overlaps the frames and moves at a physical speed,
unit quaternions, one image file per list line, profile and section keys in ``--set``, a local
registry path that is a file. Each bad input is an error naming the file and line, the field or
the option, before any image is decoded or any work is done."""

from __future__ import annotations

import os
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
    (_gt_with_jump(5.0), r"groundtruth\.txt:12: the camera moves 5\.01 m in 0\.01 s from line 11 \(t = "
                         r"1305031100\.0400\) to this line \(t = 1305031100\.0500\): 501 m/s, faster "
                         r"than the 20 m/s"),
    (_gt_with_quaternion("0 0 1e-6 1e-6"), r"groundtruth\.txt:9: quaternion qx qy qz qw \(0, 0, 1e-6, 1e-6\) has "
                                           r"norm 1\.41421e-06, not 1"),
    (_gt_with_quaternion("0 0 0 2"), r"groundtruth\.txt:9: quaternion .* has norm 2, not 1"),
], ids=["500-s-early", "500-s-late", "5-m-jump", "quaternion-norm-1e-6", "quaternion-norm-2"])
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

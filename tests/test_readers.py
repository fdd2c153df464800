"""Dataset readers: each layout written here in its exact form, read into the same
FrameManifest: TUM with JPEG colour, 7-Scenes, Replica (NICE-SLAM release), ScanNet (SensReader
export), ROS 1 and ROS 2 bags. No network; small frames."""

from __future__ import annotations

import json
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.images import colour_sampling_map, resample_rgb
from atlas_pipeline.sensors.layouts import (
    REPLICA_CAMERA,
    SEVEN_SCENES_CAMERA,
    detect_kind,
    load_7scenes_sequence,
    load_replica_sequence,
    load_scannet_sequence,
)
from atlas_pipeline.sensors.tum import FrameManifest, load_tum_sequence

# ScanNet scene0000_00's calibration (intrinsic_color.txt / intrinsic_depth.txt of the export).
SCANNET_KC = (1170.187988, 1170.187988, 647.75, 483.75)
SCANNET_KD = (577.590698, 578.729797, 318.905426, 242.683609)


def _pose(k: int) -> np.ndarray:
    """A camera-to-world pose of frame ``k``: a turn about z and y, a step along x and z."""
    a, b = np.radians(7.0 * k), np.radians(3.0 * k)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry
    T[:3, 3] = [0.1 * k, -0.03 * k, 0.5 + 0.02 * k]
    return T


def _rgb(h: int, w: int, k: int) -> np.ndarray:
    """Colour ``[H, W, 3]``: smooth ramps (JPEG keeps them within a few levels) shifted per frame."""
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([(u * 200 // max(w - 1, 1) + 10 * k) % 256, v * 200 // max(h - 1, 1),
                     np.full_like(u, 60 + 20 * k)], axis=-1).astype(np.uint8)


def _depth_m(h: int, w: int, k: int) -> np.ndarray:
    """Depth ``[H, W]`` metres: a slanted plane 1-2 m, different per frame."""
    v, u = np.mgrid[0:h, 0:w]
    return (1.0 + u / w + 0.1 * k + 0.2 * v / h).astype(np.float64)


def _write_matrix(path: Path, T: np.ndarray, sep: str = " ", trailing: str = "") -> None:
    path.write_text("".join(sep.join(f"{x:.10e}" for x in row) + trailing + "\n" for row in T))


def _has_error(exc: pytest.ExceptionInfo, name: str, line: int | None = None) -> None:
    assert exc.value.path.name == name, str(exc.value)
    if line is not None:
        assert exc.value.line == line, str(exc.value)


# ---- TUM with JPEG colour --------------------------------------------------------------------------


def _tum(root: Path, n: int = 4, h: int = 48, w: int = 64, ext: str = "jpg") -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, gt = [], [], []
    for k in range(n):
        t = 100.0 + k / 30
        iio.imwrite(root / "rgb" / f"{t:.6f}.{ext}", _rgb(h, w, k), **({"quality": 95} if ext == "jpg" else {}))
        iio.imwrite(root / "depth" / f"{t + 0.004:.6f}.png", np.rint(_depth_m(h, w, k) * 5000).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.{ext}")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        from atlas_pipeline.geometry import tq_from_pose

        tt, q = tq_from_pose(_pose(k))
        gt.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in [*tt, *q]))
    (root / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    return root


def test_tum_reads_jpeg_colour(tmp_path):
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 5000.0)
    m = load_tum_sequence(_tum(tmp_path / "tum"), cam, "t")
    assert detect_kind(tmp_path / "tum") == "tum"
    assert m.n_frames == 4 and m.rgb_files[0].endswith(".jpg") and m.has_gt.all()
    rgb = m.read_rgb(2)
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
    assert np.abs(rgb.astype(int) - _rgb(48, 64, 2)).mean() < 3  # JPEG at quality 95
    np.testing.assert_allclose(m.read_depth_m(1), _depth_m(48, 64, 1), atol=1e-4)
    np.testing.assert_allclose(m.T_world_cam_gt[3], _pose(3), atol=1e-6)


def test_tum_jpeg_of_wrong_size_or_grey_names_file_and_line(tmp_path):
    root = _tum(tmp_path / "tum")
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 5000.0)
    name = sorted((root / "rgb").iterdir())[1].name
    iio.imwrite(root / "rgb" / name, np.zeros((48, 64), np.uint8), quality=90)  # greyscale JPEG
    with pytest.raises(DatasetError, match=r"8-bit colour PNG or JPEG .*rgb.txt line 3") as exc:
        load_tum_sequence(root, cam, "t")
    _has_error(exc, name)
    (root / "rgb" / name).write_bytes(b"\xff\xd8\xff\xe0garbage")  # JPEG marker, broken header
    with pytest.raises(DatasetError, match="JPEG header") as exc:
        load_tum_sequence(root, cam, "t")
    _has_error(exc, name)


def test_manifest_saved_before_layouts_still_loads_and_reads(tmp_path):
    cam = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5, 5000.0)
    m = load_tum_sequence(_tum(tmp_path / "tum", ext="png"), cam, "t")
    m.save(tmp_path / "saved")
    meta = json.loads((tmp_path / "saved" / "manifest.json").read_text())
    del meta["source"]  # as manifests written before these readers
    (tmp_path / "saved" / "manifest.json").write_text(json.dumps(meta))
    old = FrameManifest.load(tmp_path / "saved")
    assert old.source == {} and old.colour_camera == cam
    np.testing.assert_array_equal(old.read_rgb(1), _rgb(48, 64, 1))
    np.testing.assert_allclose(old.read_depth_m(1), _depth_m(48, 64, 1), atol=1e-4)


# ---- 7-Scenes ----------------------------------------------------------------------------------


def _seven_scenes(scene: Path, n: int = 4, seq: str = "seq-01") -> Path:
    folder = scene / seq
    folder.mkdir(parents=True)
    h, w = SEVEN_SCENES_CAMERA.height, SEVEN_SCENES_CAMERA.width
    for k in range(n):
        ext = "jpg" if k == 1 else "png"  # the release is PNG; JPEG conversions are common
        iio.imwrite(folder / f"frame-{k:06d}.color.{ext}", _rgb(h, w, k), **({"quality": 95} if ext == "jpg" else {}))
        raw = np.rint(_depth_m(h, w, k) * 1000).astype(np.uint16)
        raw[:10, :20] = 65535  # the Kinect's "no reading"
        raw[10:20, :20] = 0
        iio.imwrite(folder / f"frame-{k:06d}.depth.png", raw)
        _write_matrix(folder / f"frame-{k:06d}.pose.txt", _pose(k), sep="\t", trailing="\t")  # as 7-Scenes writes
    return folder


def test_7scenes_sequence(tmp_path):
    folder = _seven_scenes(tmp_path / "chess")
    assert detect_kind(folder) == "7scenes" and detect_kind(tmp_path / "chess") == "7scenes"
    m = load_7scenes_sequence(folder, SEVEN_SCENES_CAMERA, "chess")
    assert m.n_frames == 4 and m.camera == SEVEN_SCENES_CAMERA and m.camera.depth_scale == 1000
    np.testing.assert_allclose(m.timestamps_s, np.arange(4) / 30.0)
    d = m.read_depth_m(2)
    assert (d[:20, :20] == 0).all()  # 65535 and 0 both "no reading"
    np.testing.assert_allclose(d[20:], _depth_m(480, 640, 2)[20:], atol=6e-4)
    assert m.read_rgb(0).shape == (480, 640, 3)
    np.testing.assert_array_equal(m.read_rgb(0), _rgb(480, 640, 0))
    assert np.abs(m.read_rgb(1).astype(int) - _rgb(480, 640, 1)).mean() < 3
    assert m.has_gt.all()
    np.testing.assert_allclose(m.T_world_cam_gt, np.stack([_pose(k) for k in range(4)]), atol=1e-6)
    # the scene folder plus a sequence, and an fps override
    m2 = load_7scenes_sequence(tmp_path / "chess", SEVEN_SCENES_CAMERA, "chess", fps=15, sequence="seq-01")
    np.testing.assert_allclose(m2.timestamps_s, np.arange(4) / 15.0)
    assert m2.content_hash == m.content_hash
    with pytest.raises(DatasetError, match="scene folder"):
        load_7scenes_sequence(tmp_path / "chess", SEVEN_SCENES_CAMERA, "chess")
    # the content hash covers the pose files too
    _write_matrix(folder / "frame-000003.pose.txt", _pose(4))
    assert load_7scenes_sequence(folder, SEVEN_SCENES_CAMERA, "chess").content_hash != m.content_hash


def test_7scenes_malformed_pose_and_missing_depth(tmp_path):
    folder = _seven_scenes(tmp_path / "chess")
    (folder / "frame-000002.pose.txt").write_text("1 0 0 0\n0 1 0 x\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match="not a number") as exc:
        load_7scenes_sequence(folder, SEVEN_SCENES_CAMERA, "chess")
    _has_error(exc, "frame-000002.pose.txt", 2)
    (folder / "frame-000002.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(DatasetError, match="4 rows") as exc:
        load_7scenes_sequence(folder, SEVEN_SCENES_CAMERA, "chess")
    _has_error(exc, "frame-000002.pose.txt")
    _write_matrix(folder / "frame-000002.pose.txt", _pose(2))
    (folder / "frame-000003.depth.png").unlink()
    with pytest.raises(DatasetError, match="frame-000003.depth.png") as exc:
        load_7scenes_sequence(folder, SEVEN_SCENES_CAMERA, "chess")
    _has_error(exc, "frame-000003.color.png")


# ---- Replica (NICE-SLAM / iMAP release) ------------------------------------------------------------


def _replica(root: Path, n: int = 4) -> Path:
    (root / "results").mkdir(parents=True)
    h, w = REPLICA_CAMERA.height, REPLICA_CAMERA.width
    lines = []
    for k in range(n):
        iio.imwrite(root / "results" / f"frame{k:06d}.jpg", _rgb(h, w, k), quality=95)
        raw = np.rint(_depth_m(h, w, k) * 6553.5).astype(np.uint16)
        raw[:5] = 0
        iio.imwrite(root / "results" / f"depth{k:06d}.png", raw)
        lines.append(" ".join(f"{x:.18e}" for x in _pose(k).ravel()))
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    return root


def test_replica_sequence(tmp_path):
    root = _replica(tmp_path / "room0")
    assert detect_kind(root) == "replica"
    m = load_replica_sequence(root, REPLICA_CAMERA, "room0")
    assert m.n_frames == 4 and m.camera.depth_scale == 6553.5 and m.rgb_files[0] == "results/frame000000.jpg"
    d = m.read_depth_m(3)
    assert d.shape == (680, 1200) and (d[:5] == 0).all()
    np.testing.assert_allclose(d[5:], _depth_m(680, 1200, 3)[5:], atol=1e-4)
    np.testing.assert_allclose(m.T_world_cam_gt, np.stack([_pose(k) for k in range(4)]), atol=1e-9)
    np.testing.assert_allclose(m.timestamps_s, np.arange(4) / 30.0)


def test_replica_malformed_trajectory(tmp_path):
    root = _replica(tmp_path / "room0")
    lines = (root / "traj.txt").read_text().splitlines()
    lines[2] = " ".join(lines[2].split()[:15])
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="16 numbers") as exc:
        load_replica_sequence(root, REPLICA_CAMERA, "room0")
    _has_error(exc, "traj.txt", 3)
    (root / "traj.txt").write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(DatasetError, match="needs pose line 4") as exc:
        load_replica_sequence(root, REPLICA_CAMERA, "room0")
    _has_error(exc, "traj.txt")


# ---- ScanNet export --------------------------------------------------------------------------------


def _k4(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float)


SQUARE_AT = (800.0, 300.0)  # centre of a white square in every colour image (colour pixels)


def _scannet(root: Path, n: int = 3) -> Path:
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    _write_matrix(root / "intrinsic" / "intrinsic_color.txt", _k4(*SCANNET_KC))
    _write_matrix(root / "intrinsic" / "intrinsic_depth.txt", _k4(*SCANNET_KD))
    for k in range(n):
        rgb = np.full((968, 1296, 3), 40, np.uint8)
        x, y = SQUARE_AT
        rgb[int(y) - 20:int(y) + 21, int(x) - 20:int(x) + 21] = 255
        iio.imwrite(root / "color" / f"{k}.jpg", rgb, quality=95)
        iio.imwrite(root / "depth" / f"{k}.png", np.rint(_depth_m(480, 640, k) * 1000).astype(np.uint16))
        if k == 1:
            (root / "pose" / f"{k}.txt").write_text("-inf -inf -inf -inf\n" * 4)  # ScanNet's lost tracking
        else:
            _write_matrix(root / "pose" / f"{k}.txt", _pose(k))
    return root


def test_scannet_export_resamples_colour_onto_depth(tmp_path):
    root = _scannet(tmp_path / "scene0000_00")
    assert detect_kind(root) == "scannet"
    m = load_scannet_sequence(root, "scene")
    assert m.n_frames == 3 and (m.camera.width, m.camera.height) == (640, 480)
    assert (m.camera.fx, m.camera.fy, m.camera.cx, m.camera.cy) == SCANNET_KD and m.camera.depth_scale == 1000
    assert m.colour_camera.width == 1296 and m.colour_camera.fx == SCANNET_KC[0]
    assert m.has_gt.tolist() == [True, False, True]
    np.testing.assert_allclose(m.T_world_cam_gt[2], _pose(2), atol=1e-6)
    np.testing.assert_allclose(m.read_depth_m(0), _depth_m(480, 640, 0), atol=6e-4)
    rgb = m.read_rgb(0)
    assert rgb.shape == (480, 640, 3)
    # the square lands where K_depth K_colour^-1 puts it
    fxc, fyc, cxc, cyc = SCANNET_KC
    fxd, fyd, cxd, cyd = SCANNET_KD
    u_exp = (SQUARE_AT[0] - cxc) * fxd / fxc + cxd
    v_exp = (SQUARE_AT[1] - cyc) * fyd / fyc + cyd
    bright = rgb[..., 0].astype(float) - 40
    vv, uu = np.mgrid[0:480, 0:640]
    w = np.clip(bright, 0, None)
    assert abs((uu * w).sum() / w.sum() - u_exp) < 0.3 and abs((vv * w).sum() / w.sum() - v_exp) < 0.3
    # saved and loaded, the manifest still resamples
    m.save(tmp_path / "saved")
    back = FrameManifest.load(tmp_path / "saved")
    np.testing.assert_array_equal(back.read_rgb(0), rgb)
    assert back.source["colour_camera"] == m.source["colour_camera"]


def test_scannet_malformed_files(tmp_path):
    root = _scannet(tmp_path / "scene")
    (root / "intrinsic" / "intrinsic_depth.txt").write_text("577 0 319\n")
    with pytest.raises(DatasetError, match="expected 4 numbers") as exc:
        load_scannet_sequence(root, "scene")
    _has_error(exc, "intrinsic_depth.txt", 1)
    _write_matrix(root / "intrinsic" / "intrinsic_depth.txt", _k4(*SCANNET_KD))
    (root / "pose" / "2.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n0 0 0 1\n")
    with pytest.raises(DatasetError, match="more than 4 rows") as exc:
        load_scannet_sequence(root, "scene")
    _has_error(exc, "2.txt", 5)
    (root / "pose" / "2.txt").unlink()
    iio.imwrite(root / "depth" / "2.png", np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(DatasetError, match="16-bit greyscale") as exc:
        load_scannet_sequence(root, "scene")
    _has_error(exc, "2.png")


def test_resample_puts_a_dot_where_k_says():
    colour = CameraIntrinsics(200, 100, 180.0, 170.0, 101.0, 48.0, 1000.0)
    depth = CameraIntrinsics(80, 60, 60.0, 55.0, 40.0, 30.0, 1000.0)
    u, v = 50, 20  # a depth pixel; the colour pixel it sees:
    x = (u - depth.cx) * colour.fx / depth.fx + colour.cx
    y = (v - depth.cy) * colour.fy / depth.fy + colour.cy
    xs, ys = colour_sampling_map(colour, depth)
    assert xs[v, u] == pytest.approx(x) and ys[v, u] == pytest.approx(y)
    img = np.zeros((100, 200, 3), np.uint8)
    img[int(round(y)), int(round(x))] = 255
    out = resample_rgb(img, colour, depth)
    assert np.unravel_index(np.argmax(out[..., 0]), out.shape[:2]) == (v, u)
    # a bilinear ramp is reproduced exactly (up to rounding)
    ramp = np.repeat(np.repeat(np.arange(200, dtype=np.uint8)[None, :, None], 100, 0), 3, 2)
    inside = (xs >= -0.5) & (xs <= 199.5) & (ys >= -0.5) & (ys <= 99.5)
    got = resample_rgb(ramp, colour, depth)[..., 0]
    assert inside.any() and (~inside).any()
    np.testing.assert_allclose(got[inside], np.clip(np.rint(xs[inside]), 0, 199), atol=1)
    assert (got[~inside] == 0).all()  # rays leaving the colour image are black
    assert resample_rgb(img, depth, depth) is img


# ---- ROS 1 / ROS 2 bags ----------------------------------------------------------------------------

T0 = 1_700_000_000.0  # bag header stamps (seconds)
BAG_K = (50.0, 50.0, 31.5, 23.5)  # 64x48 depth camera
BAG_COLOUR_K = (100.0, 100.0, 63.5, 47.5)  # 128x96 colour camera (registered, twice the size)


def _stamp(ts, t: float, ros1: bool):
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    sec = int(t)
    stamp = Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))
    return Header(seq=0, stamp=stamp, frame_id="cam") if ros1 else Header(stamp=stamp, frame_id="cam")


def _camera_info(ts, t, ros1, w, h, K):
    CI, ROI = ts.types["sensor_msgs/msg/CameraInfo"], ts.types["sensor_msgs/msg/RegionOfInterest"]
    fx, fy, cx, cy = K
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], float)
    r = np.eye(3).ravel()
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], float)
    roi = ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    fields = dict(header=_stamp(ts, t, ros1), height=h, width=w, distortion_model="plumb_bob", binning_x=0,
                  binning_y=0, roi=roi)
    if ros1:
        return CI(**fields, D=np.zeros(5), K=k, R=r, P=p)
    return CI(**fields, d=np.zeros(5), k=k, r=r, p=p)


def _image(ts, t, ros1, arr: np.ndarray, encoding: str):
    Image = ts.types["sensor_msgs/msg/Image"]
    h, w = arr.shape[:2]
    data = np.ascontiguousarray(arr).view(np.uint8).ravel()
    return Image(header=_stamp(ts, t, ros1), height=h, width=w, encoding=encoding, is_bigendian=0,
                 step=data.size // h, data=data)


def _write_bag(path: Path, ros2: bool, n: int = 5) -> dict:
    """A bag with colour, depth and camera_info topics; returns what was written."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    ser = ts.serialize_cdr if ros2 else ts.serialize_ros1
    ros1 = not ros2
    if ros2:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
    else:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    written = {"rgb": [], "depth_m": []}
    with writer as w:
        def conn(topic, msgtype):
            return w.add_connection(topic, msgtype, typestore=ts)

        if ros2:  # colour: JPEG CompressedImage at 128x96 with its own camera_info; depth 32FC1 metres
            c_rgb = conn("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage")
            c_cinfo = conn("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo")
            c_depth = conn("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image")
            c_dinfo = conn("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo")
        else:  # colour: bgr8 Image at 64x48; depth 16UC1 millimetres; one camera_info
            c_rgb = conn("/camera/rgb/image_color", "sensor_msgs/msg/Image")
            c_depth = conn("/camera/depth/image_raw", "sensor_msgs/msg/Image")
            c_dinfo = conn("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo")
        for k in range(n):
            t = T0 + k / 30.0
            ns = int(t * 1e9)
            d = _depth_m(48, 64, k)
            d[:4, :4] = 0
            if ros2:
                rgb = np.full((96, 128, 3), 30 + 40 * k, np.uint8)
                rgb[40:56, 56:72] = 250  # a square around colour pixel (63.5, 47.5) = depth (31.5, 23.5)
                import io

                from PIL import Image as PILImage

                buf = io.BytesIO()
                PILImage.fromarray(rgb).save(buf, format="JPEG", quality=95)
                Compressed = ts.types["sensor_msgs/msg/CompressedImage"]
                msg = Compressed(header=_stamp(ts, t, ros1), format="jpeg",
                                 data=np.frombuffer(buf.getvalue(), np.uint8))
                w.write(c_rgb, ns, ser(msg, "sensor_msgs/msg/CompressedImage"))
                w.write(c_cinfo, ns, ser(_camera_info(ts, t, ros1, 128, 96, BAG_COLOUR_K), "sensor_msgs/msg/CameraInfo"))
                df = d.astype(np.float32)
                df[4:8, :4] = np.nan
                w.write(c_depth, ns + 5_000_000, ser(_image(ts, t + 0.005, ros1, df, "32FC1"), "sensor_msgs/msg/Image"))
            else:
                rgb = _rgb(48, 64, k)
                w.write(c_rgb, ns, ser(_image(ts, t, ros1, rgb[..., ::-1], "bgr8"), "sensor_msgs/msg/Image"))
                mm = np.rint(d * 1000).astype(np.uint16)
                w.write(c_depth, ns + 5_000_000, ser(_image(ts, t + 0.005, ros1, mm, "16UC1"), "sensor_msgs/msg/Image"))
            w.write(c_dinfo, ns, ser(_camera_info(ts, t, ros1, 64, 48, BAG_K), "sensor_msgs/msg/CameraInfo"))
            written["rgb"].append(rgb)
            written["depth_m"].append(d)
        # a colour frame with no depth within 20 ms is dropped
        t = T0 + n / 30.0 + 0.5
        if ros1:
            w.write(c_rgb, int(t * 1e9), ser(_image(ts, t, ros1, _rgb(48, 64, 0), "rgb8"), "sensor_msgs/msg/Image"))
    return written


def test_ros1_bag_converted_once_and_read_as_tum(tmp_path, monkeypatch):
    from atlas_pipeline.sensors import bags

    bag = tmp_path / "rec.bag"
    written = _write_bag(bag, ros2=False)
    assert detect_kind(bag) == "bag"
    m = bags.load_bag_sequence(bag, "rec", tmp_path / "cache")
    assert m.n_frames == 5 and m.source["layout"] == "bag" and m.source["rgb_topic"] == "/camera/rgb/image_color"
    assert (m.camera.width, m.camera.height, m.camera.fx, m.camera.cx) == (64, 48, 50.0, 31.5)
    assert m.camera.depth_scale == 1000.0 and not m.has_gt.any()
    np.testing.assert_allclose(m.timestamps_s, T0 + np.arange(5) / 30.0, atol=2e-6)
    np.testing.assert_array_equal(m.read_rgb(3), written["rgb"][3])  # bgr8 back to RGB, lossless
    d = m.read_depth_m(2)
    assert (d[:4, :4] == 0).all()
    np.testing.assert_allclose(d, written["depth_m"][2], atol=6e-4)
    cache = Path(m.source["cache"])
    assert (cache / ".atlas-gs.json").is_file() and json.loads((cache / ".atlas-gs.json").read_text())["kind"] == "bag_import"
    record = json.loads((cache / "bag_import.json").read_text())
    assert record["bag_files"][0]["size"] == bag.stat().st_size

    # unchanged bag: reused without reading it again
    def boom(*a, **k):
        raise AssertionError("converted again")

    monkeypatch.setattr(bags, "_convert", boom)
    again = bags.load_bag_sequence(bag, "rec", tmp_path / "cache")
    assert again.content_hash == m.content_hash
    # a touched bag is converted again
    os.utime(bag, ns=(bag.stat().st_atime_ns, bag.stat().st_mtime_ns + 10**9))
    with pytest.raises(AssertionError, match="converted again"):
        bags.load_bag_sequence(bag, "rec", tmp_path / "cache")


def test_ros2_bag_compressed_colour_resampled_float_depth(tmp_path):
    from atlas_pipeline.sensors.bags import load_bag_sequence

    bag = tmp_path / "rec2"
    written = _write_bag(bag, ros2=True)
    assert detect_kind(bag) == "bag"
    m = load_bag_sequence(bag, "rec2", tmp_path / "cache")
    assert m.n_frames == 5 and (m.camera.width, m.camera.height) == (64, 48)
    d = m.read_depth_m(1)
    assert (d[:8, :4] == 0).all()  # zero and NaN: no reading
    np.testing.assert_allclose(d[8:], written["depth_m"][1][8:], atol=6e-4)
    rgb = m.read_rgb(1)
    # colour pixel x = 2 (u - 31.5) + 63.5: the 16 px square of 128x96 is 8 px at the depth camera's centre
    assert rgb[20:28, 28:36, 0].min() > 200 and rgb[:10, :10, 0].max() < 120
    assert abs(int(rgb[0, 0, 1]) - (30 + 40)) < 6


def test_bag_topics_ambiguous_then_chosen_and_garbage_bag(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from atlas_pipeline.sensors.bags import load_bag_sequence

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "two.bag"
    with Writer(bag) as w:
        conns = {name: w.add_connection(name, "sensor_msgs/msg/Image", typestore=ts)
                 for name in ("/a/color", "/b/color", "/a/depth")}
        info = w.add_connection("/a/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        for k in range(3):
            t = T0 + k / 30
            for name in ("/a/color", "/b/color"):
                w.write(conns[name], int(t * 1e9), ts.serialize_ros1(_image(ts, t, True, _rgb(48, 64, k), "rgb8"),
                                                                      "sensor_msgs/msg/Image"))
            mm = np.rint(_depth_m(48, 64, k) * 1000).astype(np.uint16)
            w.write(conns["/a/depth"], int(t * 1e9), ts.serialize_ros1(_image(ts, t, True, mm, "16UC1"),
                                                                        "sensor_msgs/msg/Image"))
            w.write(info, int(t * 1e9), ts.serialize_ros1(_camera_info(ts, t, True, 64, 48, BAG_K),
                                                          "sensor_msgs/msg/CameraInfo"))
    with pytest.raises(DatasetError, match="several colour.*'rgb_topic'") as exc:
        load_bag_sequence(bag, "two", tmp_path / "cache")
    _has_error(exc, "two.bag")
    m = load_bag_sequence(bag, "two", tmp_path / "cache", rgb_topic="/b/color")
    assert m.n_frames == 3 and m.source["rgb_topic"] == "/b/color"
    with pytest.raises(DatasetError, match="not a supported colour stream"):
        load_bag_sequence(bag, "two", tmp_path / "cache", rgb_topic="/a/depth")
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"#ROSBAG V2.0\n" + os.urandom(300))
    with pytest.raises(DatasetError, match="cannot read bag") as exc:
        load_bag_sequence(garbage, "g", tmp_path / "cache")
    _has_error(exc, "garbage.bag")
    assert not any(p.name.endswith(".tmp") for p in (tmp_path / "cache").iterdir())  # staging discarded


def test_realsense_bag_topics_and_depth_units(tmp_path):
    """librealsense's .bag naming: image and camera_info under one sensor stream, depth as mono16
    in the 'Depth Units' option's metres per unit."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from atlas_pipeline.sensors.bags import load_bag_sequence

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "d435.bag"
    unit = 0.00025  # an L515's depth unit
    with Writer(bag) as w:
        c_d = w.add_connection("/device_0/sensor_0/Depth_0/image/data", "sensor_msgs/msg/Image", typestore=ts)
        c_di = w.add_connection("/device_0/sensor_0/Depth_0/info/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_c = w.add_connection("/device_0/sensor_1/Color_0/image/data", "sensor_msgs/msg/Image", typestore=ts)
        c_ci = w.add_connection("/device_0/sensor_1/Color_0/info/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_u = w.add_connection("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", typestore=ts)
        w.write(c_u, int(T0 * 1e9), ts.serialize_ros1(ts.types["std_msgs/msg/Float32"](data=unit), "std_msgs/msg/Float32"))
        for k in range(3):
            t = T0 + k / 30
            raw = np.rint(_depth_m(48, 64, k) / unit).astype(np.uint16)
            w.write(c_d, int(t * 1e9), ts.serialize_ros1(_image(ts, t, True, raw, "mono16"), "sensor_msgs/msg/Image"))
            w.write(c_di, int(t * 1e9), ts.serialize_ros1(_camera_info(ts, t, True, 64, 48, BAG_K),
                                                          "sensor_msgs/msg/CameraInfo"))
            w.write(c_c, int(t * 1e9), ts.serialize_ros1(_image(ts, t, True, _rgb(48, 64, k), "rgb8"),
                                                         "sensor_msgs/msg/Image"))
            w.write(c_ci, int(t * 1e9), ts.serialize_ros1(_camera_info(ts, t, True, 64, 48, BAG_K),
                                                          "sensor_msgs/msg/CameraInfo"))
    m = load_bag_sequence(bag, "d435", tmp_path / "cache")
    assert m.n_frames == 3 and m.source["camera_info_topic"] == "/device_0/sensor_0/Depth_0/info/camera_info"
    # 0.25 mm units rounded to the cache's millimetres: within 0.5 mm + half a unit
    np.testing.assert_allclose(m.read_depth_m(2), _depth_m(48, 64, 2), atol=0.5e-3 + unit / 2 + 1e-6)
    np.testing.assert_array_equal(m.read_rgb(2), _rgb(48, 64, 2))


# ---- registry and `dataset add` ------------------------------------------------------------------


def test_registry_kinds_detection_and_presets(isolated, tmp_path):
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.errors import ConfigError
    from atlas_pipeline.sensors.registry import load_dataset
    from atlas_pipeline.sensors.registry import load_registry, register_local_dataset

    _seven_scenes(tmp_path / "heads")
    _scannet(tmp_path / "scan", n=2)
    _write_bag(tmp_path / "rec.bag", ros2=False, n=3)
    e7 = register_local_dataset("heads", tmp_path / "heads", params={"sequence": "seq-01", "fps": 15})
    es = register_local_dataset("scan", tmp_path / "scan")
    eb = register_local_dataset("rec", tmp_path / "rec.bag")
    assert (e7.kind, es.kind, eb.kind) == ("7scenes", "scannet", "bag")
    assert e7.camera == SEVEN_SCENES_CAMERA and es.camera is None and eb.camera is None
    reg = load_registry()
    assert reg["heads"].params == {"sequence": "seq-01", "fps": 15.0}
    cfg = load_profile("default")
    m = load_dataset(reg["heads"], cfg)
    assert m.n_frames == 4 and m.timestamps_s[1] == pytest.approx(1 / 15)
    assert load_dataset(reg["rec"], cfg).n_frames == 3
    assert (isolated / "data" / "bag_imports").is_dir()  # converted under the data folder
    with pytest.raises(ConfigError, match="intrinsic"):
        register_local_dataset("scan2", tmp_path / "scan", camera="default")
    with pytest.raises(DatasetError, match="cannot tell the layout"):
        register_local_dataset("nothing", tmp_path / "scan" / "pose")


def test_cli_dataset_add_detects_kind_and_preset(isolated, tmp_path, capsys):
    from assets.cli import main

    _replica(tmp_path / "office0", n=2)
    assert main(["dataset", "add", "office0", str(tmp_path / "office0")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["registered"]["kind"] == "replica" and out["registered"]["camera"]["fx"] == 600.0
    _tum(tmp_path / "tum", h=48, w=64)
    # --kind overrides detection (here: wrong), and the error names the folder
    assert main(["dataset", "add", "tumx", str(tmp_path / "tum"), "--kind", "replica"]) == 2
    assert main(["dataset", "add", "tumx", str(tmp_path / "tum"), "--intrinsics", "60 60 31.5 23.5",
                 "--width", "64", "--height", "48"]) == 0
    assert json.loads(capsys.readouterr().out)["registered"]["kind"] == "tum"


def test_frames_decode_to_the_arrays_their_files_hold(tmp_path: Path):
    from PIL import Image

    from atlas_pipeline.sensors.images import read_depth_m, read_rgb

    camera = CameraIntrinsics(width=6, height=4, fx=10.0, fy=10.0, cx=2.5, cy=1.5)
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (4, 6, 4), dtype=np.uint8)
    iio.imwrite(tmp_path / "rgba.png", rgba)
    rgb = read_rgb(tmp_path / "rgba.png", camera)
    np.testing.assert_array_equal(rgb, rgba[..., :3])  # alpha dropped
    iio.imwrite(tmp_path / "rgb.png", rgba[..., :3])
    assert read_rgb(tmp_path / "rgb.png", camera).flags.writeable  # a caller may draw on its frame
    palette = Image.fromarray(rgba[..., :3]).quantize(4)
    palette.save(tmp_path / "palette.png")
    np.testing.assert_array_equal(read_rgb(tmp_path / "palette.png", camera), np.asarray(palette.convert("RGB")))
    raw = rng.integers(0, 65536, (4, 6), dtype=np.uint16)
    iio.imwrite(tmp_path / "depth.png", raw)
    depth = read_depth_m(tmp_path / "depth.png", camera)
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, raw.astype(np.float32) / np.float32(camera.depth_scale))


def test_a_frame_whose_pixels_are_cut_off_names_its_file(tmp_path: Path):
    from atlas_pipeline.sensors.images import read_rgb

    camera = CameraIntrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    path = tmp_path / "cut.png"
    iio.imwrite(path, np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8))
    path.write_bytes(path.read_bytes()[:200])  # the header intact, the image data cut short
    with pytest.raises(DatasetError, match="cut.png.*cannot decode image"):
        read_rgb(path, camera)

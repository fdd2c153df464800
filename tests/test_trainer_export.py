"""Exports for GPU trainers, read back with COLMAP's own reader (pycolmap) and checked against
nerfstudio's documented transforms.json schema; the export command's errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from atlas_pipeline.interop.frames import ExportSource, frame_name, undistorted_depth_m, undistorted_rgb
from atlas_pipeline.interop.nerfstudio import OPENCV_TO_OPENGL
from atlas_pipeline.interop.trainer_export import DEPTH_PNG_UNITS_PER_M, seed_points, write_trainer_export

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def source(small_manifest, small_world):
    m = small_manifest
    idx = np.flatnonzero(m.has_gt)[::2]
    return ExportSource(small_world, m, idx, m.T_world_cam_gt[idx], "ground_truth", "test-map")


def _cam_from_world(img) -> np.ndarray:
    rigid = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
    return np.vstack([rigid.matrix(), [0, 0, 0, 1]])


@pytest.mark.parametrize("reader", ["read_binary", "read_text"])
def test_colmap_model_reads_back_with_pycolmap(tmp_path, source, reader):
    import imageio.v3 as iio

    out = tmp_path / "colmap"
    summary = write_trainer_export(out, source, "colmap")
    rec = pycolmap.Reconstruction()
    getattr(rec, reader)(str(out / "sparse" / "0"))
    cam = source.manifest.camera
    assert rec.num_cameras() == 1 and rec.num_images() == len(source.frame_indices) == summary["n_images"]
    c = rec.camera(1)
    assert c.model_name == "PINHOLE" and (c.width, c.height) == (cam.width, cam.height)
    assert np.array_equal(c.params, [cam.fx, cam.fy, cam.cx, cam.cy])
    for k, i in enumerate(source.frame_indices):
        img = rec.image(k + 1)
        assert img.name == frame_name(i) and (out / "images" / img.name).is_file()
        # COLMAP holds world -> camera; ours is camera -> world
        assert np.allclose(np.linalg.inv(_cam_from_world(img)), source.T_world_cam[k], atol=1e-12)
        depth_png = iio.imread(out / "depths" / img.name)
        assert depth_png.dtype == np.uint16
        want = np.rint(source.manifest.read_depth_m(int(i), allow_empty=True).astype(np.float64) * DEPTH_PNG_UNITS_PER_M)
        assert np.array_equal(depth_png, want)
        assert np.array_equal(iio.imread(out / "images" / img.name)[..., :3], source.manifest.read_rgb(int(i)))
    xyz, rgb = seed_points(source.field)
    assert rec.num_points3D() == len(xyz) == summary["n_points3D"]
    got = np.array([rec.point3D(j + 1).xyz for j in range(len(xyz))])
    col = np.array([rec.point3D(j + 1).color for j in range(len(xyz))])
    assert np.array_equal(got, xyz) and np.array_equal(col, rgb)  # exact: text floats are repr()s


def test_nerfstudio_transforms_follow_the_documented_schema(tmp_path, source):
    from plyfile import PlyData

    out = tmp_path / "ns"
    write_trainer_export(out, source, "nerfstudio")
    meta = json.loads((out / "transforms.json").read_text())
    cam = source.manifest.camera
    # docs.nerf.studio, "Data conventions": intrinsics at the top, frames with file_path and a 4x4
    # camera-to-world transform_matrix in the OpenGL camera convention
    assert meta["camera_model"] in ("OPENCV", "PINHOLE", "OPENCV_FISHEYE")
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"]) == (
        cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    assert isinstance(meta["w"], int) and isinstance(meta["h"], int)
    assert all(meta[k] == 0.0 for k in ("k1", "k2", "p1", "p2"))
    assert meta["depth_unit_scale_factor"] == 1e-3  # millimetre PNGs: nerfstudio's default factor
    assert len(meta["frames"]) == len(source.frame_indices)
    for k, fr in enumerate(meta["frames"]):
        assert set(fr) >= {"file_path", "transform_matrix", "depth_file_path"}
        assert (out / fr["file_path"]).is_file() and (out / fr["depth_file_path"]).is_file()
        M = np.array(fr["transform_matrix"])
        assert M.shape == (4, 4) and np.allclose(M[3], [0, 0, 0, 1])
        # OpenGL: the camera looks down -z, y up; flipping y and z back gives our OpenCV pose
        assert np.allclose(M @ OPENCV_TO_OPENGL, source.T_world_cam[k], atol=1e-12)
        assert np.allclose(-M[:3, 2], source.T_world_cam[k][:3, 2])  # the viewing direction
    ply = PlyData.read(str(out / meta["ply_file_path"]))
    xyz, rgb = seed_points(source.field)
    v = ply["vertex"].data
    assert len(v) == len(xyz) and np.array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), rgb)


def test_undistortion_moves_pixels_to_the_pinhole_grid():
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5, 5000.0, (0.2, -0.1, 0.001, 0.002, 0.0))
    plain = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5, 5000.0)
    rgb = np.random.default_rng(0).integers(0, 256, (48, 64, 3)).astype(np.uint8)
    assert undistorted_rgb(rgb, plain) is rgb
    depth = np.full((48, 64), 2.0, np.float32)
    out = undistorted_depth_m(depth, cam)
    assert out[24, 32] == 2.0 and (out[[0, -1]] == 0).any()  # the corners fall outside the raw image
    # the principal point does not move; a pixel away from it samples further out (k1 > 0)
    assert np.array_equal(undistorted_rgb(rgb, cam)[23:25, 31:33].shape, (2, 2, 3))


def test_export_command_end_to_end_and_its_errors(isolated, capsys, caplog):
    from assets.cli import main

    world = isolated / "world"
    assert main(["build", "--input", "synth-small", "--output", str(world), "--set", "mapping.fit.epochs=0",
                 "--set", "mapping.colour_refinement.iterations=0"]) == 0
    capsys.readouterr()
    out = isolated / "colmap"
    assert main(["export", str(world), "--format", "colmap", "--output", str(out)]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["pose_source"] == "keyframes" and res["n_images"] > 0  # no localization yet: the keyframes
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == res["n_images"]
    assert main(["export", str(world), "--format", "colmap", "--output", str(out)]) == 0  # our own: replaced
    capsys.readouterr()
    # bad options are refused before any frame is read, naming the option
    for argv, msg in ((["--frame-step", "0"], "--frame-step must be an integer >= 1"),
                      (["--format", "mesh", "--voxel", "nan"], "--voxel must be a number of metres"),
                      (["--format", "occupancy", "--resolution", "5"], "--resolution must be a number of metres"),
                      (["--poses", "estimated"], "--poses estimated: this world has no localization")):
        caplog.clear()
        fmt = [] if "--format" in argv else ["--format", "nerfstudio"]
        assert main(["export", str(world), *fmt, *argv, "--output", str(isolated / "x")]) == 2, argv
        assert msg in caplog.text, (argv, caplog.text)
    # the synthetic world was mapped at ground-truth poses: its ground truth is the world's frame
    assert main(["export", str(world), "--format", "nerfstudio", "--poses", "ground_truth", "--frame-step", "3",
                 "--output", str(isolated / "gt")]) == 0
    assert json.loads(capsys.readouterr().out)["pose_source"] == "ground_truth"
    # a user's folder is never replaced, nor the world itself
    mine = isolated / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    caplog.clear()
    assert main(["export", str(world), "--format", "colmap", "--output", str(mine)]) == 2
    assert "was not written by atlas-gs" in caplog.text and (mine / "notes.txt").read_text() == "mine"
    caplog.clear()
    assert main(["export", str(world), "--format", "colmap", "--output", str(world), "--force"]) == 2
    assert "is the same folder as the input" in caplog.text
    caplog.clear()
    assert main(["export", str(isolated / "nowhere"), "--format", "colmap", "--output", str(isolated / "y")]) == 2
    assert "is neither a bundle folder nor a partition" in caplog.text

"""The mesh and the occupancy grid: their files read back by other readers, and their figures on the
synthetic room, whose geometry is known exactly (benchmarks/bench_robot_outputs.py prints them)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from atlas_pipeline.interop.frames import ExportSource

ROOT = Path(__file__).resolve().parents[1]
MAX_CHAMFER_M = 0.01  # at 2 cm voxels
MIN_MEAN_IOU = 0.9


@pytest.fixture(scope="module")
def small_source(small_manifest, small_world):
    m = small_manifest
    idx = np.flatnonzero(m.has_gt)
    return ExportSource(small_world, m, idx, m.T_world_cam_gt[idx], "ground_truth")


@pytest.mark.slow
def test_mesh_files_read_back(tmp_path, small_source):
    from plyfile import PlyData

    from atlas_pipeline.interop.exports import build_mesh

    art = build_mesh(small_source)
    art.save(tmp_path)
    mesh = art.mesh
    assert len(mesh) > 1000 and mesh.colors.std() > 5  # coloured, not one grey
    ply = PlyData.read(str(tmp_path / "mesh.ply"))
    assert len(ply["vertex"].data) == len(mesh.vertices) and len(ply["face"].data) == len(mesh.triangles)
    assert np.array_equal(np.stack([ply["vertex"].data[c] for c in ("red", "green", "blue")], 1), mesh.colors)
    trimesh = pytest.importorskip("trimesh")
    scene = trimesh.load(tmp_path / "mesh.glb")
    g = scene.to_geometry() if hasattr(scene, "to_geometry") else scene.dump(concatenate=True)
    assert len(g.faces) == len(mesh.triangles)
    # COLOR_0 is linear (glTF's definition), 16 bits: back to sRGB, the mesh's own colours
    linear = np.asarray(_glb_color0(tmp_path / "mesh.glb"), np.float64) / 65535.0
    srgb = np.where(linear <= 0.0031308, linear * 12.92, 1.055 * linear ** (1 / 2.4) - 0.055)
    assert np.abs(np.rint(srgb[:, :3] * 255) - mesh.colors).max() <= 1
    # the node turns z-up into glTF's y-up: the world's z becomes y
    assert np.allclose(g.vertices[:, 1], mesh.vertices[:, 2], atol=1e-5)
    info = json.loads((tmp_path / "mesh.json").read_text())
    assert info["n_triangles"] == len(mesh.triangles) and (tmp_path / "preview.png").read_bytes()[:4] == b"\x89PNG"


def _glb_color0(path):
    """The raw COLOR_0 accessor of a GLB (uint16 RGBA), read with the glTF layout alone."""
    import struct

    data = path.read_bytes()
    js_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + js_len])
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]]
    assert acc["componentType"] == 5123 and acc["normalized"] and acc["type"] == "VEC4"
    view = doc["bufferViews"][acc["bufferView"]]
    start = 20 + js_len + 8 + view.get("byteOffset", 0)
    return np.frombuffer(data[start:start + view["byteLength"]], "<u2").reshape(-1, 4)


def test_occupancy_map_is_a_map_server_map(tmp_path, small_source):
    import yaml

    from atlas_pipeline.interop.exports import build_occupancy
    from atlas_pipeline.interop.occupancy import FREE, OCCUPIED, PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN, read_pgm

    art = build_occupancy(small_source)
    art.save(tmp_path)
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    # what Nav2's map_server reads (nav2_map_server map_io: image, resolution, origin, negate, thresholds, mode)
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == 0.05 and len(meta["origin"]) == 3
    assert 0 < meta["free_thresh"] < meta["occupied_thresh"] < 1
    pgm = read_pgm(tmp_path / "map.pgm")
    state = art.grid.state
    assert pgm.shape == state.shape and set(np.unique(pgm)) <= {PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN}
    # map_server's rule: occupancy (255 - p) / 255 against the thresholds, the image's last row at origin y
    occ = (255 - pgm[::-1].astype(float)) / 255
    assert np.array_equal(occ > meta["occupied_thresh"], state == OCCUPIED)
    assert np.array_equal(occ < meta["free_thresh"], state == FREE)
    assert np.allclose(art.grid.T_world_map[:3, 2], [0, 0, 1], atol=5e-3)  # the floor of the room: z = 0


def test_open3d_scalable_tsdf_is_still_empty():
    """The installed Open3D's ScalableTSDFVolume integrates nothing (why tsdf_mesh builds its own
    blocks of UniformTSDFVolume); when this fails, Open3D works again and tsdf_mesh can use it."""
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    h, w = 60, 80
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.full((h, w, 3), 128, np.uint8)), o3d.geometry.Image(np.full((h, w), 2.0, np.float32)),
        depth_scale=1.0, depth_trunc=8.0, convert_rgb_to_intensity=False)
    intr = o3d.camera.PinholeCameraIntrinsic(w, h, 60.0, 60.0, 39.5, 29.5)
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=0.02, sdf_trunc=0.08, color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    vol.integrate(rgbd, intr, np.eye(4))
    uni = o3d.pipelines.integration.UniformTSDFVolume(length=2.56, resolution=128, sdf_trunc=0.08,
                                                      color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
                                                      origin=np.array([[-1.28], [-1.28], [1.0]]))
    uni.integrate(rgbd, intr, np.eye(4))
    assert len(uni.extract_triangle_mesh().triangles) > 0
    if len(vol.extract_triangle_mesh().triangles):
        pytest.fail("Open3D's ScalableTSDFVolume works again: interop/mesh.py can use it instead of its blocks")


@pytest.mark.slow
def test_mesh_and_occupancy_figures_on_the_synthetic_room():
    """~40 s: the default 60-frame room at 640x480 (the benchmark's figures)."""
    spec = importlib.util.spec_from_file_location("bench_robot_outputs", ROOT / "benchmarks" / "bench_robot_outputs.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    r = bench.measure("synthetic")
    assert r["mesh"]["chamfer_mm"] <= 1e3 * MAX_CHAMFER_M, r["mesh"]
    assert r["mesh"]["completeness_mm"] <= 1e3 * MAX_CHAMFER_M and r["mesh"]["accuracy_mm"] <= 1e3 * MAX_CHAMFER_M
    o = r["occupancy"]
    assert o["mean_iou"] >= MIN_MEAN_IOU and o["iou_free"] >= MIN_MEAN_IOU, o
    assert o["floor_tilt_deg"] < 0.5 and abs(o["floor_offset_mm"]) < 10


@pytest.mark.slow
def test_export_assets_materialize_after_a_run_and_are_reused(isolated):
    """The ``exports`` group on a partition a run materialized: each artifact typed and on disk, the
    mesh and grid with an inline preview; a second run reuses all four. Not part of atlas_gs_all."""
    import zipfile

    from dagster import DagsterInstance

    from assets.cli import main
    from assets.definitions import build_definitions

    assert main(["run", "synth-small", "--set", "mapping.fit.epochs=0"]) == 0
    defs = build_definitions()
    job = defs.resolve_job_def("atlas_gs_exports")
    with DagsterInstance.get() as inst:
        res = job.execute_in_process(partition_key="synth-small", instance=inst)
        assert res.success
        mats = {m.asset_key.path[-1]: m for m in res.asset_materializations_for_node("world_mesh")}
        assert "preview" in mats["world_mesh"].metadata
        again = job.execute_in_process(partition_key="synth-small", instance=inst)
        for node in ("colmap_export", "nerfstudio_export", "world_mesh", "occupancy_map"):
            assert all(m.metadata["reused"].value for m in again.asset_materializations_for_node(node)), node
    art = isolated / "artifacts"
    with zipfile.ZipFile(art / "colmap_export" / "synth-small" / "colmap.zip") as zf:
        assert {"sparse/0/cameras.bin", "sparse/0/images.txt", "export.json"} <= set(zf.namelist())
    assert (art / "occupancy_map" / "synth-small" / "map.yaml").is_file()
    assert (art / "world_mesh" / "synth-small" / "mesh.glb").is_file()
    assert "colmap_export" not in {n.name for n in defs.resolve_job_def("atlas_gs_all").graph.node_defs}

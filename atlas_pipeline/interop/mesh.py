"""A triangle mesh of the world: the keyframes' depth fused into Open3D's ScalableTSDFVolume at the
keyframes' poses, then marching cubes; written as PLY and GLB with vertex colours.

A world bundle keeps no keyframe depth (only the keyframes' indices and poses), so the depth and
colour come from the bundle's dataset frames, read at those poses (``interop.frames``: the
recording is checked against the content hash the bundle records). Frames with lens distortion are
undistorted first.

The volume is allocated in blocks where the depth lands (:func:`tsdf_mesh`). The truncation distance is :data:`SDF_TRUNC_VOXELS` voxels: wide enough that the depth noise of a
Kinect-class sensor at a few metres stays inside it, narrow enough that thin objects keep both
sides. Fragments of fewer than :data:`MIN_COMPONENT_TRIANGLES` triangles (flying pixels at depth
edges fused once) are dropped.

GLB: glTF 2.0 binary, one mesh of ``POSITION`` (float32), ``COLOR_0`` (normalised uint16 RGBA, linear
as glTF defines vertex colours: the frames' sRGB colours linearised, 16 bits so the darks keep their
steps) and
uint32 triangle indices, written by this module (byte-for-byte deterministic). glTF's up axis is +y;
the node carries a rotation of -90 degrees about x so a z-up world stands upright in glTF viewers,
while the vertex data stay in the world frame (metres).
"""

from __future__ import annotations

import json
import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from atlas_pipeline.config import MappingConfig
from atlas_pipeline.errors import ArtifactError, ConfigError
from atlas_pipeline.interop.frames import ExportSource
from atlas_pipeline.io_utils import atomic_path, write_json_atomic

logger = logging.getLogger(__name__)

__all__ = ["MESH_VOXEL_M", "TriangleMesh", "tsdf_mesh", "write_mesh_ply", "write_mesh_glb", "srgb_to_linear_rgba16",
           "WorldMesh", "mesh_preview_png", "check_voxel"]

MESH_VOXEL_M = 0.02
SDF_TRUNC_VOXELS = 4.0
MIN_VOXEL_M, MAX_VOXEL_M = 0.002, 0.5  # below: memory explodes; above: no room is left
MESH_MAX_DEPTH_M = MappingConfig().max_depth_m  # the map's own depth range
MIN_COMPONENT_TRIANGLES = 50
# Blocks of 64^3 voxels (1.28 m at 2 cm; ~9 MB each in Open3D's voxel layout): a room needs a few
# dozen, allocated where the depth lands.
BLOCK_VOXELS = 64
BLOCK_PROBE_STRIDE_PX = 8  # which blocks a frame touches, from every 8th pixel's point
MERGE_EPS_VOXELS = 1e-3  # vertices of two blocks on their shared plane coincide to float precision
# glTF 2.0 constants
_GLTF_FLOAT, _GLTF_USHORT, _GLTF_UINT = 5126, 5123, 5125
_GLTF_ARRAY_BUFFER, _GLTF_ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLTF_TRIANGLES = 4
_GLB_MAGIC, _GLB_VERSION, _CHUNK_JSON, _CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
_Z_UP_TO_Y_UP_XYZW = [-0.7071067811865476, 0.0, 0.0, 0.7071067811865476]  # -90 deg about x
# Preview: a view from the first keyframe, shaded by the surface normal (key light from the camera)
_PREVIEW_AMBIENT = 0.35
_PREVIEW_MAX_WIDTH_PX = 480
_PREVIEW_SUBDIV = 4  # points per triangle edge: no gaps at 2 cm triangles seen from 0.5 m


def check_voxel(voxel_m: float, option: str = "--voxel") -> float:
    v = float(voxel_m)
    if not (np.isfinite(v) and MIN_VOXEL_M <= v <= MAX_VOXEL_M):
        raise ConfigError(f"{option} must be a number of metres in [{MIN_VOXEL_M}, {MAX_VOXEL_M}], got {voxel_m}")
    return v


@dataclass
class TriangleMesh:
    """Vertices ``[V, 3]`` float32 (world, metres), colours ``[V, 3]`` uint8, triangles ``[T, 3]``
    int32 (counter-clockwise seen from outside), normals ``[V, 3]`` float32 (unit)."""

    vertices: np.ndarray
    colors: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return len(self.triangles)


def _touched_blocks(points_world: np.ndarray, block_m: float, margin_m: float) -> set[tuple[int, int, int]]:
    """Blocks (integer ``[3]`` keys, ``block_m`` wide) within ``margin_m`` of any point ``[N, 3]``."""
    keys: set[tuple[int, int, int]] = set()
    for dx in (-margin_m, margin_m):
        for dy in (-margin_m, margin_m):
            for dz in (-margin_m, margin_m):
                k = np.floor((points_world + [dx, dy, dz]) / block_m).astype(np.int64)
                keys.update(map(tuple, np.unique(k, axis=0).tolist()))
    return keys


def tsdf_mesh(src: ExportSource, voxel_m: float = MESH_VOXEL_M, max_depth_m: float = MESH_MAX_DEPTH_M,
              log: Callable[[str], None] | None = None) -> TriangleMesh:
    """Fuse ``src``'s frames (depth and colour at ``src.T_world_cam``) into a TSDF of ``voxel_m``
    voxels and extract its surface (marching cubes).

    The volume is scalable: Open3D ``UniformTSDFVolume`` blocks of :data:`BLOCK_VOXELS` voxels,
    allocated only where some frame's depth lands (within the truncation distance), each frame
    integrated into the blocks its points touch. Neighbouring blocks share one plane of voxels, so
    their marching-cubes surfaces meet without a seam (the shared vertices are merged).
    Open3D's own ``ScalableTSDFVolume`` (and the tensor ``VoxelBlockGrid``) would be the one-call
    version, but in the Open3D 0.20 wheel installed here both integrate nothing and return an
    empty mesh (``tests/test_robot_outputs.py::test_open3d_scalable_tsdf_is_still_empty`` watches it).
    """
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    log = log or logger.info
    voxel_m = check_voxel(voxel_m)
    trunc = SDF_TRUNC_VOXELS * voxel_m
    step_m = (BLOCK_VOXELS - 1) * voxel_m  # block spacing: one shared voxel plane
    cam = src.camera  # every frame undistorted onto it
    intrinsic = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    v, u = np.mgrid[0:cam.height:BLOCK_PROBE_STRIDE_PX, 0:cam.width:BLOCK_PROBE_STRIDE_PX]
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, np.float64)], axis=-1)
    blocks: dict[tuple[int, int, int], Any] = {}
    color = o3d.pipelines.integration.TSDFVolumeColorType.RGB8
    for k, T in enumerate(src.T_world_cam):
        rgb = np.ascontiguousarray(src.pinhole_rgb(k))  # frame k of its own recording
        depth = np.ascontiguousarray(src.pinhole_depth_m(k))
        d = depth[v, u].astype(np.float64)
        ok = (d > 0) & (d <= max_depth_m)
        if not ok.any():
            continue
        p_world = (ray[ok] * d[ok, None]) @ T[:3, :3].T + T[:3, 3]  # [M, 3] probe points of this frame
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=max_depth_m,
            convert_rgb_to_intensity=False)
        extrinsic = np.linalg.inv(T)  # world -> camera
        for key in sorted(_touched_blocks(p_world, step_m, trunc + voxel_m)):
            if key not in blocks:
                blocks[key] = o3d.pipelines.integration.UniformTSDFVolume(
                    length=BLOCK_VOXELS * voxel_m, resolution=BLOCK_VOXELS, sdf_trunc=trunc, color_type=color,
                    origin=(np.asarray(key, np.float64) * step_m).reshape(3, 1))
            blocks[key].integrate(rgbd, intrinsic, extrinsic)
        if (k + 1) % 10 == 0:
            log(f"TSDF: fused {k + 1}/{len(src.frame_indices)} frames into {len(blocks)} blocks")
    mesh = o3d.geometry.TriangleMesh()
    for key in sorted(blocks):
        mesh += blocks[key].extract_triangle_mesh()
    if len(mesh.triangles):
        mesh.merge_close_vertices(voxel_m * MERGE_EPS_VOXELS)
        mesh.remove_degenerate_triangles()
        clusters, counts, _ = mesh.cluster_connected_triangles()
        small = np.asarray(counts)[np.asarray(clusters)] < MIN_COMPONENT_TRIANGLES
        mesh.remove_triangles_by_mask(small)
        mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    return TriangleMesh(np.asarray(mesh.vertices, np.float32),
                        np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8),
                        np.asarray(mesh.triangles, np.int32), np.asarray(mesh.vertex_normals, np.float32))


def write_mesh_ply(mesh: TriangleMesh, path: str | Path) -> Path:
    """Binary little-endian PLY: vertex ``x y z nx ny nz red green blue``, face ``vertex_indices``."""
    from plyfile import PlyData, PlyElement

    v = np.zeros(len(mesh.vertices), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                      ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = mesh.vertices.T
    v["nx"], v["ny"], v["nz"] = mesh.normals.T
    v["red"], v["green"], v["blue"] = mesh.colors.T
    f = np.zeros(len(mesh.triangles), [("vertex_indices", "<i4", (3,))])
    f["vertex_indices"] = mesh.triangles
    path = Path(path)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face", len_types={"vertex_indices": "u1"})],
                byte_order="<", comments=["Atlas-GS: TSDF mesh of the world (metres)"]).write(str(tmp))
    return path


def _pad4(b: bytes, fill: bytes = b"\0") -> bytes:
    return b + fill * (-len(b) % 4)


def srgb_to_linear_rgba16(colors: np.ndarray) -> np.ndarray:
    """``[N, 3]`` uint8 sRGB colours as ``[N, 4]`` little-endian uint16 linear RGBA (alpha 1), as
    glTF's normalised ``COLOR_0`` holds them."""
    c = np.asarray(colors, np.float64) / 255.0
    rgba = np.ones((len(c), 4))
    rgba[:, :3] = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return np.ascontiguousarray(np.round(rgba * 65535.0), "<u2")


def write_mesh_glb(mesh: TriangleMesh, path: str | Path) -> Path:
    """glTF 2.0 binary (see the module docstring)."""
    pos = np.ascontiguousarray(mesh.vertices, "<f4")
    rgba = srgb_to_linear_rgba16(mesh.colors)
    idx = np.ascontiguousarray(mesh.triangles, "<u4")
    blobs = [pos.tobytes(), np.ascontiguousarray(rgba).tobytes(), idx.tobytes()]
    offsets = np.cumsum([0] + [len(_pad4(b)) for b in blobs])[:-1].tolist()
    lo = pos.min(axis=0).tolist() if len(pos) else [0.0] * 3
    hi = pos.max(axis=0).tolist() if len(pos) else [0.0] * 3
    doc = {
        "asset": {"version": "2.0", "generator": "Atlas-GS"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "rotation": _Z_UP_TO_Y_UP_XYZW, "name": "world"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "indices": 2,
                                    "mode": _GLTF_TRIANGLES}]}],
        "accessors": [
            {"bufferView": 0, "componentType": _GLTF_FLOAT, "count": len(pos), "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": _GLTF_USHORT, "normalized": True, "count": len(rgba), "type": "VEC4"},
            {"bufferView": 2, "componentType": _GLTF_UINT, "count": int(idx.size), "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": offsets[0], "byteLength": len(blobs[0]), "target": _GLTF_ARRAY_BUFFER},
            {"buffer": 0, "byteOffset": offsets[1], "byteLength": len(blobs[1]), "target": _GLTF_ARRAY_BUFFER},
            {"buffer": 0, "byteOffset": offsets[2], "byteLength": len(blobs[2]), "target": _GLTF_ELEMENT_ARRAY_BUFFER},
        ],
        "buffers": [{"byteLength": int(sum(len(_pad4(b)) for b in blobs))}],
    }
    js = _pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    binary = b"".join(_pad4(b) for b in blobs)
    total = 12 + 8 + len(js) + 8 + len(binary)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(struct.pack("<III", _GLB_MAGIC, _GLB_VERSION, total) + struct.pack("<II", len(js), _CHUNK_JSON)
                        + js + struct.pack("<II", len(binary), _CHUNK_BIN) + binary)
    return path


def _in_view(mesh: TriangleMesh, T_cam_world: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """``[T]`` bool: the triangles that may draw a pixel of the ``w`` x ``h`` preview. A triangle in
    front of the camera whose three corners lie beyond one side of the image (a pixel's margin)
    draws none of its points, which lie between the corners; the image is the same without it."""
    p = mesh.vertices.astype(np.float64) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = p[:, 2]
    front = z > 1e-3
    uv = (p @ K.T)[:, :2] / np.where(front, z, 1.0)[:, None]
    t = mesh.triangles
    out = np.zeros(len(t), bool)
    for side in (uv[:, 0] < -1, uv[:, 0] > w + 1, uv[:, 1] < -1, uv[:, 1] > h + 1):
        out |= (side & front)[t].all(axis=1)
    return ~out


def mesh_preview_png(mesh: TriangleMesh, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> bytes:
    """The mesh seen from ``T_world_cam`` (``[4, 4]``, intrinsics ``K`` ``[3, 3]`` at ``width`` x
    ``height``): points on its triangles drawn nearest last, in their triangle's colour shaded by
    its normal; at most :data:`_PREVIEW_MAX_WIDTH_PX` wide."""
    import io

    from PIL import Image

    scale = min(1.0, _PREVIEW_MAX_WIDTH_PX / width)
    w, h = max(1, int(width * scale)), max(1, int(height * scale))
    K = np.diag([scale, scale, 1.0]) @ np.asarray(K, np.float64)
    img = np.full((h, w, 3), 255, np.uint8)
    if len(mesh.triangles):
        # points on every triangle (a barycentric grid), each with its triangle's colour and normal
        a, b = np.meshgrid(np.arange(_PREVIEW_SUBDIV + 1), np.arange(_PREVIEW_SUBDIV + 1), indexing="ij")
        keep = a + b <= _PREVIEW_SUBDIV
        bary = np.stack([a[keep], b[keep], _PREVIEW_SUBDIV - a[keep] - b[keep]], axis=1) / _PREVIEW_SUBDIV  # [S, 3]
        T_cam_world = np.linalg.inv(T_world_cam)
        triangles = mesh.triangles[_in_view(mesh, T_cam_world, K, w, h)]
        tri = mesh.vertices[triangles].astype(np.float64)  # [T, 3, 3]
        pts = np.einsum("sk,tkd->tsd", bary, tri).reshape(-1, 3)
        n_s = len(bary)
        col_t = mesh.colors[triangles].astype(np.float64).mean(axis=1)  # [T, 3]
        nrm_t = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm_t /= np.maximum(np.linalg.norm(nrm_t, axis=1, keepdims=True), 1e-12)
        p = pts @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        z = p[:, 2]
        ok = z > 1e-3
        uv = (p[ok] @ K.T)[:, :2] / z[ok, None]
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (u >= 0) & (v >= 0) & (u < w) & (v < h)
        drawn = np.flatnonzero(ok)[inside]
        which = drawn // n_s  # the triangle of each drawn point
        n_cam = nrm_t[which] @ T_cam_world[:3, :3].T
        pd = p[drawn]
        view = pd / np.linalg.norm(pd, axis=1, keepdims=True)
        shade = _PREVIEW_AMBIENT + (1 - _PREVIEW_AMBIENT) * np.abs(np.sum(n_cam * view, axis=1))
        col = np.clip(col_t[which] * shade[:, None], 0, 255).astype(np.uint8)
        order = np.argsort(-z[drawn], kind="stable")  # far first: the nearest is written last
        img[v[inside][order], u[inside][order]] = col[order]
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=False)
    return buf.getvalue()


@dataclass
class WorldMesh:
    """The ``world_mesh`` asset's artifact: ``mesh.ply``, ``mesh.glb``, ``preview.png`` and
    ``mesh.json`` (counts, voxel, bounds, the frames fused)."""

    mesh: TriangleMesh | None
    info: dict[str, Any]
    preview_png: bytes = b""

    def save(self, directory: Path) -> list[Path]:
        if self.mesh is None:
            raise ArtifactError("a loaded WorldMesh holds only its summary; compute it again to write it")
        paths = [write_mesh_ply(self.mesh, directory / "mesh.ply"), write_mesh_glb(self.mesh, directory / "mesh.glb")]
        if self.preview_png:
            with atomic_path(directory / "preview.png") as tmp:
                tmp.write_bytes(self.preview_png)
            paths.append(directory / "preview.png")
        paths.append(write_json_atomic(directory / "mesh.json", self.info))
        return paths

    @classmethod
    def load(cls, directory: Path) -> "WorldMesh":
        from atlas_pipeline.safe_arrays import load_json_object_checked

        if not (directory / "mesh.json").is_file() or not (directory / "mesh.ply").is_file():
            raise ArtifactError(f"{directory}: mesh.json or mesh.ply missing")
        return cls(None, load_json_object_checked(directory / "mesh.json"))


def mesh_info(mesh: TriangleMesh, src: ExportSource, voxel_m: float) -> dict[str, Any]:
    """What ``mesh.json`` says about ``mesh``."""
    lo = mesh.vertices.min(axis=0).tolist() if len(mesh.vertices) else None
    hi = mesh.vertices.max(axis=0).tolist() if len(mesh.vertices) else None
    return {"n_vertices": int(len(mesh.vertices)), "n_triangles": int(len(mesh.triangles)), "voxel_m": voxel_m,
            "sdf_trunc_m": SDF_TRUNC_VOXELS * voxel_m, "bounds_min_m": lo, "bounds_max_m": hi,
            "map_id": src.map_id, "dataset": src.manifest.dataset, "pose_source": src.pose_source,
            "frame_indices": [int(i) for i in src.frame_indices], "glb_up_axis": "world z shown as glTF +y",
            "recordings": src.recordings_summary(), "frame_recordings": [int(j) for j in src.frame_recording]}

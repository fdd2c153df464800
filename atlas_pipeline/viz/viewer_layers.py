"""The viewer's mesh and occupancy layers: read from export folders or computed from the keyframes,
then bounded in size for the browser.

Where they come from (:func:`load_layers`):

* folders given by the caller, each an output of ``atlas-gs export --format mesh`` (``mesh.ply``
  with ``mesh.json``) or ``--format occupancy`` (``map.pgm`` with ``occupancy.json``), or the
  Dagster ``world_mesh`` / ``occupancy_map`` artifacts, which hold the same files;
* else, with ``compute``, from the bundle's keyframes and the dataset's frames on disk, as the
  exports make them (:func:`~atlas_pipeline.interop.mesh.tsdf_mesh`,
  :func:`~atlas_pipeline.interop.occupancy.occupancy_grid`) but on at most
  :data:`COMPUTE_MAX_KEYFRAMES` evenly spaced keyframes and a :data:`COMPUTE_MESH_VOXEL_M` voxel,
  so a viewer starts in seconds. What cannot be had is a note, never an error.

Size bound (what the page receives on top of the Gaussians): the mesh at most
:data:`MAX_MESH_TRIANGLES` triangles (vertex clustering until it fits; ~3 MB of GLB), the occupancy
grid a texture of at most :data:`MAX_OCCUPANCY_PX` pixels a side (cells merged, occupied winning
over free over unknown; a PNG of tens of kB).

Geometry is cleaned before it is sent: non-finite vertices, triangles using them and degenerate
triangles are dropped, and an empty layer is not drawn at all (three.js logs a NaN bounding sphere
for a mesh with a non-finite or missing position).
"""

from __future__ import annotations

import json
import logging
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.errors import AtlasError
from atlas_pipeline.interop.mesh import srgb_to_linear_rgba16

logger = logging.getLogger(__name__)

__all__ = ["MeshLayer", "OccupancyLayer", "load_layers", "clean_mesh", "decimate", "mesh_glb",
           "occupancy_layer", "MAX_MESH_TRIANGLES", "MAX_OCCUPANCY_PX"]

MAX_MESH_TRIANGLES = 100_000
MAX_OCCUPANCY_PX = 1024
COMPUTE_MAX_KEYFRAMES = 40
COMPUTE_MESH_VOXEL_M = 0.03
CLUSTER_GROWTH = 1.3  # voxel growth per vertex-clustering retry
# Cell colours (RGBA): free a pale green, occupied near black, unknown a faint grey, so the floor
# plan reads at a glance and unknown space does not hide the Gaussians below it.
FREE_RGBA = (150, 215, 150, 255)
OCCUPIED_RGBA = (45, 45, 55, 255)
UNKNOWN_RGBA = (190, 190, 200, 90)
FLOOR_LIFT_M = 0.005  # the quad floats this far above the floor, clear of the floor's Gaussians


@dataclass
class MeshLayer:
    """Vertices ``[V, 3]`` float32 (world, metres), colours ``[V, 3]`` uint8, triangles ``[T, 3]``
    uint32; ``n_source_triangles`` before decimation; ``source`` says where it came from."""

    vertices: np.ndarray
    colors: np.ndarray
    triangles: np.ndarray
    n_source_triangles: int
    source: str


@dataclass
class OccupancyLayer:
    """``rgba`` ``[H, W, 4]`` uint8 (row 0 the map's far +y edge, as an image is drawn), the quad's
    size ``width_m`` x ``height_m`` and pose ``T_world_quad`` ``[4, 4]`` (its centre, z the floor's
    normal); ``cell_counts`` of free / occupied / unknown cells; ``source``."""

    rgba: np.ndarray
    width_m: float
    height_m: float
    T_world_quad: np.ndarray
    cell_counts: dict[str, int]
    source: str


def clean_mesh(vertices: np.ndarray, colors: np.ndarray, triangles: np.ndarray):
    """``(vertices, colors, triangles)`` without non-finite vertices, triangles that use them or
    repeat a vertex, and vertices no triangle uses."""
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    c = np.asarray(colors, np.uint8).reshape(-1, 3)
    t = np.asarray(triangles, np.int64).reshape(-1, 3)
    t = t[((t >= 0) & (t < len(v))).all(axis=1)]
    finite = np.isfinite(v).all(axis=1)
    t = t[finite[t].all(axis=1) & (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    used = np.zeros(len(v), bool)
    used[t.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], c[used], remap[t].astype(np.uint32)


def decimate(vertices: np.ndarray, colors: np.ndarray, triangles: np.ndarray,
             max_triangles: int = MAX_MESH_TRIANGLES):
    """The mesh with at most ``max_triangles`` triangles: Open3D's vertex clustering (colours
    averaged per cell), the cell grown until it fits; the mesh itself when it already does."""
    if len(triangles) <= max_triangles:
        return vertices, colors, triangles
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(triangles.astype(np.int32)))
    m.vertex_colors = o3d.utility.Vector3dVector(colors.astype(np.float64) / 255.0)
    # A cell of side s leaves about area / (s^2 / 2) triangles on a surface.
    s = max(math.sqrt(2.0 * m.get_surface_area() / max_triangles), 1e-4)
    for _ in range(40):
        d = m.simplify_vertex_clustering(s)
        if len(d.triangles) <= max_triangles:
            break
        s *= CLUSTER_GROWTH
    cols = np.clip(np.asarray(d.vertex_colors) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return clean_mesh(np.asarray(d.vertices), cols, np.asarray(d.triangles))


def mesh_glb(layer: MeshLayer) -> bytes:
    """A GLB of ``layer`` in the world frame as is (viser places a GLB's vertices in its world),
    unlit (``KHR_materials_unlit``: the colours are the frames' own, already lit) and double-sided.
    glTF's vertex colours are linear, so the sRGB colours are linearised (16 bits, no banding in
    the darks) and the browser shows the frames' own colours."""
    pos = np.ascontiguousarray(layer.vertices, "<f4")
    rgba = srgb_to_linear_rgba16(layer.colors)
    idx = np.ascontiguousarray(layer.triangles, "<u4")
    blobs = [pos.tobytes(), rgba.tobytes(), idx.tobytes()]
    pad = [(-len(b)) % 4 for b in blobs]
    offsets = np.cumsum([0] + [len(b) + p for b, p in zip(blobs, pad)]).tolist()
    doc = {
        "asset": {"version": "2.0", "generator": "Atlas-GS viewer"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "mesh"}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0},
                       "doubleSided": True, "extensions": {"KHR_materials_unlit": {}}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "indices": 2, "material": 0,
                                    "mode": 4}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
             "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5123, "normalized": True, "count": len(rgba), "type": "VEC4"},
            {"bufferView": 2, "componentType": 5125, "count": int(idx.size), "type": "SCALAR"},
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": offsets[i], "byteLength": len(blobs[i]),
                         "target": 34963 if i == 2 else 34962} for i in range(3)],
        "buffers": [{"byteLength": offsets[3]}],
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * ((-len(js)) % 4)
    binary = b"".join(b + b"\0" * p for b, p in zip(blobs, pad))
    return (struct.pack("<III", 0x46546C67, 2, 28 + len(js) + len(binary)) + struct.pack("<II", len(js), 0x4E4F534A)
            + js + struct.pack("<II", len(binary), 0x004E4942) + binary)


def _mesh_layer(vertices, colors, triangles, source: str, max_triangles: int) -> MeshLayer | None:
    v, c, t = clean_mesh(vertices, colors, triangles)
    n = len(t)
    if n == 0:
        return None
    v, c, t = decimate(v, c, t, max_triangles)
    return MeshLayer(v, c, t, n, source) if len(t) else None


def _merge_cells(state: np.ndarray, f: int) -> np.ndarray:
    """``state`` ``[H, W]`` in blocks of ``f`` x ``f`` cells: occupied if any cell is, else free if
    any is, else unknown (an obstacle is never merged away)."""
    from atlas_pipeline.interop.occupancy import FREE, OCCUPIED, UNKNOWN

    h, w = -(-state.shape[0] // f) * f, -(-state.shape[1] // f) * f
    padded = np.full((h, w), UNKNOWN, np.int8)
    padded[:state.shape[0], :state.shape[1]] = state
    blocks = padded.reshape(h // f, f, w // f, f)
    out = np.full((h // f, w // f), UNKNOWN, np.int8)
    out[(blocks == FREE).any(axis=(1, 3))] = FREE
    out[(blocks == OCCUPIED).any(axis=(1, 3))] = OCCUPIED
    return out


def occupancy_layer(state: np.ndarray, resolution_m: float, origin_xy: np.ndarray, T_world_map: np.ndarray,
                    source: str, max_px: int = MAX_OCCUPANCY_PX) -> OccupancyLayer | None:
    """The quad of a grid ``state`` ``[H, W]`` (row 0 at the map frame's lowest y; cells
    ``resolution_m`` wide from ``origin_xy`` in the map frame ``T_world_map``); None when empty."""
    from atlas_pipeline.interop.occupancy import FREE, OCCUPIED, UNKNOWN

    state = np.asarray(state, np.int8)
    T = np.asarray(T_world_map, np.float64)
    if state.ndim != 2 or state.size == 0 or T.shape != (4, 4) or not np.isfinite(T).all() \
            or not (np.isfinite(resolution_m) and resolution_m > 0) or not np.isfinite(origin_xy).all():
        return None
    counts = {"free": int((state == FREE).sum()), "occupied": int((state == OCCUPIED).sum()),
              "unknown": int((state == UNKNOWN).sum())}
    width_m, height_m = state.shape[1] * resolution_m, state.shape[0] * resolution_m
    f = max(1, math.ceil(max(state.shape) / max_px))
    if f > 1:
        state = _merge_cells(state, f)
    rgba = np.empty((*state.shape, 4), np.uint8)
    rgba[:] = UNKNOWN_RGBA
    rgba[state == FREE] = FREE_RGBA
    rgba[state == OCCUPIED] = OCCUPIED_RGBA
    # Padding by the merge widens the texture a little: the quad keeps the cells' own size.
    width_m, height_m = state.shape[1] * f * resolution_m, state.shape[0] * f * resolution_m
    centre = np.array([origin_xy[0] + width_m / 2, origin_xy[1] + height_m / 2, FLOOR_LIFT_M, 1.0])
    T_quad = T.copy()
    T_quad[:, 3] = T @ centre
    return OccupancyLayer(np.ascontiguousarray(rgba[::-1]), width_m, height_m, T_quad, counts, source)


def _read_mesh_dir(d: Path, max_triangles: int) -> MeshLayer | None:
    from atlas_pipeline._open3d import open3d

    m = open3d().io.read_triangle_mesh(str(d / "mesh.ply"))
    v, t = np.asarray(m.vertices), np.asarray(m.triangles)
    if m.has_vertex_colors():
        c = np.clip(np.asarray(m.vertex_colors) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    else:
        c = np.full((len(v), 3), 180, np.uint8)
    return _mesh_layer(v, c, t, str(d), max_triangles)


def _read_occupancy_dir(d: Path) -> OccupancyLayer | None:
    from atlas_pipeline.interop.occupancy import (FREE, OCCUPIED, PGM_FREE, PGM_OCCUPIED, UNKNOWN, read_pgm)
    from atlas_pipeline.safe_arrays import load_json_object_checked

    info = load_json_object_checked(d / "occupancy.json")
    pgm = read_pgm(d / "map.pgm")[::-1]  # the PGM's first row is the map's far (+y) edge
    state = np.full(pgm.shape, UNKNOWN, np.int8)
    state[pgm == PGM_FREE] = FREE
    state[pgm == PGM_OCCUPIED] = OCCUPIED
    try:
        res = float(info["resolution_m"])
        origin = np.asarray(info["origin_xy_m"], np.float64).reshape(2)
        T = np.asarray(info["T_world_map"], np.float64).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise AtlasError(f"{d / 'occupancy.json'}: resolution_m, origin_xy_m or T_world_map unusable ({exc})") from exc
    return occupancy_layer(state, res, origin, T, str(d))


def load_layers(world_dir: Path, folders: list[Path] | tuple[Path, ...] = (), compute: bool = True,
                notes: list[str] | None = None, max_triangles: int = MAX_MESH_TRIANGLES):
    """``(mesh layer or None, occupancy layer or None)`` of the world at ``world_dir``: from
    ``folders`` (module docstring) first, the rest computed from the keyframes when ``compute``;
    what is missing is said in ``notes``."""
    notes = notes if notes is not None else []
    mesh: MeshLayer | None = None
    occ: OccupancyLayer | None = None
    for d in (Path(p) for p in folders):
        try:
            if (d / "mesh.ply").is_file() and mesh is None:
                mesh = _read_mesh_dir(d, max_triangles)
                if mesh is None:
                    notes.append(f"mesh of {d} is empty: not drawn")
            if (d / "map.pgm").is_file() and (d / "occupancy.json").is_file() and occ is None:
                occ = _read_occupancy_dir(d)
                if occ is None:
                    notes.append(f"occupancy grid of {d} is empty: not drawn")
            if not (d / "mesh.ply").is_file() and not (d / "map.pgm").is_file():
                notes.append(f"{d} holds neither mesh.ply nor map.pgm (an `atlas-gs export --format mesh|occupancy` "
                             "folder): nothing read from it")
        except (AtlasError, OSError, ValueError) as exc:
            notes.append(f"layer folder {d} unreadable ({str(exc)[:200]})")
    if not compute or (mesh is not None and occ is not None):
        return mesh, occ
    from atlas_pipeline.interop.frames import source_from_bundle

    try:
        src = source_from_bundle(world_dir, "keyframes")
    except AtlasError as exc:
        notes.append(f"no mesh or occupancy layer computed: the keyframes' frames are not available ({str(exc)[:200]})")
        return mesh, occ
    n = len(src.frame_indices)
    src = src.thinned(max(1, math.ceil(n / COMPUTE_MAX_KEYFRAMES)))
    quiet = logger.debug
    if mesh is None:
        from atlas_pipeline.interop.mesh import tsdf_mesh

        try:
            m = tsdf_mesh(src, COMPUTE_MESH_VOXEL_M, log=quiet)
            mesh = _mesh_layer(m.vertices, m.colors, m.triangles,
                               f"computed from {len(src.frame_indices)} of {n} keyframes", max_triangles)
            if mesh is None:
                notes.append("the keyframes' depth fused to no surface: no mesh layer")
        except (AtlasError, ValueError) as exc:
            notes.append(f"no mesh layer: {str(exc)[:200]}")
    if occ is None:
        from atlas_pipeline.interop.occupancy import occupancy_grid

        try:
            g = occupancy_grid(src, log=quiet)
            occ = occupancy_layer(g.state, g.grid.resolution_m, np.asarray(g.grid.origin_xy), g.T_world_map,
                                  f"computed from {len(src.frame_indices)} of {n} keyframes")
        except (AtlasError, ValueError) as exc:
            notes.append(f"no occupancy layer: {str(exc)[:200]}")
    return mesh, occ


def layer_summary(mesh: MeshLayer | None, occ: OccupancyLayer | None) -> dict[str, Any]:
    """Counts of the layers for the viewer's summary."""
    return {"n_mesh_triangles": len(mesh.triangles) if mesh else 0,
            "n_mesh_source_triangles": mesh.n_source_triangles if mesh else 0,
            "mesh_source": mesh.source if mesh else None,
            "occupancy_px": list(occ.rgba.shape[:2]) if occ else None,
            "occupancy_cells": occ.cell_counts if occ else None,
            "occupancy_source": occ.source if occ else None}

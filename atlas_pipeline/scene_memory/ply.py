"""Gaussian PLY in the layout of the reference 3D Gaussian Splatting implementation.

Per vertex (binary little endian, float32 unless noted)::

    x y z                 mean
    nx ny nz              unit normal: the axis of the smallest scale (zeros where the Gaussian is
                          not flat; the reference writes zeros, viewers of point clouds shade with it)
    f_dc_0 f_dc_1 f_dc_2  SH degree-0 colour: (rgb - 0.5) / C0, C0 = 0.28209479
    opacity               logit(opacity)
    scale_0 scale_1 scale_2   log(standard deviation)
    rot_0 rot_1 rot_2 rot_3   quaternion w x y z
    red green blue        uint8 colour, so plain point-cloud viewers show colours
    id_hi id_lo           uint32 halves of the stable uint64 id (PLY has no 64-bit integer type)

Gaussian-splat viewers and gsplat read the 3DGS properties and ignore the extra ones. Reading
accepts any PLY with at least the 3DGS properties (ids are assigned when absent).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import (
    GaussianField,
    logit_to_opacity as _decode_opacity,
    log_to_scale as _decode_scale,
    opacity_to_logit as _encode_opacity,
    scale_to_log as _encode_scale,
)
from atlas_pipeline.io_utils import atomic_path

__all__ = ["SH_C0", "write_gaussian_ply", "read_gaussian_ply"]

SH_C0 = 0.28209479177387814

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
    "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}

_FLOAT_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
_MAX_HEADER_BYTES = 64 * 1024


def _normals(field: GaussianField) -> np.ndarray:
    """``[N, 3]`` float32: each Gaussian's shortest axis in the world frame where it is clearly
    the shortest (under half the middle scale), else zeros."""
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    out = np.zeros((len(field), 3), np.float32)
    if not len(field):
        return out
    s = np.sort(field.scales, axis=1)
    flat = s[:, 0] < 0.5 * s[:, 1]
    if flat.any():
        R = quat_xyzw_to_rotmat(field.rotations_xyzw[flat].astype(np.float64))  # [M, 3, 3]
        axis = np.argmin(field.scales[flat], axis=1)
        out[flat] = R[np.arange(len(axis)), :, axis]
    return out


def write_gaussian_ply(field: GaussianField, path: str | Path) -> Path:
    """Write ``field`` as a binary little-endian 3DGS PLY (atomically)."""
    path = Path(path)
    n = len(field)
    dtype = [(p, "<f4") for p in _FLOAT_PROPS] + [("red", "u1"), ("green", "u1"), ("blue", "u1"),
                                                  ("id_hi", "<u4"), ("id_lo", "<u4")]
    v = np.empty(n, dtype=dtype)
    v["x"], v["y"], v["z"] = field.positions.T
    v["nx"], v["ny"], v["nz"] = _normals(field).T
    dc = ((field.colors.astype(np.float64) / 255.0) - 0.5) / SH_C0
    v["f_dc_0"], v["f_dc_1"], v["f_dc_2"] = dc.astype(np.float32).T
    v["opacity"] = _encode_opacity(field.opacities)
    ls = _encode_scale(field.scales)
    v["scale_0"], v["scale_1"], v["scale_2"] = ls.T
    q = field.rotations_xyzw
    v["rot_0"], v["rot_1"], v["rot_2"], v["rot_3"] = q[:, 3], q[:, 0], q[:, 1], q[:, 2]
    v["red"], v["green"], v["blue"] = field.colors.T
    v["id_hi"] = (field.ids >> np.uint64(32)).astype(np.uint32)
    v["id_lo"] = (field.ids & np.uint64(0xFFFFFFFF)).astype(np.uint32)
    header = ["ply", "format binary_little_endian 1.0", "comment Atlas-GS Gaussian world (3DGS layout)",
              f"element vertex {n}"]
    for name, t in dtype:
        header.append(f"property {'float' if t == '<f4' else 'uchar' if t == 'u1' else 'uint'} {name}")
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(v.tobytes())
    return path


def _parse_header(path: Path, f) -> tuple[int, np.dtype, int]:
    head = f.read(_MAX_HEADER_BYTES)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        raise BundleFormatError(path, "not a PLY file (no 'ply' magic or no end_header in the first 64 KiB)")
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    count = None
    props: list[tuple[str, str]] = []
    in_vertex = False
    for ln, line in enumerate(lines[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else None
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(r"\d+", parts[2]):
                raise BundleFormatError(path, f"header line {ln}: malformed element line {line!r}")
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                count = int(parts[2])
            elif count is not None:
                break  # elements after the vertices (faces) are not part of a Gaussian file
            else:
                raise BundleFormatError(path, f"header line {ln}: element '{parts[1]}' before 'vertex' is not supported")
        elif parts[0] == "property" and in_vertex:
            if len(parts) != 3 or parts[1] == "list":
                raise BundleFormatError(path, f"header line {ln}: unsupported vertex property {line!r}")
            if parts[1] not in _PLY_TYPES:
                raise BundleFormatError(path, f"header line {ln}: unknown property type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt != "binary_little_endian":
        raise BundleFormatError(path, f"only binary_little_endian PLY is supported, file says {fmt!r}")
    if count is None:
        raise BundleFormatError(path, "no 'element vertex' in header")
    names = [p for p, _ in props]
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise BundleFormatError(path, f"missing Gaussian properties: {', '.join(missing)}")
    if len(set(names)) != len(names):
        raise BundleFormatError(path, "duplicate vertex property names")
    return count, np.dtype(props), end + len(b"end_header\n")


def read_gaussian_ply(path: str | Path) -> GaussianField:
    """Read a 3DGS-layout PLY into a :class:`GaussianField`.

    The vertex count is checked against the file size before any array is allocated, and every
    value must be finite.
    """
    path = Path(path)
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    size = path.stat().st_size
    with open(path, "rb") as f:
        count, dtype, data_start = _parse_header(path, f)
        need = count * dtype.itemsize
        if size - data_start < need:
            raise BundleFormatError(
                path, f"header declares {count} vertices ({need} bytes) but only {size - data_start} bytes follow"
            )
        f.seek(data_start)
        v = np.frombuffer(f.read(need), dtype=dtype, count=count)
    floats = [p for p in _REQUIRED if p in dtype.names]
    for p in floats:
        if not np.isfinite(v[p]).all():
            raise BundleFormatError(path, f"property '{p}' has NaN or infinite values")
    pos = np.stack([v["x"], v["y"], v["z"]], axis=1)
    if all(c in dtype.names for c in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)
    else:
        dc = np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], axis=1).astype(np.float64)
        colors = np.clip(np.rint((dc * SH_C0 + 0.5) * 255.0), 0, 255).astype(np.uint8)
    with np.errstate(over="ignore"):
        scales = _decode_scale(np.stack([v["scale_0"], v["scale_1"], v["scale_2"]], axis=1))
    if not np.isfinite(scales).all():
        bad = int(np.flatnonzero(~np.isfinite(scales).all(axis=1))[0])
        raise BundleFormatError(path, f"vertex {bad}: log scale too large (exp overflows float32)")
    rot = np.stack([v["rot_1"], v["rot_2"], v["rot_3"], v["rot_0"]], axis=1).astype(np.float32)
    norms = np.linalg.norm(rot.astype(np.float64), axis=1)
    if np.any(norms < 1e-12):
        raise BundleFormatError(path, "a rotation quaternion has zero norm")
    if "id_hi" in dtype.names and "id_lo" in dtype.names:
        ids = (v["id_hi"].astype(np.uint64) << np.uint64(32)) | v["id_lo"].astype(np.uint64)
        if len(np.unique(ids)) != len(ids):
            raise BundleFormatError(path, "Gaussian ids are not unique")
    else:
        ids = np.arange(count, dtype=np.uint64)  # foreign PLY: ids by vertex order
    return GaussianField(pos, scales, rot, colors, _decode_opacity(v["opacity"]), ids)

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
accepts any PLY with at least the 3DGS properties (ids are assigned when absent). Spherical
harmonics beyond degree 0 (``f_rest_*``, 45 of them at the reference's degree 3) are not supported
yet: they are dropped with a warning naming the file, their number and the SH degree.

Both directions work in chunks of ``_CHUNK`` vertices, so a PLY of any size is written and read
with the field plus a few MB: ``PLY_BYTES_PER_GAUSSIAN`` (79) bytes per vertex on disk; reading
holds the field (``FIELD_BYTES_PER_GAUSSIAN``), one chunk and, for foreign files whose ids are not
sorted, one sorted copy of the ids.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import (
    GaussianField,
    ids_unique,
    logit_to_opacity as _decode_opacity,
    log_to_scale as _decode_scale,
    opacity_to_logit as _encode_opacity,
    scale_to_log as _encode_scale,
)
from atlas_pipeline.io_utils import atomic_path

logger = logging.getLogger(__name__)

__all__ = ["SH_C0", "write_gaussian_ply", "read_gaussian_ply", "PLY_BYTES_PER_GAUSSIAN"]

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
# A vertex count has at most 20 digits (uint64); longer digit strings are garbage, and int() of
# more than 4300 digits raises ValueError in Python >= 3.11.
_MAX_COUNT_DIGITS = 20
# Vertices encoded or decoded at a time: a chunk's structured rows and float64 temporaries stay
# ~20 MB, and a few thousand write calls cover millions of Gaussians.
_CHUNK = 1 << 16
_WRITE_DTYPE = np.dtype([(p, "<f4") for p in _FLOAT_PROPS] + [("red", "u1"), ("green", "u1"), ("blue", "u1"),
                                                              ("id_hi", "<u4"), ("id_lo", "<u4")])
PLY_BYTES_PER_GAUSSIAN = _WRITE_DTYPE.itemsize  # 79: what write_gaussian_ply stores per vertex


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


def _encode_vertices(field: GaussianField) -> np.ndarray:
    """``[N]`` structured vertex rows (``_WRITE_DTYPE``) of ``field``."""
    n = len(field)
    v = np.empty(n, dtype=_WRITE_DTYPE)
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
    return v


def write_gaussian_ply(field: GaussianField, path: str | Path) -> Path:
    """Write ``field`` as a binary little-endian 3DGS PLY (atomically), ``_CHUNK`` vertices at a
    time (every value is encoded per vertex, so the bytes do not depend on the chunking)."""
    path = Path(path)
    n = len(field)
    header = ["ply", "format binary_little_endian 1.0", "comment Atlas-GS Gaussian world (3DGS layout)",
              f"element vertex {n}"]
    for name in _WRITE_DTYPE.names:
        t = _WRITE_DTYPE[name].str
        header.append(f"property {'float' if t == '<f4' else 'uchar' if t == '|u1' else 'uint'} {name}")
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            for i in range(0, n, _CHUNK):
                f.write(_encode_vertices(field.subset(slice(i, i + _CHUNK))).tobytes())
    return path


def _parse_header(path: Path, f) -> tuple[int, np.dtype, int]:
    """Parse the header at the start of ``f``: ``(vertex count, vertex dtype, data offset)``.

    Every problem is a ``BundleFormatError`` naming the file and the header line; nothing here
    allocates more than the (bounded) header.
    """
    head = f.read(_MAX_HEADER_BYTES)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        raise BundleFormatError(path, "not a PLY file (no 'ply' magic or no end_header in the first 64 KiB)")
    # split on "\n" only, so the reported line numbers are the file's (splitlines also splits on \x0b ...)
    lines = head[:end].decode("ascii", errors="replace").split("\n")
    if lines[0].strip() != "ply":
        raise BundleFormatError(path, f"header line 1: expected 'ply', found {lines[0][:80]!r}")
    fmt = None
    count = None
    props: list[tuple[str, str]] = []
    seen: set[str] = set()
    in_vertex = False
    for ln, line in enumerate(lines[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) != 3:
                raise BundleFormatError(path, f"header line {ln}: malformed format line {line[:80]!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(r"[0-9]{1,%d}" % _MAX_COUNT_DIGITS, parts[2]):
                raise BundleFormatError(path, f"header line {ln}: malformed element line {line[:80]!r}")
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                if count is not None:
                    raise BundleFormatError(path, f"header line {ln}: a second 'element vertex'")
                count = int(parts[2])
            elif count is not None:
                break  # elements after the vertices (faces) are not part of a Gaussian file
            else:
                raise BundleFormatError(path, f"header line {ln}: element {parts[1][:40]!r} before 'vertex' is not supported")
        elif parts[0] == "property":
            if not in_vertex:
                raise BundleFormatError(path, f"header line {ln}: property outside an element")
            if len(parts) != 3 or parts[1] == "list":
                raise BundleFormatError(path, f"header line {ln}: unsupported vertex property {line[:80]!r}")
            if parts[1] not in _PLY_TYPES:
                raise BundleFormatError(path, f"header line {ln}: unknown property type {parts[1][:40]!r}")
            if parts[2] in seen:
                raise BundleFormatError(path, f"header line {ln}: duplicate vertex property {parts[2][:40]!r}")
            seen.add(parts[2])
            props.append((parts[2], _PLY_TYPES[parts[1]]))
        else:
            raise BundleFormatError(path, f"header line {ln}: unknown header keyword {parts[0][:40]!r}")
    if fmt != "binary_little_endian":
        raise BundleFormatError(path, f"only binary_little_endian PLY is supported, file says {fmt!r}")
    if count is None:
        raise BundleFormatError(path, "no 'element vertex' in header")
    names = [p for p, _ in props]
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise BundleFormatError(path, f"missing Gaussian properties: {', '.join(missing)}")
    return count, np.dtype(props), end + len(b"end_header\n")


def _warn_dropped_sh(path: Path, names: tuple[str, ...]) -> None:
    """Warn (visible without -v) that the ``f_rest_*`` properties of ``path`` are not imported:
    view-dependent colour is not supported yet, so only the degree-0 colour (``f_dc_*``) is kept."""
    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    if not n_rest:
        return
    # 3 colour channels x ((degree + 1)^2 - 1) coefficients beyond degree 0: 9, 24, 45 for 1, 2, 3
    degree = round(math.sqrt(n_rest / 3 + 1) - 1)
    whole = 3 * ((degree + 1) ** 2 - 1) == n_rest
    logger.warning("%s: %d f_rest_* properties (spherical harmonics of %s) are dropped: only the degree-0 "
                   "colour (f_dc_*) is imported, so view-dependent colour is lost", path, n_rest,
                   f"degree {degree}" if whole else "no whole degree: 3 x ((degree + 1)^2 - 1) expected")


def _finite_float32(path: Path, v: np.ndarray, names: list[str]) -> np.ndarray:
    """``[N, len(names)]`` float32 of the named properties; values that are not finite, or become
    infinite as float32 (a double 1e300), are refused naming the property."""
    out = np.empty((len(v), len(names)), np.float32)
    for k, p in enumerate(names):
        if not np.isfinite(v[p]).all():
            raise BundleFormatError(path, f"property '{p}' has NaN or infinite values")
        with np.errstate(over="ignore", invalid="ignore"):
            out[:, k] = v[p]
        if not np.isfinite(out[:, k]).all():
            raise BundleFormatError(path, f"property '{p}' has values outside the float32 range")
    return out


def read_gaussian_ply(path: str | Path, allow_empty: bool = False) -> GaussianField:
    """Read a 3DGS-layout PLY into a :class:`GaussianField`.

    The vertex count is checked against the file size before any array is allocated, and every
    value must be finite (also once stored as float32). A file of 0 vertices holds no world (it
    can be neither localized in nor saved as a bundle): a ``BundleFormatError`` naming the file,
    unless ``allow_empty`` (the encoding round-trip check of an empty field). ``red green blue`` are used when they are
    ``uchar``, else colours come from ``f_dc_*``; ``id_hi id_lo`` when they are ``uint``. The
    vertices are read and decoded ``_CHUNK`` at a time into the field's arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            count, dtype, data_start = _parse_header(path, f)
            if count == 0 and not allow_empty:
                raise BundleFormatError(path, "header declares 0 vertices: the file holds no Gaussians, "
                                              "so there is no world to read")
            _warn_dropped_sh(path, dtype.names)
            need = count * dtype.itemsize  # Python ints: a count of 10**19 cannot overflow here
            if size - data_start < need:
                raise BundleFormatError(
                    path, f"header declares {count} vertices ({need} bytes) but only {size - data_start} bytes follow"
                )
            f.seek(data_start)
            return _read_vertices(path, f, count, dtype)
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read ({exc.strerror or exc})") from None


def _read_vertices(path: Path, f, count: int, dtype: np.dtype) -> GaussianField:
    """Decode ``count`` vertices of ``dtype`` from ``f`` (at the first vertex), ``_CHUNK`` at a time."""
    col = {p: k for k, p in enumerate(_REQUIRED)}
    names = dtype.names
    rgb_u8 = all(c in names and dtype[c] == np.uint8 for c in ("red", "green", "blue"))
    if not rgb_u8 and any(c in names for c in ("red", "green", "blue")):
        logger.warning("%s: red/green/blue are not all uchar; colours come from f_dc_*", path)
    has_ids = "id_hi" in names and "id_lo" in names
    ids_ok = not has_ids or all(dtype[c].kind == "u" and dtype[c].itemsize <= 4 for c in ("id_hi", "id_lo"))
    pos = np.empty((count, 3), np.float32)
    scales = np.empty((count, 3), np.float32)
    rot = np.empty((count, 4), np.float32)
    colors = np.empty((count, 3), np.uint8)
    opacities = np.empty(count, np.float32)
    ids = np.empty(count, np.uint64) if has_ids and ids_ok else np.arange(count, dtype=np.uint64)
    buf = np.empty(min(count, _CHUNK) * dtype.itemsize, np.uint8)
    for i in range(0, count, _CHUNK):
        m = min(_CHUNK, count - i)
        view = buf[: m * dtype.itemsize]
        got = f.readinto(view)
        if got != len(view):  # the file shrank after stat()
            raise BundleFormatError(path, f"header declares {count} vertices ({count * dtype.itemsize} bytes) but only "
                                          f"{i * dtype.itemsize + (got or 0)} bytes could be read")
        v = np.frombuffer(view, dtype=dtype, count=m)
        vals = _finite_float32(path, v, _REQUIRED)  # [m, 14] in _REQUIRED order
        c = slice(i, i + m)
        pos[c] = vals[:, [col["x"], col["y"], col["z"]]]
        if rgb_u8:
            colors[c, 0], colors[c, 1], colors[c, 2] = v["red"], v["green"], v["blue"]
        else:
            dc = vals[:, [col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]]].astype(np.float64)
            colors[c] = np.clip(np.rint((dc * SH_C0 + 0.5) * 255.0), 0, 255)
        with np.errstate(over="ignore"):
            s = _decode_scale(vals[:, [col["scale_0"], col["scale_1"], col["scale_2"]]])
        if not np.isfinite(s).all():
            bad = i + int(np.flatnonzero(~np.isfinite(s).all(axis=1))[0])
            raise BundleFormatError(path, f"vertex {bad}: log scale too large (exp overflows float32)")
        scales[c] = s
        rot[c] = vals[:, [col["rot_1"], col["rot_2"], col["rot_3"], col["rot_0"]]]
        if np.any(np.linalg.norm(rot[c].astype(np.float64), axis=1) < 1e-12):
            raise BundleFormatError(path, "a rotation quaternion has zero norm")
        if has_ids and ids_ok:
            ids[c] = (v["id_hi"].astype(np.uint64) << np.uint64(32)) | v["id_lo"].astype(np.uint64)
        with np.errstate(over="ignore"):  # exp(-logit) may overflow to inf: opacity 0, as intended
            opacities[c] = _decode_opacity(vals[:, col["opacity"]])
    if not ids_ok:
        raise BundleFormatError(path, "properties id_hi and id_lo must be unsigned integers of at most 32 bits")
    if has_ids and not ids_unique(ids):
        raise BundleFormatError(path, "Gaussian ids are not unique")
    return GaussianField(pos, scales, rot, colors, opacities, ids)

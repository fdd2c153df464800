"""Gaussian PLY in the layout of the reference 3D Gaussian Splatting implementation.

Per vertex (binary little endian, float32 unless noted)::

    x y z                 mean
    nx ny nz              unit normal: the axis of the smallest scale (zeros where the Gaussian is
                          not flat; the reference writes zeros, viewers of point clouds shade with it)
    f_dc_0 f_dc_1 f_dc_2  SH degree-0 colour: (rgb - 0.5) / C0, C0 = 0.28209479
    f_rest_0 .. f_rest_{3K-1}  SH coefficients beyond degree 0 (only for a field with view-dependent
                          colour; K = 3, 8, 15 for degree 1-3), channel-major as the reference
                          writes them: f_rest_{c K + k} = sh_rest[:, k, c]
    opacity               logit(opacity)
    scale_0 scale_1 scale_2   log(standard deviation)
    rot_0 rot_1 rot_2 rot_3   quaternion w x y z
    red green blue        uint8 colour, so plain point-cloud viewers show colours
    id_hi id_lo           uint32 halves of the stable uint64 id (PLY has no 64-bit integer type)

Gaussian-splat viewers and gsplat read the 3DGS properties and ignore the extra ones. Reading goes
through plyfile (the reference implementation's own reader) and accepts any PLY with at least the
3DGS properties, in any format (ascii, binary little or big endian) and with any property types
(ids are assigned when absent); our header pass before it names the header line of a problem and
checks the counts against the file size before anything is allocated. Spherical harmonics beyond
degree 0 (``f_rest_*``, 45 of them at the reference's degree 3) are kept as the field's ``sh_rest``;
the degree follows from their number (9, 24 or 45), and any other number, or names that are not
``f_rest_0 .. f_rest_{n-1}``, is an error naming the file and the property.

Writing is ours, in chunks of ``_CHUNK`` vertices (faster than plyfile's writer and without its
copy of the whole vertex table: ``benchmarks/bench_ply.py``); binary vertex data is memory-mapped
by plyfile and decoded ``_CHUNK`` at a time, so a PLY of any size is written and read with the
field plus a few MB: ``PLY_BYTES_PER_GAUSSIAN`` (79) bytes per vertex on disk, 12 more per SH
coefficient (``ply_bytes_per_gaussian``); reading
holds the field (``FIELD_BYTES_PER_GAUSSIAN``), one chunk and, for foreign files whose ids are not
sorted, one sorted copy of the ids.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
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
    sh_degree_of_rest_count,
    sh_rest_count,
)
from atlas_pipeline.io_utils import atomic_path

logger = logging.getLogger(__name__)

__all__ = ["SH_C0", "write_gaussian_ply", "read_gaussian_ply", "PLY_BYTES_PER_GAUSSIAN", "ply_bytes_per_gaussian",
           "ply_header_max_bytes"]

SH_C0 = 0.28209479177387814

# PLY scalar types (both spellings of the standard): (bytes, numpy kind).
_PLY_TYPES = {
    "char": (1, "i"), "int8": (1, "i"), "uchar": (1, "u"), "uint8": (1, "u"), "short": (2, "i"), "int16": (2, "i"),
    "ushort": (2, "u"), "uint16": (2, "u"), "int": (4, "i"), "int32": (4, "i"), "uint": (4, "u"), "uint32": (4, "u"),
    "float": (4, "f"), "float32": (4, "f"), "double": (8, "f"), "float64": (8, "f"),
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_ASCII_MIN_BYTES_PER_VALUE = 2  # a digit and a separator

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
_REST_PREFIX = "f_rest_"
_REST_AFTER = "f_dc_2"  # where the reference puts f_rest_* among the properties


def _write_dtype(sh_degree: int = 0) -> np.dtype:
    """The vertex row ``write_gaussian_ply`` writes for a field of SH degree ``sh_degree``."""
    floats = []
    for p in _FLOAT_PROPS:
        floats.append(p)
        if p == _REST_AFTER:
            floats += [f"{_REST_PREFIX}{j}" for j in range(3 * sh_rest_count(sh_degree))]
    return np.dtype([(p, "<f4") for p in floats] + [("red", "u1"), ("green", "u1"), ("blue", "u1"),
                                                    ("id_hi", "<u4"), ("id_lo", "<u4")])


_WRITE_DTYPE = _write_dtype(0)
PLY_BYTES_PER_GAUSSIAN = _WRITE_DTYPE.itemsize  # 79: what write_gaussian_ply stores per vertex of degree 0
# Header bytes beyond the property lines: magic, format, comment, element and end_header lines.
_HEADER_FIXED_BYTES = 160
_HEADER_BYTES_PER_PROPERTY = 32  # "property float f_rest_44\n" and the like


def ply_bytes_per_gaussian(sh_degree: int = 0) -> int:
    """Bytes per vertex of ``write_gaussian_ply``: 79, plus 12 per SH coefficient beyond degree 0."""
    return _write_dtype(sh_degree).itemsize


def ply_header_max_bytes(sh_degree: int = 0) -> int:
    """Upper bound of ``write_gaussian_ply``'s header (its property lines and a 20-digit count)."""
    return _HEADER_FIXED_BYTES + _HEADER_BYTES_PER_PROPERTY * len(_write_dtype(sh_degree).names)


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


def _encode_vertices(field: GaussianField, dtype: np.dtype | None = None) -> np.ndarray:
    """``[N]`` structured vertex rows (``dtype``: ``_write_dtype(field.sh_degree)``, computed when
    not given) of ``field``."""
    n = len(field)
    dtype = _write_dtype(field.sh_degree) if dtype is None else dtype
    v = np.empty(n, dtype=dtype)
    v["x"], v["y"], v["z"] = field.positions.T
    v["nx"], v["ny"], v["nz"] = _normals(field).T
    dc = ((field.colors.astype(np.float64) / 255.0) - 0.5) / SH_C0
    v["f_dc_0"], v["f_dc_1"], v["f_dc_2"] = dc.astype(np.float32).T
    k_rest = field.sh_rest.shape[1]
    for c in range(3):  # channel-major, as the reference's save_ply
        for k in range(k_rest):
            v[f"{_REST_PREFIX}{c * k_rest + k}"] = field.sh_rest[:, k, c]
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
    time (every value is encoded per vertex, so the bytes do not depend on the chunking). A field with
    view-dependent colour gets its ``f_rest_*`` after ``f_dc_*``, as the reference writes them."""
    path = Path(path)
    n = len(field)
    dtype = _write_dtype(field.sh_degree)
    header = ["ply", "format binary_little_endian 1.0", "comment Atlas-GS Gaussian world (3DGS layout)",
              f"element vertex {n}"]
    for name in dtype.names:
        t = dtype[name].str
        header.append(f"property {'float' if t == '<f4' else 'uchar' if t == '|u1' else 'uint'} {name}")
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            for i in range(0, n, _CHUNK):
                f.write(_encode_vertices(field.subset(slice(i, i + _CHUNK)), dtype).tobytes())
    return path


@dataclass(frozen=True)
class _Element:
    """One ``element`` of a PLY header: its name, count and properties (name, value type, and
    for a list the type of its length, else None)."""

    name: str
    count: int
    props: tuple[tuple[str, str, str | None], ...]
    line: int  # header line of the 'element' keyword


def _parse_header(path: Path, f) -> tuple[str, list[_Element], int]:
    """Parse the header at the start of ``f``: ``(format, elements, data offset)``.

    Every problem is a ``BundleFormatError`` naming the file and the header line; nothing here
    allocates more than the (bounded) header. plyfile parses the header again when it reads the
    data; this pass exists for the line-numbered messages and the size check before any allocation.
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
    elements: list[_Element] = []
    props: list[tuple[str, str, str | None]] = []
    seen: set[str] = set()
    current: tuple[str, int, int] | None = None  # name, count, line of the element being read

    def close() -> None:
        if current is not None:
            elements.append(_Element(current[0], current[1], tuple(props), current[2]))

    for ln, line in enumerate(lines[1:], start=2):
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) != 3:
                raise BundleFormatError(path, f"header line {ln}: malformed format line {line[:80]!r}")
            fmt = parts[1]
            if fmt not in _PLY_FORMATS:
                raise BundleFormatError(path, f"header line {ln}: unknown PLY format {fmt[:40]!r} (expected one of "
                                              f"{', '.join(_PLY_FORMATS)})")
        elif parts[0] == "element":
            if len(parts) != 3 or not re.fullmatch(r"[0-9]{1,%d}" % _MAX_COUNT_DIGITS, parts[2]):
                raise BundleFormatError(path, f"header line {ln}: malformed element line {line[:80]!r}")
            close()
            if parts[1] in {e.name for e in elements}:
                raise BundleFormatError(path, f"header line {ln}: a second 'element {parts[1][:40]}'")
            current, props, seen = (parts[1], int(parts[2]), ln), [], set()
        elif parts[0] == "property":
            if current is None:
                raise BundleFormatError(path, f"header line {ln}: property outside an element")
            if parts[1:2] == ["list"]:
                if len(parts) != 5:
                    raise BundleFormatError(path, f"header line {ln}: malformed list property {line[:80]!r}")
                length_type, value_type, name = parts[2], parts[3], parts[4]
                if length_type not in _PLY_TYPES or _PLY_TYPES[length_type][1] == "f":
                    raise BundleFormatError(path, f"header line {ln}: list length type {length_type[:40]!r} is not "
                                                  "an integer type")
            elif len(parts) == 3:
                length_type, value_type, name = None, parts[1], parts[2]
            else:
                raise BundleFormatError(path, f"header line {ln}: malformed property line {line[:80]!r}")
            if value_type not in _PLY_TYPES:
                raise BundleFormatError(path, f"header line {ln}: unknown property type {value_type[:40]!r}")
            if name in seen:
                raise BundleFormatError(path, f"header line {ln}: duplicate {current[0][:40]} property {name[:40]!r}")
            seen.add(name)
            props.append((name, value_type, length_type))
        else:
            raise BundleFormatError(path, f"header line {ln}: unknown header keyword {parts[0][:40]!r}")
    close()
    if fmt is None:
        raise BundleFormatError(path, "no 'format' line in header")
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise BundleFormatError(path, "no 'element vertex' in header")
    names = [p for p, _, _ in vertex.props]
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise BundleFormatError(path, f"missing Gaussian properties: {', '.join(missing)}")
    lists = [p for p, _, n in vertex.props if n is not None and p in _REQUIRED]
    if lists:
        raise BundleFormatError(path, f"Gaussian properties must be scalars, not lists: {', '.join(lists)}")
    return fmt, elements, end + len(b"end_header\n")


def _min_bytes(fmt: str, element: _Element) -> int:
    """The fewest bytes the data of ``element`` can take in a file of format ``fmt``: what a
    count is checked against before anything is allocated (Python ints: no overflow)."""
    if fmt == "ascii":  # every value at least one character and one separator (a list: its length)
        return element.count * _ASCII_MIN_BYTES_PER_VALUE * len(element.props)
    row = sum(_PLY_TYPES[length or value][0] for _, value, length in element.props)  # a list: its length field
    return element.count * row


def _sh_rest_names(path: Path, vertex: _Element) -> list[str]:
    """The vertex's ``f_rest_*`` property names in coefficient order (``f_rest_0`` first); none for
    a degree-0 file. Their number must be a whole SH degree (9, 24, 45 for 1-3) and their names
    ``f_rest_0 .. f_rest_{n-1}``, each a scalar: else a ``BundleFormatError`` naming the property."""
    props = [(p, n) for p, _, n in vertex.props if p.startswith(_REST_PREFIX)]
    if not props:
        return []
    index: dict[int, str] = {}
    for p, length in props:
        suffix = p[len(_REST_PREFIX):]
        if length is not None:
            raise BundleFormatError(path, f"property '{p[:40]}' must be a scalar, not a list")
        if not re.fullmatch(r"0|[1-9][0-9]{0,3}", suffix):
            raise BundleFormatError(path, f"property '{p[:40]}': expected f_rest_<index> (0, 1, 2, ...)")
        index[int(suffix)] = p
    n_rest = len(props)
    degree = sh_degree_of_rest_count(n_rest // 3) if n_rest % 3 == 0 else None
    if not degree:
        raise BundleFormatError(path, f"{n_rest} f_rest_* properties: spherical harmonics of degree 1, 2 or 3 have "
                                      "9, 24 or 45 (3 channels x ((degree + 1)^2 - 1))")
    missing = [j for j in range(n_rest) if j not in index]
    if missing:
        raise BundleFormatError(path, f"property 'f_rest_{missing[0]}' is missing (f_rest_* must be numbered "
                                      f"0..{n_rest - 1}, found '{index[max(index)]}')")
    return [index[j] for j in range(n_rest)]


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
    """Read a 3DGS-layout PLY of any format (``ascii``, ``binary_little_endian``,
    ``binary_big_endian``) and property types into a :class:`GaussianField`, through plyfile.

    The element counts are checked against the file size before any array is allocated, and every
    value must be finite (also once stored as float32). A file of 0 vertices holds no world (it
    can be neither localized in nor saved as a bundle): a ``BundleFormatError`` naming the file,
    unless ``allow_empty`` (the encoding round-trip check of an empty field). ``red green blue`` are
    used when they are ``uchar``, else colours come from ``f_dc_*``; ``id_hi id_lo`` when they are
    unsigned integers of at most 32 bits. Binary vertex data is memory-mapped by plyfile and decoded
    ``_CHUNK`` vertices at a time into the field's arrays.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            fmt, elements, data_start = _parse_header(path, f)
            vertex = next(e for e in elements if e.name == "vertex")
            if vertex.count == 0 and not allow_empty:
                raise BundleFormatError(path, "header declares 0 vertices: the file holds no Gaussians, "
                                              "so there is no world to read")
            rest_names = _sh_rest_names(path, vertex)
            need = sum(_min_bytes(fmt, e) for e in elements)
            if size - data_start < need:
                what = (f"{vertex.count} vertices" if len(elements) == 1 else
                        ", ".join(f"{e.count} {e.name}" for e in elements))
                raise BundleFormatError(
                    path, f"header declares {what} (at least {need} bytes) but only {size - data_start} bytes follow"
                )
            f.seek(0)
            try:
                ply = PlyData.read(f)
            except BundleFormatError:
                raise
            except Exception as exc:  # plyfile's parse errors, and numpy's on data it cannot convert
                raise BundleFormatError(path, f"cannot parse the PLY data: {exc}") from None
            return _decode_vertices(path, ply["vertex"].data, rest_names)
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read ({exc.strerror or exc})") from None


def _decode_vertices(path: Path, data: np.ndarray, rest_names: list[str]) -> GaussianField:
    """Decode the ``[N]`` structured vertex rows ``data`` (any byte order and property types, as
    plyfile returns them: memory-mapped for binary files), ``_CHUNK`` at a time; ``rest_names``: the
    ``f_rest_*`` properties in coefficient order (``_sh_rest_names``)."""
    col = {p: k for k, p in enumerate(_REQUIRED)}
    count = len(data)
    dtype = data.dtype
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
    sh_rest = np.empty((count, len(rest_names) // 3, 3), np.float32)
    clamped, furthest = 0, 0.0  # base colours outside [0, 1] (f_dc_*), kept only clamped to 8 bits
    for i in range(0, count, _CHUNK):
        m = min(_CHUNK, count - i)
        v = data[i:i + m]
        vals = _finite_float32(path, v, _REQUIRED)  # [m, 14] in _REQUIRED order
        c = slice(i, i + m)
        pos[c] = vals[:, [col["x"], col["y"], col["z"]]]
        if rgb_u8:
            colors[c, 0], colors[c, 1], colors[c, 2] = v["red"], v["green"], v["blue"]
        else:
            dc = vals[:, [col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]]].astype(np.float64)
            base = dc * SH_C0 + 0.5
            outside = np.abs(base - 0.5).max(axis=1) - 0.5  # > 0: beyond [0, 1] by this much
            beyond = outside > 0.5 / 255.0  # more than the 8-bit rounding
            clamped += int(beyond.sum())
            furthest = max(furthest, float(outside.max(initial=0.0)))
            colors[c] = np.clip(np.rint(base * 255.0), 0, 255)
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
        if rest_names:  # [m, 3 K] channel-major -> [m, K, 3]
            sh_rest[c] = _finite_float32(path, v, rest_names).reshape(m, 3, -1).transpose(0, 2, 1)
    if not ids_ok:
        raise BundleFormatError(path, "properties id_hi and id_lo must be unsigned integers of at most 32 bits")
    if clamped and rest_names:  # with degree 0 the render clamps the colour to [0, 1] anyway
        logger.warning("%s: %d of %d Gaussians have a base colour (f_dc_*) outside [0, 1] (by up to %.3g); colours "
                       "are kept as 8-bit values, so it is clamped and their view-dependent colour (base plus f_rest_*) "
                       "differs from the file's", path, clamped, count, furthest)
    if has_ids and not ids_unique(ids):
        raise BundleFormatError(path, "Gaussian ids are not unique")
    return GaussianField(pos, scales, rot, colors, opacities, ids, sh_rest)

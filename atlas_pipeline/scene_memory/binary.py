"""Binary world formats, little endian.

ATLASGS1 (the paper's Appendix B; isotropic fields)::

    magic     8 bytes  b"ATLASGS1"
    count     uint64
    positions count x 3 x float32
    scales    count x float32          (isotropic standard deviation, metres)
    colors    count x 3 x uint8
    opacity   count x float32
    ids       count x uint64

ATLASGS2 (its versioned successor; any field, anisotropic included)::

    magic     8 bytes  b"ATLASGS2"
    version   uint32   (2)
    flags     uint32   (0; reserved)
    count     uint64
    positions count x 3 x float32      (metres)
    scales    count x 3 x float32      (standard deviations along the local axes, metres)
    rotations count x 4 x float32      (unit quaternion x y z w, local -> world)
    colors    count x 3 x uint8
    opacity   count x float32
    ids       count x uint64

Version 3 of ATLASGS2 carries view-dependent colour: the same header with ``sh_degree`` (uint32,
1-3) in place of ``flags``, the same arrays, then::

    sh_rest   count x K x 3 x float32  (SH coefficients beyond degree 0, K = (sh_degree + 1)^2 - 1;
                                        per Gaussian coefficient by coefficient, RGB within each:
                                        GaussianField.sh_rest [N, K, 3] as it is in memory)

A field of degree 0 is written as version 2, byte for byte as before; a version-2 reader refuses
version 3 naming the version.

55 bytes per Gaussian (ATLASGS1: 31; version 3: 55 + 12 K). :func:`read_gaussian_binary` reads
either, by magic.

Memory: writing copies nothing (each array goes to the file from its own buffer; ATLASGS1's one
scale column is written in chunks); reading holds the file's bytes once, and the field's arrays
are views of them (55 bytes per Gaussian for ATLASGS2; ATLASGS1 adds the rotations and the three
scales it expands to, 28 more), plus checks in chunks of ``_CHECK_CHUNK`` rows and one sorted copy
of the ids when they are not already sorted (8 bytes per Gaussian).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField, ids_unique, sh_rest_count, SH_MAX_DEGREE
from atlas_pipeline.io_utils import atomic_path

__all__ = ["MAGIC_V1", "MAGIC_V2", "write_atlasgs1", "read_atlasgs1", "write_atlasgs2", "read_atlasgs2",
           "write_gaussian_binary", "read_gaussian_binary", "BYTES_PER_GAUSSIAN", "HEADER_BYTES",
           "atlasgs2_bytes_per_gaussian"]

MAGIC_V1 = b"ATLASGS1"
MAGIC_V2 = b"ATLASGS2"
_BYTES_PER_GAUSSIAN_V1 = 12 + 4 + 3 + 4 + 8
_BYTES_PER_GAUSSIAN_V2 = 12 + 12 + 16 + 3 + 4 + 8
_HEADER_V2 = 24
_HEADER_V1 = 16
BYTES_PER_GAUSSIAN = {1: _BYTES_PER_GAUSSIAN_V1, 2: _BYTES_PER_GAUSSIAN_V2}
_V2_PLAIN = 2  # ATLASGS2 versions: without and with SH coefficients
_V2_SH = 3
_SH_BYTES_PER_COEFF = 3 * 4  # one coefficient of three float32 channels


def atlasgs2_bytes_per_gaussian(sh_degree: int = 0) -> int:
    """Bytes per Gaussian in ATLASGS2: 55, plus 12 per SH coefficient beyond degree 0 (version 3)."""
    return _BYTES_PER_GAUSSIAN_V2 + _SH_BYTES_PER_COEFF * sh_rest_count(sh_degree)
HEADER_BYTES = {1: _HEADER_V1, 2: _HEADER_V2}
# Rows checked (or converted for writing) at a time: float64 temporaries of a chunk stay ~8 MB.
_CHECK_CHUNK = 1 << 18


def _write_array(f, a: np.ndarray, dtype: str) -> None:
    """Write ``a`` as ``dtype`` bytes: straight from its buffer when it already has that layout
    (no copy), else converted ``_CHECK_CHUNK`` rows at a time."""
    if a.dtype == np.dtype(dtype) and a.flags.c_contiguous:
        f.write(memoryview(a).cast("B") if a.size else b"")
        return
    for i in range(0, len(a), _CHECK_CHUNK):
        f.write(np.ascontiguousarray(a[i:i + _CHECK_CHUNK], dtype=dtype).tobytes())


def _read_checked(path: Path, magic: bytes, header_len: int, bytes_per: int | Callable[[tuple], int],
                  parse_header) -> tuple[tuple, bytes, int]:
    """Read a binary world file: check the magic, let ``parse_header(head)`` return
    ``(header_fields, count)``, check the file size against the count (``bytes_per`` per Gaussian,
    or ``bytes_per(header_fields)``) *before* reading the arrays, and return ``(header_fields, body, count)``."""
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(header_len)
            if len(head) < header_len or head[:8] != magic:
                raise BundleFormatError(path, f"not an {magic.decode()} file (magic {head[:8]!r}, {size} bytes)")
            fields, n = parse_header(head)
            expected = header_len + n * (bytes_per(fields) if callable(bytes_per) else bytes_per)  # Python ints: any uint64 count compares safely
            if size != expected:
                raise BundleFormatError(path, f"count {n} needs {expected} bytes, file has {size}")
            body = f.read(expected - header_len + 1)  # one byte more shows a file that grew
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read ({exc.strerror or exc})") from None
    if len(body) != expected - header_len:
        raise BundleFormatError(path, f"count {n} needs {expected} bytes, {header_len + len(body)} could be read "
                                "(file changed while reading)")
    return fields, body, n


def _check_values(path: Path, pos: np.ndarray, scales: np.ndarray, rot: np.ndarray | None, opa: np.ndarray,
                  ids: np.ndarray, sh_rest: np.ndarray | None = None) -> None:
    """The invariants of a :class:`GaussianField`, so a corrupt file is refused rather than loaded:
    finite values, scales >= 0, non-zero quaternions, opacities in [0, 1], unique ids."""
    arrays = (pos, scales, opa) if rot is None else (pos, scales, rot, opa)
    arrays += () if sh_rest is None else (sh_rest,)
    for i in range(0, len(pos), _CHECK_CHUNK):  # in chunks: temporaries stay small at any N
        c = slice(i, i + _CHECK_CHUNK)
        if not all(np.isfinite(a[c]).all() for a in arrays):
            raise BundleFormatError(path, "NaN or infinite values")
    if len(pos) and scales.min() < 0:
        raise BundleFormatError(path, "negative scale")
    if rot is not None:
        for i in range(0, len(pos), _CHECK_CHUNK):
            if np.any(np.linalg.norm(rot[i:i + _CHECK_CHUNK].astype(np.float64), axis=1) < 1e-12):
                raise BundleFormatError(path, "zero-norm rotation")
    if len(pos) and (opa.min() < 0 or opa.max() > 1):
        raise BundleFormatError(path, "opacity outside [0, 1]")
    if not ids_unique(ids):
        raise BundleFormatError(path, "Gaussian ids are not unique")


class _Columns:
    """Consecutive little-endian arrays of a buffer, read without copying."""

    def __init__(self, buf: bytes):
        self.buf, self.off = buf, 0

    def take(self, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
        a = np.frombuffer(self.buf, dtype=dtype, count=int(np.prod(shape)), offset=self.off).reshape(shape)
        self.off += a.nbytes
        return a


def write_atlasgs1(field: GaussianField, path: str | Path) -> Path:
    """Write an isotropic field as ATLASGS1 (atomically). Anisotropic fields are refused."""
    if not field.is_isotropic:
        raise ValueError("ATLASGS1 stores one scale per Gaussian; this field is anisotropic")
    n = len(field)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(MAGIC_V1)
            f.write(struct.pack("<Q", n))
            _write_array(f, field.positions, "<f4")
            _write_array(f, field.scales[:, 0], "<f4")
            _write_array(f, field.colors, "u1")
            _write_array(f, field.opacities, "<f4")
            _write_array(f, field.ids, "<u8")
    return Path(path)


def read_atlasgs1(path: str | Path) -> GaussianField:
    """Read an ATLASGS1 file; the size must match the count exactly and values must be finite."""
    path = Path(path)
    _, buf, n = _read_checked(path, MAGIC_V1, _HEADER_V1, _BYTES_PER_GAUSSIAN_V1,
                              lambda h: ((), struct.unpack("<Q", h[8:16])[0]))
    take = _Columns(buf).take
    pos = take("<f4", (n, 3))
    scale = take("<f4", (n,))
    col = take("u1", (n, 3))
    opa = take("<f4", (n,))
    ids = take("<u8", (n,))
    _check_values(path, pos, scale, None, opa, ids)
    rot = np.zeros((n, 4), np.float32)
    rot[:, 3] = 1.0
    return GaussianField(pos, np.repeat(scale[:, None], 3, axis=1), rot, col, opa, ids)


def write_atlasgs2(field: GaussianField, path: str | Path) -> Path:
    """Write any field as ATLASGS2 (atomically): version 2, or 3 with its SH coefficients."""
    n = len(field)
    degree = field.sh_degree
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(MAGIC_V2)
            # version 3's second word is the SH degree (version 2's reserved flags, 0)
            f.write(struct.pack("<IIQ", _V2_SH if degree else _V2_PLAIN, degree, n))
            _write_array(f, field.positions, "<f4")
            _write_array(f, field.scales, "<f4")
            _write_array(f, field.rotations_xyzw, "<f4")
            _write_array(f, field.colors, "u1")
            _write_array(f, field.opacities, "<f4")
            _write_array(f, field.ids, "<u8")
            if degree:
                _write_array(f, field.sh_rest, "<f4")
    return Path(path)


def read_atlasgs2(path: str | Path) -> GaussianField:
    """Read an ATLASGS2 file; version, size and values are checked before arrays are built."""
    path = Path(path)

    def header(h: bytes) -> tuple[tuple, int]:
        version, second, count = struct.unpack("<IIQ", h[8:24])
        if version not in (_V2_PLAIN, _V2_SH):
            raise BundleFormatError(path, f"ATLASGS2 version {version} is not supported (this reader knows "
                                          f"{_V2_PLAIN} and {_V2_SH})")
        if version == _V2_SH and not 1 <= second <= SH_MAX_DEGREE:
            raise BundleFormatError(path, f"ATLASGS2 version 3: SH degree {second} (expected 1-{SH_MAX_DEGREE})")
        return (version, second if version == _V2_SH else 0), count

    (_, degree), buf, n = _read_checked(path, MAGIC_V2, _HEADER_V2, lambda f: atlasgs2_bytes_per_gaussian(f[1]),
                                        header)
    k_rest = sh_rest_count(degree)
    take = _Columns(buf).take
    pos, scl, rot = take("<f4", (n, 3)), take("<f4", (n, 3)), take("<f4", (n, 4))
    col, opa, ids = take("u1", (n, 3)), take("<f4", (n,)), take("<u8", (n,))
    sh_rest = take("<f4", (n, k_rest, 3))
    _check_values(path, pos, scl, rot, opa, ids, sh_rest if k_rest else None)
    return GaussianField(pos, scl, rot, col, opa, ids, sh_rest)


def write_gaussian_binary(field: GaussianField, path: str | Path) -> Path:
    """ATLASGS1 for an isotropic field without SH (the paper's readers open it), ATLASGS2 otherwise."""
    plain = field.sh_degree == 0 and field.is_isotropic and (len(field) == 0 or _identity_rotations(field))
    return write_atlasgs1(field, path) if plain else write_atlasgs2(field, path)


def _identity_rotations(field: GaussianField) -> bool:
    q = field.rotations_xyzw
    return all(bool(np.all(q[i:i + _CHECK_CHUNK, :3] == 0) and np.all(q[i:i + _CHECK_CHUNK, 3] == 1))
               for i in range(0, len(q), _CHECK_CHUNK))


def read_gaussian_binary(path: str | Path) -> GaussianField:
    """Read ATLASGS1 or ATLASGS2, chosen by the file's magic."""
    path = Path(path)
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    try:
        with open(path, "rb") as f:
            magic = f.read(len(MAGIC_V1))
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read ({exc.strerror or exc})") from None
    if magic == MAGIC_V1:
        return read_atlasgs1(path)
    if magic == MAGIC_V2:
        return read_atlasgs2(path)
    raise BundleFormatError(path, f"not an ATLASGS binary (magic {magic!r})")

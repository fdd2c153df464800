"""Checked ``.npz`` reading: every size is proven by the file before anything is allocated.

``numpy.load`` trusts an ``.npz``: a member whose npy header claims ``shape (10**12, 3)`` makes it
allocate 11 TiB before noticing the data is not there, a corrupt archive raises whatever
``zipfile``/``zlib``/``ast`` happen to raise, and a deflate bomb inflates without limit.
:func:`load_npz_checked` instead

1. opens the archive with :mod:`zipfile` and checks every member's record against the file:
   stored members must hold exactly their declared size, deflated ones may not claim more than
   deflate can produce from their compressed bytes (about 1032:1), members must lie inside the file
   and not overlap (the overlapping-member zip bomb), no encryption, no other compression;
2. reads each member's npy header itself (bounded length), parses it with
   ``numpy.lib.format.read_magic`` / ``read_array_header_1_0`` / ``read_array_header_2_0``,
   refuses object dtypes (never unpickles) and anything but plain numbers and booleans, and checks
   that ``prod(shape) * itemsize`` is exactly the member's declared size minus its header;
3. only then allocates the array and fills it in bounded chunks; ``zipfile`` verifies the CRC as
   the last byte is read.

:func:`load_json_object_checked` reads the JSON sidecar of such an artifact the same way (size
bounded, any malformation a project error naming the file).

Every failure is one of the project's errors (``BundleFormatError`` by default, or the
``error_type`` the caller names) and says which file and member, e.g.::

    .../surfels.npz: member 'centres.npy' claims shape (1000000000000, 3) float32 = 12 TB but the
    archive holds 2 kB
"""

from __future__ import annotations

import io
import logging
import math
import struct
import tokenize
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Mapping, Union

import numpy as np
from numpy.lib import format as npy_format

from atlas_pipeline.errors import ArtifactError, AtlasError, BundleFormatError, DatasetError

logger = logging.getLogger(__name__)

__all__ = ["load_npz_checked", "save_npz_deterministic", "load_json_object_checked", "is_finite_number", "NPZ_MAX_DEFLATE_RATIO",
           "NPY_MAX_HEADER_BYTES", "NPZ_MAX_MEMBERS", "JSON_SIDECAR_MAX_BYTES"]

# Deflate emits at most 258 bytes per ~2-bit code, so its output is at most ~1032 times its input
# (zlib's technical note); a member claiming more is lying about its size.
NPZ_MAX_DEFLATE_RATIO = 1032
# Same limit as numpy's own ``max_header_size`` default: a real npy header is ~128 bytes.
NPY_MAX_HEADER_BYTES = 10_000
# Our archives hold at most ~15 arrays; thousands of members is garbage, not data.
NPZ_MAX_MEMBERS = 1024
# Fixed part of a zip local file header (signature .. extra-field length).
_ZIP_LOCAL_HEADER_BYTES = 30
# npy preamble: 6-byte magic, 2-byte version, then a 2-byte (v1) or 4-byte (v2) header length.
_NPY_MAGIC_BYTES = 8
_NPY_HEADER_LENGTH_FORMAT = {(1, 0): "<H", (2, 0): "<I"}
# Plain numbers and booleans only: no objects (pickles), strings, structured or datetime types.
_ALLOWED_KINDS = "biufc"
# Member data is copied in pieces of this size so reading never holds two copies of an array.
_READ_CHUNK_BYTES = 1 << 20
_ZIP_FLAG_ENCRYPTED = 0x1

# What zipfile / zlib raise on a corrupt archive (ValueError includes UnicodeDecodeError of member
# names, OverflowError a seek past any file); each becomes the caller's error type. Deliberately
# narrow: a bug of this module must not be reported as a corrupt file.
_CORRUPT_ZIP = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, OverflowError, struct.error,
                NotImplementedError, RuntimeError)
# What parsing an npy header (``ast.literal_eval`` of untrusted text, then ``np.dtype``) can raise.
_CORRUPT_NPY_HEADER = (ValueError, SyntaxError, TypeError, KeyError, IndexError, OverflowError, RecursionError,
                       tokenize.TokenError)

# A spec of one member: (allowed dtype kinds such as "f" or "iu", or an exact dtype; ndim or None).
MemberSpec = tuple[Union[str, np.dtype, type], Union[int, None]]


def _human_bytes(n: int) -> str:
    """``12 TB``, ``2 kB``: decimal units, enough to see how far apart two sizes are."""
    for unit, scale in (("EB", 10**18), ("PB", 10**15), ("TB", 10**12), ("GB", 10**9), ("MB", 10**6), ("kB", 10**3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} B"


def _error(error_type: type[AtlasError], path: Path, message: str) -> AtlasError:
    """Build ``error_type`` naming ``path``, whatever its constructor's signature."""
    if issubclass(error_type, (BundleFormatError, DatasetError)):
        return error_type(path, message)
    return error_type(f"{path}: {message}")


def _check_records(path: Path, zf: zipfile.ZipFile, file_size: int, error_type: type[AtlasError]) -> None:
    """Check every member record against the archive before any member is read."""
    infos = zf.infolist()
    if len(infos) > NPZ_MAX_MEMBERS:
        raise _error(error_type, path, f"archive has {len(infos)} members (at most {NPZ_MAX_MEMBERS} expected)")
    names = [i.filename for i in infos]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise _error(error_type, path, f"archive lists member(s) {dup} more than once")
    for info in infos:
        where = f"member {info.filename!r}"
        if info.flag_bits & _ZIP_FLAG_ENCRYPTED:
            raise _error(error_type, path, f"{where} is encrypted")
        if info.compress_type == zipfile.ZIP_STORED:
            if info.compress_size != info.file_size:
                raise _error(error_type, path, f"{where} is stored uncompressed but its record says "
                             f"{info.compress_size} bytes stored for {info.file_size} bytes of data")
        elif info.compress_type == zipfile.ZIP_DEFLATED:
            if info.file_size > info.compress_size * NPZ_MAX_DEFLATE_RATIO:
                raise _error(error_type, path, f"{where} claims {_human_bytes(info.file_size)} from "
                             f"{_human_bytes(info.compress_size)} of deflate data (more than deflate can produce)")
        else:
            raise _error(error_type, path, f"{where} uses compression method {info.compress_type} "
                         "(only stored and deflate are supported)")
        end = info.header_offset + _ZIP_LOCAL_HEADER_BYTES + info.compress_size
        if info.header_offset < 0 or end > file_size:
            raise _error(error_type, path, f"{where} extends past the end of the file "
                         f"(ends at byte {end}, file has {file_size})")
    # Members may not share bytes: overlapping members would let one compressed stream be counted
    # (and inflated) many times.
    by_offset = sorted(infos, key=lambda i: i.header_offset)
    for a, b in zip(by_offset, by_offset[1:]):
        if a.header_offset + _ZIP_LOCAL_HEADER_BYTES + a.compress_size > b.header_offset:
            raise _error(error_type, path, f"members {a.filename!r} and {b.filename!r} overlap in the archive")


def _read_npy_header(path: Path, member: str, fp, error_type: type[AtlasError]) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Parse the npy header at the start of ``fp``: ``(shape, fortran_order, dtype, header_bytes)``.

    The header length is read and bounded here, so a header claiming 4 GB is refused without
    reading it; numpy's parser then runs on the bounded bytes.
    """
    where = f"member {member!r}"
    pre = fp.read(_NPY_MAGIC_BYTES)
    try:
        version = npy_format.read_magic(io.BytesIO(pre))
    except ValueError as exc:
        raise _error(error_type, path, f"{where} is not an npy array ({exc})") from None
    fmt = _NPY_HEADER_LENGTH_FORMAT.get(version)
    if fmt is None:
        raise _error(error_type, path, f"{where}: npy format version {version[0]}.{version[1]} is not supported "
                     "(1.0 and 2.0 are)")
    raw_len = fp.read(struct.calcsize(fmt))
    if len(raw_len) != struct.calcsize(fmt):
        raise _error(error_type, path, f"{where}: npy header is truncated")
    (header_len,) = struct.unpack(fmt, raw_len)
    if header_len > NPY_MAX_HEADER_BYTES:
        raise _error(error_type, path, f"{where}: npy header of {header_len} bytes "
                     f"(at most {NPY_MAX_HEADER_BYTES} accepted)")
    header = fp.read(header_len)
    if len(header) != header_len:
        raise _error(error_type, path, f"{where}: npy header is truncated")
    parse = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns about Python-2 headers it can still parse
            shape, fortran_order, dtype = parse(io.BytesIO(raw_len + header), max_header_size=NPY_MAX_HEADER_BYTES)
    except _CORRUPT_NPY_HEADER as exc:
        raise _error(error_type, path, f"{where}: malformed npy header ({type(exc).__name__}: {str(exc)[:200]})") from None
    if dtype.hasobject or dtype.kind not in _ALLOWED_KINDS or dtype.itemsize == 0:
        raise _error(error_type, path, f"{where} has dtype {dtype.str!r}; only plain numeric and boolean arrays "
                     "are read (never pickled objects)")
    if any(isinstance(d, bool) or d < 0 for d in shape):
        raise _error(error_type, path, f"{where}: invalid shape {shape}")
    return tuple(int(d) for d in shape), bool(fortran_order), dtype, len(pre) + len(raw_len) + header_len


def _kind_matches(dtype: np.dtype, want) -> bool:
    if isinstance(want, str):
        return dtype.kind in want
    return dtype.newbyteorder("=") == np.dtype(want).newbyteorder("=")


def _describe(want) -> str:
    if isinstance(want, str):
        names = {"b": "bool", "i": "signed integer", "u": "unsigned integer", "f": "float", "c": "complex"}
        return " or ".join(names.get(k, k) for k in want)
    return np.dtype(want).name


def _read_member(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, archive_size: int,
                 spec: MemberSpec | None, error_type: type[AtlasError]) -> np.ndarray:
    """Read one checked member: header first, sizes proven, then the data in chunks."""
    where = f"member {info.filename!r}"
    try:
        return _read_member_unchecked(path, zf, info, archive_size, spec, error_type)
    except AtlasError:
        raise
    except _CORRUPT_ZIP as exc:
        raise _error(error_type, path, f"{where} is corrupt ({type(exc).__name__}: {str(exc)[:200]})") from None


def _read_member_unchecked(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, archive_size: int,
                           spec: MemberSpec | None, error_type: type[AtlasError]) -> np.ndarray:
    where = f"member {info.filename!r}"
    with zf.open(info) as fp:
        shape, fortran_order, dtype, header_bytes = _read_npy_header(path, info.filename, fp, error_type)
        count = math.prod(shape)
        nbytes = count * dtype.itemsize  # Python ints: no overflow whatever the header claims
        data_bytes = info.file_size - header_bytes
        claim = f"{where} claims shape {shape} {dtype.name} = {_human_bytes(nbytes)}"
        if nbytes > archive_size * NPZ_MAX_DEFLATE_RATIO:
            raise _error(error_type, path, f"{claim} but the archive holds {_human_bytes(archive_size)}")
        if nbytes != data_bytes:
            raise _error(error_type, path, f"{claim} but the member holds {_human_bytes(max(data_bytes, 0))} of data")
        if spec is not None:
            want_kind, want_ndim = spec
            if not _kind_matches(dtype, want_kind):
                raise _error(error_type, path, f"{where} has dtype {dtype.name}, expected {_describe(want_kind)}")
            if want_ndim is not None and len(shape) != want_ndim:
                raise _error(error_type, path, f"{where} has shape {shape} ({len(shape)} dimensions), "
                             f"expected {want_ndim}")
        flat = np.empty(count, dtype)
        buf = flat.view(np.uint8)
        pos = 0
        while pos < nbytes:
            got = fp.readinto(buf[pos: pos + _READ_CHUNK_BYTES])
            if not got:
                raise _error(error_type, path, f"{where} is truncated: {pos} of {nbytes} data bytes")
            pos += got
        if fp.read(1):  # also makes zipfile reach the end of the member and check its CRC
            raise _error(error_type, path, f"{where} holds more data than its header describes")
    if fortran_order:
        return flat.reshape(shape[::-1]).transpose()
    return flat.reshape(shape)


def load_npz_checked(path: str | Path, expected: Mapping[str, MemberSpec] | None = None,
                     error_type: type[AtlasError] = BundleFormatError) -> dict[str, np.ndarray]:
    """Read an ``.npz`` written by ``np.savez`` / ``np.savez_compressed`` without trusting it.

    Args:
        path: the archive.
        expected: ``{name: (kind, ndim)}`` of the members to read (``name`` without ``.npy``).
            ``kind`` is a string of numpy dtype kind letters (``"f"``, ``"iu"``, ``"b"``) or an
            exact dtype (``np.uint8``; byte order ignored); ``ndim`` an int or None for any. Every
            named member must be present; others are checked but not read. None: read every member.
        error_type: the project error to raise (``BundleFormatError``, ``ArtifactError``, ...).

    Returns:
        ``{name: array}``; arrays keep the archive's dtype (byte order included).

    Raises:
        error_type: unreadable or corrupt archive, a member whose header, dtype, shape or size is
            wrong, or a missing expected member; the message names the file and the member.
    """
    path = Path(path)
    try:
        archive_size = path.stat().st_size
    except OSError as exc:
        raise _error(error_type, path, f"cannot read ({exc.strerror or exc})") from None
    if not path.is_file():
        raise _error(error_type, path, "not a file")
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            _check_records(path, zf, archive_size, error_type)
            members = {}
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    raise _error(error_type, path, f"member {info.filename!r} is not an .npy array")
                members[info.filename[: -len(".npy")]] = info
            if expected is not None:
                missing = [k for k in expected if k not in members]
                if missing:
                    raise _error(error_type, path, f"missing member(s) {', '.join(k + '.npy' for k in missing)}")
                extra = sorted(set(members) - set(expected))
                if extra:
                    logger.debug("%s: ignoring unexpected member(s) %s", path, extra)
            for name, info in members.items():
                if expected is not None and name not in expected:
                    continue
                spec = None if expected is None else expected[name]
                out[name] = _read_member(path, zf, info, archive_size, spec, error_type)
    except AtlasError:
        raise
    except _CORRUPT_ZIP as exc:
        raise _error(error_type, path, f"corrupt npz archive ({type(exc).__name__}: {str(exc)[:200]})") from None
    return out


# Every member of a project-written .npz carries this timestamp (the zip format's earliest), so the
# same arrays give the same bytes: numpy's savez stamps the wall clock, which made equal artifacts
# hash differently (content hashes are data versions).
NPZ_MEMBER_DATE_TIME = (1980, 1, 1, 0, 0, 0)


def save_npz_deterministic(file, **arrays: np.ndarray) -> None:
    """``np.savez`` (uncompressed, loadable by ``np.load``) with fixed member timestamps and order,
    so equal arrays give byte-identical files. ``file`` is a path or a binary file object."""
    with zipfile.ZipFile(file, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=NPZ_MEMBER_DATE_TIME)
            info.compress_type = zipfile.ZIP_STORED
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(arr), allow_pickle=False)


# Sidecar JSON of an npz artifact (world.json, fused.json, keyframes.json) is a few kB; a file
# far larger than this is not one of ours.
JSON_SIDECAR_MAX_BYTES = 64 << 20


def is_finite_number(value) -> bool:
    """True for a JSON number (int or float, not bool) that is finite as a float; False for
    anything else, including integers too large for a float (``10**400``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def load_json_object_checked(path: str | Path, error_type: type[AtlasError] = ArtifactError) -> dict:
    """Read a JSON file whose top level must be an object, raising ``error_type`` naming the file
    (and line, for a syntax error) for missing, oversized, non-UTF-8 or malformed content."""
    import json

    path = Path(path)
    try:
        size = path.stat().st_size
        if size > JSON_SIDECAR_MAX_BYTES:
            raise _error(error_type, path, f"{_human_bytes(size)} is too large for a metadata file "
                         f"(at most {_human_bytes(JSON_SIDECAR_MAX_BYTES)})")
        data = json.loads(path.read_bytes().decode("utf-8"))
    except json.JSONDecodeError as exc:
        raise _error(error_type, path, f"invalid JSON at line {exc.lineno}: {exc.msg}") from None
    except UnicodeDecodeError as exc:
        raise _error(error_type, path, f"not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise _error(error_type, path, f"cannot read ({exc.strerror or exc})") from None
    except RecursionError:
        raise _error(error_type, path, "JSON nested too deeply") from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits (Python's int limit)
        raise _error(error_type, path, f"invalid JSON ({str(exc)[:200]})") from None
    if not isinstance(data, dict):
        raise _error(error_type, path, f"top level must be a JSON object, found {type(data).__name__}")
    return data

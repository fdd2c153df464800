"""ATLASGS1 binary world format (paper Appendix B), little endian::

    magic     8 bytes  b"ATLASGS1"
    count     uint64
    positions count x 3 x float32
    scales    count x float32          (isotropic standard deviation, metres)
    colors    count x 3 x uint8
    opacity   count x float32
    ids       count x uint64
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.io_utils import atomic_path

__all__ = ["MAGIC_V1", "write_atlasgs1", "read_atlasgs1"]

MAGIC_V1 = b"ATLASGS1"
_BYTES_PER_GAUSSIAN_V1 = 12 + 4 + 3 + 4 + 8


def write_atlasgs1(field: GaussianField, path: str | Path) -> Path:
    """Write an isotropic field as ATLASGS1 (atomically). Anisotropic fields are refused."""
    if not field.is_isotropic:
        raise ValueError("ATLASGS1 stores one scale per Gaussian; this field is anisotropic")
    n = len(field)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(MAGIC_V1)
            f.write(struct.pack("<Q", n))
            f.write(field.positions.astype("<f4").tobytes())
            f.write(field.scales[:, 0].astype("<f4").tobytes())
            f.write(field.colors.astype("u1").tobytes())
            f.write(field.opacities.astype("<f4").tobytes())
            f.write(field.ids.astype("<u8").tobytes())
    return Path(path)


def read_atlasgs1(path: str | Path) -> GaussianField:
    """Read an ATLASGS1 file; the size must match the count exactly and values must be finite."""
    path = Path(path)
    if not path.is_file():
        raise BundleFormatError(path, "file not found")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(16)
        if len(head) < 16 or head[:8] != MAGIC_V1:
            raise BundleFormatError(path, f"not an ATLASGS1 file (magic {head[:8]!r})")
        (n,) = struct.unpack("<Q", head[8:16])
        expected = 16 + n * _BYTES_PER_GAUSSIAN_V1
        if size != expected:
            raise BundleFormatError(path, f"count {n} needs {expected} bytes, file has {size}")
        buf = f.read()
    off = 0

    def take(dtype: str, shape: tuple[int, ...]) -> np.ndarray:
        nonlocal off
        a = np.frombuffer(buf, dtype=dtype, count=int(np.prod(shape)), offset=off).reshape(shape)
        off += a.nbytes
        return a

    pos = take("<f4", (n, 3))
    scale = take("<f4", (n,))
    col = take("u1", (n, 3))
    opa = take("<f4", (n,))
    ids = take("<u8", (n,))
    if not (np.isfinite(pos).all() and np.isfinite(scale).all() and np.isfinite(opa).all()):
        raise BundleFormatError(path, "NaN or infinite values")
    rot = np.zeros((n, 4), np.float32)
    rot[:, 3] = 1.0
    return GaussianField(pos, np.repeat(scale[:, None], 3, axis=1), rot, col, opa, ids)

"""The Gaussian field: the world's state as a set of 3D Gaussians with stable ids."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

__all__ = [
    "GaussianField", "opacity_to_logit", "logit_to_opacity", "scale_to_log", "log_to_scale", "canonicalize",
    "FIELD_BYTES_PER_GAUSSIAN", "ids_unique", "SH_MAX_DEGREE", "sh_rest_count", "sh_degree_of_rest_count",
    "field_bytes_per_gaussian",
]

# Memory of one Gaussian in a GaussianField: positions, scales (3 x float32 each), rotation
# (4 x float32), colour (3 x uint8), opacity (float32), id (uint64) -- the same 55 bytes as a
# Gaussian in ATLASGS2 (gaussians.bin), so a loaded field is the file's size.
FIELD_BYTES_PER_GAUSSIAN = 12 + 12 + 16 + 3 + 4 + 8

# View-dependent colour: spherical harmonics up to degree 3, as 3D Gaussian Splatting trains them.
# The degree-0 term is the uint8 colour; degree d adds (d + 1)^2 - 1 coefficients per channel.
SH_MAX_DEGREE = 3
_SH_REST_COUNTS = {d: (d + 1) ** 2 - 1 for d in range(SH_MAX_DEGREE + 1)}  # 0, 3, 8, 15
_SH_DEGREE_OF_COUNT = {k: d for d, k in _SH_REST_COUNTS.items()}


def sh_rest_count(degree: int) -> int:
    """Coefficients per channel beyond the degree-0 colour: 0, 3, 8, 15 for degree 0-3."""
    if degree not in _SH_REST_COUNTS:
        raise ValueError(f"SH degree must be 0..{SH_MAX_DEGREE}, got {degree!r}")
    return _SH_REST_COUNTS[degree]


def sh_degree_of_rest_count(count: int) -> int | None:
    """The SH degree with ``count`` coefficients per channel beyond degree 0 (0, 3, 8 or 15), else None."""
    return _SH_DEGREE_OF_COUNT.get(int(count))


def field_bytes_per_gaussian(sh_degree: int = 0) -> int:
    """Memory of one Gaussian in a field of SH degree ``sh_degree``: 55 bytes plus 12 per SH coefficient."""
    return FIELD_BYTES_PER_GAUSSIAN + 12 * sh_rest_count(sh_degree)


def ids_unique(ids: np.ndarray) -> bool:
    """Whether the ``[N]`` ids are all different.

    Fields keep their ids sorted (voxel order), so a strictly increasing check (O(N), no copy)
    usually decides; otherwise one sorted copy (8 bytes per id). ``np.unique`` on uint64 takes its
    hash path, about 1.5 s per million ids: most of the load time of a big world.
    """
    ids = np.asarray(ids)
    if len(ids) < 2:
        return True
    if bool((ids[1:] > ids[:-1]).all()):
        return True
    s = np.sort(ids)
    return bool((s[1:] != s[:-1]).all())


@dataclass
class GaussianField:
    """A set of N 3D Gaussians in the world frame.

    Attributes:
        positions: ``[N, 3]`` float32 means, metres.
        scales: ``[N, 3]`` float32 standard deviations along the Gaussian's local axes, metres
            (equal for the isotropic v1 proxy field).
        rotations_xyzw: ``[N, 4]`` float32 unit quaternions, local axes to world.
        colors: ``[N, 3]`` uint8 RGB, view-independent.
        opacities: ``[N]`` float32 in (0, 1].
        ids: ``[N]`` uint64 stable identifiers (unique; the same surface patch keeps its id across
            incremental merges and reruns).
        sh_rest: ``[N, K, 3]`` float32 spherical-harmonic coefficients beyond degree 0 (``K`` = 0, 3,
            8 or 15 for SH degree 0-3), in the order of 3D Gaussian Splatting's ``features_rest``:
            coefficient ``k + 1`` of the basis, then the RGB channel; in the units of ``f_dc_*`` (the
            colour in [0, 1] is ``0.5 + C0 f_dc + sum_k Y_k(d) sh_rest[:, k]``, see
            :mod:`atlas_pipeline.gaussian_world.sh`). ``None`` (the default) is degree 0, ``[N, 0, 3]``.
    """

    positions: np.ndarray
    scales: np.ndarray
    rotations_xyzw: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    ids: np.ndarray
    sh_rest: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = np.ascontiguousarray(self.positions, dtype=np.float32)
        self.scales = np.ascontiguousarray(self.scales, dtype=np.float32)
        self.rotations_xyzw = np.ascontiguousarray(self.rotations_xyzw, dtype=np.float32)
        self.colors = np.ascontiguousarray(self.colors, dtype=np.uint8)
        self.opacities = np.ascontiguousarray(self.opacities, dtype=np.float32)
        self.ids = np.ascontiguousarray(self.ids, dtype=np.uint64)
        n = len(self.positions)
        if self.sh_rest is None:
            self.sh_rest = np.zeros((n, 0, 3), np.float32)
        self.sh_rest = np.ascontiguousarray(self.sh_rest, dtype=np.float32)
        sh = self.sh_rest.shape
        if len(sh) != 3 or sh[0] != n or sh[2] != 3 or sh_degree_of_rest_count(sh[1]) is None:
            raise ValueError(f"GaussianField.sh_rest has shape {sh}, expected ({n}, K, 3) with K in "
                             f"{sorted(_SH_DEGREE_OF_COUNT)} (SH degree 0-{SH_MAX_DEGREE})")
        expect = {
            "positions": (n, 3), "scales": (n, 3), "rotations_xyzw": (n, 4), "colors": (n, 3),
            "opacities": (n,), "ids": (n,),
        }
        for name, shape in expect.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(f"GaussianField.{name} has shape {got}, expected {shape}")

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def sh_degree(self) -> int:
        """Degree of the view-dependent colour: 0 (none) to ``SH_MAX_DEGREE``."""
        return _SH_DEGREE_OF_COUNT[self.sh_rest.shape[1]]

    @property
    def nbytes(self) -> int:
        """Bytes the arrays hold: ``field_bytes_per_gaussian(self.sh_degree) * len(self)``."""
        return sum(getattr(self, k).nbytes for k in ("positions", "scales", "rotations_xyzw", "colors",
                                                      "opacities", "ids", "sh_rest"))

    @classmethod
    def empty(cls) -> "GaussianField":
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)),
                   np.zeros(0), np.zeros(0, np.uint64))

    @property
    def is_isotropic(self) -> bool:
        return bool(np.all(self.scales == self.scales[:, :1]))

    def is_finite(self) -> bool:
        return bool(
            np.isfinite(self.positions).all() and np.isfinite(self.scales).all()
            and np.isfinite(self.rotations_xyzw).all() and np.isfinite(self.opacities).all()
            and np.isfinite(self.sh_rest).all()
        )

    def subset(self, mask_or_index: np.ndarray) -> "GaussianField":
        m = mask_or_index
        return GaussianField(self.positions[m], self.scales[m], self.rotations_xyzw[m],
                             self.colors[m], self.opacities[m], self.ids[m], self.sh_rest[m])

    def content_hash(self) -> str:
        """sha256 over every array, in a fixed order: the map id of a world state (the arrays are
        hashed in place, contiguous as ``__post_init__`` makes them: no copy). ``sh_rest`` is hashed
        only when the field has any, so a degree-0 world keeps the id it had before fields carried SH."""
        h = hashlib.sha256()
        names = ("ids", "positions", "scales", "rotations_xyzw", "colors", "opacities")
        for name in names + (("sh_rest",) if self.sh_degree else ()):
            arr = getattr(self, name)
            h.update(name.encode())
            h.update(str(arr.shape).encode())
            if arr.size:  # an empty array has no bytes, and a memoryview of it cannot be cast
                h.update(memoryview(np.ascontiguousarray(arr)).cast("B"))
        return h.hexdigest()

    def equals(self, other: "GaussianField") -> bool:
        """Bit-for-bit equality of every array."""
        return all(
            np.array_equal(getattr(self, k), getattr(other, k))
            for k in _ARRAYS
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box ``(min [3], max [3])`` of the means."""
        if len(self) == 0:
            return np.zeros(3), np.zeros(3)
        return self.positions.min(axis=0).astype(np.float64), self.positions.max(axis=0).astype(np.float64)


_ARRAYS = ("positions", "scales", "rotations_xyzw", "colors", "opacities", "ids", "sh_rest")


# ---- the 3DGS parametrisation: opacity as a logit, scales as logarithms ----------------------
def opacity_to_logit(o: np.ndarray) -> np.ndarray:
    o = np.clip(o.astype(np.float64), 1e-7, 1 - 1e-7)
    return np.log(o / (1 - o)).astype(np.float32)


def logit_to_opacity(logit: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-logit.astype(np.float64)))).astype(np.float32)


def scale_to_log(s: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(s.astype(np.float64), 1e-30)).astype(np.float32)


def log_to_scale(log_s: np.ndarray) -> np.ndarray:
    return np.exp(log_s.astype(np.float64)).astype(np.float32)


def _fixed_point(x: np.ndarray, enc, dec, rounds: int = 4) -> np.ndarray:
    """Smallest change to ``x`` after which ``dec(enc(x)) == x`` exactly in float32."""
    for _ in range(rounds):
        y = dec(enc(x))
        if np.array_equal(y, x):
            return x
        x = y
    return x


def canonicalize(field: GaussianField) -> GaussianField:
    """Snap opacities, scales and rotations to values the PLY encoding reproduces bit for bit.

    The PLY stores logit(opacity) and log(scale) in float32; decoding those does not always give
    back the same float32. Snapping once (a change of a few ulp) makes save/load exact.
    """
    rot = field.rotations_xyzw.astype(np.float64)
    rot /= np.linalg.norm(rot, axis=1, keepdims=True)
    return GaussianField(
        field.positions,
        _fixed_point(field.scales, scale_to_log, log_to_scale),
        rot.astype(np.float32),
        field.colors,
        _fixed_point(field.opacities, opacity_to_logit, logit_to_opacity),
        field.ids,
        field.sh_rest,
    )

"""Which parts of a surfel map a view can see, by chunks of space, so that splatting a view costs
what the camera sees rather than the size of the map.

Space is cut into cubes (chunks) of a fixed world grid; only the occupied ones are indexed. A
chunk is *unseen* by a view when all eight corners of its cube lie on the outer side of one of
the view's culling planes: behind the near clip, beyond the far clip, or beyond an image edge
widened by the largest disk footprint. Every surfel the splat kernel would draw passes its own
tests against the same planes, so the test is conservative: culling changes which surfels the
kernel looks at, never the image it renders.

The grid is anchored at the world origin, not at the map's bounding box, so a growing map keeps
its chunks: :class:`ChunkIndex` assigns the surfels a keyframe moved or added and leaves the rest.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from atlas_pipeline.gaussian_world.builder import pack_voxel_ids
from atlas_pipeline.localization._kernels import PinholeView, SplatParams

__all__ = ["ChunkGrid", "ChunkIndex", "CHUNK_M", "MAX_CHUNKS"]

CHUNK_M = 1.0  # edge of a chunk: a room is a few chunks across, a view sees a few dozen
# A map occupying more chunks than this (a kilometre of corridor) gets coarser chunks instead: the
# per-view test is over the occupied chunks, and it must stay well under a millisecond.
MAX_CHUNKS = 1 << 15
# Extra pixels and metres on the outer side of every plane: the kernel's own tests are in floating
# point, and a surfel exactly on a plane must never be culled here while drawn there.
MARGIN_PX = 1.0
MARGIN_M = 1e-6
# Each cube is widened by this on every side: ``floor(c / chunk_m)`` may round a centre on a
# chunk's face into the neighbour, and the cube must still hold it.
CUBE_PAD_M = 1e-4

# The eight corners of the unit cube, [8, 3].
_CUBE = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)


class ChunkGrid(NamedTuple):
    """A map's surfels binned into the occupied cubes of a ``chunk_m`` grid.

    ``chunk_of [N]`` int32 is each surfel's chunk, an index into ``corners_w [O, 8, 3]`` (the world
    corners of the occupied cubes, padded by :data:`CUBE_PAD_M`); ``n_chunks`` (O) is the size of
    the masks :meth:`seen` returns."""

    chunk_of: np.ndarray
    corners_w: np.ndarray
    n_chunks: int

    @classmethod
    def build(cls, centres_w: np.ndarray, chunk_m: float = CHUNK_M, max_chunks: int = MAX_CHUNKS) -> "ChunkGrid":
        """Bin ``centres_w [N, 3]`` (world, m) into cubes of ``chunk_m``, doubled until at most
        ``max_chunks`` of them are occupied."""
        c = np.asarray(centres_w, np.float64).reshape(-1, 3)
        while True:
            index = ChunkIndex(chunk_m)
            chunk_of = index.chunks_of(c)
            if len(index) <= max_chunks:
                return index.grid(chunk_of)
            chunk_m *= 2.0

    def seen(self, view: PinholeView, params: SplatParams) -> np.ndarray:
        """``[n_chunks]`` bool: the chunks ``view`` may see; False only where no surfel of the
        chunk can be drawn (its centre nearer than ``params.min_depth_m`` or farther than
        ``params.max_depth_m``, or its disk of at most ``params.max_radius_px`` off the image)."""
        if self.n_chunks == 0:
            return np.zeros(0, bool)
        fx, fy, cx, cy, width, height = view.fx, view.fy, view.cx, view.cy, view.width, view.height
        min_depth_m = params.min_depth_m
        R, t = view.T_world_cam[:3, :3], view.T_world_cam[:3, 3]
        p = (self.corners_w - t) @ R  # [O, 8, 3] camera frame: R^T (p - t), row-wise
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        reach = params.max_radius_px + MARGIN_PX
        # u = fx x / z + cx: u + reach < 0 <=> fx x + (cx + reach) z < 0 for z > 0, and the
        # same for the other edges; the near plane catches z <= 0.
        off = ((z < min_depth_m - MARGIN_M).all(axis=1)
               | (z > params.max_depth_m + MARGIN_M).all(axis=1)
               | (fx * x + (cx + reach) * z < 0.0).all(axis=1)
               | (fx * x + (cx - reach - (width - 1)) * z > 0.0).all(axis=1)
               | (fy * y + (cy + reach) * z < 0.0).all(axis=1)
               | (fy * y + (cy - reach - (height - 1)) * z > 0.0).all(axis=1))
        return ~off


class ChunkIndex:
    """The occupied chunks of a ``chunk_m`` world grid, numbered in the order they were first met
    (so the same centres in the same order give the same numbers)."""

    def __init__(self, chunk_m: float = CHUNK_M):
        self.chunk_m = float(chunk_m)
        self._number: dict[int, int] = {}  # packed chunk coordinates -> chunk number
        self._lower: list[np.ndarray] = []  # [3] int64 chunk coordinates, by number
        self._corners = np.zeros((0, 8, 3))  # the cubes of the first len(_corners) chunks

    def __len__(self) -> int:
        return len(self._number)

    def chunks_of(self, centres_w: np.ndarray) -> np.ndarray:
        """``[K]`` int32: the chunk number of each of ``centres_w [K, 3]`` (world, m); chunks not
        met before are numbered now."""
        c = np.asarray(centres_w, np.float64).reshape(-1, 3)
        if len(c) == 0:
            return np.zeros(0, np.int32)
        ijk = np.floor(c / self.chunk_m).astype(np.int64)  # [K, 3]
        keys, first, inverse = np.unique(pack_voxel_ids(ijk), return_index=True, return_inverse=True)
        numbers = np.empty(len(keys), np.int32)
        for n, (key, at) in enumerate(zip(keys.tolist(), first.tolist())):
            number = self._number.get(key)
            if number is None:
                number = self._number[key] = len(self._lower)
                self._lower.append(ijk[at])
            numbers[n] = number
        return numbers[inverse.reshape(-1)]

    def grid(self, chunk_of: np.ndarray) -> ChunkGrid:
        """The :class:`ChunkGrid` of surfels whose chunk numbers are ``chunk_of [N]`` (from
        :meth:`chunks_of`)."""
        n_old = len(self._corners)
        if n_old < len(self._lower):
            lower = np.asarray(self._lower[n_old:], np.float64)  # [O_new, 3]
            cubes = (lower[:, None, :] + _CUBE[None]) * self.chunk_m + (2.0 * _CUBE - 1.0) * CUBE_PAD_M
            self._corners = np.concatenate([self._corners, cubes])
        return ChunkGrid(np.ascontiguousarray(chunk_of, np.int32), self._corners, len(self._corners))

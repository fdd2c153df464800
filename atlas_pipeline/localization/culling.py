"""Which parts of a surfel map a view can see, by chunks of space, so that splatting a view costs
what the camera sees rather than the size of the map.

The map's bounding box is cut into cubes (chunks); a chunk is *unseen* by a view when all eight
corners of its cube lie on the outer side of one of the view's culling planes: behind the near
clip, beyond the far clip, or beyond an image edge widened by the largest disk footprint. Every
surfel the splat kernel would draw passes its own tests against the same planes, so the test is
conservative: culling changes which surfels the kernel looks at, never the image it renders.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from atlas_pipeline.localization._kernels import PinholeView, SplatParams

__all__ = ["ChunkGrid", "CHUNK_M", "MAX_CHUNKS"]

CHUNK_M = 1.0  # edge of a chunk: a room is a few chunks across, a view sees a few dozen
# A map larger than this many chunks (a kilometre of corridor) gets coarser chunks instead: the
# per-view test is over the occupied chunks, and it must stay well under a millisecond.
MAX_CHUNKS = 1 << 15
# Extra pixels and metres on the outer side of every plane: the kernel's own tests are in floating
# point, and a surfel exactly on a plane must never be culled here while drawn there.
MARGIN_PX = 1.0
MARGIN_M = 1e-6

# The eight corners of the unit cube, [8, 3].
_CUBE = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)


class ChunkGrid(NamedTuple):
    """The map's surfels binned into cubes of ``chunk_m``.

    ``chunk_of [N]`` int32 is each surfel's chunk; ``occupied [O]`` int64 the chunks holding at
    least one surfel; ``corners_w [O, 8, 3]`` the world corners of their cubes; ``n_chunks`` the
    size of the masks :meth:`seen` returns."""

    chunk_of: np.ndarray
    occupied: np.ndarray
    corners_w: np.ndarray
    n_chunks: int

    @classmethod
    def build(cls, centres_w: np.ndarray, chunk_m: float = CHUNK_M, max_chunks: int = MAX_CHUNKS) -> "ChunkGrid":
        """Bin ``centres_w [N, 3]`` (world, m) into cubes of ``chunk_m``, doubled until the box of
        the map holds at most ``max_chunks`` of them."""
        c = np.asarray(centres_w, np.float64).reshape(-1, 3)
        if len(c) == 0:
            return cls(np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros((0, 8, 3)), 0)
        lo = c.min(axis=0)
        extent = c.max(axis=0) - lo
        while np.prod(np.floor(extent / chunk_m) + 1) > max_chunks:
            chunk_m *= 2.0
        dims = (np.floor(extent / chunk_m) + 1).astype(np.int64)  # [3]
        ijk = np.minimum(np.floor((c - lo) / chunk_m).astype(np.int64), dims - 1)  # [N, 3]
        chunk_of = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        n_chunks = int(np.prod(dims))
        occupied = np.flatnonzero(np.bincount(chunk_of, minlength=n_chunks))
        occ_ijk = np.stack([occupied // (dims[1] * dims[2]), (occupied // dims[2]) % dims[1], occupied % dims[2]], 1)
        corners = lo + (occ_ijk[:, None, :] + _CUBE[None]) * chunk_m  # [O, 8, 3]
        return cls(chunk_of.astype(np.int32), occupied, corners, n_chunks)

    def seen(self, view: PinholeView, params: SplatParams) -> np.ndarray:
        """``[n_chunks]`` bool: the chunks ``view`` may see; False only where no surfel of the
        chunk can be drawn (its centre nearer than ``params.min_depth_m`` or farther than
        ``params.max_depth_m``, or its disk of at most ``params.max_radius_px`` off the image)."""
        mask = np.zeros(self.n_chunks, bool)
        if len(self.occupied) == 0:
            return mask
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
        mask[self.occupied[~off]] = True
        return mask

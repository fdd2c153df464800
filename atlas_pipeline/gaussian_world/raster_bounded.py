"""Stages 3-5 of the raster core in bounded memory: what ``render.render_gaussians`` runs.

Same image bit for bit as the one-pass stages (``raster.prepare_splats`` + ``composite.composite_tiles``)
with no per-input-Gaussian buffers and no whole-view pair list: ``project_visible`` projects
``PROJECT_CHUNK`` Gaussians at a time and keeps only the drawn ones (compacted, input order);
``sort_visible`` puts them front to back in place (no sorted copy); ``tile_pair_counts`` counts the
(tile, Gaussian) pairs per tile without listing them; ``tile_batches`` cuts the tiles (row-major)
into runs of at most ``max_tile_pairs`` pairs; ``bin_tile_batch`` lists one run's pairs and
``composite.composite_tile_batch`` draws it into the output images. Peak memory is then O(N) with a
small constant plus O(pairs per batch), whatever the view (``render.render_peak_bytes`` states it).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from atlas_pipeline.gaussian_world.raster import (
    MAX_TILE_PAIRS, N_AUX, N_FEAT, NEAR_M, PROJECT_CHUNK, TILE_SIZE, GaussianArrays, RasterView, project_kernel,
    radix_argsort_positive,
)
from atlas_pipeline.gaussian_world.sh import view_colors

__all__ = ["VisibleSplats", "project_visible", "sort_visible", "tile_pair_counts", "tile_batches", "bin_tile_batch"]



class VisibleSplats(NamedTuple):
    """The drawn Gaussians of one view, compacted (``project_visible``; ``sort_visible`` puts them
    front to back in place)."""

    feat: np.ndarray  # [M, N_FEAT] float32 feature rows
    box: np.ndarray  # [M, 4] int32 inclusive pixel boxes (x0, x1, y0, y1)
    depth: np.ndarray  # [M] float64 camera z


@njit(cache=True)
def _compact_rows(valid, depth, feat, box, depth_out, feat_out, box_out, m):
    """Append the rows of ``feat`` ``[C, N_FEAT]`` / ``box`` ``[C, 4]`` / ``depth`` ``[C]`` where
    ``valid`` ``[C]`` to the outputs at row ``m``, in order; returns the new row count."""
    for i in range(valid.shape[0]):
        if valid[i]:
            depth_out[m] = depth[i]
            for j in range(feat.shape[1]):
                feat_out[m, j] = feat[i, j]
            for j in range(4):
                box_out[m, j] = box[i, j]
            m += 1
    return m


def _shrink_rows(a: np.ndarray, m: int) -> np.ndarray:
    """``a[:m]`` without a copy: the buffer is reallocated to ``m`` rows (``ndarray.resize``; a large
    buffer gives back its tail pages), so a capacity of N rows of which M were written costs M."""
    a.resize((m,) + a.shape[1:], refcheck=False)
    return a


def project_visible(
    positions: np.ndarray,  # [N, 3]
    scales: np.ndarray,  # [N, 3]
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3] (float32, or uint8: converted per row)
    opacities: np.ndarray,  # [N]
    view: RasterView,
    near_m: float = NEAR_M,
    chunk: int = PROJECT_CHUNK,
    sh_rest: np.ndarray | None = None,  # [N, K, 3] float32 view-dependent colour (None: colors as given)
) -> VisibleSplats:
    """Stage 3 in bounded memory: ``project_gaussians`` on ``chunk`` Gaussians at a time, keeping the
    drawn rows only (input order). The rows equal ``project_gaussians``'s valid rows bit for bit.
    With ``sh_rest`` each chunk's colours are first those seen from the camera (``sh.view_colors``,
    ``colors`` the degree-0 term), so no per-Gaussian colour buffer is needed.

    Memory: the outputs are allocated for N rows but only the M drawn ones are written and kept
    (64 bytes per drawn Gaussian: ``N_FEAT`` float32, 4 int32, a float64 depth), plus the per-chunk
    buffers (65 bytes per chunk row).
    """
    n = positions.shape[0]
    feat = np.empty((n, N_FEAT), np.float32)
    box = np.empty((n, 4), np.int32)
    depth = np.empty(n, np.float64)
    no_aux = np.empty((0, N_AUX))
    m = 0
    for i in range(0, n, max(1, int(chunk))):
        c = slice(i, i + chunk)
        col = colors[c] if sh_rest is None else view_colors(positions[c], colors[c], sh_rest[c], view.centre_world)
        chunk_gaussians = GaussianArrays(positions[c], scales[c], rotations_xyzw[c], col, opacities[c])
        valid, d, f, b, _ = project_kernel(chunk_gaussians, view, near_m, no_aux)
        m = _compact_rows(valid, d, f, b, depth, feat, box, m)
    return VisibleSplats(_shrink_rows(feat, m), _shrink_rows(box, m), _shrink_rows(depth, m))


@njit(cache=True)
def _permute_rows_inplace(order, feat, box, depth):
    """``feat[:] = feat[order]``, ``box[:] = box[order]``, ``depth[:] = depth[order]`` in place,
    cycle by cycle (``order`` ``[M]`` int32, a permutation, is used as the visited mark and
    restored)."""
    m = order.shape[0]
    nf = feat.shape[1]
    ftmp = np.empty(nf, feat.dtype)
    btmp = np.empty(4, box.dtype)
    for start in range(m):
        if order[start] < 0 or order[start] == start:
            continue
        for j in range(nf):
            ftmp[j] = feat[start, j]
        for j in range(4):
            btmp[j] = box[start, j]
        dtmp = depth[start]
        k = start
        while True:
            src = order[k]
            order[k] = -1 - src  # visited
            if src == start:
                for j in range(nf):
                    feat[k, j] = ftmp[j]
                for j in range(4):
                    box[k, j] = btmp[j]
                depth[k] = dtmp
                break
            for j in range(nf):
                feat[k, j] = feat[src, j]
            for j in range(4):
                box[k, j] = box[src, j]
            depth[k] = depth[src]
            k = src
    for k in range(m):
        if order[k] < 0:
            order[k] = -1 - order[k]


def sort_visible(vis: VisibleSplats) -> np.ndarray:
    """Stage 4 in place: rows of ``vis`` front to back, ties in input order (the order of
    ``sort_by_depth``); returns that order ``[M]`` int32 (rows of the unsorted ``vis``). No sorted
    copy: 8 bytes per drawn Gaussian for the radix sort."""
    if len(vis.depth) == 0:
        return np.zeros(0, np.int32)
    order = radix_argsort_positive(vis.depth)
    _permute_rows_inplace(order, vis.feat, vis.box, vis.depth)
    return order


@njit(cache=True)
def _tile_pair_counts_kernel(box, tiles_x, tiles_y):
    """Pairs per tile ``[tiles_y, tiles_x]`` int64 of ``box`` ``[M, 4]`` (2D difference array: O(M)
    work whatever the footprints)."""
    diff = np.zeros((tiles_y + 1, tiles_x + 1), dtype=np.int64)
    for k in range(box.shape[0]):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE + 1
        ty0 = box[k, 2] // TILE_SIZE
        ty1 = box[k, 3] // TILE_SIZE + 1
        diff[ty0, tx0] += 1
        diff[ty0, tx1] -= 1
        diff[ty1, tx0] -= 1
        diff[ty1, tx1] += 1
    for ty in range(tiles_y + 1):
        for tx in range(1, tiles_x + 1):
            diff[ty, tx] += diff[ty, tx - 1]
    for ty in range(1, tiles_y + 1):
        for tx in range(tiles_x + 1):
            diff[ty, tx] += diff[ty - 1, tx]
    return diff[:tiles_y, :tiles_x].copy()


def tile_pair_counts(
    box: np.ndarray,  # [M, 4] int32 boxes (x0, x1, y0, y1)
    width: int,
    height: int,
) -> np.ndarray:
    """Stage 5a: ``[n_tiles]`` int64 number of boxes touching each tile (row major), the lengths of
    ``bin_tiles``'s lists, without listing them."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    return _tile_pair_counts_kernel(box, tiles_x, tiles_y).reshape(-1)


def tile_batches(
    counts: np.ndarray,  # [n_tiles] pairs per tile
    max_tile_pairs: int | None = MAX_TILE_PAIRS,
) -> list[tuple[int, int]]:
    """Stage 5b: runs ``[(t0, t1)]`` of consecutive tiles (row major) covering every tile, each with at
    most ``max_tile_pairs`` pairs (a run of one tile may hold more: a tile is never split). None:
    one run."""
    n_tiles = len(counts)
    if max_tile_pairs is None or n_tiles == 0:
        return [(0, n_tiles)]
    cum = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])  # [n_tiles + 1]
    out = []
    t0 = 0
    while t0 < n_tiles:
        # the last tile whose run from t0 stays within the budget; at least one tile
        t1 = int(np.searchsorted(cum, cum[t0] + int(max_tile_pairs), side="right")) - 1
        t1 = min(n_tiles, max(t1, t0 + 1))
        out.append((t0, t1))
        t0 = t1
    return out


@njit(cache=True)
def _bin_tile_batch_kernel(box, tiles_x, t0, t1, tile_start, tile_ids):
    """Fill ``tile_ids`` with the rows of ``box`` ``[M, 4]`` touching tiles ``t0 .. t1 - 1``, per tile
    in row order (``tile_start`` ``[t1 - t0 + 1]``: the run's offsets)."""
    fill = tile_start[:-1].copy()
    ty_a = t0 // tiles_x
    ty_b = (t1 - 1) // tiles_x
    for k in range(box.shape[0]):
        tx0 = box[k, 0] // TILE_SIZE
        tx1 = box[k, 1] // TILE_SIZE
        for ty in range(max(box[k, 2] // TILE_SIZE, ty_a), min(box[k, 3] // TILE_SIZE, ty_b) + 1):
            row = ty * tiles_x
            for tx in range(max(tx0, t0 - row), min(tx1, t1 - 1 - row) + 1):
                t = row + tx - t0
                tile_ids[fill[t]] = k
                fill[t] += 1


def bin_tile_batch(
    box: np.ndarray,  # [M, 4] int32 boxes of the sorted Gaussians
    counts: np.ndarray,  # [n_tiles] from tile_pair_counts
    width: int,
    t0: int,
    t1: int,
    out: np.ndarray | None = None,  # [>= P] int32 buffer to fill (reused across runs)
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 5c: ``(tile_start [t1 - t0 + 1] int64, tile_ids [P] int32)`` of tiles ``t0 .. t1 - 1``:
    the slice of ``bin_tiles``'s lists for those tiles (same rows, same order)."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tile_start = np.zeros(t1 - t0 + 1, np.int64)
    np.cumsum(counts[t0:t1], out=tile_start[1:])
    p = int(tile_start[-1])
    tile_ids = np.empty(p, np.int32) if out is None else out[:p]
    _bin_tile_batch_kernel(box, tiles_x, t0, t1, tile_start, tile_ids)
    return tile_start, tile_ids

"""Stage 6 of the raster core: compositing, one kernel for the renderer and the keyframe fit.

Per pixel, front to back, ``alpha_i = min(ALPHA_MAX, opacity_i exp(-0.5 d^T conic_i d))``, skipped
below ``ALPHA_MIN``; ``C += T alpha_i c_i``, ``D += T alpha_i z_i(p)``, ``T *= 1 - alpha_i``; a pixel
stops once ``T < T_MIN`` (the contribution that crosses the threshold is kept). ``rgb = round(C + T
bg)``, ``alpha = 1 - T``, ``depth = D / alpha`` where ``alpha >= DEPTH_MIN_ALPHA``, else 0.

The pieces, each written once and used by every tile loop (the renderer's ``composite_tiles`` /
``composite_tile_batch`` here, the fit's forward and backward passes in ``fit_kernels``):

* ``load_splat``: one sorted Gaussian's feature row as a tile reads it (:class:`Splat`).
* ``lane_alpha``: the alpha of one lane (pixel) of a tile row, with the alpha tests.
* ``composite_row``: one tile row (``TILE_SIZE`` lanes of float32, branch-free so it vectorises)
  through one Gaussian: colour, depth, transmittance, the median-depth crossing and the
  transmittance through the measured surface (the fit's coverage term).
* ``composite_tile``: a tile's Gaussians front to back through ``composite_row``, with early
  termination; returns where its list stopped (the backward pass stops there too).

``z_i(p)`` is the depth of Gaussian ``i`` at the pixel. ``_compositor`` compiles the one source for
two models: the renderer's (``composite_tile_centre``: centre depths, and the median-depth crossing)
and the fit's (``composite_tile``: the depth of the Gaussian's plane, ``z + slope_u dx + slope_v dy``
from the projection's ``AUX_SLOPE_*``, and the transmittance through the measured surface).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.cores import kernel_threads
from atlas_pipeline.gaussian_world.raster import (
    ALPHA_MAX, ALPHA_MIN, AUX_SLOPE_U, AUX_SLOPE_V, DEPTH_MIN_ALPHA, FEAT_BLUE, FEAT_CONIC_A, FEAT_CONIC_B,
    FEAT_CONIC_C, FEAT_GREEN, FEAT_OPACITY, FEAT_RED, FEAT_U, FEAT_V, FEAT_Z, MEDIAN_DEPTH_T, N_AUX, POWER_MIN,
    T_MIN, TILE_SIZE, SplatTiles, tile_pixel_bounds,
)

# Numba's on-disk cache (cache=True) keys a kernel on its own file only: after editing this module,
# delete the cached kernels of the modules that inline it (__pycache__/fit_kernels.*.nbi / .nbc).

__all__ = [
    "Splat", "TileAccum", "RenderImages", "exp_neg_fast", "lane_alpha", "load_splat", "composite_row",
    "composite_tile", "load_splat_centre", "composite_row_centre", "composite_tile_centre", "new_tile_accum",
    "reset_tile_accum", "composite_tiles", "composite_tile_batch",
]


class Splat(NamedTuple):
    """One sorted Gaussian as the lanes of one tile read it (float32; ``ux`` and the lane range are
    relative to the tile's left column)."""

    ux: np.float32  # mean u minus the tile's first column (px)
    v: np.float32  # mean v (px)
    conic_a: np.float32  # conic (inverse pixel covariance) [[a, b], [b, c]]
    conic_b: np.float32
    conic_c: np.float32
    nha: np.float32  # -0.5 conic_a
    nhc: np.float32  # -0.5 conic_c
    opacity: np.float32
    red: np.float32
    green: np.float32
    blue: np.float32
    z: np.float32  # camera depth of the mean (m)
    slope_u: np.float32  # dz/du, dz/dv of the Gaussian's plane (0: centre depth)
    slope_v: np.float32
    lx0: np.float32  # first and last lane of the tile inside the Gaussian's box
    lx1: np.float32


class TileAccum(NamedTuple):
    """Per-pixel sums of one tile, ``[TILE_SIZE, TILE_SIZE]`` float32 each (rows = tile rows)."""

    trans: np.ndarray  # transmittance T
    red: np.ndarray  # colour sums C
    green: np.ndarray
    blue: np.ndarray
    depth: np.ndarray  # depth sum D
    median: np.ndarray  # depth where T crossed MEDIAN_DEPTH_T (0: never)
    surface_trans: np.ndarray  # T through the Gaussians whose plane depth is <= limit
    limit: np.ndarray  # depth limit of the measured surface (m); 0 where there is none


class RenderImages(NamedTuple):
    """Output images of the renderer's compositing, written tile by tile."""

    rgb: np.ndarray  # [H, W, 3] uint8
    depth_m: np.ndarray  # [H, W] float32
    alpha: np.ndarray  # [H, W] float32
    depth_median_m: np.ndarray  # [H, W] float32


@njit(cache=True, inline="always")
def exp_neg_fast(x):
    """``exp(x)`` for float32 ``x`` in ``[POWER_MIN, 0]`` to ~2e-6 relative error, plain arithmetic.

    ``math.exp`` is a libm call that blocks SIMD; this (Taylor polynomial of ``exp(x / 16)``,
    squared four times) lets the compiler vectorise a whole tile row.
    """
    y = x * np.float32(1.0 / 16.0)
    p = np.float32(1.0 / 5040.0)
    p = p * y + np.float32(1.0 / 720.0)
    p = p * y + np.float32(1.0 / 120.0)
    p = p * y + np.float32(1.0 / 24.0)
    p = p * y + np.float32(1.0 / 6.0)
    p = p * y + np.float32(0.5)
    p = p * y + np.float32(1.0)
    p = p * y + np.float32(1.0)
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(cache=True, inline="always")
def lane_alpha(j, s, qy, by, Tv):
    """Lane ``j`` (column in the tile) of a row through Splat ``s`` (``qy``, ``by``: the row's
    ``-0.5 c dy^2`` and ``b dy``) whose transmittances are ``Tv``: ``(Tl, dx, gauss, e, alpha, ok,
    a, wgt)`` with ``Tl = Tv[j]``, ``gauss = exp(power)``, ``e = opacity gauss``, ``alpha = min(e,
    ALPHA_MAX)``, ``ok`` the alpha tests (visible, not terminated, inside the box), ``a`` the alpha
    applied (0 unless ok) and ``wgt = a Tl`` the lane's blend weight."""
    lj = np.float32(j)
    Tl = Tv[j]
    dx = lj - s.ux
    power = s.nha * dx * dx + qy - by * dx
    p_min = np.float32(POWER_MIN)  # lanes clamped here are rejected by the alpha test
    power = power if power > p_min else p_min
    gauss = exp_neg_fast(power)
    e = s.opacity * gauss
    a_max = np.float32(ALPHA_MAX)
    alpha = e if e < a_max else a_max
    ok = (alpha >= np.float32(ALPHA_MIN)) & (Tl >= np.float32(T_MIN)) & (lj >= s.lx0) & (lj <= s.lx1)
    a = alpha if ok else np.float32(0.0)
    return Tl, dx, gauss, e, alpha, ok, a, a * Tl


def _compositor(plane_depths: bool):
    """``(load_splat, composite_row, composite_tile)`` of one compositing model, compiled for it.

    ``plane_depths=False`` (the renderer): each Gaussian's depth is its centre's, and the row keeps
    the median-depth crossing. ``True`` (the keyframe fit): its plane's depth at the pixel (the
    projection's ``AUX_SLOPE_*``), and the row keeps the transmittance through the measured surface.
    One source for both; the flag is a compile-time constant, so neither pays for the other's work.
    """

    @njit(inline="always")
    def load_splat(sp, g, px0, px1):
        """Sorted Gaussian ``g`` of ``sp`` (``raster.SplatTiles``; ``aux`` kept when
        ``plane_depths``) for the tile whose columns are ``px0 .. px1``."""
        ca = sp.feat[g, FEAT_CONIC_A]
        cc = sp.feat[g, FEAT_CONIC_C]
        slope_u = np.float32(0.0)
        slope_v = np.float32(0.0)
        if plane_depths:
            slope_u = np.float32(sp.aux[sp.order[g], AUX_SLOPE_U])
            slope_v = np.float32(sp.aux[sp.order[g], AUX_SLOPE_V])
        return Splat(sp.feat[g, FEAT_U] - np.float32(px0), sp.feat[g, FEAT_V], ca, sp.feat[g, FEAT_CONIC_B], cc,
                     np.float32(-0.5) * ca, np.float32(-0.5) * cc, sp.feat[g, FEAT_OPACITY], sp.feat[g, FEAT_RED],
                     sp.feat[g, FEAT_GREEN], sp.feat[g, FEAT_BLUE], sp.feat[g, FEAT_Z], slope_u, slope_v,
                     np.float32(max(sp.box[g, 0], px0) - px0), np.float32(min(sp.box[g, 1], px1) - px0))

    @njit(inline="always")
    def composite_row(acc, r, s, dy):
        """Tile row ``r`` of ``acc`` (:class:`TileAccum`) through Splat ``s`` (``dy``: the row's
        ``v - mean v``), all ``TILE_SIZE`` lanes as one branch-free vector: lanes outside the box,
        below ``ALPHA_MIN`` or terminated get alpha 0. Returns the lanes that terminated here. (A
        narrower 8-lane window for Gaussians that span few columns is slower: 16 lanes are one
        AVX-512 vector.)"""
        one = np.float32(1.0)
        t_min = np.float32(T_MIN)
        t_median = np.float32(MEDIAN_DEPTH_T)
        qy = s.nhc * dy * dy
        by = s.conic_b * dy
        zy = s.z + s.slope_v * dy if plane_depths else s.z
        Tv = acc.trans[r]
        Crv = acc.red[r]
        Cgv = acc.green[r]
        Cbv = acc.blue[r]
        Dv = acc.depth[r]
        Dmv = acc.median[r]
        Sv = acc.surface_trans[r]
        Lv = acc.limit[r]
        done = np.uint64(0)
        lanes = np.uint64(TILE_SIZE)  # unsigned: no negative-index code, so the loop vectorises
        for j in range(lanes):
            Tl, dx, _, _, _, ok, a, wgt = lane_alpha(j, s, qy, by, Tv)
            Crv[j] += wgt * s.red
            Cgv[j] += wgt * s.green
            Cbv[j] += wgt * s.blue
            zp = zy + s.slope_u * dx if plane_depths else zy
            Dv[j] += wgt * zp
            Tn = Tl * (one - a)
            if plane_depths:
                Sv[j] = Sv[j] * (one - a) if zp <= Lv[j] else Sv[j]
            else:
                Dmv[j] = zp if (Tl > t_median) & (Tn <= t_median) else Dmv[j]
            Tv[j] = Tn
            done += np.uint64(ok & (Tn < t_min))
        return done

    @njit
    def composite_tile(sp, t, t_global, acc):
        """Tile ``t`` of ``sp``'s lists (``t_global`` its row-major index in the image) front to
        back into ``acc``; returns the end of its list actually drawn (every pixel terminated
        before it)."""
        px0, py0, px1, py1 = tile_pixel_bounds(t_global, sp.tiles_x, sp.width, sp.height)
        n_active = (px1 - px0 + 1) * (py1 - py0 + 1)
        k = sp.tile_start[t]
        k1 = sp.tile_start[t + 1]
        while k < k1 and n_active > 0:
            g = sp.tile_ids[k]
            k += 1
            s = load_splat(sp, g, px0, px1)
            for py in range(max(sp.box[g, 2], py0), min(sp.box[g, 3], py1) + 1):
                done = composite_row(acc, py - py0, s, np.float32(py) - s.v)
                n_active -= np.int64(done)
        return k

    return load_splat, composite_row, composite_tile


# The renderer's model (centre depths, median depth) and the fit's (plane depths, surface transmittance).
load_splat_centre, composite_row_centre, composite_tile_centre = _compositor(plane_depths=False)
load_splat, composite_row, composite_tile = _compositor(plane_depths=True)


@njit(cache=True, inline="always")
def new_tile_accum():
    """An uninitialised :class:`TileAccum` (``reset_tile_accum`` before each tile)."""
    shape = (TILE_SIZE, TILE_SIZE)
    return TileAccum(np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32),
                     np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32),
                     np.empty(shape, np.float32), np.empty(shape, np.float32))


@njit(cache=True, inline="always")
def reset_tile_accum(acc):
    """Nothing drawn yet: transmittances 1, sums 0, no measured surface (limit 0)."""
    acc.trans[:] = 1.0
    acc.red[:] = 0.0
    acc.green[:] = 0.0
    acc.blue[:] = 0.0
    acc.depth[:] = 0.0
    acc.median[:] = 0.0
    acc.surface_trans[:] = 1.0
    acc.limit[:] = 0.0


# --------------------------------------------------------------------------------------------
# The renderer's compositing
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _to_u8(x):
    """Round half up and clip to a uint8 colour level."""
    return np.uint8(min(255.0, max(0.0, math.floor(x + 0.5))))


@njit(cache=True)
def _render_worker(worker, n_workers, sp, t0, bg, out):
    """Composite tiles ``worker, worker + n_workers, ...`` of ``sp``'s lists (image tiles ``t0 + t``)
    into ``out`` (:class:`RenderImages`). Kept out of the ``prange`` body so the parallel transform
    cannot get in the way of the row vectorisation."""
    one = np.float32(1.0)
    acc = new_tile_accum()
    for t in range(worker, sp.n_tiles, n_workers):
        reset_tile_accum(acc)
        composite_tile_centre(sp, t, t0 + t, acc)
        px0, py0, px1, py1 = tile_pixel_bounds(t0 + t, sp.tiles_x, sp.width, sp.height)
        for py in range(py0, py1 + 1):
            r = py - py0
            for px in range(px0, px1 + 1):
                c = px - px0
                Tl = acc.trans[r, c]
                out.rgb[py, px, 0] = _to_u8(acc.red[r, c] + Tl * bg[0])
                out.rgb[py, px, 1] = _to_u8(acc.green[r, c] + Tl * bg[1])
                out.rgb[py, px, 2] = _to_u8(acc.blue[r, c] + Tl * bg[2])
                alpha = one - Tl
                out.alpha[py, px] = alpha
                out.depth_m[py, px] = acc.depth[r, c] / alpha if alpha >= DEPTH_MIN_ALPHA else 0.0
                out.depth_median_m[py, px] = acc.median[r, c]


@njit(cache=True, parallel=True)
def _render_kernel(sp, t0, bg, out, n_workers):
    """Tiles ``t0 .. t0 + sp.n_tiles - 1`` into ``out``, ``n_workers`` threads; worker ``w`` takes
    tiles ``w, w + n_workers, ...``: interleaving balances busy and empty regions."""
    for w in prange(n_workers):
        _render_worker(w, n_workers, sp, t0, bg, out)


def _empty_images(width: int, height: int) -> RenderImages:
    return RenderImages(np.empty((height, width, 3), np.uint8), np.empty((height, width), np.float32),
                        np.empty((height, width), np.float32), np.empty((height, width), np.float32))


_NO_AUX = np.empty((0, N_AUX))
_NO_ORDER = np.empty(0, np.int64)


def composite_tiles(
    splats: SplatTiles,
    background: np.ndarray,  # [3] in [0, 255]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb [H, W, 3] uint8, depth_m, alpha, depth_median_m [H, W] float32)``, threaded over tiles
    (compiled). Depths are centre depths (the renderer's model), whatever ``splats.aux`` holds."""
    out = _empty_images(splats.width, splats.height)
    sp = splats._replace(aux=_NO_AUX, order=_NO_ORDER)  # one compiled type whatever the caller kept
    n_workers = min(sp.n_tiles, kernel_threads())
    _render_kernel(sp, 0, np.asarray(background, np.float32), out, n_workers)
    return tuple(out)


def composite_tile_batch(
    feat: np.ndarray,  # [M, N_FEAT] float32 sorted front to back
    box: np.ndarray,  # [M, 4] int32 in that order
    tile_start: np.ndarray,  # [t1 - t0 + 1] int64 from bin_tile_batch
    tile_ids: np.ndarray,  # [P] int32 from bin_tile_batch
    t0: int,
    background: np.ndarray,  # [3] in [0, 255]
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],  # rgb [H, W, 3] uint8, depth, alpha, median [H, W]
) -> None:
    """One run of tiles (``raster_bounded.bin_tile_batch``): writes those tiles' pixels of ``out``;
    every tile is drawn exactly as ``composite_tiles`` draws it."""
    images = RenderImages(*out)
    height, width = images.rgb.shape[:2]
    n_tiles = len(tile_start) - 1
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    sp = SplatTiles(_NO_ORDER, feat, box, tile_start, tile_ids, tiles_x, n_tiles, width, height, _NO_AUX)
    n_workers = max(1, min(n_tiles, kernel_threads()))
    _render_kernel(sp, int(t0), np.asarray(background, np.float32), images, n_workers)

"""The keyframe fit's compiled passes over one view: forward loss, tile backward, chain rule.

1. *forward* (``forward_tiles``): the renderer's compositing core
   (``composite.composite_tile``: the same tile rows, alpha tests and early termination), the depth
   of each Gaussian at each pixel from its plane's slopes; then per pixel the loss and ``d loss / d
   (colour, depth, transmittance)`` into the rows handed to the backward pass.
2. *backward*: (a) ``backward_tiles`` visits each tile's Gaussians front to back again through the
   same lane kernel (``composite.lane_alpha``, alphas and transmittances recomputed bit for bit)
   and gets each one's ``d loss / d alpha`` from prefix sums (``C = prefix + T a c + T (1 - a)
   behind``: nothing per pixel and Gaussian is stored); each (tile, Gaussian) pair writes its
   image-space gradient into its own slot, so the tiles run in parallel with no atomics and no
   locks; (b) ``_param_grads`` sums each Gaussian's slots in a fixed order and applies the chain
   rule through the projection's kept intermediates to position, log scales, rotation, opacity
   logit and colour.

Every sum runs in an order fixed by the data (tiles, slots), never by the threads: the same inputs
give the same gradients bit for bit on any machine and any thread count.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.cores import kernel_threads
from atlas_pipeline.gaussian_world import raster
from atlas_pipeline.gaussian_world.composite import (
    composite_tile, lane_alpha, load_splat, new_tile_accum, reset_tile_accum,
)
from atlas_pipeline.gaussian_world.raster import (
    ALPHA_MAX, AUX_A, AUX_B, AUX_CXX, AUX_CXY, AUX_CYY, AUX_P, AUX_TXZ, AUX_TYZ, AUX_X, AUX_Y, AUX_Z, DEPTH_MIN_ALPHA,
    TILE_SIZE, GaussianArrays, RasterView, jacobian_clamp_limits, rotmat_from_quat, rows_times, tile_pixel_bounds,
)

__all__ = [
    "N_PARAM", "P_POS", "P_LOG_SCALE", "P_ROT", "P_LOGIT", "P_COL", "P_SH", "FIT_STAGES", "StageClock",
    "LossWeights", "FitTarget", "ViewGradients", "ForwardRows",
    "forward_tiles", "backward_tiles", "view_gradients", "render_loss_and_gradients",
]

# Columns of the per-Gaussian image-space gradient rows (and of the per-pair slots).
_G_U, _G_V, _G_A, _G_B, _G_C, _G_OP, _G_R, _G_G, _G_BL, _G_Z = range(10)
_N_GRAD = 10
# Rows of the per-Gaussian parameter gradient / Adam moment arrays [N_PARAM, N].
_P_POS, _P_LOG_SCALE, _P_ROT, _P_LOGIT, _P_COL = 0, 3, 6, 9, 10
_N_PARAM = 13
N_PARAM, P_POS, P_LOG_SCALE, P_ROT, P_LOGIT, P_COL = _N_PARAM, _P_POS, _P_LOG_SCALE, _P_ROT, _P_LOGIT, _P_COL
# A fit that learns view-dependent colour has 3 K more rows after these: coefficient k of channel c
# at row P_SH + 3 k + c (fit_sh).
P_SH = _N_PARAM
# Per-pixel rows handed from the forward to the backward pass: d loss / d colour (3), d loss / d
# depth sum (already divided by the accumulated alpha), the gradient-weighted total S (below), the
# coverage term's weighted transmittance through the measured surface and that surface's far limit.
_D_R, _D_G, _D_B, _D_DEPTH, _D_TOTAL, _D_COVER, _D_LIMIT = range(7)
_N_DOUT = 7

FIT_STAGES = ("projection", "forward", "backward", "adam", "densify")  # OptimizationResult.stage_cpu_s keys


class LossWeights(NamedTuple):
    """Weights of the loss terms (already divided by the pixel count inside the kernels)."""

    rgb: float = 1.0  # colour L1 ([0, 1] colours)
    depth: float = 0.0  # depth L1 (metres), at pixels with a reading the render covers
    cover: float = 0.0  # transmittance through the measured surface, at pixels with a reading


class FitTarget(NamedTuple):
    """One view's targets at the size it is rendered at."""

    image: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth_m: np.ndarray  # [H, W] float32, 0 = no reading
    depth_weight: np.ndarray  # [H, W] float32 >= 0, per-pixel weight of the depth term
    depth_limit_m: np.ndarray  # [H, W] float32: the coverage term counts Gaussians whose plane depth is <= this
    background: np.ndarray  # [3] float64 in [0, 1]


class ForwardRows(NamedTuple):
    """What the forward pass writes, per tile and per pixel."""

    dout: np.ndarray  # [_N_DOUT, H, W] float32 per-pixel rows for the backward pass (_D_*)
    k_end: np.ndarray  # [n_tiles] int64 end of each tile's list actually drawn
    tile_loss: np.ndarray  # [n_tiles] float64


class ViewGradients(NamedTuple):
    """Where one view's gradients go (float32 state, in place)."""

    gparam: np.ndarray  # [N_PARAM, N] float32, parameter gradients (P_* rows)
    vs_sum: np.ndarray  # [N] float64, sum of view-space (NDC) positional gradient norms
    vs_cnt: np.ndarray  # [N] int32, views that drew each Gaussian
    seen: np.ndarray | None  # [N] uint8 set to 1 for the Gaussians the view draws (None: not kept)


class StageClock:
    """CPU seconds (``time.process_time``: every thread of the process) per ``FIT_STAGES`` stage."""

    def __init__(self) -> None:
        self.cpu = dict.fromkeys(FIT_STAGES, 0.0)
        self._t = time.process_time()

    def start(self) -> None:
        self._t = time.process_time()

    def lap(self, stage: str) -> None:
        t = time.process_time()
        self.cpu[stage] += t - self._t
        self._t = t


# --------------------------------------------------------------------------------------------
# Forward: the renderer's compositing, then the per-pixel loss
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def _tile_loss(t, sp, acc, target, weights, dout):
    """Loss of tile ``t`` from its composited sums ``acc`` (float64), and its pixels' rows of
    ``dout`` ``[_N_DOUT, H, W]``.

    With ``G`` = d loss / d final colour, ``GD`` = d loss / d depth sum ``D`` (the alpha-normalised
    depth ``D / acc``'s gradient over ``acc``) and ``gcov`` the coverage weight,
    ``d loss / d alpha_i = T_i h_i - (S - Q_i - w_i h_i) / (1 - alpha_i)`` with
    ``h_i = G . c_i + GD z_i``, ``Q_i = sum_{j < i} w_j h_j`` and the per-pixel total
    ``S = G . f + GD (D + dn T_f)`` (``f`` final colour, ``dn`` rendered depth, ``T_f``
    final transmittance): ``S`` is kept, ``Q`` is rebuilt by the backward pass. The coverage term
    ``gcov T_s`` (``T_s`` the transmittance through the Gaussians within the limit, a product over
    them) adds ``-gcov T_s / (1 - alpha_i)`` for those Gaussians only; ``gcov T_s`` is kept.
    """
    px0, py0, px1, py1 = tile_pixel_bounds(t, sp.tiles_x, sp.width, sp.height)
    image, depth_obs, depth_w, _, bg = target
    w_rgb, w_depth, w_cover = weights
    loss = 0.0
    for py in range(py0, py1 + 1):
        r = py - py0
        for px in range(px0, px1 + 1):
            c = px - px0
            tf = np.float64(acc.trans[r, c])
            f0 = np.float64(acc.red[r, c]) + tf * bg[0]
            f1 = np.float64(acc.green[r, c]) + tf * bg[1]
            f2 = np.float64(acc.blue[r, c]) + tf * bg[2]
            r0 = f0 - image[py, px, 0]
            r1 = f1 - image[py, px, 1]
            r2 = f2 - image[py, px, 2]
            loss += w_rgb * (abs(r0) + abs(r1) + abs(r2))
            g0 = w_rgb * np.sign(r0)
            g1 = w_rgb * np.sign(r1)
            g2 = w_rgb * np.sign(r2)
            obs = depth_obs[py, px]
            alpha = 1.0 - tf
            d = np.float64(acc.depth[r, c])
            gdp = 0.0
            dn = 0.0
            if obs > 0.0 and alpha >= DEPTH_MIN_ALPHA:  # alpha-normalised depth, mostly opaque pixels
                dn = d / alpha
                rd = dn - obs
                wd = w_depth * np.float64(depth_w[py, px])
                loss += wd * abs(rd)
                gdp = wd * np.sign(rd) / alpha
            cover = 0.0
            if obs > 0.0 and w_cover > 0.0:  # a sensor reading: a surface there, opaque
                cover = w_cover * np.float64(acc.surface_trans[r, c])
                loss += cover
            dout[_D_R, py, px] = g0
            dout[_D_G, py, px] = g1
            dout[_D_B, py, px] = g2
            dout[_D_DEPTH, py, px] = gdp
            dout[_D_TOTAL, py, px] = g0 * f0 + g1 * f1 + g2 * f2 + gdp * (d + dn * tf)
            dout[_D_COVER, py, px] = cover
            dout[_D_LIMIT, py, px] = acc.limit[r, c]
    return loss


@njit(cache=True)
def _forward_worker(worker, n_workers, sp, target, weights, out):
    """Tiles ``worker, worker + n_workers, ...`` of ``sp`` (``raster.SplatTiles`` with ``aux``):
    composited by the renderer's core with each Gaussian's plane depth, then the loss against
    ``target`` (:class:`FitTarget`) into ``out`` (:class:`ForwardRows`)."""
    acc = new_tile_accum()
    for t in range(worker, sp.n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t, sp.tiles_x, sp.width, sp.height)
        reset_tile_accum(acc)  # lanes past the image edge: no surface
        for py in range(py0, py1 + 1):
            for px in range(px0, px1 + 1):
                acc.limit[py - py0, px - px0] = target.depth_limit_m[py, px]
        out.k_end[t] = composite_tile(sp, t, t, acc)
        out.tile_loss[t] = _tile_loss(t, sp, acc, target, weights, out.dout)


@njit(cache=True, parallel=True)
def _forward_kernel(sp, target, weights, out, n_workers):
    for w in prange(n_workers):
        _forward_worker(w, n_workers, sp, target, weights, out)
    loss = 0.0
    for t in range(sp.n_tiles):  # fixed order
        loss += out.tile_loss[t]
    return loss


def forward_tiles(sp: raster.SplatTiles, target: FitTarget, weights: LossWeights,
                  n_workers: int) -> tuple[float, np.ndarray, np.ndarray]:
    """All tiles: ``(loss, dout [_N_DOUT, H, W] float32, k_end [n_tiles] int64)``. Worker ``w`` takes
    tiles ``w, w + n_workers, ...``; every result is per tile, so the split does not change a bit.
    ``weights`` are per pixel (divided by the pixel count)."""
    out = ForwardRows(np.zeros((_N_DOUT, sp.height, sp.width), np.float32), np.empty(sp.n_tiles, np.int64),
                      np.zeros(sp.n_tiles))
    weights = LossWeights(*(float(w) for w in weights))
    loss = _forward_kernel(sp, target, weights, out, n_workers)
    return loss, out.dout, out.k_end


# --------------------------------------------------------------------------------------------
# Backward: tiles -> per-pair slots -> per Gaussian -> parameters
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _backward_row(Tv, Qv, G, r, acc, s, dy):
    """Tile row ``r`` through Splat ``s`` once more (the lane kernel of the forward pass, so alphas
    and transmittances are recomputed bit for bit), adding its per-lane gradient sums into ``acc
    [_N_GRAD, lanes]``: d loss / d opacity; d loss / d power (alpha-weighted) times dx, dy, dx^2,
    dx dy, dy^2; d loss / d colour (3); d loss / d z. ``Tv``, ``Qv``: the row's transmittance and
    prefix sums; ``G`` ``[_N_DOUT, TILE_SIZE, TILE_SIZE]``: the tile's forward rows. The coverage
    term (weight times the transmittance through the measured surface) moves only the Gaussians
    whose plane depth is within the lane's limit."""
    one = np.float32(1.0)
    zero = np.float32(0.0)
    a_max = np.float32(ALPHA_MAX)
    qy = s.nhc * dy * dy
    by = s.conic_b * dy
    zy = s.z + s.slope_v * dy
    G0 = G[_D_R, r]
    G1 = G[_D_G, r]
    G2 = G[_D_B, r]
    GD = G[_D_DEPTH, r]
    S = G[_D_TOTAL, r]
    CV = G[_D_COVER, r]
    LV = G[_D_LIMIT, r]
    a_op = acc[0]
    a_gpx = acc[1]
    a_gpy = acc[2]
    a_gpxx = acc[3]
    a_gpxy = acc[4]
    a_gpyy = acc[5]
    a_r = acc[6]
    a_g = acc[7]
    a_b = acc[8]
    a_z = acc[9]
    lanes = np.uint64(TILE_SIZE)  # unsigned: no negative-index code, so the loop vectorises
    for j in range(lanes):
        Tl, dx, gauss, e, alpha, ok, a, wgt = lane_alpha(j, s, qy, by, Tv)
        zp = zy + s.slope_u * dx
        gdj = GD[j]
        h = G0[j] * s.red + G1[j] * s.green + G2[j] * s.blue + gdj * zp
        Ql = Qv[j]
        cv = CV[j] if zp <= LV[j] else zero  # d (w T_surface) / d alpha = -w T_surface / (1 - alpha)
        ga = Tl * h - (S[j] - Ql - wgt * h + cv) / (one - a)  # d loss / d alpha
        gs = ga if ok & (e < a_max) else zero  # a capped alpha moves with nothing
        gp = gs * alpha  # d loss / d power
        gpx = gp * dx
        gpy = gp * dy
        a_op[j] += gs * gauss
        a_gpx[j] += gpx
        a_gpy[j] += gpy
        a_gpxx[j] += gpx * dx
        a_gpxy[j] += gpx * dy
        a_gpyy[j] += gpy * dy
        a_r[j] += wgt * G0[j]
        a_g[j] += wgt * G1[j]
        a_b[j] += wgt * G2[j]
        a_z[j] += wgt * gdj
        Qv[j] = Ql + wgt * h
        Tv[j] = Tl * (one - a)


@njit(cache=True)
def _backward_worker(worker, n_workers, sp, tile_slot, k_end, dout, pair_grad):
    """Tiles ``worker, worker + n_workers, ...``: the tile's Gaussians front to back once more, 16
    lanes at a time; each (tile, Gaussian) pair's image-space gradient (``_G_*`` columns) goes to
    its own row ``pair_grad[tile_slot[k]]``."""
    T = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Q = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    G = np.zeros((_N_DOUT, TILE_SIZE, TILE_SIZE), dtype=np.float32)
    acc = np.empty((_N_GRAD, TILE_SIZE), dtype=np.float32)
    sums = np.empty(_N_GRAD)
    for t in range(worker, sp.n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t, sp.tiles_x, sp.width, sp.height)
        T[:] = 1.0
        Q[:] = 0.0
        G[:] = 0.0  # lanes past the image edge stay 0
        for q in range(_N_DOUT):
            for py in range(py0, py1 + 1):
                for px in range(px0, px1 + 1):
                    G[q, py - py0, px - px0] = dout[q, py, px]
        for k in range(sp.tile_start[t], k_end[t]):
            g = sp.tile_ids[k]
            s = load_splat(sp, g, px0, px1)
            acc[:] = 0.0  # per lane: _backward_row's sums
            for py in range(max(sp.box[g, 2], py0), min(sp.box[g, 3], py1) + 1):
                r = py - py0
                _backward_row(T[r], Q[r], G, r, acc, s, np.float32(py) - s.v)
            sums[:] = 0.0  # lanes summed in float64, in lane order
            for c in range(_N_GRAD):
                for j in range(TILE_SIZE):
                    sums[c] += acc[c, j]
            sl = tile_slot[k]
            pair_grad[sl, _G_OP] = sums[0]
            pair_grad[sl, _G_A] = -0.5 * sums[3]
            pair_grad[sl, _G_B] = -sums[4]
            pair_grad[sl, _G_C] = -0.5 * sums[5]
            # d power / d u = conic d; the slope depth z + s_u dx + s_v dy moves with u, v too
            pair_grad[sl, _G_U] = s.conic_a * sums[1] + s.conic_b * sums[2] - s.slope_u * sums[9]
            pair_grad[sl, _G_V] = s.conic_c * sums[2] + s.conic_b * sums[1] - s.slope_v * sums[9]
            pair_grad[sl, _G_R] = sums[6]
            pair_grad[sl, _G_G] = sums[7]
            pair_grad[sl, _G_BL] = sums[8]
            pair_grad[sl, _G_Z] = sums[9]
        for k in range(k_end[t], sp.tile_start[t + 1]):  # after every pixel terminated: nothing
            sl = tile_slot[k]
            for c in range(_N_GRAD):
                pair_grad[sl, c] = 0.0


@njit(cache=True, parallel=True)
def _backward_kernel(sp, tile_slot, k_end, dout, n_workers):
    pair_grad = np.empty((sp.tile_ids.shape[0], _N_GRAD), dtype=np.float32)
    for w in prange(n_workers):
        _backward_worker(w, n_workers, sp, tile_slot, k_end, dout, pair_grad)
    return pair_grad


def backward_tiles(sp: raster.SplatTiles, tile_slot: np.ndarray, k_end: np.ndarray, dout: np.ndarray,
                   n_workers: int) -> np.ndarray:
    """``pair_grad [P, _N_GRAD]`` float32: the image-space gradient of every (tile, Gaussian) pair,
    in the pair's slot (``raster.pair_slots``)."""
    return _backward_kernel(sp, tile_slot, k_end, dout, n_workers)


@njit(cache=True, parallel=True)
def _param_grads(rank, gauss_start, pair_grad, aux, scl, quat, opa, view, gparam, vs_sum, vs_cnt):
    """For each drawn Gaussian (input row ``i``, sorted row ``k = rank[i]``, -1 when not drawn): its
    image-space gradient (u, v, conic a b c, opacity, r, g, b, z) as the sum of its pair slots
    ``gauss_start[k] ..`` in slot order, then the chain rule to its world position, log scales,
    local rotation vector, opacity logit and colour into ``gparam[:, i]`` (``_P_*`` rows; rows in
    input order, so the per-Gaussian arrays are read in memory order), from the projection's kept
    intermediates ``aux`` (``raster.AUX_*``: no second projection). Also adds the norm of its
    view-space positional gradient in NDC units (``d loss / d u * W / 2``, as 3DGS) to ``vs_sum[i]``
    and one view to ``vs_cnt[i]`` (densification statistics). ``view``: :class:`raster.RasterView`."""
    Rcw, _, fx, fy, cx, cy, width_px, height_px = view
    width = np.float64(width_px)
    height = np.float64(height_px)
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = jacobian_clamp_limits(fx, fy, cx, cy, width, height)
    for i in prange(rank.shape[0]):
        kk = rank[i]
        if kk < 0:
            continue
        gu = 0.0
        gv = 0.0
        gA = 0.0
        gB = 0.0
        gC = 0.0
        gop = 0.0
        gr = 0.0
        gg = 0.0
        gbl = 0.0
        gzz = 0.0
        for sl in range(gauss_start[kk], gauss_start[kk + 1]):
            gu += pair_grad[sl, _G_U]
            gv += pair_grad[sl, _G_V]
            gA += pair_grad[sl, _G_A]
            gB += pair_grad[sl, _G_B]
            gC += pair_grad[sl, _G_C]
            gop += pair_grad[sl, _G_OP]
            gr += pair_grad[sl, _G_R]
            gg += pair_grad[sl, _G_G]
            gbl += pair_grad[sl, _G_BL]
            gzz += pair_grad[sl, _G_Z]
        o = np.float64(opa[i])
        gparam[_P_LOGIT, i] = gop * o * (1.0 - o)
        gparam[_P_COL + 0, i] = gr
        gparam[_P_COL + 1, i] = gg
        gparam[_P_COL + 2, i] = gbl
        ndc_u = gu * 0.5 * width
        ndc_v = gv * 0.5 * height
        vs_sum[i] += math.sqrt(ndc_u * ndc_u + ndc_v * ndc_v)
        vs_cnt[i] += 1
        x = aux[i, AUX_X]
        y = aux[i, AUX_Y]
        z = aux[i, AUX_Z]
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotmat_from_quat(quat, i)
        s0 = np.float64(scl[i, 0])
        s1 = np.float64(scl[i, 1])
        s2 = np.float64(scl[i, 2])
        p00 = aux[i, AUX_P + 0]  # P = J W, rows p0 and p1
        p01 = aux[i, AUX_P + 1]
        p02 = aux[i, AUX_P + 2]
        p10 = aux[i, AUX_P + 3]
        p11 = aux[i, AUX_P + 4]
        p12 = aux[i, AUX_P + 5]
        a0 = aux[i, AUX_A + 0]  # rows a, b of P M, M = R S
        a1 = aux[i, AUX_A + 1]
        a2 = aux[i, AUX_A + 2]
        b0 = aux[i, AUX_B + 0]
        b1 = aux[i, AUX_B + 1]
        b2 = aux[i, AUX_B + 2]
        cxx = aux[i, AUX_CXX]
        cxy = aux[i, AUX_CXY]
        cyy = aux[i, AUX_CYY]
        idet = 1.0 / (cxx * cyy - cxy * cxy)
        id2 = idet * idet
        # conic (A, B, C) = (cyy, -cxy, cxx) / det
        gcxx = gA * (-cyy * cyy * id2) + gB * (cxy * cyy * id2) + gC * (idet - cxx * cyy * id2)
        gcyy = gA * (idet - cxx * cyy * id2) + gB * (cxy * cxx * id2) + gC * (-cxx * cxx * id2)
        gcxy = gA * (2.0 * cxy * cyy * id2) + gB * (-idet - 2.0 * cxy * cxy * id2) + gC * (2.0 * cxy * cxx * id2)
        # cov2d = a a^T + b b^T terms: d / d a, d / d b
        ga0 = 2.0 * gcxx * a0 + gcxy * b0
        ga1 = 2.0 * gcxx * a1 + gcxy * b1
        ga2 = 2.0 * gcxx * a2 + gcxy * b2
        gb0 = 2.0 * gcyy * b0 + gcxy * a0
        gb1 = 2.0 * gcyy * b1 + gcxy * a1
        gb2 = 2.0 * gcyy * b2 + gcxy * a2
        # a = p0 R S: with u0 = R^T p0, u1 = R^T p1 (the projection rows in the Gaussian's frame),
        # H = R^T dL/dR S-weighted: H[r, c] = s_c (ga_c u0_r + gb_c u1_r)
        u00, u01, u02, u10, u11, u12 = rows_times((p00, p01, p02, p10, p11, p12),
                                                  (r00, r01, r02, r10, r11, r12, r20, r21, r22))
        # log scales: d L / d log s_c = s_c (ga_c u0_c + gb_c u1_c) = H[c, c]
        gparam[_P_LOG_SCALE + 0, i] = s0 * (ga0 * u00 + gb0 * u10)
        gparam[_P_LOG_SCALE + 1, i] = s1 * (ga1 * u01 + gb1 * u11)
        gparam[_P_LOG_SCALE + 2, i] = s2 * (ga2 * u02 + gb2 * u12)
        # rotation (right-multiplied rotation vector): the skew part of H
        h21 = s1 * (ga1 * u02 + gb1 * u12)
        h12 = s2 * (ga2 * u01 + gb2 * u11)
        h02 = s2 * (ga2 * u00 + gb2 * u10)
        h20 = s0 * (ga0 * u02 + gb0 * u12)
        h10 = s0 * (ga0 * u01 + gb0 * u11)
        h01 = s1 * (ga1 * u00 + gb1 * u10)
        gparam[_P_ROT + 0, i] = h21 - h12
        gparam[_P_ROT + 1, i] = h02 - h20
        gparam[_P_ROT + 2, i] = h10 - h01
        # d L / d P: row 0 is R S ga, row 1 is R S gb (the rows S ga, S gb times R^T)
        gp00, gp01, gp02, gp10, gp11, gp12 = rows_times((s0 * ga0, s1 * ga1, s2 * ga2, s0 * gb0, s1 * gb1, s2 * gb2),
                                                        (r00, r10, r20, r01, r11, r21, r02, r12, r22))
        # Jacobian entries -> camera-frame mean (P = J W, W = Rcw)
        gj00 = gp00 * Rcw[0, 0] + gp01 * Rcw[0, 1] + gp02 * Rcw[0, 2]
        gj02 = gp00 * Rcw[2, 0] + gp01 * Rcw[2, 1] + gp02 * Rcw[2, 2]
        gj11 = gp10 * Rcw[1, 0] + gp11 * Rcw[1, 1] + gp12 * Rcw[1, 2]
        gj12 = gp10 * Rcw[2, 0] + gp11 * Rcw[2, 1] + gp12 * Rcw[2, 2]
        iz = 1.0 / z
        iz2 = iz * iz
        rx = x / z  # as the projection's clamp test
        ry = y / z
        gx = gu * fx * iz
        gy = gv * fy * iz
        gz = -gu * fx * x * iz2 - gv * fy * y * iz2 + gzz
        gz += gj00 * (-fx * iz2) + gj11 * (-fy * iz2)
        if -lim_x_neg < rx < lim_x_pos:  # j02 = -fx x / z^2
            gx += gj02 * (-fx * iz2)
            gz += gj02 * (2.0 * fx * x * iz2 * iz)
        else:  # j02 = -fx txz / z with txz fixed
            gz += gj02 * (fx * aux[i, AUX_TXZ] * iz2)
        if -lim_y_neg < ry < lim_y_pos:
            gy += gj12 * (-fy * iz2)
            gz += gj12 * (2.0 * fy * y * iz2 * iz)
        else:
            gz += gj12 * (fy * aux[i, AUX_TYZ] * iz2)
        for c in range(3):
            gparam[_P_POS + c, i] = Rcw[0, c] * gx + Rcw[1, c] * gy + Rcw[2, c] * gz


# --------------------------------------------------------------------------------------------
# One view: loss and parameter gradients
# --------------------------------------------------------------------------------------------


def _n_workers(n_tiles: int) -> int:
    # two tile streams per thread balance busy and empty regions; the results do not depend on it
    return max(1, min(n_tiles, 2 * kernel_threads()))


def view_gradients(gaussians: GaussianArrays, view: RasterView, target: FitTarget, weights: LossWeights,
                   out: ViewGradients, clock: StageClock, near_m: float = raster.NEAR_M) -> float:
    """Loss of one view and the gradient of every parameter into ``out.gparam`` (zero for Gaussians
    the view does not draw; ``out.seen``, if given, set to 1 for those it draws). ``gaussians``:
    the float32 state (colours in [0, 1]); ``target`` at the view's size."""
    width, height = view.width, view.height
    npix = float(width * height)
    pos, scl, quat, col, opa = gaussians
    sp = raster.prepare_splats(pos, scl, quat, col, opa, view, near_m, keep_aux=True)
    if sp is None:
        clock.lap("projection")
        bg = target.background.astype(np.float64)
        return float(weights.rgb * np.abs(bg - target.image).sum() / npix)  # no depth to compare
    tile_slot, gauss_start = raster.pair_slots(sp.box, sp.tile_start, sp.tiles_x)
    if out.seen is not None:
        out.seen[sp.order] = 1
    clock.lap("projection")
    nw = _n_workers(sp.n_tiles)
    per_pixel = LossWeights(weights.rgb / npix, weights.depth / npix, weights.cover / npix)
    loss, dout, k_end = forward_tiles(sp, target, per_pixel, nw)
    clock.lap("forward")
    pair_grad = backward_tiles(sp, tile_slot, k_end, dout, nw)
    rank = np.full(len(pos), -1, np.int64)
    rank[sp.order] = np.arange(len(sp.order))
    _param_grads(rank, gauss_start, pair_grad, sp.aux, scl, quat, opa, view, out.gparam, out.vs_sum, out.vs_cnt)
    clock.lap("backward")
    return float(loss)


def fit_target(image01: np.ndarray, depth_m: np.ndarray, depth_weight: np.ndarray | None = None,
               band_m: np.ndarray | None = None, background01=(0.0, 0.0, 0.0)) -> FitTarget:
    """A :class:`FitTarget` from ``image01 [H, W, 3]``, ``depth_m [H, W]`` (0: no reading), the
    depth term's per-pixel weights (None: 1) and the coverage band behind each reading within which
    a Gaussian counts as the measured surface (None: any depth)."""
    depth = np.ascontiguousarray(depth_m, np.float32)
    w = np.ones(depth.shape, np.float32) if depth_weight is None else np.ascontiguousarray(depth_weight, np.float32)
    limit = np.full(depth.shape, np.inf, np.float32) if band_m is None else np.asarray(depth + band_m, np.float32)
    return FitTarget(np.ascontiguousarray(image01, np.float32), depth, w, limit,
                     np.asarray(background01, np.float64))


def render_loss_and_gradients(gaussians: GaussianArrays, T_world_cam: np.ndarray, K: np.ndarray,
                              image01: np.ndarray, depth_m: np.ndarray, weights: LossWeights = LossWeights(),
                              background01: tuple[float, float, float] = (0.0, 0.0, 0.0),
                              near_m: float = raster.NEAR_M, depth_weight_map: np.ndarray | None = None,
                              coverage_band_map: np.ndarray | None = None):
    """Loss of one rendered view and its gradient w.r.t. every parameter (the fit's own kernels).

    Args:
        gaussians: positions ``[N, 3]``, scales ``[N, 3]`` (m), rotations ``[N, 4]`` xyzw, colours
            ``[N, 3]`` in [0, 1], opacities ``[N]`` (any float dtype; the fit's state is float32).
        image01 ``[H, W, 3]`` in [0, 1]; depth_m ``[H, W]``, 0 where there is no reading. The loss
        is a mean over pixels. depth_weight_map ``[H, W]``: per-pixel weight of the depth term
        (None: 1 everywhere). coverage_band_map ``[H, W]`` (m): the coverage term counts the
        transmittance through the Gaussians whose plane depth is at most the reading plus this
        (None: every Gaussian, the final transmittance).

    Returns:
        ``(loss, grads)`` with grads a dict of float64 ``position [N, 3]``, ``log_scale [N, 3]``,
        ``rotation [N, 3]`` (local rotation vector, ``R' = R exp([w]x)``), ``logit [N]``,
        ``color [N, 3]``; rows of Gaussians the view does not see are zero.
    """
    f32 = GaussianArrays(*(np.ascontiguousarray(a, np.float32) for a in gaussians))
    n = f32.positions.shape[0]
    height, width = image01.shape[:2]
    view = raster.view_from_pose(T_world_cam, K, width, height)
    out = ViewGradients(np.zeros((_N_PARAM, n), np.float32), np.zeros(n), np.zeros(n, np.int32), None)
    target = fit_target(image01, depth_m, depth_weight_map, None if coverage_band_map is None else
                        np.ascontiguousarray(coverage_band_map, np.float32), background01)
    loss = view_gradients(f32, view, target, LossWeights(*weights), out, StageClock(), near_m)
    g = out.gparam.T.astype(np.float64)
    return loss, {"position": g[:, _P_POS:_P_POS + 3].copy(), "log_scale": g[:, _P_LOG_SCALE:_P_LOG_SCALE + 3].copy(),
                  "rotation": g[:, _P_ROT:_P_ROT + 3].copy(), "logit": g[:, _P_LOGIT].copy(),
                  "color": g[:, _P_COL:_P_COL + 3].copy()}

"""Photometric optimisation of a Gaussian world on its keyframes: the 3DGS training loop on a CPU.

The voxel builder places one Gaussian per occupied voxel with the voxel's mean colour and a
covariance from its points. That field is blurry (each Gaussian averages a 2 cm cell seen from many
views) and its blend ignores occlusion order. This module fits every Gaussian's position, scales,
rotation, opacity and colour to the keyframe images and depths by gradient descent, as Kerbl et al.
(2023) and the RGB-D Gaussian SLAM systems (SplaTAM, MonoGS) do on a GPU:

    loss = w_rgb * mean |render_rgb - image| + w_depth * mean w_p |render_depth - depth_m|

plus ``w_cover * mean_{depth > 0} T_surface`` (a measured surface is opaque: ``T_surface`` is the
transmittance through the Gaussians whose plane depth at the pixel is within a band behind the
reading, ``T_final`` without bands; so a surface behind the measured one, such as a far wall seen
past a silhouette, cannot stand in for it), the depth term over
pixels with a reading that the render covers (accumulated alpha >= 0.5; pixels without a reading
add nothing), ``w_p`` in [0, 1] a per-pixel weight (default 1; the mapper passes the inverse of the
sensor's depth noise, so far, noisy readings pull less), with
``render_depth = sum_i w_i z_i(p) / sum_i w_i`` and ``z_i(p)`` the depth at pixel ``p`` of the
plane through Gaussian ``i`` normal to its shortest axis. Both choices remove a bias that would
push the map away from the cameras: an unnormalised sum reads a half-transparent surface as nearer,
and centre depths read a slanted surface as nearer (its front-most Gaussians dominate each pixel).
Coverage itself is the colour term's job. One keyframe per step, in a seeded order, Adam on each
parameter group (log scales, opacity logits, rotations as a local rotation vector composed onto the
quaternion).

**One step** (``_view_gradients``, then ``_adam_step``), every stage compiled and threaded, the
Gaussians, images and per-pixel arithmetic float32 (the projection and the chain rule float64):

1. *projection*: ``raster.prepare_splats(keep_aux=True)`` projects, sorts and bins the Gaussians
   once and keeps each one's projection intermediates (``raster.AUX_*``, the screen-space depth
   slopes of its plane among them) for the chain rule, so the backward pass never projects the view
   again; ``raster.pair_slots`` numbers the (tile, Gaussian) pairs Gaussian by Gaussian.
2. *forward* (``_forward_tiles``): the renderer's own tile loop (``raster.composite_tiles``: 16
   lanes of float32 per tile row, ``raster.exp_neg_fast``, the same alpha tests and early
   termination), then per pixel the loss and ``d loss / d (colour, depth, transmittance)``.
3. *backward*: (a) ``_backward_tiles`` visits each tile's Gaussians front to back again, 16 lanes
   at a time, and gets each one's ``d loss / d alpha`` from prefix sums (``C = prefix + T a c + T
   (1 - a) behind``: nothing per pixel and Gaussian is stored); each (tile, Gaussian) pair writes
   its image-space gradient into its own slot, so the tiles run in parallel with no atomics and no
   locks; (b) ``_param_grads`` sums each Gaussian's slots in a fixed order and applies the chain
   rule through the kept projection to position, log scales, rotation, opacity logit and colour.
4. *Adam* (``_adam_step``): one fused pass over every Gaussian.

Every sum runs in an order fixed by the data (tiles, slots), never by the threads: the same inputs
give the same world bit for bit on any machine and any thread count.

**The schedule** (``optimize_gaussians``), 3DGS's with fewer steps:

* *coarse to fine*: passes at ``scale / coarse_factor`` (a quarter of the image side: 16x fewer
  pixels than the full image, 4x fewer than the fit scale), with every step size times
  ``coarse_lr_scale``, until their loss stops falling or ``coarse_max_steps``. The coarse level
  does the slow, large moves (scales growing over what the depth did not map, colours, gross
  geometry) with larger steps on a cheaper image; a few passes at the fit scale then restore the
  detail (on the synthetic room 66 steps took the pixels with depth from 26 to 33 dB).
* *early stop*: after each pass over the keyframes its mean loss is compared with the best pass so
  far at that scale; a pass that does not beat it by ``plateau_rel_tol`` (relative) is a pass
  without progress, and ``plateau_patience`` of them in a row end the level (the coarse one) or
  the fit (``stop_reason: plateau``); a densification round restarts the count. ``max_steps`` and
  ``epochs`` cap it (``step_cap`` / ``epochs``).
* *densification and pruning* (Kerbl et al. 2023, section 5): every ``densify_interval`` steps up
  to ``densify_until_step``, Gaussians whose mean view-space positional gradient (in NDC units,
  averaged over the views that saw them since the last densification) exceeds
  ``densify_grad_threshold`` are cloned when small (largest scale <= ``densify_scale_m``) or split
  in two when large (samples of the Gaussian, scales / 1.6); Gaussians whose opacity fell below
  ``prune_opacity`` are removed. So the Gaussians go where the error is: a region the map covers
  badly keeps pulling its Gaussians, and they multiply there.

``OptimizationSettings.legacy()`` is the schedule of the first version of this fit (600 steps at
the fit scale, no coarse level, no early stop, no densification), kept so benchmarks can compare.

Only keyframes are used; held-out frames still measure generalisation.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field as dataclass_field
from typing import Callable

import numpy as np
from numba import njit, prange

from atlas_pipeline.cores import kernel_threads
from atlas_pipeline.gaussian_world import raster
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize
from atlas_pipeline.gaussian_world.raster import (
    ALPHA_MAX, ALPHA_MIN, AUX_A, AUX_B, AUX_CXX, AUX_CXY, AUX_CYY, AUX_P, AUX_SLOPE_U, AUX_SLOPE_V, AUX_TXZ, AUX_TYZ,
    AUX_X, AUX_Y, AUX_Z,
    DEPTH_MIN_ALPHA, FEAT_BLUE, FEAT_CONIC_A, FEAT_CONIC_B, FEAT_CONIC_C, FEAT_GREEN, FEAT_OPACITY, FEAT_RED,
    FEAT_U, FEAT_V, FEAT_Z, POWER_MIN, T_MIN, TILE_SIZE, exp_neg_fast, jacobian_clamp_limits, rotmat_from_quat,
    tile_pixel_bounds,
)
from atlas_pipeline.geometry import quat_xyzw_to_rotmat
from atlas_pipeline.progress import Progress

logger = logging.getLogger(__name__)

__all__ = ["OptimizationSettings", "OptimizationResult", "optimize_gaussians", "render_loss_and_gradients",
           "STOP_PLATEAU", "STOP_STEP_CAP", "STOP_EPOCHS", "FIT_STAGES", "CHILD_ID_BIT"]

# Columns of the per-Gaussian image-space gradient rows (and of the per-pair slots).
_G_U, _G_V, _G_A, _G_B, _G_C, _G_OP, _G_R, _G_G, _G_BL, _G_Z = range(10)
_N_GRAD = 10
# Columns of the per-Gaussian parameter gradient / Adam moment rows.
_P_POS, _P_LOG_SCALE, _P_ROT, _P_LOGIT, _P_COL = 0, 3, 6, 9, 10
_N_PARAM = 13
# Per-pixel rows handed from the forward to the backward pass: d loss / d colour (3), d loss / d
# depth sum (already divided by the accumulated alpha), the gradient-weighted total S (below), the
# coverage term's weighted transmittance through the measured surface and that surface's far limit.
_D_R, _D_G, _D_B, _D_DEPTH, _D_TOTAL, _D_COVER, _D_LIMIT = range(7)
_N_DOUT = 7

STOP_PLATEAU = "plateau"  # plateau_patience passes in a row without a relative gain of plateau_rel_tol
STOP_STEP_CAP = "step_cap"  # max_steps reached
STOP_EPOCHS = "epochs"  # every allowed pass ran
FIT_STAGES = ("projection", "forward", "backward", "adam", "densify")  # OptimizationResult.stage_cpu_s keys

# Ids of Gaussians made by densification: the top bit (voxel ids use 63 bits) and a counter.
CHILD_ID_BIT = np.uint64(1 << 63)
_SPLIT_SCALE_DIV = 1.6  # Kerbl et al.: the two halves of a split Gaussian have 1/1.6 of its scales
_LOGIT_CLAMP = 12.0
# The coarse level gets at most this share of the fit's passes: the fit scale must keep enough
# passes to restore the detail (a 4-keyframe world with 30 passes otherwise ran 29 of them coarse).
COARSE_MAX_PASS_FRACTION = 0.5
# No coarse level when its image would be narrower than this: a few dozen pixels hold no geometry
# worth fitting, and their larger steps only shake what the fit scale then has to undo.
MIN_COARSE_WIDTH_PX = 32


@dataclass(frozen=True)
class OptimizationSettings:
    """How the keyframe fit runs.

    Attributes:
        epochs: cap on the passes over the keyframes (one Adam step per keyframe per pass); 0 = off.
        max_steps: cap on the steps in all (None: no cap), so a long sequence with many keyframes
            costs a bounded time (each step renders one keyframe forward and backward).
        min_steps_per_view: with ``max_steps``, at least this many steps per keyframe: beyond
            ``max_steps / min_steps_per_view`` keyframes the cap, ``coarse_max_steps``,
            ``densify_interval`` and ``densify_until_step`` all grow by the same factor, so the
            fit's cost is linear in the keyframes and each keyframe gets the same share of it
            (a fixed cap gave a 520-keyframe sequence one step per keyframe). 0: a fixed cap.
        scale: image scale of the fit (0.5 = half size: 4x cheaper, enough for 2 cm Gaussians).
        lr_position_m, lr_log_scale, lr_rotation_rad, lr_opacity_logit, lr_color: Adam step sizes
            (colours in [0, 1]).
        depth_weight: weight of the depth L1 term (metres) against the colour L1 term ([0, 1]).
        coverage_weight: weight of the transparency left at pixels with a sensor reading (a surface
            was measured there, so the render should be opaque).
        max_scale_m, min_scale_m: clamp of the scales after each step.
        normal_offset_max_scales: how far a centre may move along its starting surface normal (the
            axis of its smallest starting scale), in its largest starting scale; clamped after each
            step (0: free). The fit otherwise spreads centres into a layer a few cm thick while the
            blended depth holds (benchmarks/bench_import_ply.py: 1.6 cm median along the normal on
            the synthetic room), which an exported PLY's geometry keeps. At 0.5 an imported PLY
            relocalizes at 0.5-0.8 cm instead of 1.7-2.1 cm, at about the same PSNR (the room
            +0.07 dB, teddy -0.11 dB; bench_fit.py), so it is an option, off by default.
        lr_final_ratio: every step size decays exponentially to this fraction of its start over
            the step cap. 1 = constant: with a few hundred steps the fit is still improving at the
            end (decay to 0.1 cost 1 dB on teddy).
        seed: order of the keyframes in each pass, and the samples of split Gaussians.
        coarse_factor: the first passes run at ``scale / coarse_factor`` (2: a quarter of the image
            side when the fit is at half; 1 = no coarse level).
        coarse_max_steps: cap on the steps at the coarse scale (whole passes, at most
            ``COARSE_MAX_PASS_FRACTION`` of the fit's passes; 0 = no coarse level; none either when
            its image would be narrower than ``MIN_COARSE_WIDTH_PX``); the level also ends on a plateau.
        coarse_lr_scale: every step size times this at the coarse level (the gross geometry: scales
            growing over what depth did not map, positions moving; the fit scale then refines).
        plateau_patience: passes in a row without progress that end a level (0: never stop early).
        plateau_rel_tol: a pass makes progress when its mean loss is below ``(1 - plateau_rel_tol)``
            times the best pass mean so far at that scale.
        densify_interval: steps between two densify-and-prune rounds (0: never).
        densify_until_step: no densification at or after this step (3DGS stops at half its run).
        densify_grad_threshold: mean view-space (NDC) positional gradient above which a Gaussian is
            cloned or split (3DGS: 2e-4 with its loss; this loss has its depth and coverage terms).
        densify_scale_m: a Gaussian with all scales at most this is cloned, a larger one split.
        densify_max_growth: the densified field holds at most this times the starting count.
        prune_opacity: Gaussians below this opacity are removed at each round (3DGS: 0.005).
        selective_adam: Adam steps only the Gaussians the view draws (as gsplat's ``SelectiveAdam``,
            after Mallick et al.'s Taming 3DGS), each with the bias correction of its own step count
            (gsplat's kernel has none; the step sizes here are set for corrected Adam).
            Dense Adam (False, 3DGS) also moves every unseen Gaussian on its momentum: a Gaussian
            seen in a fraction f of the steps then travels about 1/sqrt(f) step sizes per view that
            sees it, so the longer the path (the smaller each Gaussian's f), the larger its
            effective step and the noisier the fit. Selective, its updates depend only on the
            views that see it, and each step costs the Gaussians in view, not all of them.

    The step sizes are larger than 3DGS's (which runs 30,000 steps): here a few hundred steps start
    from a field already close to the images. They were tuned on TUM fr3/teddy
    (benchmarks/bench_photometric.py). The schedule was chosen on the synthetic room and checked on
    teddy (benchmarks/bench_fit.py; held-out frames from ground-truth poses, PSNR full frame / pixels
    with depth): the first schedule (600 steps at 320x240) gave 24.9 / 32.6 dB on the room and
    20.2 / 24.5 dB on teddy (450 steps). Coarse passes progress the full frame (walls beyond the
    depth range, covered by growing Gaussians) as far per step as fine ones and at 4x the step sizes
    much further: 264 coarse and 66 fine steps gave 27.8 / 33.1 dB on the room; 8x lost 1.7 dB with
    depth (opacities collapsed), a 1/8-scale (80x60) coarse level lagged 2.4 dB. Densification during
    the coarse level gave the room 30.7 / 33.4 dB and teddy 21.5 / 24.9 dB at 360 steps; rounds in
    the fine phase upset its loss, so they end with the coarse level. A pass mean moves ~2 % with
    the keyframe order, so the plateau test waits 3 passes: with 2 it stopped teddy while its
    masked PSNR still rose. Neither sequence reaches a plateau within 300 steps: the cap ends both.
    These defaults (bench_fit.py, two runs on a shared 2-core machine): the room 30.3 / 32.8 dB in
    42-53 CPU-s against 24.9 / 32.6 dB in 334-385 CPU-s for the first fit (7-8x); teddy 21.3 / 24.7
    dB in 32-46 CPU-s against 20.2 / 24.5 dB in 221-263 CPU-s (6-7x).
    """

    epochs: int = 30
    max_steps: int | None = 300
    min_steps_per_view: int = 10
    scale: float = 0.5
    lr_position_m: float = 5e-4
    lr_log_scale: float = 2e-2
    lr_rotation_rad: float = 1e-2
    lr_opacity_logit: float = 5e-2
    lr_color: float = 1e-2
    depth_weight: float = 1.0
    coverage_weight: float = 2.0
    lr_final_ratio: float = 1.0
    max_scale_m: float = 0.1
    min_scale_m: float = 1e-4
    normal_offset_max_scales: float = 0.0
    seed: int = 0
    coarse_factor: int = 2
    coarse_max_steps: int = 160
    coarse_lr_scale: float = 4.0
    plateau_patience: int = 3
    plateau_rel_tol: float = 0.005
    densify_interval: int = 50
    densify_until_step: int = 160
    densify_grad_threshold: float = 2e-4
    densify_scale_m: float = 0.02
    densify_max_growth: float = 1.3
    prune_opacity: float = 0.005
    selective_adam: bool = True

    @classmethod
    def legacy(cls, **overrides) -> "OptimizationSettings":
        """The first schedule: up to 30 passes and 600 steps, every one at half size, no early stop,
        no densification or pruning (``overrides`` replace any field)."""
        return cls(**{"epochs": 30, "max_steps": 600, "min_steps_per_view": 0, "scale": 0.5, "coarse_factor": 1,
                      "coarse_max_steps": 0,
                      "plateau_patience": 0, "densify_interval": 0, "selective_adam": False, **overrides})

    @classmethod
    def from_mapping(cls, mc) -> "OptimizationSettings":
        """The settings of a ``config.MappingConfig``."""
        return cls(epochs=mc.optimization_epochs, max_steps=mc.optimization_max_steps,
                   min_steps_per_view=mc.optimization_min_steps_per_keyframe, scale=mc.optimization_scale,
                   depth_weight=mc.optimization_depth_weight, coarse_factor=mc.optimization_coarse_factor,
                   normal_offset_max_scales=mc.optimization_normal_offset_max_scales,
                   coarse_max_steps=mc.optimization_coarse_max_steps, coarse_lr_scale=mc.optimization_coarse_lr_scale,
                   plateau_patience=mc.optimization_plateau_patience, plateau_rel_tol=mc.optimization_plateau_rel_tol,
                   densify_interval=mc.optimization_densify_interval,
                   densify_until_step=mc.optimization_densify_until_step,
                   densify_grad_threshold=mc.optimization_densify_grad_threshold,
                   prune_opacity=mc.optimization_prune_opacity, selective_adam=mc.optimization_selective_adam)


def stretch_schedule(s: OptimizationSettings, n_views: int) -> OptimizationSettings:
    """``s`` with its step counts grown for ``n_views`` keyframes (``min_steps_per_view``): the
    cap, the coarse level's cap and the densification interval and end, all by the same factor
    ``min_steps_per_view * n_views / max_steps`` when that exceeds 1; else ``s`` unchanged."""
    if s.max_steps is None or s.min_steps_per_view <= 0 or s.min_steps_per_view * n_views <= s.max_steps:
        return s
    k = s.min_steps_per_view * n_views / s.max_steps
    return dataclasses.replace(s, max_steps=s.min_steps_per_view * n_views,
                               coarse_max_steps=int(round(s.coarse_max_steps * k)),
                               densify_interval=int(round(s.densify_interval * k)),
                               densify_until_step=int(round(s.densify_until_step * k)))


@dataclass
class OptimizationResult:
    """The fitted field, how the fit went, and what it cost.

    Attributes:
        field: the fitted (canonical) field.
        loss: ``[steps]`` float64, the loss of every step (at the scale that step ran at).
        n_pruned: Gaussians removed (below ``prune_opacity`` at a densify round, or below 1/255 at
            the end, where they can no longer be drawn).
        record: what the world stores about its fit (JSON-ready, no timings): ``steps``,
            ``epochs`` (passes begun; the last may be partial), ``stop_reason`` (``STOP_*``),
            ``final_loss`` (mean of the last pass), ``loss_first_epoch`` (first pass at the fit
            scale), ``scale``, ``coarse`` (``scale``, ``steps``, ``epochs`` of the coarse level or
            None), ``n_gaussians_start`` / ``_end``, ``n_cloned``, ``n_split``, ``n_pruned``.
        seconds: wall time; cpu_seconds: process CPU time (all threads);
        stage_cpu_s: CPU seconds per stage (``FIT_STAGES``). Timings are not content: they are
            returned here, never in ``record``.
        step_scale: ``[steps]`` the image scale of each step.
    """

    field: GaussianField
    loss: np.ndarray
    n_pruned: int
    seconds: float
    record: dict = dataclass_field(default_factory=dict)
    cpu_seconds: float = 0.0
    stage_cpu_s: dict = dataclass_field(default_factory=dict)
    step_scale: np.ndarray = dataclass_field(default_factory=lambda: np.zeros(0))


# --------------------------------------------------------------------------------------------
# Tile rows: one (tile row, Gaussian) step, 16 lanes of float32
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _forward_row(Tv, Crv, Cgv, Cbv, Dv, Sv, Lv, ux, qy, by, nha, op, cr, cgr, cbl, zy, slu, lx0, lx1):
    """One tile row through one Gaussian, front to back: the renderer's compositing step (one
    branch-free vector of ``TILE_SIZE`` lanes; lanes outside ``lx0 .. lx1``, below ``ALPHA_MIN`` or
    terminated get alpha 0), with the depth of the Gaussian's plane; ``Sv`` keeps the transmittance
    through the Gaussians whose plane depth at the lane is at most its limit ``Lv`` (the measured
    surface and what lies before it). Returns the lanes that terminated here. (A narrower 8-lane
    window for the many Gaussians that span few columns measured 2.5x slower here: the 16 lanes are
    one AVX-512 vector.)"""
    t_min = np.float32(T_MIN)
    a_min = np.float32(ALPHA_MIN)
    a_max = np.float32(ALPHA_MAX)
    p_min = np.float32(POWER_MIN)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    done = np.uint64(0)
    lanes = np.uint64(TILE_SIZE)  # unsigned: no negative-index code, so the loop vectorises
    for j in range(lanes):
        lj = np.float32(j)
        dx = lj - ux
        power = nha * dx * dx + qy - by * dx
        power = power if power > p_min else p_min
        e = op * exp_neg_fast(power)
        alpha = e if e < a_max else a_max
        Tl = Tv[j]
        ok = (alpha >= a_min) & (Tl >= t_min) & (lj >= lx0) & (lj <= lx1)
        a = alpha if ok else zero
        wgt = a * Tl
        Crv[j] += wgt * cr
        Cgv[j] += wgt * cgr
        Cbv[j] += wgt * cbl
        zp = zy + slu * dx
        Dv[j] += wgt * zp
        Tn = Tl * (one - a)
        Tv[j] = Tn
        Sv[j] = Sv[j] * (one - a) if zp <= Lv[j] else Sv[j]
        done += np.uint64(ok & (Tn < t_min))
    return done


@njit(cache=True, inline="always")
def _backward_row(Tv, Qv, G0, G1, G2, GD, S, CV, LV, acc, ux, dy, qy, by, nha, op, cr, cgr, cbl, zy, slu, lx0,
                  lx1):
    """The same row and Gaussian once more (alphas, transmittances recomputed bit for bit), adding its
    per-lane gradient sums into ``acc [_N_GRAD, lanes]``: d loss / d opacity; d loss / d power
    (alpha-weighted) times dx, dy, dx^2, dx dy, dy^2; d loss / d colour (3); d loss / d z. ``CV``:
    the coverage term (weight times the transmittance through the measured surface), which only
    the Gaussians whose plane depth is within the lane's limit ``LV`` move."""
    t_min = np.float32(T_MIN)
    a_min = np.float32(ALPHA_MIN)
    a_max = np.float32(ALPHA_MAX)
    p_min = np.float32(POWER_MIN)
    one = np.float32(1.0)
    zero = np.float32(0.0)
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
        lj = np.float32(j)
        dx = lj - ux
        power = nha * dx * dx + qy - by * dx
        power = power if power > p_min else p_min
        gauss = exp_neg_fast(power)
        e = op * gauss
        alpha = e if e < a_max else a_max
        Tl = Tv[j]
        ok = (alpha >= a_min) & (Tl >= t_min) & (lj >= lx0) & (lj <= lx1)
        a = alpha if ok else zero
        wgt = a * Tl
        zp = zy + slu * dx
        gdj = GD[j]
        h = G0[j] * cr + G1[j] * cgr + G2[j] * cbl + gdj * zp
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


# --------------------------------------------------------------------------------------------
# Stage 2: forward (the renderer's tile loop) and the per-pixel loss
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def _forward_worker(worker, n_workers, tile_start, tile_ids, feat, order, aux, box, width, height, tiles_x, n_tiles,
                    bg, image, depth_obs, depth_w, depth_limit, w_rgb, w_depth, w_cover, dout, k_end, tile_loss):
    """Tiles ``worker, worker + n_workers, ...``: composite front to back exactly as
    ``raster._composite_worker`` does (16-lane float32 rows, same alpha tests, same termination), the
    depth of each Gaussian at each pixel from its slope; then per pixel the L1 loss against
    ``image [H, W, 3]`` and ``depth_obs [H, W]`` (float32, 0 = no reading; its L1 term weighted by
    ``depth_w [H, W]`` float32 per pixel; its coverage term counts the transmittance through the
    Gaussians whose plane depth is at most ``depth_limit [H, W]`` float32) into ``tile_loss[t]``
    (float64), the per-pixel rows ``dout [_N_DOUT, H, W]`` and ``k_end[t]``, the end of the tile's
    list where every pixel had terminated (the backward pass stops there too).

    With ``G`` = d loss / d final colour, ``GD`` = d loss / d depth sum ``D`` (the alpha-normalised
    depth ``D / acc``'s gradient over ``acc``) and ``gcov`` the coverage weight,
    ``d loss / d alpha_i = T_i h_i - (S - Q_i - w_i h_i) / (1 - alpha_i)`` with
    ``h_i = G . c_i + GD z_i``, ``Q_i = sum_{j < i} w_j h_j`` and the per-pixel total
    ``S = G . f + GD (D + dn T_f)`` (``f`` final colour, ``dn`` rendered depth, ``T_f``
    final transmittance): ``S`` is kept, ``Q`` is rebuilt by the backward pass. The coverage term
    ``gcov T_s`` (``T_s`` the transmittance through the Gaussians within the limit, a product over
    them) adds ``-gcov T_s / (1 - alpha_i)`` for those Gaussians only; ``gcov T_s`` is kept.
    """
    T = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cr = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cg = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Cb = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    D = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Ts = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    L = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    for t in range(worker, n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t, tiles_x, width, height)
        T[:] = 1.0
        Cr[:] = 0.0
        Cg[:] = 0.0
        Cb[:] = 0.0
        D[:] = 0.0
        Ts[:] = 1.0
        L[:] = 0.0  # lanes past the image edge: no surface
        for py in range(py0, py1 + 1):
            for px in range(px0, px1 + 1):
                L[py - py0, px - px0] = depth_limit[py, px]
        n_active = (px1 - px0 + 1) * (py1 - py0 + 1)
        k = tile_start[t]
        k1 = tile_start[t + 1]
        while k < k1 and n_active > 0:
            g = tile_ids[k]
            k += 1
            ux = feat[g, FEAT_U] - np.float32(px0)
            v = feat[g, FEAT_V]
            nha = np.float32(-0.5) * feat[g, FEAT_CONIC_A]
            cb = feat[g, FEAT_CONIC_B]
            nhc = np.float32(-0.5) * feat[g, FEAT_CONIC_C]
            op = feat[g, FEAT_OPACITY]
            cr = feat[g, FEAT_RED]
            cgr = feat[g, FEAT_GREEN]
            cbl = feat[g, FEAT_BLUE]
            z = feat[g, FEAT_Z]
            slu = np.float32(aux[order[g], AUX_SLOPE_U])
            slv = np.float32(aux[order[g], AUX_SLOPE_V])
            lx0 = np.float32(max(box[g, 0], px0) - px0)
            lx1 = np.float32(min(box[g, 1], px1) - px0)
            for py in range(max(box[g, 2], py0), min(box[g, 3], py1) + 1):
                dy = np.float32(py) - v
                r = py - py0
                done = _forward_row(T[r], Cr[r], Cg[r], Cb[r], D[r], Ts[r], L[r], ux, nhc * dy * dy, cb * dy, nha,
                                    op, cr, cgr, cbl, z + slv * dy, slu, lx0, lx1)
                n_active -= np.int64(done)
        k_end[t] = k
        loss = 0.0
        for py in range(py0, py1 + 1):
            r = py - py0
            for px in range(px0, px1 + 1):
                c = px - px0
                tf = np.float64(T[r, c])
                f0 = np.float64(Cr[r, c]) + tf * bg[0]
                f1 = np.float64(Cg[r, c]) + tf * bg[1]
                f2 = np.float64(Cb[r, c]) + tf * bg[2]
                r0 = f0 - image[py, px, 0]
                r1 = f1 - image[py, px, 1]
                r2 = f2 - image[py, px, 2]
                loss += w_rgb * (abs(r0) + abs(r1) + abs(r2))
                g0 = w_rgb * np.sign(r0)
                g1 = w_rgb * np.sign(r1)
                g2 = w_rgb * np.sign(r2)
                obs = depth_obs[py, px]
                acc = 1.0 - tf
                d = np.float64(D[r, c])
                gdp = 0.0
                dn = 0.0
                if obs > 0.0 and acc >= DEPTH_MIN_ALPHA:  # alpha-normalised depth, mostly opaque pixels
                    dn = d / acc
                    rd = dn - obs
                    wd = w_depth * np.float64(depth_w[py, px])
                    loss += wd * abs(rd)
                    gdp = wd * np.sign(rd) / acc
                cover = 0.0
                if obs > 0.0 and w_cover > 0.0:  # a sensor reading: a surface there, opaque
                    cover = w_cover * np.float64(Ts[r, c])
                    loss += cover
                dout[_D_R, py, px] = g0
                dout[_D_G, py, px] = g1
                dout[_D_B, py, px] = g2
                dout[_D_DEPTH, py, px] = gdp
                dout[_D_TOTAL, py, px] = g0 * f0 + g1 * f1 + g2 * f2 + gdp * (d + dn * tf)
                dout[_D_COVER, py, px] = cover
                dout[_D_LIMIT, py, px] = L[r, c]
        tile_loss[t] = loss


@njit(cache=True, parallel=True)
def _forward_tiles(tile_start, tile_ids, feat, order, aux, box, width, height, tiles_x, n_tiles, bg, image,
                   depth_obs, depth_w, depth_limit, w_rgb, w_depth, w_cover, n_workers):
    """All tiles: ``(loss, dout [_N_DOUT, H, W] float32, k_end [n_tiles] int64)``. Worker ``w`` takes
    tiles ``w, w + n_workers, ...``; every result is per tile, so the split does not change a bit."""
    dout = np.zeros((_N_DOUT, height, width), dtype=np.float32)
    k_end = np.empty(n_tiles, dtype=np.int64)
    tile_loss = np.zeros(n_tiles)
    for w in prange(n_workers):
        _forward_worker(w, n_workers, tile_start, tile_ids, feat, order, aux, box, width, height, tiles_x, n_tiles,
                        bg, image, depth_obs, depth_w, depth_limit, w_rgb, w_depth, w_cover, dout, k_end, tile_loss)
    loss = 0.0
    for t in range(n_tiles):  # fixed order
        loss += tile_loss[t]
    return loss, dout, k_end


# --------------------------------------------------------------------------------------------
# Stage 3: backward (tiles -> per-pair slots -> per Gaussian -> parameters)
# --------------------------------------------------------------------------------------------


@njit(cache=True)
def _backward_worker(worker, n_workers, tile_start, tile_ids, tile_slot, k_end, feat, order, aux, box, width, height,
                     tiles_x, n_tiles, dout, pair_grad):
    """Tiles ``worker, worker + n_workers, ...``: the tile's Gaussians front to back once more (the
    forward pass's lanes, alphas and transmittances, recomputed bit for bit), 16 lanes at a time;
    each (tile, Gaussian) pair's image-space gradient (``_G_*`` columns) goes to its own row
    ``pair_grad[tile_slot[k]]``."""
    T = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    Q = np.empty((TILE_SIZE, TILE_SIZE), dtype=np.float32)
    G = np.zeros((_N_DOUT, TILE_SIZE, TILE_SIZE), dtype=np.float32)
    acc = np.empty((_N_GRAD, TILE_SIZE), dtype=np.float32)
    sums = np.empty(_N_GRAD)
    for t in range(worker, n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t, tiles_x, width, height)
        T[:] = 1.0
        Q[:] = 0.0
        G[:] = 0.0  # lanes past the image edge stay 0
        for q in range(_N_DOUT):
            for py in range(py0, py1 + 1):
                for px in range(px0, px1 + 1):
                    G[q, py - py0, px - px0] = dout[q, py, px]
        for k in range(tile_start[t], k_end[t]):
            g = tile_ids[k]
            ux = feat[g, FEAT_U] - np.float32(px0)
            v = feat[g, FEAT_V]
            ca = feat[g, FEAT_CONIC_A]
            cb = feat[g, FEAT_CONIC_B]
            cc = feat[g, FEAT_CONIC_C]
            nha = np.float32(-0.5) * ca
            nhc = np.float32(-0.5) * cc
            op = feat[g, FEAT_OPACITY]
            cr = feat[g, FEAT_RED]
            cgr = feat[g, FEAT_GREEN]
            cbl = feat[g, FEAT_BLUE]
            z = feat[g, FEAT_Z]
            slu = np.float32(aux[order[g], AUX_SLOPE_U])
            slv = np.float32(aux[order[g], AUX_SLOPE_V])
            lx0 = np.float32(max(box[g, 0], px0) - px0)
            lx1 = np.float32(min(box[g, 1], px1) - px0)
            acc[:] = 0.0  # per lane: _backward_row's sums
            for py in range(max(box[g, 2], py0), min(box[g, 3], py1) + 1):
                dy = np.float32(py) - v
                r = py - py0
                _backward_row(T[r], Q[r], G[_D_R, r], G[_D_G, r], G[_D_B, r], G[_D_DEPTH, r], G[_D_TOTAL, r],
                              G[_D_COVER, r], G[_D_LIMIT, r], acc, ux, dy, nhc * dy * dy, cb * dy, nha, op, cr, cgr,
                              cbl, z + slv * dy, slu, lx0, lx1)
            sums[:] = 0.0  # lanes summed in float64, in lane order
            for c in range(_N_GRAD):
                for j in range(TILE_SIZE):
                    sums[c] += acc[c, j]
            s = tile_slot[k]
            pair_grad[s, _G_OP] = sums[0]
            pair_grad[s, _G_A] = -0.5 * sums[3]
            pair_grad[s, _G_B] = -sums[4]
            pair_grad[s, _G_C] = -0.5 * sums[5]
            # d power / d u = conic d; the slope depth z + s_u dx + s_v dy moves with u, v too
            pair_grad[s, _G_U] = ca * sums[1] + cb * sums[2] - slu * sums[9]
            pair_grad[s, _G_V] = cc * sums[2] + cb * sums[1] - slv * sums[9]
            pair_grad[s, _G_R] = sums[6]
            pair_grad[s, _G_G] = sums[7]
            pair_grad[s, _G_BL] = sums[8]
            pair_grad[s, _G_Z] = sums[9]
        for k in range(k_end[t], tile_start[t + 1]):  # after every pixel terminated: nothing
            s = tile_slot[k]
            for c in range(_N_GRAD):
                pair_grad[s, c] = 0.0


@njit(cache=True, parallel=True)
def _backward_tiles(tile_start, tile_ids, tile_slot, k_end, feat, order, aux, box, width, height, tiles_x, n_tiles,
                    dout, n_workers):
    """``pair_grad [P, _N_GRAD]`` float32: the image-space gradient of every (tile, Gaussian) pair,
    in the pair's slot (``raster.pair_slots``)."""
    pair_grad = np.empty((tile_ids.shape[0], _N_GRAD), dtype=np.float32)
    for w in prange(n_workers):
        _backward_worker(w, n_workers, tile_start, tile_ids, tile_slot, k_end, feat, order, aux, box, width,
                         height, tiles_x, n_tiles, dout, pair_grad)
    return pair_grad


@njit(cache=True, parallel=True)
def _param_grads(rank, gauss_start, pair_grad, aux, scl, quat, opa, Rcw, fx, fy, cx, cy, width, height, gparam,
                 vs_sum, vs_cnt):
    """For each drawn Gaussian (input row ``i``, sorted row ``k = rank[i]``, -1 when not drawn): its
    image-space gradient (u, v, conic a b c, opacity, r, g, b, z) as the sum of its pair slots
    ``gauss_start[k] ..`` in slot order, then the chain rule to its world position, log scales,
    local rotation vector, opacity logit and colour into ``gparam[:, i]`` (``_P_*`` rows; rows in
    input order, so the per-Gaussian arrays are read in memory order), from the projection's kept
    intermediates ``aux`` (``raster.AUX_*``: no second projection). Also adds the norm of its
    view-space positional gradient in NDC units (``d loss / d u * W / 2``, as 3DGS) to ``vs_sum[i]``
    and one view to ``vs_cnt[i]`` (densification statistics)."""
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
        u00 = r00 * p00 + r10 * p01 + r20 * p02
        u01 = r01 * p00 + r11 * p01 + r21 * p02
        u02 = r02 * p00 + r12 * p01 + r22 * p02
        u10 = r00 * p10 + r10 * p11 + r20 * p12
        u11 = r01 * p10 + r11 * p11 + r21 * p12
        u12 = r02 * p10 + r12 * p11 + r22 * p12
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
        # d L / d P: row 0 is R S ga, row 1 is R S gb
        sa0 = s0 * ga0
        sa1 = s1 * ga1
        sa2 = s2 * ga2
        sb0 = s0 * gb0
        sb1 = s1 * gb1
        sb2 = s2 * gb2
        gp00 = r00 * sa0 + r01 * sa1 + r02 * sa2
        gp01 = r10 * sa0 + r11 * sa1 + r12 * sa2
        gp02 = r20 * sa0 + r21 * sa1 + r22 * sa2
        gp10 = r00 * sb0 + r01 * sb1 + r02 * sb2
        gp11 = r10 * sb0 + r11 * sb1 + r12 * sb2
        gp12 = r20 * sb0 + r21 * sb1 + r22 * sb2
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
# Stage 4: Adam, one fused pass
# --------------------------------------------------------------------------------------------


_ADAM_BLOCK = 2048  # Gaussians per block of the fused Adam pass


@njit(cache=True, parallel=True)
def _adam_step(gparam, m1, m2, lr, b1, b2, ibc1_t, ibc2_t, t_all, eps, lo, hi, pos, log_s, quat, logit, col, scl,
               opa, seen, n_steps):
    """One Adam step (moments per element, eps 1e-15) with step sizes ``lr [_N_PARAM]`` (per
    gradient row); then the clamps (log scales to ``[lo, hi]``, logits to +-12, colours to
    [0, 1]), the rotation update ``q <- q exp(w)`` and the derived ``scl = exp(log_s)``,
    ``opa = sigmoid(logit)``. In place.

    ``ibc1_t``, ``ibc2_t`` ``[T + 1]`` float32: ``1 / (1 - b ** t)`` for each step count ``t``
    (:func:`_bias_corrections`). ``seen [N]`` uint8, ``n_steps [N]`` int32 (empty arrays: dense):
    selective Adam, only the Gaussians the view draws (``seen``) step, each with the bias
    correction of its own step count ``n_steps`` (counted up here); the others keep their
    parameters and moments. Dense (3DGS): every Gaussian steps, with the bias correction of the
    fit's step ``t_all``, and unseen Gaussians keep moving on their momentum.

    ``gparam``, ``m1``, ``m2`` are ``[_N_PARAM, N]`` float32 (one row per scalar parameter), so the
    moment update runs along contiguous float32 rows; blocks of ``_ADAM_BLOCK`` Gaussians
    run in parallel, each then applies its steps Gaussian by Gaussian."""
    n = pos.shape[0]
    selective = seen.shape[0] == n
    n_blocks = (n + _ADAM_BLOCK - 1) // _ADAM_BLOCK
    fb1 = np.float32(b1)
    fb2 = np.float32(b2)
    c1 = np.float32(1.0 - b1)
    c2 = np.float32(1.0 - b2)
    feps = np.float32(eps)
    for blk in prange(n_blocks):
        i0 = blk * _ADAM_BLOCK
        i1 = min(n, i0 + _ADAM_BLOCK)
        d = np.empty((_N_PARAM, i1 - i0), dtype=np.float32)
        on = np.ones(i1 - i0, dtype=np.bool_)
        ibc1 = np.empty(i1 - i0, dtype=np.float32)  # 1 / the bias corrections, per Gaussian
        ibc2 = np.empty(i1 - i0, dtype=np.float32)
        for j in range(i1 - i0):
            t = t_all
            if selective:
                on[j] = seen[i0 + j] != 0
                if on[j]:
                    n_steps[i0 + j] += 1
                t = n_steps[i0 + j]
            ibc1[j] = ibc1_t[t]
            ibc2[j] = ibc2_t[t]
        for c in range(_N_PARAM):
            step = np.float32(-lr[c])
            g = gparam[c, i0:i1]
            mm = m1[c, i0:i1]
            vv = m2[c, i0:i1]
            dc = d[c]
            for j in range(i1 - i0):
                if not on[j]:
                    continue
                gj = g[j]
                mj = fb1 * mm[j] + c1 * gj
                vj = fb2 * vv[j] + c2 * gj * gj
                mm[j] = mj
                vv[j] = vj
                dc[j] = step * (mj * ibc1[j]) / (np.sqrt(vj * ibc2[j]) + feps)
        for j in range(i1 - i0):
            if not on[j]:
                continue
            i = i0 + j
            for c in range(3):
                pos[i, c] += d[_P_POS + c, j]
                ls = min(hi, max(lo, np.float64(log_s[i, c]) + d[_P_LOG_SCALE + c, j]))
                log_s[i, c] = ls
                scl[i, c] = math.exp(np.float64(log_s[i, c]))
                col[i, c] = min(1.0, max(0.0, np.float64(col[i, c]) + d[_P_COL + c, j]))
            w0 = np.float64(d[_P_ROT + 0, j])
            w1 = np.float64(d[_P_ROT + 1, j])
            w2 = np.float64(d[_P_ROT + 2, j])
            angle = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            kq = math.sin(0.5 * angle) / angle if angle > 1e-12 else 0.5  # sin(half) / angle -> 1/2
            bx = w0 * kq
            by = w1 * kq
            bz = w2 * kq
            bw = math.cos(0.5 * angle)
            ax = np.float64(quat[i, 0])
            ay = np.float64(quat[i, 1])
            az = np.float64(quat[i, 2])
            aw = np.float64(quat[i, 3])
            qx = aw * bx + ax * bw + ay * bz - az * by  # q <- q exp(w): a local (right) rotation
            qy = aw * by - ax * bz + ay * bw + az * bx
            qz = aw * bz + ax * by - ay * bx + az * bw
            qw = aw * bw - ax * bx - ay * by - az * bz
            qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
            quat[i, 0] = qx / qn
            quat[i, 1] = qy / qn
            quat[i, 2] = qz / qn
            quat[i, 3] = qw / qn
            lg = min(_LOGIT_CLAMP, max(-_LOGIT_CLAMP, np.float64(logit[i]) + d[_P_LOGIT, j]))
            logit[i] = lg
            opa[i] = 1.0 / (1.0 + math.exp(-np.float64(logit[i])))


def _bias_corrections(beta: float, n_steps: int) -> np.ndarray:
    """``[n_steps + 1]`` float32 ``1 / (1 - beta ** t)`` for ``t = 0 .. n_steps`` (``t = 0`` as 1:
    never read for a Gaussian that steps, which counts its step first)."""
    t = np.maximum(np.arange(n_steps + 1), 1).astype(np.float64)
    return (1.0 / (1.0 - beta ** t)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# One view: loss and parameter gradients
# --------------------------------------------------------------------------------------------


class _StageClock:
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


def _n_workers(n_tiles: int) -> int:
    # two tile streams per thread balance busy and empty regions; the results do not depend on it
    return max(1, min(n_tiles, 2 * kernel_threads()))


def _view_gradients(pos, scl, quat, col, opa, view: raster.PinholeView, image, depth, w_rgb: float, w_depth: float,
                    w_cover: float, bg: np.ndarray, near_m: float, gparam: np.ndarray, vs_sum: np.ndarray,
                    vs_cnt: np.ndarray, clock: _StageClock, depth_w: np.ndarray | None = None,
                    band: np.ndarray | None = None, seen: np.ndarray | None = None) -> float:
    """Loss of one view (``image [h, w, 3]``, ``depth [h, w]`` float32 at the view's size, its
    per-pixel depth-term weights ``depth_w [h, w]`` float32, None = 1, and the depth band
    ``band [h, w]`` (m) behind each reading within which a Gaussian counts as the measured surface
    for the coverage term, None = any depth) and the gradient of every
    parameter into ``gparam [_N_PARAM, N]`` (zero for Gaussians the view does not draw); ``seen
    [N]`` uint8, if given, is set to 1 for the Gaussians the view draws. The state arrays are float32."""
    width, height = view.width, view.height
    npix = float(width * height)
    sp = raster.prepare_splats(pos, scl, quat, col, opa, view, near_m, keep_aux=True)
    if sp is None:
        clock.lap("projection")
        return float(w_rgb * np.abs(bg.astype(np.float64) - image).sum() / npix)  # no depth to compare
    tile_slot, gauss_start = raster.pair_slots(sp.box, sp.tile_start, sp.tiles_x)
    if seen is not None:
        seen[sp.order] = 1
    clock.lap("projection")
    nw = _n_workers(sp.n_tiles)
    if depth_w is None:
        depth_w = np.ones(depth.shape, np.float32)
    limit = np.full(depth.shape, np.inf, np.float32) if band is None else np.asarray(depth + band, np.float32)
    loss, dout, k_end = _forward_tiles(sp.tile_start, sp.tile_ids, sp.feat, sp.order, sp.aux, sp.box, width, height,
                                       sp.tiles_x, sp.n_tiles, bg.astype(np.float64), image, depth,
                                       np.ascontiguousarray(depth_w, np.float32), limit, w_rgb / npix,
                                       w_depth / npix, w_cover / npix, nw)
    clock.lap("forward")
    pair_grad = _backward_tiles(sp.tile_start, sp.tile_ids, tile_slot, k_end, sp.feat, sp.order, sp.aux, sp.box,
                                width, height, sp.tiles_x, sp.n_tiles, dout, nw)
    rank = np.full(len(pos), -1, np.int64)
    rank[sp.order] = np.arange(len(sp.order))
    _param_grads(rank, gauss_start, pair_grad, sp.aux, scl, quat, opa, view.R_cam_world, view.fx, view.fy,
                 view.cx, view.cy, float(width), float(height), gparam, vs_sum, vs_cnt)
    clock.lap("backward")
    return float(loss)


def render_loss_and_gradients(positions: np.ndarray, scales: np.ndarray, quat_xyzw: np.ndarray,
                              colors01: np.ndarray, opacities: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray,
                              image01: np.ndarray, depth_m: np.ndarray, w_rgb: float = 1.0, w_depth: float = 0.0,
                              background01: tuple[float, float, float] = (0.0, 0.0, 0.0), near_m: float = 0.05,
                              w_cover: float = 0.0, depth_weight_map: np.ndarray | None = None,
                              coverage_band_map: np.ndarray | None = None):
    """L1 loss of one rendered view and its gradient w.r.t. every parameter (the fit's own kernels).

    Args:
        positions ``[N, 3]``, scales ``[N, 3]`` (m), quat_xyzw ``[N, 4]``, colors01 ``[N, 3]`` in
        [0, 1], opacities ``[N]``: the Gaussians (any float dtype; the fit's state is float32).
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
    n = positions.shape[0]
    height, width = image01.shape[:2]
    view = raster.view_from_pose(T_world_cam, K, width, height)
    f32 = [np.ascontiguousarray(a, np.float32) for a in (positions, scales, quat_xyzw, colors01, opacities)]
    gparam = np.zeros((_N_PARAM, n), np.float32)
    loss = _view_gradients(*f32, view, np.ascontiguousarray(image01, np.float32),
                           np.ascontiguousarray(depth_m, np.float32), w_rgb, w_depth, w_cover,
                           np.asarray(background01, np.float64), near_m, gparam, np.zeros(n), np.zeros(n, np.int32),
                           _StageClock(), depth_weight_map,
                           None if coverage_band_map is None else np.ascontiguousarray(coverage_band_map, np.float32))
    g = gparam.T.astype(np.float64)
    return loss, {"position": g[:, _P_POS:_P_POS + 3].copy(), "log_scale": g[:, _P_LOG_SCALE:_P_LOG_SCALE + 3].copy(),
                  "rotation": g[:, _P_ROT:_P_ROT + 3].copy(), "logit": g[:, _P_LOGIT].copy(),
                  "color": g[:, _P_COL:_P_COL + 3].copy()}


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _quat_mul_xyzw(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a b`` of ``[N, 4]`` x y z w quaternions."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=1)


def _rotvec_to_quat_xyzw(w: np.ndarray) -> np.ndarray:
    """``[N, 3]`` rotation vectors to ``[N, 4]`` unit quaternions."""
    angle = np.linalg.norm(w, axis=1)
    half = 0.5 * angle
    # sin(half)/angle -> 1/2 as angle -> 0
    k = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)
    return np.concatenate([w * k[:, None], np.cos(half)[:, None]], axis=1)


scaled_intrinsics = raster.scale_intrinsics  # the one convention, kept under its former name here


def _downsample(img: np.ndarray, f: int) -> np.ndarray:
    """Box filter by an integer factor ``f`` (crops a remainder)."""
    if f == 1:
        return img
    h, w = img.shape[0] // f, img.shape[1] // f
    img = img[: h * f, : w * f]
    return img.reshape(h, f, w, f, *img.shape[2:]).mean(axis=(1, 3))


def _downsample_depth(depth: np.ndarray, f: int) -> np.ndarray:
    """Mean of the valid readings of each ``f x f`` block; 0 where a block has fewer than half."""
    if f == 1:
        return depth
    h, w = depth.shape[0] // f, depth.shape[1] // f
    blocks = depth[: h * f, : w * f].reshape(h, f, w, f)
    ok = blocks > 0
    n = ok.sum(axis=(1, 3))
    s = np.where(ok, blocks, 0.0).sum(axis=(1, 3))
    return np.where(n * 2 >= f * f, s / np.maximum(n, 1), 0.0)


def _reciprocal_factor(scale: float, name: str) -> int:
    f = int(round(1.0 / scale)) if scale > 0 else 0
    if f < 1 or abs(1.0 / f - scale) > 1e-9:
        raise ValueError(f"optimisation {name} must be 1/n for an integer n, got {scale}")
    return f


# Working copies of one level (float32 image, depth and depth weight per keyframe) are held while
# they fit in this; above it (hundreds of keyframes) each view's copy is made when its step needs
# it (one image decode and box filter per step, ~10 % of a step at 320x240), so the fit's memory
# does not grow with the sequence.
LEVEL_MEMORY_BUDGET_BYTES = 384 << 20
_LEVEL_BYTES_PER_PIXEL = (3 + 1 + 1 + 1) * 4  # float32 RGB, depth, depth weight, coverage band


class OnDemandViews(Sequence):
    """A read-only sequence of ``n`` arrays made by ``make(k)`` at each access, the last one kept
    (a fit step reads one view's image, depth and weight in turn; nothing else is held). Used for
    the keyframes of long sequences: the fit's levels here, its inputs in ``mapping/mapper.py``."""

    def __init__(self, n: int, make: Callable[[int], np.ndarray]) -> None:
        self.n, self.make, self._last = n, make, (None, None)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self.n))]
        if not -self.n <= k < self.n:
            raise IndexError(k)
        k %= self.n
        if self._last[0] != k:
            self._last = (k, self.make(k))
        return self._last[1]


class _Level:
    """The keyframes at one image scale (float32 images in [0, 1], depths, depth-term weights,
    coverage bands (None when not given), intrinsics): held, or made per view on access when they
    would exceed ``LEVEL_MEMORY_BUDGET_BYTES``."""

    def __init__(self, name: str, f: int, images, depths_m, K: np.ndarray, depth_weights=None,
                 coverage_bands=None) -> None:
        self.name, self.f, self.scale = name, f, 1.0 / f
        h0, w0 = np.shape(images[0])[:2]
        n = len(images)

        def image(k):
            return np.ascontiguousarray(_downsample(np.asarray(images[k], np.float64) / 255.0, f), np.float32)

        def depth(k):
            return np.ascontiguousarray(_downsample_depth(np.asarray(depths_m[k], np.float64), f), np.float32)

        def per_reading(maps, k):  # the mean of the readings' values each block averages (same validity rule)
            d = np.asarray(depths_m[k])
            return np.ascontiguousarray(
                _downsample_depth(np.where(d > 0, np.asarray(maps[k], np.float64), 0.0), f), np.float32)

        def weight(k):
            if depth_weights is None:
                return np.ones(((h0 // f), (w0 // f)), np.float32)  # the shape _downsample_depth gives
            return per_reading(depth_weights, k)

        def band(k):
            return per_reading(coverage_bands, k)

        if n * (h0 // f) * (w0 // f) * _LEVEL_BYTES_PER_PIXEL <= LEVEL_MEMORY_BUDGET_BYTES:
            self.images = [image(k) for k in range(n)]
            self.depths = [depth(k) for k in range(n)]
            self.depth_w = [weight(k) for k in range(n)]
            self.bands = None if coverage_bands is None else [band(k) for k in range(n)]
        else:
            self.images, self.depths, self.depth_w = (OnDemandViews(n, image), OnDemandViews(n, depth),
                                                      OnDemandViews(n, weight))
            self.bands = None if coverage_bands is None else OnDemandViews(n, band)
        self.K = raster.scale_intrinsics(K, 1.0 / f)
        self.height, self.width = self.images[0].shape[:2]


class _FitState:
    """The Gaussians being fitted (float32, 3DGS parametrisation), their Adam moments and the
    densification statistics. Rows may be added (densification) and removed (pruning)."""

    def __init__(self, field: GaussianField, s: OptimizationSettings) -> None:
        self.pos = np.array(field.positions, np.float32)  # a copy: the fit moves it in place
        self.log_s = np.log(np.clip(field.scales.astype(np.float64), s.min_scale_m, s.max_scale_m)).astype(np.float32)
        q = field.rotations_xyzw.astype(np.float64)
        self.quat = np.ascontiguousarray(q / np.linalg.norm(q, axis=1, keepdims=True), np.float32)
        op = np.clip(field.opacities.astype(np.float64), 1e-4, 1 - 1e-4)
        self.logit = np.log(op / (1 - op)).astype(np.float32)
        self.col = (field.colors.astype(np.float64) / 255.0).astype(np.float32)
        self.ids = field.ids.copy()
        # Where each Gaussian started ([N, 3]), its surface normal there ([N, 3], the axis of its
        # smallest scale) and how far along it the fit may move it ([N, 1], normal_offset_max_scales
        # times its largest scale). Without a bound they are [N, 0] and never read: no memory.
        n = len(field)
        width = 3 if s.normal_offset_max_scales > 0 else 0
        self.anchor = self.pos[:, :width].copy()  # a copy: pos moves in place
        self.anchor_n = np.zeros((n, width), np.float32)
        self.anchor_b = np.zeros((n, min(width, 1)), np.float32)
        if width and n:
            R = quat_xyzw_to_rotmat(self.quat.astype(np.float64))  # [N, 3, 3]
            sc = field.scales.astype(np.float64)
            self.anchor_n = np.ascontiguousarray(R[np.arange(n), :, np.argmin(sc, axis=1)], np.float32)
            self.anchor_b = (s.normal_offset_max_scales * sc.max(axis=1, keepdims=True)).astype(np.float32)
        self.m1 = np.zeros((_N_PARAM, n), np.float32)  # Adam moments, one row per scalar parameter
        self.m2 = np.zeros((_N_PARAM, n), np.float32)
        self.n_steps = np.zeros(n, np.int32)  # Adam steps each Gaussian has taken (selective Adam)
        self.refresh()
        self.reset_stats()
        child = self.ids[(self.ids & CHILD_ID_BIT) != 0] & ~CHILD_ID_BIT
        self.next_child = int(child.max()) + 1 if len(child) else 0

    def __len__(self) -> int:
        return len(self.pos)

    def refresh(self) -> None:
        self.scl = np.exp(self.log_s)
        self.opa = (1.0 / (1.0 + np.exp(-self.logit.astype(np.float64)))).astype(np.float32)

    def reset_stats(self) -> None:
        self.vs_sum = np.zeros(len(self))
        self.vs_cnt = np.zeros(len(self), np.int32)

    _ROWS = ("pos", "log_s", "quat", "logit", "col", "ids", "anchor", "anchor_n", "anchor_b", "n_steps")
    _MOMENTS = ("m1", "m2")  # [_N_PARAM, N]: Gaussians along axis 1

    def take(self, rows: np.ndarray) -> None:
        for name in self._ROWS:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[rows]))
        for name in self._MOMENTS:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[:, rows]))
        self.refresh()

    def append(self, rows: np.ndarray, ids: np.ndarray) -> None:
        """Copies of ``rows`` with new ``ids`` and a fresh optimizer state (3DGS: new Gaussians
        start fresh)."""
        n = len(self)
        for name in self._ROWS:
            a = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(np.concatenate([a, ids if name == "ids" else a[rows]])))
        for name in self._MOMENTS:
            a = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(np.concatenate([a, a[:, rows]], axis=1)))
        self.restart_optimizer(np.arange(n, len(self)))
        self.refresh()

    def restart_optimizer(self, rows: np.ndarray) -> None:
        """Zero moments and no steps taken for ``rows`` (new and split Gaussians)."""
        for name in self._MOMENTS:
            getattr(self, name)[:, rows] = 0.0
        self.n_steps[rows] = 0

    def hold_to_surface(self) -> None:
        """Clamp each centre's offset from its start along its starting normal to ``anchor_b``."""
        off = np.einsum("ij,ij->i", self.pos - self.anchor, self.anchor_n)[:, None]  # [N, 1]
        excess = off - np.clip(off, -self.anchor_b, self.anchor_b)
        self.pos -= excess * self.anchor_n

    def to_field(self, keep: np.ndarray) -> GaussianField:
        return canonicalize(GaussianField(self.pos[keep], np.exp(self.log_s[keep].astype(np.float64)),
                                          self.quat[keep], np.rint(self.col[keep].astype(np.float64) * 255.0),
                                          self.opa[keep], self.ids[keep]))


def _densify_and_prune(st: _FitState, s: OptimizationSettings, n_start: int,
                       rng: np.random.Generator) -> tuple[int, int, int]:
    """One round of Kerbl et al.'s adaptive density control; returns ``(cloned, split, pruned)``.

    Gaussians whose mean view-space positional gradient since the last round is at least
    ``densify_grad_threshold`` are under-reconstructing (small: cloned, the copy starts with fresh
    moments and drifts its own way) or over-reconstructing (large: split into two samples of the
    Gaussian with scales / 1.6; the first keeps the row and id). At most ``densify_max_growth`` times
    the starting count, the largest gradients first. Then Gaussians below ``prune_opacity`` go.
    New ids: ``CHILD_ID_BIT`` plus a counter (voxel ids never set that bit), so they are unique and
    the same run gives the same ids.
    """
    n = len(st)
    avg = np.where(st.vs_cnt > 0, st.vs_sum / np.maximum(st.vs_cnt, 1), 0.0)
    idx = np.flatnonzero(avg >= s.densify_grad_threshold)
    room = max(0, int(s.densify_max_growth * n_start) - n)
    if len(idx) > room:  # the largest gradients first, ties by row
        idx = np.sort(idx[np.argsort(-avg[idx], kind="stable")[:room]])
    big = st.scl[idx].max(axis=1) > s.densify_scale_m
    clone, split = idx[~big], idx[big]
    if len(split):
        R = quat_xyzw_to_rotmat(st.quat[split].astype(np.float64))  # [S, 3, 3]
        sd = st.scl[split].astype(np.float64)
        z = rng.standard_normal((2, len(split), 3))
        samples = st.pos[split].astype(np.float64)[None] + np.einsum("sij,ksj->ksi", R, sd[None] * z)
        st.pos[split] = samples[0]
        st.log_s[split] = np.log(sd / _SPLIT_SCALE_DIV)
        st.restart_optimizer(split)
    new_rows = np.concatenate([clone, split])
    if len(new_rows):
        ids = CHILD_ID_BIT | (np.uint64(st.next_child) + np.arange(len(new_rows), dtype=np.uint64))
        st.next_child += len(new_rows)
        st.append(new_rows, ids)
        if len(split):
            st.pos[n + len(clone):] = samples[1]
    st.refresh()
    keep = st.opa >= s.prune_opacity
    n_pruned = int(len(st) - keep.sum())
    if n_pruned:
        st.take(np.flatnonzero(keep))
    st.reset_stats()
    return len(clone), len(split), n_pruned


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------


def optimize_gaussians(field: GaussianField, images: Sequence[np.ndarray], depths_m: Sequence[np.ndarray],
                       poses: Sequence[np.ndarray], K: np.ndarray, settings: OptimizationSettings = OptimizationSettings(),
                       log: Callable[[str], None] | None = None,
                       depth_weights: Sequence[np.ndarray] | None = None,
                       coverage_bands_m: Sequence[np.ndarray] | None = None) -> OptimizationResult:
    """Fit ``field`` to keyframe ``images`` (``[H, W, 3]`` uint8) and ``depths_m`` (``[H, W]``,
    0 = no reading) seen from ``poses`` (``[4, 4]`` camera-to-world each, intrinsics ``K``).
    ``depth_weights`` (``[H, W]`` each, >= 0; None = 1): per-pixel weights of the depth term
    (the mapper's: inverse depth noise, so far readings pull less). ``coverage_bands_m``
    (``[H, W]`` each, >= 0, metres; None = no limit): the coverage term at a reading counts only
    the Gaussians whose plane depth there is within this of it, so the measured surface must be
    opaque itself, not a surface behind it (the mapper's: a few sigma of the depth noise).

    Returns a new (canonical) field (the starting Gaussians keep their ids; densification adds
    Gaussians with ``CHILD_ID_BIT`` ids; pruning, and at the end every Gaussian whose opacity fell
    below 1/255, which can no longer be drawn, removes some), the loss of every step, the fit
    record and the CPU seconds per stage. Progress (rate, time left) goes to ``log``.
    """
    s = settings
    if not (len(images) == len(depths_m) == len(poses)):
        raise ValueError("optimize_gaussians: one depth image and one pose per image")
    if depth_weights is not None and (len(depth_weights) != len(images) or any(
            np.shape(w) != np.shape(d) or not (np.isfinite(w).all() and (np.asarray(w) >= 0).all())
            for w, d in zip(depth_weights, depths_m))):
        raise ValueError("optimize_gaussians: depth_weights must be one finite, non-negative [H, W] map per depth")
    if coverage_bands_m is not None and (len(coverage_bands_m) != len(images) or any(
            np.shape(b) != np.shape(d) or not (np.isfinite(b).all() and (np.asarray(b) >= 0).all())
            for b, d in zip(coverage_bands_m, depths_m))):
        raise ValueError("optimize_gaussians: coverage_bands_m must be one finite, non-negative [H, W] map per depth")
    t0, c0 = time.perf_counter(), time.process_time()
    if s.epochs < 1 or not images or len(field) == 0:
        return OptimizationResult(field, np.zeros(0), 0, 0.0)
    f = _reciprocal_factor(s.scale, "scale")
    if s.coarse_factor < 1:
        raise ValueError(f"optimisation coarse_factor must be a whole number >= 1, got {s.coarse_factor}")
    coarse = s.coarse_max_steps > 0 and s.coarse_factor > 1
    fc = f * int(s.coarse_factor)
    h0, w0 = images[0].shape[:2]
    for k, (im, d, T) in enumerate(zip(images, depths_m, poses)):
        if np.shape(im) != (h0, w0, 3) or np.shape(d) != (h0, w0):
            raise ValueError(f"optimize_gaussians: view {k}: image {list(np.shape(im))} and depth {list(np.shape(d))} "
                             f"must be [{h0}, {w0}, 3] and [{h0}, {w0}] like view 0")
        if np.shape(T) != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"optimize_gaussians: view {k}: pose must be a finite 4x4 matrix")
    n_views = len(images)
    s = stretch_schedule(s, n_views)
    n_cap = s.epochs * n_views if s.max_steps is None else min(s.epochs * n_views, s.max_steps)
    if n_cap < 1:
        return OptimizationResult(field, np.zeros(0), 0, 0.0)
    # whole passes only, and at least as many left for the fit scale
    coarse = coarse and images[0].shape[1] / fc >= MIN_COARSE_WIDTH_PX
    coarse_passes = (max(0, min(s.coarse_max_steps // n_views, int(n_cap // n_views * COARSE_MAX_PASS_FRACTION)))
                     if coarse else 0)
    levels = ([_Level("coarse", fc, images, depths_m, K, depth_weights, coverage_bands_m)] if coarse_passes else []) + [
        _Level("fine", f, images, depths_m, K, depth_weights, coverage_bands_m)]

    st = _FitState(field, s)
    n_start = len(st)
    lo, hi = math.log(s.min_scale_m), math.log(s.max_scale_m)
    lr0 = np.repeat([s.lr_position_m, s.lr_log_scale, s.lr_rotation_rad, s.lr_opacity_logit, s.lr_color],
                    [3, 3, 3, 1, 3])  # per gradient row (_P_*)
    b1, b2, eps = 0.9, 0.999, 1e-15
    ibc1_t, ibc2_t = _bias_corrections(b1, n_cap), _bias_corrections(b2, n_cap)  # no count passes the step cap
    bg = np.zeros(3)
    rng = np.random.default_rng(s.seed)  # keyframe order
    rng_split = np.random.default_rng([s.seed, 1])  # samples of split Gaussians
    clock = _StageClock()
    progress = Progress("fitting the Gaussians to the keyframes", n_cap, log, unit="steps")
    losses: list[float] = []
    step_scale: list[float] = []
    passes: list[tuple[str, int, float]] = []  # (level, steps, mean loss) of every pass begun
    n_cloned = n_split = n_pruned = 0
    level_i = 0
    best, stale, level_passes = math.inf, 0, 0
    stop_reason = STOP_STEP_CAP if n_cap < s.epochs * n_views else STOP_EPOCHS
    while len(passes) < s.epochs and len(losses) < n_cap:
        lv = levels[level_i]
        first = len(losses)
        for v in rng.permutation(n_views)[: n_cap - first]:
            step = len(losses)
            decay = s.lr_final_ratio ** (step / max(n_cap - 1, 1))
            if lv.name == "coarse":
                decay *= s.coarse_lr_scale
            clock.start()
            view = raster.view_from_pose(poses[v], lv.K, lv.width, lv.height)
            gparam = np.zeros((_N_PARAM, len(st)), np.float32)
            seen = np.zeros(len(st) if s.selective_adam else 0, np.uint8)
            loss = _view_gradients(st.pos, st.scl, st.quat, st.col, st.opa, view, lv.images[v], lv.depths[v], 1.0,
                                   s.depth_weight, s.coverage_weight, bg, raster.NEAR_M, gparam, st.vs_sum,
                                   st.vs_cnt, clock, lv.depth_w[v], None if lv.bands is None else lv.bands[v],
                                   seen if s.selective_adam else None)
            t = step + 1
            _adam_step(gparam, st.m1, st.m2, lr0 * decay, b1, b2, ibc1_t, ibc2_t, t, eps, lo, hi, st.pos, st.log_s,
                       st.quat, st.logit, st.col, st.scl, st.opa, seen, st.n_steps)
            if s.normal_offset_max_scales > 0:
                st.hold_to_surface()
            clock.lap("adam")
            losses.append(loss)
            step_scale.append(lv.scale)
            if s.densify_interval > 0 and t % s.densify_interval == 0 and t < s.densify_until_step:
                c, sp, pr = _densify_and_prune(st, s, n_start, rng_split)
                n_cloned, n_split, n_pruned = n_cloned + c, n_split + sp, n_pruned + pr
                stale = 0  # new Gaussians get plateau_patience passes to pay off
                clock.lap("densify")
            progress.update(extra=f"pass {len(passes) + 1}, loss {loss:.4f} at {lv.width}x{lv.height}, "
                                  f"{len(st):,} Gaussians")
        mean = float(np.mean(losses[first:]))
        passes.append((lv.name, len(losses) - first, mean))
        level_passes += 1
        if len(losses) - first < n_views:  # a partial pass: the step cap
            break
        if mean < best * (1.0 - s.plateau_rel_tol):
            best, stale = mean, 0
        else:
            stale += 1
        plateau = s.plateau_patience > 0 and stale >= s.plateau_patience
        if lv.name == "coarse":
            if plateau or level_passes >= coarse_passes:  # on to the fit scale, with a fresh plateau test
                level_i, best, stale, level_passes = level_i + 1, math.inf, 0, 0
        elif plateau:
            stop_reason = STOP_PLATEAU
            break
    clock.start()
    keep = st.opa * 255.0 >= 1.0  # can no longer be drawn
    n_pruned += int(len(st) - keep.sum())
    out = st.to_field(keep)
    clock.lap("densify")
    fine = [p for p in passes if p[0] == "fine"]
    coarse_p = [p for p in passes if p[0] == "coarse"]
    record = {
        "steps": len(losses), "epochs": len(passes), "stop_reason": stop_reason,
        "final_loss": round(passes[-1][2], 6), "loss_first_epoch": round((fine or passes)[0][2], 6),
        "scale": s.scale,
        "coarse": ({"scale": levels[0].scale, "steps": int(sum(p[1] for p in coarse_p)), "epochs": len(coarse_p),
                    "loss_first_epoch": round(coarse_p[0][2], 6), "loss_last_epoch": round(coarse_p[-1][2], 6)}
                   if coarse_p else None),
        "n_gaussians_start": n_start, "n_gaussians_end": len(out), "n_cloned": n_cloned, "n_split": n_split,
        "n_pruned": n_pruned,
    }
    (log or logger.info)(
        f"Gaussian fit: {record['steps']} steps in {record['epochs']} passes "
        f"({record['coarse']['steps'] if coarse_p else 0} at {levels[0].width}x{levels[0].height}), stopped: "
        f"{stop_reason}; final loss {record['final_loss']:.5f}; {n_start:,} -> {len(out):,} Gaussians "
        f"(+{n_cloned:,} cloned, +{n_split:,} split, -{n_pruned:,} pruned)")
    return OptimizationResult(out, np.asarray(losses, np.float64), n_pruned, time.perf_counter() - t0, record,
                              time.process_time() - c0, dict(clock.cpu), np.asarray(step_scale))

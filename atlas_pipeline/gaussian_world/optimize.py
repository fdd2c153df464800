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

**One step**, every stage compiled and threaded, the Gaussians, images and per-pixel arithmetic
float32 (the projection and the chain rule float64):

1. *projection*: ``raster.prepare_splats(keep_aux=True)`` projects, sorts and bins the Gaussians
   once and keeps each one's projection intermediates for the chain rule.
2. *forward* and 3. *backward*: ``fit_kernels.view_gradients``, on the renderer's compositing core
   (``composite``). With ``sh_degree`` > 0 each Gaussian's colour in the view is its spherical
   harmonics along the ray from the camera centre (``fit_sh.view_colors01``, before the projection),
   and ``fit_sh.sh_backward`` turns the colour gradient into the coefficients' (after the backward
   pass). The degree starts at 0 and grows by one every ``sh_degree_interval`` steps (3DGS's
   schedule, on fewer steps); a field of a lower degree starts its missing coefficients at 0.
4. *Adam*: ``fit_adam.adam_step``, one fused pass over every Gaussian.

**The schedule** (``optimize_gaussians``; ``fit_schedule``), 3DGS's with fewer steps:

* *coarse to fine*: passes at ``scale / coarse_factor`` with every step size times
  ``coarse_lr_scale``, until their loss stops falling or ``coarse_max_steps``: the slow, large
  moves (scales growing over what the depth did not map, colours, gross geometry) on a cheaper
  image; then passes at the fit scale restore the detail.
* *early stop*: after each pass over the keyframes its mean loss is compared with the best pass so
  far at that scale; a pass that does not beat it by ``plateau_rel_tol`` (relative) is a pass
  without progress, and ``plateau_patience`` of them in a row end the level (the coarse one) or
  the fit (``stop_reason: plateau``); a densification round restarts the count. ``max_steps`` and
  ``epochs`` cap it (``step_cap`` / ``epochs``).
* *densification and pruning* (Kerbl et al. 2023, section 5): every ``densify_interval`` steps up
  to ``densify_until_step``, Gaussians whose mean view-space positional gradient exceeds
  ``densify_grad_threshold`` are cloned when small or split in two when large; Gaussians whose
  opacity fell below ``prune_opacity`` are removed. So the Gaussians go where the error is.

The keyframe images at each scale are held within a memory budget (``fit_levels``). Only
keyframes are used; held-out frames still measure generalisation.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field as dataclass_field
from typing import Callable

import numpy as np

from atlas_pipeline.config import FitConfig
from atlas_pipeline.gaussian_world import fit_kernels, fit_levels, fit_sh, raster
from atlas_pipeline.gaussian_world.field import GaussianField, sh_rest_count
from atlas_pipeline.gaussian_world.fit_adam import CHILD_ID_BIT, AdamHyper, FitState, adam_step, bias_corrections
from atlas_pipeline.gaussian_world.fit_kernels import (
    FIT_STAGES, LossWeights, StageClock, ViewGradients, fit_target, render_loss_and_gradients,
)
from atlas_pipeline.gaussian_world.fit_levels import OnDemandViews, FitLevel, reciprocal_factor
from atlas_pipeline.gaussian_world.fit_schedule import coarse_passes, densify_and_prune, stretch_schedule
from atlas_pipeline.progress import Progress

logger = logging.getLogger(__name__)

__all__ = ["FitConfig", "OptimizationResult", "optimize_gaussians", "render_loss_and_gradients",
           "LossWeights", "OnDemandViews", "stretch_schedule",
           "STOP_PLATEAU", "STOP_STEP_CAP", "STOP_EPOCHS", "FIT_STAGES", "CHILD_ID_BIT"]

STOP_PLATEAU = "plateau"  # plateau_patience passes in a row without a relative gain of plateau_rel_tol
STOP_STEP_CAP = "step_cap"  # max_steps reached
STOP_EPOCHS = "epochs"  # every allowed pass ran
ADAM_BETA1, ADAM_BETA2, ADAM_EPS = 0.9, 0.999, 1e-15


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


def optimize_gaussians(field: GaussianField, images: Sequence[np.ndarray], depths_m: Sequence[np.ndarray],
                       poses: Sequence[np.ndarray], K: np.ndarray, settings: FitConfig = FitConfig(),
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
    f = reciprocal_factor(s.scale, "scale")
    if s.coarse_factor < 1:
        raise ValueError(f"optimisation coarse_factor must be a whole number >= 1, got {s.coarse_factor}")
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
    n_coarse = coarse_passes(s, n_views, n_cap, images[0].shape[1] / fc)
    levels = ([FitLevel("coarse", fc, images, depths_m, K, depth_weights, coverage_bands_m)] if n_coarse else []) + [
        FitLevel("fine", f, images, depths_m, K, depth_weights, coverage_bands_m)]

    st = FitState(field, s.min_scale_m, s.max_scale_m, s.normal_offset_max_scales, s.sh_degree)
    n_start = len(st)
    lo, hi = math.log(s.min_scale_m), math.log(s.max_scale_m)
    lr0 = np.repeat([s.lr_position_m, s.lr_log_scale, s.lr_rotation_rad, s.lr_opacity_logit, s.lr_color, s.lr_sh_rest],
                    [3, 3, 3, 1, 3, 3 * st.k_fit])  # per gradient row (fit_kernels.P_*, fit_sh)
    ibc1_t, ibc2_t = bias_corrections(ADAM_BETA1, n_cap), bias_corrections(ADAM_BETA2, n_cap)  # no count passes the cap
    weights = LossWeights(1.0, s.depth_weight, s.coverage_weight)
    rng = np.random.default_rng(s.seed)  # keyframe order
    rng_split = np.random.default_rng([s.seed, 1])  # samples of split Gaussians
    clock = StageClock()
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
            gparam = np.zeros((fit_sh.sh_grad_rows(st.k_fit), len(st)), np.float32)
            seen = np.zeros(len(st) if s.selective_adam else 0, np.uint8)
            target = fit_target(lv.images[v], lv.depths[v], lv.depth_w[v], None if lv.bands is None else lv.bands[v])
            grads = ViewGradients(gparam, st.vs_sum, st.vs_cnt, seen if s.selective_adam else None)
            k_active = sh_rest_count(fit_sh.active_degree(step, s.sh_degree, s.sh_degree_interval))
            gs = st.gaussians()
            if k_active:  # the colour each Gaussian shows this view (part of the projection's time)
                centre = np.asarray(poses[v], np.float64)[:3, 3]
                gs = gs._replace(colors=fit_sh.view_colors01(st.pos, st.col, st.sh_rest, k_active, centre))
            loss = fit_kernels.view_gradients(gs, view, target, weights, grads, clock)
            if k_active:
                fit_sh.sh_backward(st.pos, st.col, st.sh_rest, k_active, centre, gparam)
                clock.lap("backward")
            t = step + 1
            hyper = AdamHyper(lr0 * decay, ADAM_BETA1, ADAM_BETA2, ADAM_EPS, ibc1_t, ibc2_t, t, lo, hi)
            adam_step(gparam, st.m1, st.m2, hyper, st.params(), seen, st.n_steps)
            if s.normal_offset_max_scales > 0:
                st.hold_to_surface()
            clock.lap("adam")
            losses.append(loss)
            step_scale.append(lv.scale)
            if s.densify_interval > 0 and t % s.densify_interval == 0 and t < s.densify_until_step:
                c, sp, pr = densify_and_prune(st, s, n_start, rng_split)
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
            if plateau or level_passes >= n_coarse:  # on to the fit scale, with a fresh plateau test
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

"""The keyframe fit's schedule: step counts grown with the keyframes, and Kerbl et al.'s adaptive
density control (clone, split, prune)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from atlas_pipeline.gaussian_world.fit_adam import CHILD_ID_BIT, FitState
from atlas_pipeline.geometry import quat_xyzw_to_rotmat

if TYPE_CHECKING:
    from atlas_pipeline.config import FitConfig

__all__ = ["COARSE_MAX_PASS_FRACTION", "MIN_COARSE_WIDTH_PX", "SPLIT_SCALE_DIV", "stretch_schedule",
           "coarse_passes", "densify_and_prune"]

SPLIT_SCALE_DIV = 1.6  # Kerbl et al.: the two halves of a split Gaussian have 1/1.6 of its scales
# The coarse level gets at most this share of the fit's passes: the fit scale must keep enough
# passes to restore the detail.
COARSE_MAX_PASS_FRACTION = 0.5
# No coarse level when its image would be narrower than this: a few dozen pixels hold no geometry
# worth fitting, and their larger steps only shake what the fit scale then has to undo.
MIN_COARSE_WIDTH_PX = 32


def stretch_schedule(s: FitConfig, n_views: int) -> FitConfig:
    """``s`` with its step counts grown for ``n_views`` keyframes (``min_steps_per_keyframe``): the
    cap, the coarse level's cap, the densification interval and end and the SH degree interval, all
    by the same factor
    ``min_steps_per_keyframe * n_views / max_steps`` when that exceeds 1; else ``s`` unchanged."""
    if s.max_steps is None or s.min_steps_per_keyframe <= 0 or s.min_steps_per_keyframe * n_views <= s.max_steps:
        return s
    k = s.min_steps_per_keyframe * n_views / s.max_steps
    return s.model_copy(update=dict(max_steps=s.min_steps_per_keyframe * n_views,
                                    coarse_max_steps=int(round(s.coarse_max_steps * k)),
                                    densify_interval=int(round(s.densify_interval * k)),
                                    densify_until_step=int(round(s.densify_until_step * k)),
                                    sh_degree_interval=int(round(s.sh_degree_interval * k))))


def coarse_passes(s: FitConfig, n_views: int, n_cap: int, coarse_width_px: float) -> int:
    """Whole passes at the coarse scale: at most ``coarse_max_steps`` steps and
    ``COARSE_MAX_PASS_FRACTION`` of the ``n_cap`` steps' passes; 0 without a coarse level (off, or
    its image narrower than ``MIN_COARSE_WIDTH_PX``)."""
    if not (s.coarse_max_steps > 0 and s.coarse_factor > 1 and coarse_width_px >= MIN_COARSE_WIDTH_PX):
        return 0
    return max(0, min(s.coarse_max_steps // n_views, int(n_cap // n_views * COARSE_MAX_PASS_FRACTION)))


def densify_and_prune(st: FitState, s: FitConfig, n_start: int,
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
        st.log_s[split] = np.log(sd / SPLIT_SCALE_DIV)
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

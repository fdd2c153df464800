"""The keyframe fit's schedule (atlas_pipeline/gaussian_world/optimize.py): early stop on a plateau,
coarse to fine, densification where the images are not explained, pruning of transparent Gaussians,
a truthful fit record without timings, and the same bits from the same inputs."""

from __future__ import annotations

import json

import numba
import numpy as np
import pytest

from atlas_pipeline.config import FitConfig
from atlas_pipeline.gaussian_world import fit_kernels, fit_levels
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.gaussian_world.optimize import (
    CHILD_ID_BIT, FIT_STAGES, STOP_EPOCHS, STOP_PLATEAU, STOP_STEP_CAP, optimize_gaussians,
)
from atlas_pipeline.gaussian_world.render import render_gaussians

QUIET = {"log": lambda _: None}
OFF = {"coarse_max_steps": 0, "plateau_patience": 0, "densify_interval": 0}  # every extra off


def _targets(field: GaussianField, manifest, idx):
    cam = manifest.camera
    out = []
    for i in idx:
        r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                             manifest.T_world_cam_gt[i], cam.K, cam.width, cam.height)
        out.append((r.rgb, r.depth_m.astype(np.float64), manifest.T_world_cam_gt[i]))
    return [t[0] for t in out], [t[1] for t in out], [t[2] for t in out], cam.K


def _jitter(f: GaussianField, seed: int) -> GaussianField:
    rng = np.random.default_rng(seed)
    return GaussianField(f.positions + rng.normal(0, 0.005, f.positions.shape), f.scales * 1.3, f.rotations_xyzw,
                         np.clip(f.colors.astype(int) + rng.integers(-30, 30, f.colors.shape), 0, 255),
                         f.opacities, f.ids)


# --------------------------------------------------------------------------------------------
# Early stop, coarse to fine
# --------------------------------------------------------------------------------------------


def _plateau_stop(means: np.ndarray, patience: int, rel_tol: float) -> int:
    """The pass (1-based) at which the documented rule stops: ``patience`` passes in a row that do not
    beat the best mean so far by ``rel_tol`` (relative); 0 = never."""
    best, stale = np.inf, 0
    for k, m in enumerate(means):
        best, stale = (m, 0) if m < best * (1 - rel_tol) else (best, stale + 1)
        if stale >= patience:
            return k + 1
    return 0


def test_early_stop_fires_on_a_plateau(small_manifest, small_world):
    """A fit that cannot move (step sizes 0) stops after the first pass and ``patience`` passes
    without progress. A real one stops where the rule says, applied to the passes of the same fit
    run without a patience: the early-stopped fit is that fit's prefix, bit for bit."""
    imgs, deps, poses, K = _targets(_jitter(small_world, 3), small_manifest, [0, 4, 8])
    frozen = FitConfig(epochs=30, max_steps=None, coarse_max_steps=0, densify_interval=0,
                                  plateau_patience=2, lr_position_m=0.0, lr_log_scale=0.0, lr_rotation_rad=0.0,
                                  lr_opacity_logit=0.0, lr_color=0.0)
    res = optimize_gaussians(small_world, imgs, deps, poses, K, frozen, **QUIET)
    assert res.record["stop_reason"] == STOP_PLATEAU
    assert res.record["epochs"] == 3 and res.record["steps"] == 9 == len(res.loss)
    means = res.loss.reshape(-1, 3).mean(axis=1)
    assert np.ptp(means) < 1e-6 * means[0]  # float32 state: the first step may renormalise a bit

    full = optimize_gaussians(small_world, imgs, deps, poses, K, FitConfig(epochs=12, **OFF), **QUIET)
    assert full.record["stop_reason"] == STOP_EPOCHS and full.record["epochs"] == 12
    means = full.loss.reshape(-1, 3).mean(axis=1)
    assert means[-1] < 0.5 * means[0]  # it does learn
    stop = _plateau_stop(means, 1, 0.25)
    assert 2 <= stop < 12
    early = optimize_gaussians(small_world, imgs, deps, poses, K,
                               FitConfig(epochs=12, **{**OFF, "plateau_patience": 1, "plateau_rel_tol": 0.25}),
                               **QUIET)
    assert early.record["stop_reason"] == STOP_PLATEAU and early.record["epochs"] == stop
    assert np.array_equal(early.loss, full.loss[: 3 * stop])
    assert early.record["final_loss"] == pytest.approx(means[stop - 1], rel=1e-5)


def test_step_cap_is_reported_with_the_partial_pass(small_manifest, small_world):
    imgs, deps, poses, K = _targets(small_world, small_manifest, [0, 4, 8])
    res = optimize_gaussians(small_world, imgs, deps, poses, K, FitConfig(epochs=10, max_steps=7, min_steps_per_keyframe=0, **OFF),
                             **QUIET)
    assert res.record["stop_reason"] == STOP_STEP_CAP and res.record["steps"] == 7
    assert res.record["epochs"] == 3  # two whole passes and one begun


def test_coarse_to_fine_changes_scale(small_manifest, small_world, monkeypatch):
    """The first passes render at scale / coarse_factor (40x30 for the 160x120 frames), the rest at the fit
    scale (80x60); the record says how many ran where."""
    imgs, deps, poses, K = _targets(_jitter(small_world, 0), small_manifest, [0, 4, 8])
    sizes = []
    inner = fit_kernels.view_gradients

    def spy(gaussians, view, target, *args, **kwargs):
        sizes.append((view.width, view.height, target.image.shape[:2]))
        return inner(gaussians, view, target, *args, **kwargs)

    monkeypatch.setattr(fit_kernels, "view_gradients", spy)
    s = FitConfig(epochs=6, max_steps=None, scale=0.5, coarse_factor=2, coarse_max_steps=9,
                             plateau_patience=0, densify_interval=0)
    res = optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET)
    assert sizes[:9] == [(40, 30, (30, 40))] * 9 and sizes[9:] == [(80, 60, (60, 80))] * 9
    assert np.array_equal(res.step_scale, [0.25] * 9 + [0.5] * 9)
    coarse = res.record["coarse"]
    assert coarse["scale"] == 0.25 and coarse["steps"] == 9 and coarse["epochs"] == 3
    assert res.record["epochs"] == 6 and res.record["steps"] == 18
    # the coarse level also ends when its loss stops falling: here after one stale pass
    s1 = FitConfig(epochs=6, max_steps=None, scale=0.5, coarse_factor=2, coarse_max_steps=100,
                              plateau_patience=1, plateau_rel_tol=0.9, densify_interval=0)
    res1 = optimize_gaussians(small_world, imgs, deps, poses, K, s1, **QUIET)
    assert res1.record["coarse"]["epochs"] == 2 and res1.step_scale[6] == 0.5


# --------------------------------------------------------------------------------------------
# Densification and pruning
# --------------------------------------------------------------------------------------------

K_TINY = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
W, H = 64, 48


def _wall(extra: GaussianField | None = None) -> GaussianField:
    """A grey wall of flat Gaussians 1.2 m in front of the camera, 2 cm apart, filling the view."""
    xs, ys = np.meshgrid(np.arange(-0.7, 0.71, 0.02), np.arange(-0.52, 0.53, 0.02))
    n = xs.size
    pos = np.c_[xs.ravel(), ys.ravel(), np.full(n, 1.2)]
    f = GaussianField(pos, np.tile([0.012, 0.012, 0.002], (n, 1)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
                      np.full((n, 3), 128), np.full(n, 0.9), np.arange(n, dtype=np.uint64) + 1)
    if extra is None:
        return f
    return GaussianField(*(np.concatenate([getattr(f, k), getattr(extra, k)])
                           for k in ("positions", "scales", "rotations_xyzw", "colors", "opacities", "ids")))


def _wall_views(field: GaussianField, textured: bool):
    """Three views of the wall; with ``textured`` the right third of each image shows a 2-pixel
    checkerboard that the grey Gaussians cannot explain, the rest is the wall's own render."""
    imgs, deps, poses = [], [], []
    for dx in (-0.02, 0.0, 0.02):
        T = np.eye(4)
        T[0, 3] = dx
        r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                             T, K_TINY, W, H)
        img = r.rgb.copy()
        if textured:
            yy, xx = np.mgrid[0:H, 0:W]
            check = ((xx // 2 + yy // 2) % 2 * 255).astype(np.uint8)
            img[:, 44:] = check[:, 44:, None]
        imgs.append(img)
        deps.append(r.depth_m.astype(np.float64))
        poses.append(T)
    return imgs, deps, poses


def _u_of(positions: np.ndarray) -> np.ndarray:
    return K_TINY[0, 0] * positions[:, 0] / positions[:, 2] + K_TINY[0, 2]


def test_densification_adds_gaussians_where_the_image_is_unexplained():
    """Clones and splits go where the positional gradient stays large: into the textured third,
    hardly anywhere on the part of the wall the Gaussians already render exactly."""
    wall = _wall()
    imgs, deps, poses = _wall_views(wall, textured=True)
    # on the plain wall 99 % of the Gaussians' mean NDC gradients stay under 2.6e-4, in the texture
    # the upper third of them exceeds 4e-4 (measured)
    s = FitConfig(epochs=6, max_steps=None, scale=1.0, densify_interval=3, densify_until_step=4,
                             densify_grad_threshold=3.5e-4, densify_scale_m=0.01, densify_max_growth=3.0,
                             prune_opacity=0.0, coarse_max_steps=0, plateau_patience=0)
    res = optimize_gaussians(wall, imgs, deps, poses, K_TINY, s, **QUIET)
    rec = res.record
    new = (res.field.ids & CHILD_ID_BIT) != 0
    assert rec["n_cloned"] + rec["n_split"] == new.sum() > 50 and rec["n_split"] > 0  # one round, after 3 steps
    u = _u_of(res.field.positions[new])
    assert np.mean(u > 40) > 0.9  # the textured third starts at u = 44 (and views shift by ~1 px)
    assert len(np.unique(res.field.ids)) == len(res.field)  # ids stay unique
    # the same wall with images it explains: hardly any densification
    plain = optimize_gaussians(wall, *_wall_views(wall, textured=False), K_TINY, s, **QUIET)
    assert plain.record["n_cloned"] + plain.record["n_split"] < 0.1 * new.sum()


def test_pruning_removes_transparent_gaussians():
    """Gaussians at opacity 0.0042 (above the 1/255 a render needs, below prune_opacity 0.005),
    behind the camera so no gradient moves them: a densify round removes them, without one they stay."""
    n = 5
    ghosts = GaussianField(np.c_[np.linspace(-0.1, 0.1, n), np.zeros(n), np.full(n, -1.0)],
                           np.full((n, 3), 0.01), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), np.full((n, 3), 200),
                           np.full(n, 0.0042), np.arange(n, dtype=np.uint64) + 100_000)
    field = _wall(ghosts)
    imgs, deps, poses = _wall_views(_wall(), textured=False)
    base = dict(epochs=2, max_steps=None, scale=1.0, coarse_max_steps=0, plateau_patience=0)
    pruned = optimize_gaussians(field, imgs, deps, poses, K_TINY,
                                FitConfig(densify_interval=2, densify_grad_threshold=1e9, **base), **QUIET)
    kept = optimize_gaussians(field, imgs, deps, poses, K_TINY, FitConfig(densify_interval=0, **base),
                              **QUIET)
    assert not np.isin(ghosts.ids, pruned.field.ids).any() and pruned.record["n_pruned"] >= n
    assert np.isin(ghosts.ids, kept.field.ids).all() and kept.record["n_pruned"] == 0
    assert pruned.record["n_cloned"] == pruned.record["n_split"] == 0


# --------------------------------------------------------------------------------------------
# Record, determinism
# --------------------------------------------------------------------------------------------


def test_record_is_the_truth_and_holds_no_timings(small_manifest, small_world):
    imgs, deps, poses, K = _targets(_jitter(small_world, 1), small_manifest, [0, 4, 8])
    s = FitConfig(epochs=5, max_steps=None, coarse_max_steps=6, plateau_patience=0, densify_interval=4,
                             densify_until_step=12)
    res = optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET)
    rec = res.record
    json.dumps(rec)  # JSON-ready
    assert not any("second" in k or "time" in k or k.endswith("_s") for k in rec)
    assert rec["steps"] == len(res.loss) == 15 and rec["epochs"] == 5 and rec["stop_reason"] == STOP_EPOCHS
    assert rec["coarse"]["steps"] == 6 and rec["coarse"]["epochs"] == 2
    assert rec["final_loss"] == pytest.approx(res.loss[-3:].mean(), rel=1e-5)
    assert rec["loss_first_epoch"] == pytest.approx(res.loss[6:9].mean(), rel=1e-5)  # first pass at the fit scale
    assert rec["n_gaussians_start"] == len(small_world)
    assert rec["n_gaussians_end"] == len(res.field) == (len(small_world) + rec["n_cloned"] + rec["n_split"]
                                                        - rec["n_pruned"])
    # timings are returned beside the record
    assert set(res.stage_cpu_s) == set(FIT_STAGES) and res.cpu_seconds > 0 and res.seconds > 0


def test_same_inputs_same_world_bits_whatever_the_threads(small_manifest, small_world):
    imgs, deps, poses, K = _targets(_jitter(small_world, 2), small_manifest, [0, 6])
    s = FitConfig(epochs=6, max_steps=None, coarse_max_steps=4, densify_interval=3,
                             densify_until_step=10, densify_grad_threshold=5e-5)
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in (before, before, 1):
            numba.set_num_threads(threads)
            runs.append(optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET))
    finally:
        numba.set_num_threads(before)
    assert runs[0].record["n_cloned"] + runs[0].record["n_split"] > 0  # the densification ran
    for r in runs[1:]:
        assert r.field.content_hash() == runs[0].field.content_hash()
        assert r.record == runs[0].record and np.array_equal(r.loss, runs[0].loss)


def test_input_field_is_left_alone(small_manifest, small_world):
    imgs, deps, poses, K = _targets(small_world, small_manifest, [0])
    h = small_world.content_hash()
    optimize_gaussians(small_world, imgs, deps, poses, K, FitConfig(epochs=2, **OFF), **QUIET)
    assert small_world.content_hash() == h


def test_profile_defaults_are_the_fits_defaults():
    from atlas_pipeline.config import load_profile

    assert load_profile("default").mapping.fit == FitConfig()


def test_a_schedule_without_coarse_level_or_densification_runs_every_step_at_the_fit_scale(
        small_manifest, small_world):
    imgs, deps, poses, K = _targets(_jitter(small_world, 4), small_manifest, [0, 4])
    s = FitConfig(epochs=3, max_steps=600, min_steps_per_keyframe=0, coarse_factor=1, coarse_max_steps=0,
                             plateau_patience=0, densify_interval=0, selective_adam=False)
    res = optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET)
    assert np.array_equal(res.step_scale, [0.5] * 6) and res.record["coarse"] is None
    assert res.record["stop_reason"] == STOP_EPOCHS and res.record["n_cloned"] == res.record["n_split"] == 0
    assert np.isin(res.field.ids, small_world.ids).all()


def test_long_sequences_get_proportionally_more_steps():
    """The step budget grows with the keyframes past max_steps / min_steps_per_keyframe, and
    the schedule's step counts with it; below that nothing changes."""
    from atlas_pipeline.gaussian_world.optimize import stretch_schedule

    s = FitConfig(max_steps=300, min_steps_per_keyframe=10, coarse_max_steps=160, densify_interval=50,
                             densify_until_step=160)
    assert stretch_schedule(s, 30) is s and stretch_schedule(s, 4) is s
    long = stretch_schedule(s, 120)  # 4x the keyframes the cap covers
    assert (long.max_steps, long.coarse_max_steps, long.densify_interval, long.densify_until_step) == (1200, 640, 200, 640)
    assert stretch_schedule(FitConfig(max_steps=300, min_steps_per_keyframe=0), 1000).max_steps == 300
    assert stretch_schedule(FitConfig(max_steps=None, min_steps_per_keyframe=10), 1000).max_steps is None


def test_fit_inputs_read_on_demand_give_the_same_world(small_manifest, monkeypatch):
    """Above the memory budget the keyframes are re-read at each use instead of held: same world."""
    import atlas_pipeline.mapping.mapper as mapper
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.perception.rgbd import fuse

    cfg = load_profile("default").with_overrides({"mapping.fit.epochs": 2})
    fused = fuse(small_manifest, cfg)
    kf = mapper.select_keyframes_stage(small_manifest, fused, cfg)
    held = mapper.build_gaussian_world(fused, kf, cfg, manifest=small_manifest)
    reads = []
    real = small_manifest.read_rgb
    monkeypatch.setattr(small_manifest, "read_rgb", lambda i: reads.append(i) or real(i))
    monkeypatch.setattr(mapper, "FIT_INPUT_MEMORY_BUDGET_BYTES", 0)
    streamed = mapper.build_gaussian_world(fused, kf, cfg, manifest=small_manifest)
    assert streamed.field.equals(held.field) and streamed.fit == held.fit
    assert len(reads) > 2 * len(kf.indices)  # read again at each use, not held


def test_levels_made_per_view_give_the_same_fit(small_manifest, small_world, monkeypatch):
    """Above LEVEL_MEMORY_BUDGET_BYTES each view's working copy is made when its step needs it:
    bit-identical fit, nothing held."""
    imgs, deps, poses, K = _targets(_jitter(small_world, 4), small_manifest, [0, 4, 8])
    s = FitConfig(epochs=4, max_steps=None, scale=0.5, coarse_factor=2, coarse_max_steps=3,
                             plateau_patience=0, densify_interval=5, densify_until_step=10)
    held = optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET)
    monkeypatch.setattr(fit_levels, "LEVEL_MEMORY_BUDGET_BYTES", 0)
    made = []
    real = fit_levels.OnDemandViews.__init__

    def spy(self, n, make):
        made.append(n)
        real(self, n, make)

    monkeypatch.setattr(fit_levels.OnDemandViews, "__init__", spy)
    lazy = optimize_gaussians(small_world, imgs, deps, poses, K, s, **QUIET)
    assert made  # the on-demand path ran
    assert lazy.field.equals(held.field) and np.array_equal(lazy.loss, held.loss) and lazy.record == held.record

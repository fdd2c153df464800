"""Keyframe optimisation of the Gaussians: analytic gradients against finite differences on tiny
seeded scenes, the compiled tile kernels against their NumPy reference, descent on a small synthetic
world, determinism, bad settings. (The schedule: tests/test_fit_schedule.py.)"""

import numba
import numpy as np
import pytest

from atlas_pipeline.gaussian_world import fit_adam, fit_kernels
from atlas_pipeline.gaussian_world import raster as rc
from atlas_pipeline.gaussian_world._raster_reference import fit_gradients_reference, project_reference
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.gaussian_world.fit_kernels import LossWeights
from atlas_pipeline.config import FitConfig
from atlas_pipeline.gaussian_world.optimize import optimize_gaussians, render_loss_and_gradients
from atlas_pipeline.gaussian_world.raster import GaussianArrays, scale_intrinsics
from atlas_pipeline.gaussian_world.render import render_gaussians

K_TINY = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])


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
    k = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)  # sin(half)/angle -> 1/2
    return np.concatenate([w * k[:, None], np.cos(half)[:, None]], axis=1)


def _tiny_scene(seed: int, n: int = 24, opacity=(0.3, 0.9)):
    rng = np.random.default_rng(seed)
    pos = rng.uniform([-0.3, -0.25, 1.0], [0.3, 0.25, 1.6], (n, 3))
    scl = rng.uniform(0.02, 0.06, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    col = rng.uniform(0, 1, (n, 3))
    op = rng.uniform(*opacity, n)
    T = np.eye(4)
    T[:3, 3] = [0.02, -0.01, 0.05]
    img = rng.uniform(0, 1, (48, 64, 3))
    dep = rng.uniform(1.0, 2.0, (48, 64))
    dep[::3] = 0.0  # rows without a reading
    return pos, scl, q, col, op, T, img, dep


def _loss(pos, scl, q, col, op, T, img, dep):
    return render_loss_and_gradients(GaussianArrays(pos, scl, q, col, op), T, K_TINY, img, dep, LossWeights(1.0, 0.5))


def _central(f, eps):
    return (f(eps) - f(-eps)) / (2 * eps)


def test_gradients_of_appearance_and_shape_match_finite_differences():
    """Colour, opacity logit, log scale and rotation: the loss is smooth in them, so central
    differences agree to well under a percent (float32 image-space features limit it)."""
    pos, scl, q, col, op, T, img, dep = _tiny_scene(0)
    _, g = _loss(pos, scl, q, col, op, T, img, dep)
    eps = 1e-4
    checked = 0
    for i in range(0, 24, 5):
        def f_col(e, i=i):
            c = col.copy()
            c[i, 1] += e
            return _loss(pos, scl, q, c, op, T, img, dep)[0]

        def f_logit(e, i=i):
            o = op.copy()
            lg = np.log(o[i] / (1 - o[i])) + e
            o[i] = 1 / (1 + np.exp(-lg))
            return _loss(pos, scl, q, col, o, T, img, dep)[0]

        pairs = [(f_col, g["color"][i, 1]), (f_logit, g["logit"][i])]
        for c in range(3):
            def f_scale(e, i=i, c=c):
                s = scl.copy()
                s[i, c] *= np.exp(e)
                return _loss(pos, s, q, col, op, T, img, dep)[0]

            def f_rot(e, i=i, c=c):
                w = np.zeros((len(q), 3))
                w[i, c] = e
                return _loss(pos, scl, _quat_mul_xyzw(q, _rotvec_to_quat_xyzw(w)), col, op, T, img, dep)[0]

            pairs += [(f_scale, g["log_scale"][i, c]), (f_rot, g["rotation"][i, c])]
        for f, analytic in pairs:
            num = _central(f, eps)
            if abs(num) < 1e-6 and abs(analytic) < 1e-6:
                continue  # Gaussian outside the view or in a flat spot
            assert analytic == pytest.approx(num, rel=0.02, abs=2e-6)
            checked += 1
    assert checked >= 20


def test_position_gradient_matches_finite_differences_where_footprints_are_smooth():
    """Moving a mean also moves its integer pixel footprint (a discontinuity the analytic gradient
    rightly ignores); with faint Gaussians the footprint's edge sits at alpha = 1/255, so the jumps
    are small and central differences agree except where one happens inside the step."""
    pos, scl, q, col, op, T, img, dep = _tiny_scene(1, opacity=(0.15, 0.3))
    _, g = _loss(pos, scl, q, col, op, T, img, dep)
    num = np.zeros((len(pos), 3))
    for i in range(len(pos)):
        for c in range(3):
            def f(e, i=i, c=c):
                p = pos.copy()
                p[i, c] += e
                return _loss(p, scl, q, col, op, T, img, dep)[0]
            num[i, c] = _central(f, 1e-4)
    a, n = g["position"].ravel(), num.ravel()
    seen = np.abs(a) > 1e-5
    assert seen.sum() >= 40
    rel = np.abs(n[seen] - a[seen]) / np.abs(a[seen])
    # nearly every entry agrees to 1e-3; a few catch a footprint jump (a pixel row entering)
    assert np.median(rel) < 1e-3 and np.mean(rel < 0.05) > 0.8


def _flat_scene(seed: int, n: int = 60):
    """A tiny scene with overlapping Gaussians, a third of them flat (their depth slopes act), some
    nearly opaque (capped alphas, terminated pixels)."""
    pos, scl, q, col, op, T, img, dep = _tiny_scene(seed, n, opacity=(0.2, 0.95))
    scl[::3, 2] = 0.004
    op[1::7] = 0.999
    return pos, scl, q, col, op, T, img, dep


def _compiled_image_gradients(pos, scl, q, col, op, T, img, dep, w_rgb, w_depth, w_cover, n_workers=3, limit=None):
    """The fit's compiled forward and tile backward on one view: ``(splats, loss, g2d [M, 10], slopes)``
    with ``g2d`` each sorted Gaussian's pair slots summed."""
    h, w = img.shape[:2]
    f32 = [np.ascontiguousarray(a, np.float32) for a in (pos, scl, q, col, op)]
    sp = rc.prepare_splats(*f32, rc.view_from_pose(T, K_TINY, w, h), rc.NEAR_M, keep_aux=True)
    slot, start = rc.pair_slots(sp.box, sp.tile_start, sp.tiles_x)
    npix = float(w * h)
    target = fit_kernels.FitTarget(np.float32(img), np.float32(dep), np.ones(dep.shape, np.float32),
                                   np.full(dep.shape, np.inf, np.float32) if limit is None else np.float32(limit),
                                   np.zeros(3))
    weights = fit_kernels.LossWeights(w_rgb / npix, w_depth / npix, w_cover / npix)
    loss, dout, k_end = fit_kernels.forward_tiles(sp, target, weights, n_workers)
    pair = fit_kernels.backward_tiles(sp, slot, k_end, dout, n_workers)
    g2d = np.array([pair[start[k]:start[k + 1]].astype(np.float64).sum(axis=0) for k in range(len(sp.order))])
    slopes = sp.aux[sp.order][:, [rc.AUX_SLOPE_U, rc.AUX_SLOPE_V]].astype(np.float32).astype(np.float64)
    return sp, loss, g2d, slopes


@pytest.mark.parametrize("seed", [0, 3])
def test_tile_kernels_match_the_numpy_reference(seed):
    """The compiled forward (loss) and the slot-per-pair tile backward (image-space gradient of every
    Gaussian: u, v, conic, opacity, colour, depth) against ``fit_gradients_reference``, the textbook
    prefix-sum form in float64. The kernels run float32 with a polynomial exp (2e-6 relative), so
    entries agree to ~1e-6 of each column's scale; a pixel whose alpha or transmittance lands on the
    other side of a threshold would show as one larger difference."""
    pos, scl, q, col, op, T, img, dep = _flat_scene(seed)
    sp, loss, g2d, slopes = _compiled_image_gradients(pos, scl, q, col, op, T, img, dep, 1.0, 0.5, 2.0)
    assert (np.abs(slopes) > 0).any(axis=1).sum() >= 5  # the plane depths are exercised
    npix = float(img.shape[0] * img.shape[1])
    ref_loss, ref = fit_gradients_reference(sp.feat.astype(np.float64), slopes, sp.box, img, dep, 1.0 / npix,
                                            0.5 / npix, 2.0 / npix)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    scale = np.abs(ref).max(axis=0)
    assert (scale > 0).all()
    err = np.abs(g2d - ref) / scale
    assert np.quantile(err, 0.99) < 1e-5 and err.max() < 1e-3  # measured: under 1e-6


@pytest.mark.parametrize("seed", [0, 3])
def test_coverage_band_counts_only_the_measured_surface(seed):
    """With a depth limit per pixel (the reading plus a band), the coverage term is the transmittance
    through the Gaussians whose plane depth is within it: the compiled kernels against the float64
    reference; with every limit before the Gaussians, the term is the whole coverage weight and moves
    nothing."""
    pos, scl, q, col, op, T, img, dep = _flat_scene(seed)
    seen = dep > 0
    limit = np.where(seen, np.float32(dep) + np.float32(0.02), np.float32(0.0))
    sp, loss, g2d, slopes = _compiled_image_gradients(pos, scl, q, col, op, T, img, dep, 0.0, 0.0, 2.0, limit=limit)
    npix = float(img.shape[0] * img.shape[1])
    feat = sp.feat.astype(np.float64)
    ref_loss, ref = fit_gradients_reference(feat, slopes, sp.box, img, dep, 0.0, 0.0, 2.0 / npix,
                                            depth_limit=limit.astype(np.float64))
    full_loss, _ = fit_gradients_reference(feat, slopes, sp.box, img, dep, 0.0, 0.0, 2.0 / npix)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    assert ref_loss > full_loss  # fewer Gaussians count: more transmittance left
    scale = np.abs(ref).max(axis=0)
    live = scale > 0
    err = np.abs(g2d[:, live] - ref[:, live]) / scale[live]
    assert np.quantile(err, 0.99) < 1e-5 and err.max() < 1e-3
    # limits before every Gaussian: nothing stands for the surfaces, full transmittance, no gradient
    _, loss0, g0, _ = _compiled_image_gradients(pos, scl, q, col, op, T, img, dep, 0.0, 0.0, 2.0,
                                                limit=np.zeros(dep.shape, np.float32))
    assert loss0 == pytest.approx(2.0 * seen.sum() / npix) and np.all(g0 == 0.0)


def test_projection_keeps_what_the_backward_pass_needs():
    """``keep_aux``: the camera-frame mean, ``J W``, the pixel covariance and the plane's depth slopes of
    every drawn Gaussian, as the NumPy reference computes them; the renderer's outputs unchanged."""
    pos, scl, q, col, op, T, _, _ = _flat_scene(1)
    f64 = [np.asarray(a, np.float64) for a in (pos, scl, q, col * 255, op)]
    view = rc.view_from_pose(T, K_TINY, 64, 48)
    fast = rc.project_gaussians(*f64, view, rc.NEAR_M, keep_aux=True)
    plain = rc.project_gaussians(*f64, view, rc.NEAR_M)
    assert plain.aux.shape == (0, rc.N_AUX)
    np.testing.assert_array_equal(fast.feat, plain.feat)
    np.testing.assert_array_equal(fast.box, plain.box)
    ref = project_reference(*f64, T, K_TINY, 64, 48)
    v = fast.valid
    a = fast.aux[v]
    np.testing.assert_allclose(a[:, [rc.AUX_X, rc.AUX_Y, rc.AUX_Z]],
                               (pos[v] - T[:3, 3]) @ T[:3, :3], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a[:, rc.AUX_P:rc.AUX_P + 6].reshape(-1, 2, 3), ref.jw[v], rtol=1e-10, atol=1e-10)
    cov = ref.cov2d[v]
    np.testing.assert_allclose(a[:, [rc.AUX_CXX, rc.AUX_CXY, rc.AUX_CYY]],
                               np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], axis=1), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a[:, [rc.AUX_SLOPE_U, rc.AUX_SLOPE_V]], ref.slopes[v], rtol=1e-9, atol=1e-12)
    assert (np.abs(ref.slopes[v]) > 0).any(axis=1).sum() >= 5


def test_pair_slots_number_each_gaussians_tiles_in_order():
    pos, scl, q, col, op, T, _, _ = _flat_scene(2)
    scl *= 3.0  # footprints over several tiles
    sp = rc.prepare_splats(*[np.float32(a) for a in (pos, scl, q, col, op)], rc.view_from_pose(T, K_TINY, 61, 37))
    slot, start = rc.pair_slots(sp.box, sp.tile_start, sp.tiles_x)
    p = len(sp.tile_ids)
    assert np.array_equal(np.sort(slot), np.arange(p)) and start[0] == 0 and start[-1] == p
    owner = np.searchsorted(start, slot, side="right") - 1  # the Gaussian each slot belongs to
    assert np.array_equal(owner, sp.tile_ids)
    tile_of = np.repeat(np.arange(sp.n_tiles), np.diff(sp.tile_start))
    by_slot = np.empty(p, np.int64)
    by_slot[slot] = tile_of
    for g in range(len(sp.order)):  # a Gaussian's slots go through its tiles in row-major order
        assert np.all(np.diff(by_slot[start[g]:start[g + 1]]) > 0)
    assert (np.diff(start) > 1).sum() >= 5


def test_gradients_do_not_depend_on_the_thread_count():
    pos, scl, q, col, op, T, img, dep = _flat_scene(4)
    before = numba.get_num_threads()
    out = []
    try:
        for threads in (1, before):
            numba.set_num_threads(threads)
            out.append(render_loss_and_gradients(GaussianArrays(pos, scl, q, col, op), T, K_TINY, img, dep,
                                                      LossWeights(1.0, 0.5, 2.0)))
    finally:
        numba.set_num_threads(before)
    (l1, g1), (l2, g2) = out
    assert l1 == l2 and all(np.array_equal(g1[k], g2[k]) for k in g1)


def test_loss_counts_the_background_without_gaussians():
    _, _, _, _, _, T, img, dep = _tiny_scene(2)
    z = np.zeros((0, 3))
    loss, g = render_loss_and_gradients(GaussianArrays(z, z, np.zeros((0, 4)), z, np.zeros(0)), T, K_TINY, img, dep,
                                         LossWeights(1.0, 0.5))
    expect = np.abs(img).sum() / (48 * 64)  # black background; no rendered depth to compare
    assert loss == pytest.approx(expect) and g["position"].shape == (0, 3)


def test_scaled_intrinsics_keep_pixel_centres():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    Ks = scale_intrinsics(K, 0.5, 0.5)
    # the image centre (319.5, 239.5) at full size is the centre (159.5, 119.5) at half size
    assert Ks[0, 2] == pytest.approx(159.5) and Ks[1, 2] == pytest.approx(119.5) and Ks[0, 0] == 250.0


def _views(field, manifest, idx):
    cam = manifest.camera
    out = []
    for i in idx:
        r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                             manifest.T_world_cam_gt[i], cam.K, cam.width, cam.height)
        out.append((r.rgb, r.depth_m.astype(np.float64)))
    return out


def _perturbed(f: GaussianField, seed: int) -> GaussianField:
    rng = np.random.default_rng(seed)
    return GaussianField(f.positions + rng.normal(0, 0.01, f.positions.shape), f.scales * 1.6, f.rotations_xyzw,
                         np.clip(f.colors.astype(int) + rng.integers(-50, 50, f.colors.shape), 0, 255),
                         np.clip(f.opacities * 0.5, 0.05, 1.0), f.ids)


# Every step at the full image, no coarse level, early stop or densification: plain descent.
FIRST_SCHEDULE = FitConfig(epochs=15, max_steps=600, min_steps_per_keyframe=0, scale=1.0, coarse_factor=1,
                                      coarse_max_steps=0, plateau_patience=0, densify_interval=0,
                                      selective_adam=False)


@pytest.mark.slow
def test_optimisation_recovers_a_perturbed_world(small_manifest, small_world):
    """Views rendered from the true field are the targets; a field with wrong colours, scales,
    opacities and jittered means, fitted to a few of them, renders a held-out view much closer."""
    from atlas_pipeline.gaussian_world.evaluation import psnr

    truth = small_world
    train, held = [0, 3, 6, 9], [5]
    targets = _views(truth, small_manifest, train)
    start = _perturbed(truth, 0)
    res = optimize_gaussians(start, [t[0] for t in targets], [t[1] for t in targets],
                             [small_manifest.T_world_cam_gt[i] for i in train], small_manifest.camera.K,
                             FIRST_SCHEDULE, log=lambda _: None)
    assert len(res.loss) == 60 and res.loss[-4:].mean() < 0.5 * res.loss[:4].mean()
    # ids survive the fit (only Gaussians that became invisible may go)
    assert np.isin(res.field.ids, truth.ids).all() and len(res.field) == len(truth) - res.n_pruned
    assert res.n_pruned < 0.05 * len(truth)
    (real, _), = _views(truth, small_manifest, held)
    (before, _), = _views(start, small_manifest, held)
    (after, _), = _views(res.field, small_manifest, held)
    assert psnr(real, after) > psnr(real, before) + 4.0


def test_optimisation_is_deterministic(small_manifest, small_world):
    train = [0, 6]
    targets = _views(small_world, small_manifest, train)
    start = _perturbed(small_world, 1)
    args = (start, [t[0] for t in targets], [t[1] for t in targets], [small_manifest.T_world_cam_gt[i] for i in train],
            small_manifest.camera.K, FitConfig(epochs=2, scale=0.5))
    a = optimize_gaussians(*args, log=lambda _: None).field
    b = optimize_gaussians(*args, log=lambda _: None).field
    assert a.content_hash() == b.content_hash()


def test_bad_settings_and_inputs_are_refused(small_world):
    img = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(ValueError, match="1/n"):
        optimize_gaussians(small_world, [img], [np.zeros((120, 160))], [np.eye(4)], K_TINY,
                           FitConfig(scale=0.3))
    with pytest.raises(ValueError, match="one depth image and one pose"):
        optimize_gaussians(small_world, [img], [], [np.eye(4)], K_TINY)
    with pytest.raises(ValueError, match="view 1: image"):
        optimize_gaussians(small_world, [img, img[:60]], [np.zeros((120, 160))] * 2, [np.eye(4)] * 2, K_TINY)
    with pytest.raises(ValueError, match="view 0: pose"):
        optimize_gaussians(small_world, [img], [np.zeros((120, 160))], [np.full((4, 4), np.nan)], K_TINY)


def test_profile_refuses_an_unusable_optimisation_scale():
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="fit.scale"):
        load_profile("default").with_overrides({"mapping.fit.scale": 0.3})


@pytest.mark.slow
def test_pipeline_fits_the_world_to_its_keyframes_and_records_it(small_manifest, tmp_path):
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.localization.localizer import tracking_map
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    cfg = load_profile("default").with_overrides({"mapping.fit.epochs": 3,
                                                  "mapping.fit.coarse_max_steps": 4})
    fused = fuse(small_manifest, cfg)
    kf = select_keyframes_stage(small_manifest, fused, cfg)
    world = build_gaussian_world(fused, kf, cfg, manifest=small_manifest)
    fit = world.fit  # the fit's own record (OptimizationResult.record): what ran, why it stopped, no timings
    assert len(world.keyframe_indices) == 4  # one coarse pass, two at the fit scale
    assert fit["steps"] == 12 and fit["epochs"] == 3 and fit["stop_reason"] == "epochs"
    assert fit["coarse"]["epochs"] == 1 and fit["final_loss"] < fit["loss_first_epoch"]  # both at the fit scale
    assert not any("second" in k or "time" in k for k in fit)
    world.save(tmp_path)
    back = GaussianWorld.load(tmp_path)
    assert back.fit == fit and back.field.equals(world.field)
    # the tracking map still comes from the voxel statistics, not from the moved Gaussians
    assert len(tracking_map(world)) == len(tracking_map(back)) > 0


def test_step_cap_bounds_the_work(small_manifest, small_world):
    train = [0, 3, 6]
    targets = _views(small_world, small_manifest, train)
    res = optimize_gaussians(small_world, [t[0] for t in targets], [t[1] for t in targets],
                             [small_manifest.T_world_cam_gt[i] for i in train], small_manifest.camera.K,
                             FitConfig(epochs=10, max_steps=7, min_steps_per_keyframe=0, scale=0.5), log=lambda _: None)
    assert len(res.loss) == 7  # two full passes and one view of a third


def test_normal_offset_bound_holds_centres_to_their_surface(small_manifest, small_world):
    """With ``normal_offset_max_scales`` every fitted centre stays within that many of its largest
    starting scales of where it began, along its starting normal; without it the same fit goes
    further (so the bound is what holds them)."""
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    train = [0, 4, 8]
    targets = _views(small_world, small_manifest, train)
    start = _perturbed(small_world, 2)
    args = (start, [t[0] for t in targets], [t[1] for t in targets], [small_manifest.T_world_cam_gt[i] for i in train],
            small_manifest.camera.K)
    bound = 0.1
    R = quat_xyzw_to_rotmat(start.rotations_xyzw.astype(np.float64))
    normal = R[np.arange(len(start)), :, np.argmin(start.scales, axis=1)]  # [N, 3]
    limit = bound * start.scales.max(axis=1)  # [N]

    def along_normal(fitted):
        row = {int(i): k for k, i in enumerate(start.ids)}
        kept = np.array([row[int(i)] for i in fitted.ids if int(i) in row])
        mine = np.isin(fitted.ids, start.ids)
        off = np.einsum("ij,ij->i", fitted.positions[mine] - start.positions[kept], normal[kept])
        return np.abs(off), limit[kept]

    held = optimize_gaussians(*args, FitConfig(epochs=4, scale=0.5, normal_offset_max_scales=bound),
                              log=lambda _: None).field
    free = optimize_gaussians(*args, FitConfig(epochs=4, scale=0.5), log=lambda _: None).field
    off, lim = along_normal(held)
    assert len(off) > 0.9 * len(start) and (off <= lim + 1e-5).all()
    off_free, lim_free = along_normal(free)
    assert (off_free > lim_free + 1e-5).mean() > 0.05


def test_profile_sets_the_normal_offset_bound():
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.errors import ConfigError

    cfg = load_profile("default").with_overrides({"mapping.fit.normal_offset_max_scales": 0.5})
    assert cfg.mapping.fit.normal_offset_max_scales == 0.5
    assert load_profile("default").mapping.fit.normal_offset_max_scales == 0.0
    with pytest.raises(ConfigError, match="normal_offset_max_scales"):
        load_profile("default").with_overrides({"mapping.fit.normal_offset_max_scales": -1})


def _adam_state(n: int, seed: int):
    """Random fit state of ``n`` Gaussians for ``_adam_step``: (gparam, m1, m2, params...)."""
    rng = np.random.default_rng(seed)
    P = fit_kernels.N_PARAM
    gparam = rng.normal(0, 1e-3, (P, n)).astype(np.float32)
    m1 = rng.normal(0, 1e-4, (P, n)).astype(np.float32)
    m2 = rng.uniform(1e-8, 1e-6, (P, n)).astype(np.float32)
    pos = rng.normal(0, 1, (n, 3)).astype(np.float32)
    log_s = rng.uniform(-4, -3, (n, 3)).astype(np.float32)
    q = rng.normal(size=(n, 4))
    quat = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    logit = rng.normal(0, 1, n).astype(np.float32)
    col = rng.uniform(0.2, 0.8, (n, 3)).astype(np.float32)
    return [gparam, m1, m2, pos, log_s, quat, logit, col, np.exp(log_s), 1 / (1 + np.exp(-logit))]


def _step(state, t, seen, n_steps, lr=None):
    gparam, m1, m2, pos, log_s, quat, logit, col, scl, opa = state
    lr = np.full(fit_kernels.N_PARAM, 1e-3) if lr is None else lr
    ibc1, ibc2 = fit_adam.bias_corrections(0.9, t), fit_adam.bias_corrections(0.999, t)
    hyper = fit_adam.AdamHyper(lr, 0.9, 0.999, 1e-15, ibc1, ibc2, t, np.log(1e-4), np.log(0.1))
    fit_adam.adam_step(gparam, m1, m2, hyper, fit_adam.FitParams(pos, log_s, quat, logit, col, scl, opa), seen, n_steps)


def test_selective_adam_leaves_unseen_gaussians_alone():
    """Selective Adam (the default): Gaussians the view did not draw keep their parameters and
    moments bit for bit; the drawn ones count a step and move."""
    n = 3 * fit_adam.ADAM_BLOCK + 17  # several blocks and a partial one
    state = _adam_state(n, 0)
    before = [a.copy() for a in state]
    seen = (np.random.default_rng(1).random(n) < 0.3).astype(np.uint8)
    n_steps = np.zeros(n, np.int32)
    _step(state, 500, seen, n_steps)
    off, on = seen == 0, seen == 1
    for a, b in zip(state[1:], before[1:]):  # moments and parameters
        axis_rows = a.shape[0] == fit_kernels.N_PARAM and a.ndim == 2
        sel_off = (slice(None), off) if axis_rows else off
        assert np.array_equal(a[sel_off], b[sel_off])
    assert np.array_equal(n_steps, seen.astype(np.int32))
    assert not np.allclose(state[3][on], before[3][on])  # positions moved


def test_selective_adam_corrects_bias_by_each_gaussians_own_steps():
    """A Gaussian's first step is the same whenever in the fit it comes (its own count), and is
    Adam's first step: -lr times the gradient's sign for zero moments."""
    n = 40
    state = _adam_state(n, 2)
    state[1][:] = 0.0
    state[2][:] = 0.0
    pos0 = state[3].copy()
    lr = np.full(fit_kernels.N_PARAM, 1e-3)
    _step(state, 5000, np.ones(n, np.uint8), np.zeros(n, np.int32), lr)  # a late global step
    expected = pos0 - 1e-3 * np.sign(state[0][fit_kernels.P_POS:fit_kernels.P_POS + 3].T)
    np.testing.assert_allclose(state[3], expected, atol=1e-6)


def test_dense_adam_is_standard_adam_with_the_fits_step():
    """Dense (empty seen): every Gaussian steps with the bias correction of the fit's step, unseen
    ones (zero gradient) moving on their momentum: the NumPy Adam update."""
    n = 50
    state = _adam_state(n, 3)
    g, m1, m2, pos = (a.astype(np.float64) for a in state[:4])
    g[:, ::2] = 0.0  # half the Gaussians unseen this step
    state[0][:, ::2] = 0.0
    t, b1, b2 = 7, 0.9, 0.999
    m1n, m2n = b1 * m1 + (1 - b1) * g, b2 * m2 + (1 - b2) * g * g
    step = -1e-3 * (m1n / (1 - b1 ** t)) / (np.sqrt(m2n / (1 - b2 ** t)) + 1e-15)
    _step(state, t, np.zeros(0, np.uint8), np.zeros(0, np.int32))
    np.testing.assert_allclose(state[3], pos + step[fit_kernels.P_POS:fit_kernels.P_POS + 3].T, rtol=1e-4, atol=1e-7)
    assert not np.allclose(state[3][::2], pos[::2])  # unseen ones moved on their momentum


def test_a_gaussian_no_keyframe_draws_leaves_the_fit_as_it_came(small_manifest, small_world):
    """In the fit, a Gaussian outside every keyframe's view never steps: it leaves the fit as it
    came, with selective Adam as with dense (zero gradient, zero moments)."""
    train = [0, 6]
    targets = _views(small_world, small_manifest, train)
    behind = small_manifest.T_world_cam_gt[0][:3, 3] - 50.0 * small_manifest.T_world_cam_gt[0][:3, 2]
    far = GaussianField(np.vstack([small_world.positions, behind[None]]),
                        np.vstack([small_world.scales, [[0.05, 0.05, 0.05]]]),
                        np.vstack([small_world.rotations_xyzw, [[0, 0, 0, 1.0]]]),
                        np.vstack([small_world.colors, [[200, 10, 10]]]),
                        np.concatenate([small_world.opacities, [0.9]]),
                        np.concatenate([small_world.ids, [np.uint64(123456789)]]))
    res = optimize_gaussians(far, [t[0] for t in targets], [t[1] for t in targets],
                             [small_manifest.T_world_cam_gt[i] for i in train], small_manifest.camera.K,
                             FitConfig(epochs=2, scale=0.5, densify_interval=0), log=lambda _: None)
    k = int(np.flatnonzero(res.field.ids == np.uint64(123456789))[0])
    np.testing.assert_allclose(res.field.positions[k], behind, atol=1e-5)
    assert res.field.colors[k].tolist() == [200, 10, 10]

"""The keyframe fit learns view-dependent colour: the SH stage's compiled kernels against their
NumPy reference, the SH gradient against finite differences, the degree grown during the fit, and
degree 0 giving the same worlds as before the fit could learn SH."""

import numpy as np
import pytest

from atlas_pipeline.config import FitConfig
from atlas_pipeline.gaussian_world.optimize import optimize_gaussians

TRAIN = (0, 6)
# content_hash of the default fit (below) computed on the commit before the fit learned SH: the
# degree-0 fit must not change a bit.
DEGREE0_HASH = "b264c0c8c1b3a863d9a285ab294fbe11e31a95f4f441bce9cc4ee09782616fd7"


def _inputs(manifest, train=TRAIN):
    images = [manifest.read_rgb(i) for i in train]
    depths = [manifest.read_depth_m(i, allow_empty=True) for i in train]
    return images, depths, [manifest.T_world_cam_gt[i] for i in train], manifest.camera.K


# Default settings, cut to a few dozen steps with a coarse level and two densify rounds.
SHORT = dict(epochs=30, max_steps=40, densify_interval=15, densify_until_step=35)


def test_degree_0_fit_is_bit_identical_to_before(small_manifest, small_world):
    images, depths, poses, K = _inputs(small_manifest)
    res = optimize_gaussians(small_world, images, depths, poses, K, FitConfig(**SHORT), log=lambda _: None)
    assert res.record["n_cloned"] + res.record["n_split"] > 0 and res.record["coarse"] is not None
    assert res.field.content_hash() == DEGREE0_HASH


# ---- the SH stage: compiled against its reference, gradients against finite differences -------

from atlas_pipeline.gaussian_world import fit_sh  # noqa: E402
from atlas_pipeline.gaussian_world.field import GaussianField, sh_rest_count  # noqa: E402
from atlas_pipeline.gaussian_world.fit_kernels import P_COL, P_SH, LossWeights  # noqa: E402
from atlas_pipeline.gaussian_world.raster import GaussianArrays  # noqa: E402

K_TINY = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])


def _stage_inputs(n: int, k_rest: int, seed: int, sh_scale: float):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    col = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    sh = rng.normal(0, sh_scale, (n, k_rest, 3)).astype(np.float32)
    gparam = np.zeros((P_SH + 3 * k_rest, n), np.float32)
    gparam[P_COL:P_COL + 3] = rng.normal(0, 1e-3, (3, n))
    gparam[P_SH:] = 7.0  # overwritten where active, kept above
    return pos, col, sh, gparam, np.array([0.1, -0.2, 0.3])


@pytest.mark.parametrize("k_rest,k_active", [(3, 3), (8, 8), (15, 15), (15, 3), (8, 0)])
def test_compiled_stages_equal_their_reference_bit_for_bit(k_rest, k_active):
    pos, col, sh, gparam, centre = _stage_inputs(3000, k_rest, k_rest + k_active, sh_scale=0.6)
    got = fit_sh.view_colors01(pos, col, sh, k_active, centre)
    ref = fit_sh.view_colors01_reference(pos, col, sh, k_active, centre)
    assert got.dtype == np.float32 and np.array_equal(got, ref)
    if k_active:
        assert (got == 0).any() and (got > 1).any()  # both the clamp and an unclamped top are exercised
    g_ref = gparam.copy()
    fit_sh.sh_backward(pos, col, sh, k_active, centre, gparam)
    fit_sh.sh_backward_reference(pos, col, sh, k_active, centre, g_ref)
    assert np.array_equal(gparam, g_ref)
    assert (gparam[P_SH + 3 * k_active:] == 7.0).all()  # inactive coefficients' rows untouched


def test_colour_stage_is_the_renderers_in_colour_levels():
    from atlas_pipeline.gaussian_world.sh import COLOR_LEVELS, view_colors

    pos, col, sh, _, centre = _stage_inputs(500, 15, 4, sh_scale=0.3)
    levels = np.round(col * 255).astype(np.uint8)
    got = fit_sh.view_colors01(pos, (levels / 255.0).astype(np.float32), sh, 15, centre)
    np.testing.assert_allclose(got * COLOR_LEVELS, view_colors(pos, levels, sh, centre), atol=1e-3)


def test_active_degree_grows_one_per_interval():
    assert [fit_sh.active_degree(t, 3, 25) for t in (0, 24, 25, 49, 50, 75, 1000)] == [0, 0, 1, 1, 2, 3, 3]
    assert fit_sh.active_degree(0, 2, 0) == 2 and fit_sh.active_degree(500, 0, 25) == 0


def _tiny(seed: int, n: int = 24):
    rng = np.random.default_rng(seed)
    pos = rng.uniform([-0.3, -0.25, 1.0], [0.3, 0.25, 1.6], (n, 3))
    scl = rng.uniform(0.02, 0.06, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    col = rng.uniform(0.3, 0.7, (n, 3))
    op = rng.uniform(0.3, 0.9, n)
    T = np.eye(4)
    T[:3, 3] = [0.02, -0.01, 0.05]
    img = rng.uniform(0, 1, (48, 64, 3))
    dep = rng.uniform(1.0, 2.0, (48, 64))
    return GaussianArrays(pos, scl, q, col, op), T, img, dep


def test_sh_gradient_matches_finite_differences():
    """d loss / d sh_rest (degree 3) and the colour's through the clamp: the loss is linear in the
    view colour between the L1's kinks, so central differences agree to well under a percent."""
    g_arrays, T, img, dep = _tiny(1)
    rng = np.random.default_rng(2)
    sh = rng.normal(0, 0.05, (24, 15, 3))
    sh[3, :, 0] = 0.0
    sh[3, 1, 0] = -5.0  # along +z (the view axis): a channel clamped at 0, no gradient
    kw = dict(weights=LossWeights(1.0, 0.5))

    def loss(s, c=g_arrays.colors):
        return fit_sh.render_loss_and_sh_gradients(g_arrays._replace(colors=c), s, T, K_TINY, img, dep, **kw)[0]

    _, g = fit_sh.render_loss_and_sh_gradients(g_arrays, sh, T, K_TINY, img, dep, **kw)
    assert g["sh_rest"].shape == (24, 15, 3)
    centre = T[:3, 3]
    seen = fit_sh.view_colors01_reference(g_arrays.positions, g_arrays.colors, sh.astype(np.float32), 15, centre)
    assert seen[3, 0] == 0.0 and (g["sh_rest"][3, :, 0] == 0).all() and g["color"][3, 0] == 0
    eps = 1e-4
    checked = 0
    for i in range(0, 24, 3):
        for k in (0, 4, 9, 14):
            for c in range(3):
                def f(e, i=i, k=k, c=c):
                    s = sh.copy()
                    s[i, k, c] += e
                    return loss(s)

                num = (f(eps) - f(-eps)) / (2 * eps)
                if abs(num) < 1e-6 and abs(g["sh_rest"][i, k, c]) < 1e-6:
                    continue  # outside the view, clamped, or a flat spot
                assert g["sh_rest"][i, k, c] == pytest.approx(num, rel=0.02, abs=2e-6)
                checked += 1
        col = np.array(g_arrays.colors)
        col[i, 1] += eps
        hi = loss(sh, col)
        col[i, 1] -= 2 * eps
        num = (hi - loss(sh, col)) / (2 * eps)
        if abs(num) > 1e-6:
            assert g["color"][i, 1] == pytest.approx(num, rel=0.02, abs=2e-6)
            checked += 1
    assert checked >= 40


# ---- the fit learns them -----------------------------------------------------------------------

def _look_at(eye, target=(0.0, 0.0, 1.3)) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` at ``eye`` looking at ``target`` (y down)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = eye
    return T


def _ring_views(n_views: int = 6, seed: int = 5):
    """A cluster of Gaussians seen from a ring of cameras 100 degrees wide, its true colour degree 1
    (each Gaussian brighter on one side): no single colour per Gaussian fits every view."""
    from atlas_pipeline.gaussian_world.render import render_field

    g, _, _, _ = _tiny(seed, n=60)
    rng = np.random.default_rng(seed)
    ids = np.arange(60, dtype=np.uint64)
    base = GaussianField(g.positions, g.scales, g.rotations_xyzw, np.round(g.colors * 255), g.opacities, ids)
    truth = GaussianField(*(getattr(base, a) for a in ("positions", "scales", "rotations_xyzw", "colors",
                                                       "opacities", "ids")),
                          rng.normal(0, 0.3, (60, 3, 3)))
    poses = [_look_at((1.3 * np.sin(a), 0.0, 1.3 - 1.3 * np.cos(a))) for a in np.radians(np.linspace(-50, 50, n_views))]
    images, depths = [], []
    for T in poses:
        r = render_field(truth, T, K_TINY, 64, 48)
        images.append(r.rgb)
        depths.append(r.depth_m.astype(np.float64))
    return base, images, depths, poses


# Colour only (geometry frozen), every step at the fit scale, no early stop or densification.
COLOUR_ONLY = dict(epochs=25, max_steps=None, min_steps_per_keyframe=0, scale=1.0, coarse_factor=1,
                   coarse_max_steps=0, plateau_patience=0, densify_interval=0, lr_position_m=0.0,
                   lr_log_scale=0.0, lr_rotation_rad=0.0, lr_opacity_logit=0.0, depth_weight=0.0,
                   coverage_weight=0.0, sh_degree_interval=12)


def test_fit_learns_view_dependent_colour_and_grows_the_degree():
    base, images, depths, poses = _ring_views()
    args = (base, images, depths, poses, K_TINY)
    quiet = {"log": lambda _: None}
    flat = optimize_gaussians(*args, FitConfig(**COLOUR_ONLY), **quiet)
    sh1 = optimize_gaussians(*args, FitConfig(**COLOUR_ONLY, sh_degree=1, lr_sh_rest=1e-2), **quiet)
    assert flat.field.sh_degree == 0 and sh1.field.sh_degree == 1
    n = COLOUR_ONLY["sh_degree_interval"]
    np.testing.assert_array_equal(flat.loss[:n], sh1.loss[:n])  # degree 0 until the first interval
    assert sh1.loss[n + 1] != flat.loss[n + 1]  # step n renders zero coefficients, then they move
    last = slice(-len(images), None)
    assert sh1.loss[last].mean() < 0.5 * flat.loss[last].mean()
    # the degree never grows within the fit: no coefficient moves from its zero start
    late = optimize_gaussians(*args, FitConfig(**{**COLOUR_ONLY, "sh_degree_interval": 1000}, sh_degree=2), **quiet)
    assert late.field.sh_degree == 2 and not late.field.sh_rest.any()
    np.testing.assert_array_equal(late.loss, flat.loss)


def test_fit_below_the_fields_degree_learns_its_own_and_keeps_the_rest(caplog):
    import logging

    base, images, depths, poses = _ring_views()
    rest = np.random.default_rng(8).normal(0, 0.05, (len(base), sh_rest_count(3), 3))
    start = GaussianField(base.positions, base.scales, base.rotations_xyzw, base.colors, base.opacities, base.ids,
                          rest)
    cfg = FitConfig(**{**COLOUR_ONLY, "epochs": 2, "sh_degree_interval": 0}, sh_degree=1)
    with caplog.at_level(logging.WARNING):
        out = optimize_gaussians(start, images, depths, poses, K_TINY, cfg, log=lambda _: None).field
    assert "SH up to degree 1" in caplog.text and "kept unchanged" in caplog.text
    assert out.sh_degree == 3 and np.array_equal(out.ids, start.ids)
    assert np.array_equal(out.sh_rest[:, 3:], start.sh_rest[:, 3:])
    assert not np.array_equal(out.sh_rest[:, :3], start.sh_rest[:, :3])


def test_config_bounds_the_degree():
    from pydantic import ValidationError

    assert FitConfig().sh_degree == 0
    for bad in (-1, 4):
        with pytest.raises(ValidationError, match="sh_degree"):
            FitConfig(sh_degree=bad)

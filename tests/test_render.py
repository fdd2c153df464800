"""Tests of the Gaussian rasteriser on tiny seeded scenes (compiled path against the NumPy reference
and against closed-form expectations)."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.geometry import look_at
from atlas_pipeline.gaussian_world.render import (
    RenderResult,
    render_gaussians,
    render_gaussians_reference,
)

W, H = 64, 48
K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])
RENDERERS = [render_gaussians, render_gaussians_reference]


def _one(pos, scale, color, opacity, quat=IDENTITY_Q):
    """Arrays for a single Gaussian."""
    return (
        np.array([pos], dtype=np.float32),
        np.array([scale], dtype=np.float32) * np.ones((1, 3), dtype=np.float32),
        np.array([quat], dtype=np.float32),
        np.array([color], dtype=np.uint8),
        np.array([opacity], dtype=np.float32),
    )


def _centroid_and_cov(weight: np.ndarray):
    """Weighted mean ``(x, y)`` and covariance ``[2, 2]`` of a ``[H, W]`` weight image."""
    ys, xs = np.mgrid[: weight.shape[0], : weight.shape[1]]
    w = weight / weight.sum()
    mx, my = (w * xs).sum(), (w * ys).sum()
    cxx = (w * (xs - mx) ** 2).sum()
    cyy = (w * (ys - my) ** 2).sum()
    cxy = (w * (xs - mx) * (ys - my)).sum()
    return np.array([mx, my]), np.array([[cxx, cxy], [cxy, cyy]])


def _random_scene(n, seed):
    rng = np.random.default_rng(seed)
    pos = np.c_[rng.uniform(-1.2, 1.2, n), rng.uniform(-0.9, 0.9, n), rng.uniform(0.8, 4.0, n)]
    scales = np.exp(rng.uniform(np.log(0.01), np.log(0.25), (n, 3)))
    quats = rng.normal(size=(n, 4))
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    # 40 % nearly opaque, so some pixels terminate early
    opac = np.where(rng.random(n) < 0.4, rng.uniform(0.97, 1.0, n), rng.uniform(0.05, 1.0, n))
    return (pos.astype(np.float32), scales.astype(np.float32), quats.astype(np.float32), colors,
            opac.astype(np.float32))


@pytest.mark.parametrize("render", RENDERERS)
def test_single_gaussian_blob_centred_on_projection(render):
    # (0.2, -0.1, 2) projects to u = 60 * 0.1 + 32 = 38, v = 60 * -0.05 + 24 = 21
    g = _one((0.2, -0.1, 2.0), 0.05, (200, 100, 50), 0.9)
    res = render(*g, np.eye(4), K, W, H)
    assert isinstance(res, RenderResult)
    assert res.rgb.shape == (H, W, 3) and res.rgb.dtype == np.uint8
    assert res.depth_m.shape == (H, W) and res.depth_m.dtype == np.float32
    assert res.alpha.shape == (H, W) and res.alpha.dtype == np.float32
    iy, ix = np.unravel_index(np.argmax(res.alpha), res.alpha.shape)
    assert (ix, iy) == (38, 21)
    c, _ = _centroid_and_cov(res.alpha)
    np.testing.assert_allclose(c, [38.0, 21.0], atol=0.05)
    # at the mean alpha = opacity, so colour = opacity * colour on a black background
    assert res.alpha[21, 38] == pytest.approx(0.9, abs=1e-5)
    np.testing.assert_array_equal(res.rgb[21, 38], [180, 90, 45])
    assert res.depth_m[21, 38] == pytest.approx(2.0, abs=1e-5)
    # far from the blob: nothing drawn
    assert res.alpha[0, 0] == 0 and res.depth_m[0, 0] == 0
    np.testing.assert_array_equal(res.rgb[0, 0], [0, 0, 0])


@pytest.mark.parametrize("render", RENDERERS)
def test_footprint_size_matches_projected_sigma(render):
    # isotropic sigma 0.05 m at 2 m, f = 60: 1.5 px, plus the 0.3 px^2 low-pass
    g = _one((0.0, 0.0, 2.0), 0.05, (255, 255, 255), 0.5)
    res = render(*g, np.eye(4), K, W, H)
    _, cov = _centroid_and_cov(res.alpha)
    expected_var = 1.5**2 + 0.3
    assert cov[0, 0] == pytest.approx(expected_var, rel=0.1)
    assert cov[1, 1] == pytest.approx(expected_var, rel=0.1)
    assert abs(cov[0, 1]) < 0.05


@pytest.mark.parametrize("render", RENDERERS)
def test_anisotropic_gaussian_elongated_along_rotated_axis(render):
    pos = (0.0, 0.0, 2.0)
    scale = np.array([0.15, 0.02, 0.02])  # long along the local x axis
    g = _one(pos, scale, (255, 255, 255), 0.9)
    res = render(*g, np.eye(4), K, W, H)
    _, cov = _centroid_and_cov(res.alpha)
    assert cov[0, 0] > 5 * cov[1, 1]  # long along image x
    # rotated 90 degrees about the optical (world z) axis: long along image y
    q90 = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    g = _one(pos, scale, (255, 255, 255), 0.9, quat=q90)
    _, cov = _centroid_and_cov(render(*g, np.eye(4), K, W, H).alpha)
    assert cov[1, 1] > 5 * cov[0, 0]
    # 45 degrees: elongated along the image diagonal x = y (image y points down)
    q45 = np.array([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
    g = _one(pos, scale, (255, 255, 255), 0.9, quat=q45)
    _, cov = _centroid_and_cov(render(*g, np.eye(4), K, W, H).alpha)
    evals, evecs = np.linalg.eigh(cov)
    major = evecs[:, 1] * np.sign(evecs[0, 1])
    np.testing.assert_allclose(major, [np.sqrt(0.5), np.sqrt(0.5)], atol=0.05)


@pytest.mark.parametrize("render", RENDERERS)
@pytest.mark.parametrize("front_first", [True, False])
def test_nearer_gaussian_occludes(render, front_first):
    red = [(0.0, 0.0, 2.0), 0.1, (255, 0, 0), 0.95]
    blue = [(0.0, 0.0, 3.0), 0.15, (0, 0, 255), 0.95]
    parts = [_one(*red), _one(*blue)] if front_first else [_one(*blue), _one(*red)]
    g = [np.concatenate([a, b]) for a, b in zip(*parts)]
    res = render(*g, np.eye(4), K, W, H)
    r, _, b = res.rgb[24, 32].astype(int)
    assert r > 200 and b < 20
    # expected depth: (0.95 * 2 + 0.05 * 0.95 * 3) / (1 - 0.05^2)
    assert res.depth_m[24, 32] == pytest.approx((1.9 + 0.1425) / 0.9975, abs=1e-3)
    assert res.depth_m[24, 32] < 2.1


@pytest.mark.parametrize("render", RENDERERS)
def test_posed_camera_sees_target_in_image_centre(render):
    target = np.array([1.0, 2.0, 0.5])
    T_wc = look_at(np.array([3.0, -1.0, 2.0]), target)
    g = _one(target, 0.05, (10, 200, 30), 0.8)
    res = render(*g, T_wc, K, W, H)
    c, _ = _centroid_and_cov(res.alpha)
    np.testing.assert_allclose(c, [32.0, 24.0], atol=0.05)
    assert res.depth_m[24, 32] == pytest.approx(np.linalg.norm(target - T_wc[:3, 3]), abs=1e-4)


@pytest.mark.parametrize("render", RENDERERS)
def test_behind_camera_and_before_near_plane_are_culled(render):
    g = [np.concatenate(p) for p in zip(
        _one((0.0, 0.0, -2.0), 0.2, (255, 255, 255), 1.0),
        _one((0.0, 0.0, 0.04), 0.01, (255, 255, 255), 1.0),
    )]
    res = render(*g, np.eye(4), K, W, H, background=(1, 2, 3), near_m=0.05)
    assert res.alpha.max() == 0
    assert np.all(res.rgb == [1, 2, 3])


@pytest.mark.parametrize("size", [(64, 48), (61, 37)])
def test_compiled_matches_reference_on_random_scene(size):
    w, h = size
    k = np.array([[55.0, 0.0, (w - 1) / 2], [0.0, 55.0, (h - 1) / 2], [0.0, 0.0, 1.0]])
    g = _random_scene(500, seed=3)
    T_wc = look_at(np.array([0.3, -0.2, -0.5]), np.array([0.0, 0.1, 2.5]), up=(0.0, -1.0, 0.0))
    fast = render_gaussians(*g, T_wc, k, w, h, background=(30, 60, 90))
    ref = render_gaussians_reference(*g, T_wc, k, w, h, background=(30, 60, 90))
    assert (ref.alpha > 0.5).mean() > 0.8 and (ref.alpha > 1 - 1e-4).any()  # busy, some terminate
    assert np.abs(fast.rgb.astype(int) - ref.rgb.astype(int)).max() <= 2
    np.testing.assert_allclose(fast.alpha, ref.alpha, atol=2e-3)
    both = (fast.depth_m > 0) & (ref.depth_m > 0)
    assert both.sum() >= 0.99 * max((fast.depth_m > 0).sum(), (ref.depth_m > 0).sum())
    np.testing.assert_allclose(fast.depth_m[both], ref.depth_m[both], rtol=1e-3, atol=1e-3)


def _brute_force_on_axis(z, sigma_m, colors, opac, f, w, h, cx, cy):
    """All Gaussians on the optical axis, isotropic: 2D covariance ``((f s / z)^2 + 0.3) I``.

    Composites every Gaussian at every pixel with no early termination. Returns (rgb float, depth).
    """
    order = np.argsort(z, kind="stable")
    ys, xs = np.mgrid[:h, :w]
    d2 = (xs - cx) ** 2 + (ys - cy) ** 2
    var = (f * sigma_m[order] / z[order]) ** 2 + 0.3
    alpha = np.minimum(0.99, opac[order, None, None] * np.exp(-0.5 * d2[None] / var[:, None, None]))
    alpha = np.where(alpha >= 1 / 255, alpha, 0.0)
    T_before = np.cumprod(np.concatenate([np.ones((1, h, w)), 1 - alpha[:-1]]), axis=0)
    wgt = T_before * alpha
    rgb = np.einsum("nhw,nc->hwc", wgt, colors[order].astype(np.float64))
    acc = wgt.sum(axis=0)
    depth = np.einsum("nhw,n->hw", wgt, z[order]) / acc
    return rgb, depth, acc


def test_early_termination_changes_nothing_beyond_tolerance():
    w, h, f = 32, 24, 30.0
    cx, cy = 15.5, 11.5
    k = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(7)
    n = 40
    z = rng.uniform(1.0, 3.0, n)
    sigma = rng.uniform(0.4, 0.8, n)  # 10-20 px: every 3-sigma box covers the whole image
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    opac = rng.uniform(0.5, 1.0, n)
    pos = np.c_[np.zeros(n), np.zeros(n), z]
    quats = np.tile(IDENTITY_Q, (n, 1))
    scales = np.repeat(sigma[:, None], 3, axis=1)
    res = render_gaussians(pos, scales, quats, colors, opac, np.eye(4), k, w, h)
    assert (res.alpha > 1 - 1e-4).mean() > 0.5  # most pixels terminated early
    rgb_full, depth_full, _ = _brute_force_on_axis(z, sigma, colors, opac, f, w, h, cx, cy)
    assert np.abs(res.rgb.astype(float) - rgb_full).max() <= 1.0
    np.testing.assert_allclose(res.depth_m, depth_full, atol=1e-3)


@pytest.mark.parametrize("render", RENDERERS)
def test_empty_input_gives_background(render):
    e = np.zeros((0, 3), np.float32)
    res = render(e, e, np.zeros((0, 4), np.float32), np.zeros((0, 3), np.uint8),
                 np.zeros(0, np.float32), np.eye(4), K, 20, 10, background=(5, 6, 7))
    assert res.rgb.shape == (10, 20, 3)
    assert np.all(res.rgb == [5, 6, 7])
    assert not res.alpha.any() and not res.depth_m.any()


@pytest.mark.parametrize("render", RENDERERS)
def test_all_culled_gives_background(render):
    g = _one((0.0, 0.0, 2.0), 0.05, (255, 255, 255), 0.001)  # below 1/255: never visible
    res = render(*g, np.eye(4), K, W, H, background=(9, 9, 9))
    assert np.all(res.rgb == 9) and not res.alpha.any()


def _valid_inputs():
    return list(_one((0.0, 0.0, 2.0), 0.05, (255, 0, 0), 0.5)) + [np.eye(4), K, W, H]


@pytest.mark.parametrize("render", RENDERERS)
@pytest.mark.parametrize(
    "index, value, match",
    [
        (0, np.array([[np.nan, 0.0, 2.0]]), "positions"),
        (0, np.zeros((1, 2)), "positions"),
        (1, np.array([[0.1, np.inf, 0.1]]), "scales"),
        (1, np.array([[0.1, -0.1, 0.1]]), "scales"),
        (1, np.zeros((2, 3)), "scales"),
        (2, np.zeros((1, 4)), "rotations_xyzw"),
        (3, np.array([[300, 0, 0]]), "colors"),
        (3, np.array([["a", "b", "c"]]), "colors"),
        (4, np.array([1.5]), "opacities"),
        (4, np.array([np.nan]), "opacities"),
        (5, np.full((4, 4), np.nan), "T_world_cam"),
        (5, np.diag([2.0, 1.0, 1.0, 1.0]), "T_world_cam"),
        (6, np.eye(2), "K"),
        (6, np.diag([0.0, 60.0, 1.0]), "K"),
        (7, 0, "image size"),
    ],
)
def test_invalid_input_raises_value_error(render, index, value, match):
    args = _valid_inputs()
    args[index] = value
    with pytest.raises(ValueError, match=match):
        render(*args)


def test_quaternion_sign_and_norm_do_not_matter():
    # quaternion sign and scale must not matter (normalised, q ~ -q)
    g = _random_scene(50, seed=11)
    q2 = -3.0 * g[2]
    a = render_gaussians(*g, np.eye(4), K, W, H)
    b = render_gaussians(g[0], g[1], q2, g[3], g[4], np.eye(4), K, W, H)
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1

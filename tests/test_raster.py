"""Tests of the raster core: each compiled stage against its NumPy reference on small seeded inputs,
the intrinsics scaling convention, and the core being the one the renderer and both fits use."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from atlas_pipeline.geometry import look_at
from atlas_pipeline.gaussian_world import raster as rc
from atlas_pipeline.gaussian_world.composite import composite_tiles
from atlas_pipeline.gaussian_world._raster_reference import (
    bin_tiles_reference,
    composite_reference,
    project_reference,
    sort_reference,
)
from atlas_pipeline.gaussian_world.render import render_gaussians

# Off-centre principal point and a size that is no multiple of the tile: edge tiles are partial.
W, H = 61, 37
K = np.array([[55.0, 0.0, 29.0], [0.0, 55.0, 19.5], [0.0, 0.0, 1.0]])
T_WC = look_at(np.array([0.3, -0.2, -0.5]), np.array([0.0, 0.1, 2.5]), up=(0.0, -1.0, 0.0))
BACKGROUND = np.array([30.0, 60.0, 90.0])

# A float32 rounding of a float64 value is within half a unit in the last place: 2^-24 relative.
# Both projections compute in float64 (differences ~1e-15 relative), the compiled one then rounds
# to float32 once, so one float32 ulp (2^-23) bounds the difference with a factor two to spare.
FLOAT32_ULP = 2.0**-23


def _scene(n: int, seed: int, dtype=np.float32):
    """Gaussians in and around the view: some far outside it (the Jacobian clamp acts), some behind
    the near plane, some too faint to draw, 40 % nearly opaque (pixels terminate early)."""
    rng = np.random.default_rng(seed)
    pos = np.c_[rng.uniform(-2.5, 2.5, n), rng.uniform(-1.8, 1.8, n), rng.uniform(-0.3, 4.0, n)]
    scales = np.exp(rng.uniform(np.log(0.01), np.log(0.3), (n, 3)))
    quats = rng.normal(size=(n, 4))
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    opac = np.where(rng.random(n) < 0.4, rng.uniform(0.97, 1.0, n), rng.uniform(0.0, 1.0, n))
    opac[:5] = 0.5 / 255.0  # never reaches alpha >= 1/255
    return (pos.astype(dtype), scales.astype(dtype), quats.astype(dtype), colors.astype(dtype),
            opac.astype(dtype))


def _view():
    return rc.view_from_pose(T_WC, K, W, H)


# --------------------------------------------------------------------------------------------
# Stages against their references
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])  # the renderer's and the keyframe fit's inputs
@pytest.mark.parametrize("seed", [0, 1])
def test_projection_matches_reference(seed, dtype):
    g = _scene(400, seed, dtype)
    fast = rc.project_gaussians(*g, _view(), rc.NEAR_M)
    ref = project_reference(*g, T_WC, K, W, H, rc.NEAR_M)
    np.testing.assert_array_equal(fast.valid, ref.valid)
    v = fast.valid
    assert 50 < v.sum() < 380  # culled ones (behind, faint, off-screen) and drawn ones
    np.testing.assert_array_equal(fast.box[v], ref.box[v])
    cut, full = fast.box[v], ref.box_3sigma[v]  # the cut box lies in the 3-sigma one
    assert np.all(cut[:, [0, 2]] >= full[:, [0, 2]]) and np.all(cut[:, [1, 3]] <= full[:, [1, 3]])
    # float64 camera z of two formulations (R (p - c) against p R^T + t): a few float64 ulps apart
    np.testing.assert_allclose(fast.depth[v], ref.depth[v], rtol=1e-14, atol=0)
    # relative to each row's magnitude; the conic's off-diagonal is measured against its diagonal
    scale = np.abs(ref.feat[v])
    diag = np.maximum(scale[:, rc.FEAT_CONIC_A], scale[:, rc.FEAT_CONIC_C])
    scale[:, [rc.FEAT_CONIC_A, rc.FEAT_CONIC_B, rc.FEAT_CONIC_C]] = diag[:, None]
    assert np.all(np.abs(fast.feat[v] - ref.feat[v]) <= FLOAT32_ULP * scale)
    # the Jacobian clamp was exercised by drawn Gaussians
    lim_x_pos, lim_x_neg, _, _ = rc.jacobian_clamp_limits(K[0, 0], K[1, 1], K[0, 2], K[1, 2], W, H)
    p_cam = (np.asarray(g[0], np.float64) - T_WC[:3, 3]) @ T_WC[:3, :3]
    x_over_z = p_cam[v, 0] / p_cam[v, 2]
    assert np.sum((x_over_z > lim_x_pos) | (x_over_z < -lim_x_neg)) >= 3


def test_projection_off_image_test_keeps_every_drawn_gaussian():
    """The projection skips Gaussians whose footprint bound lies outside the image before their
    covariance: wide Gaussians centred just outside the image, whose footprints reach into it,
    must still match the reference (which projects every Gaussian in full)."""
    rng = np.random.default_rng(7)
    n = 3000
    z = rng.uniform(0.3, 4.0, n)
    # centres up to 40 px outside each image edge, in camera coordinates
    u = np.where(rng.random(n) < 0.5, rng.uniform(-40.0, 0.0, n), rng.uniform(W - 1.0, W + 39.0, n))
    v = rng.uniform(-40.0, H + 39.0, n)
    swap = rng.random(n) < 0.5  # half outside the top or bottom edge instead
    u[swap], v[swap] = rng.uniform(-40.0, W + 39.0, swap.sum()), np.where(
        rng.random(swap.sum()) < 0.5, rng.uniform(-40.0, 0.0, swap.sum()), rng.uniform(H - 1.0, H + 39.0, swap.sum()))
    p_cam = np.c_[(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z]
    pos = p_cam @ T_WC[:3, :3].T + T_WC[:3, 3]
    scales = np.exp(rng.uniform(np.log(0.002), np.log(0.2), (n, 3)))
    quats = rng.normal(size=(n, 4))
    g = (pos, scales, quats, rng.uniform(0, 255, (n, 3)), rng.uniform(0.05, 1.0, n))
    fast = rc.project_gaussians(*g, _view(), rc.NEAR_M)
    ref = project_reference(*g, T_WC, K, W, H, rc.NEAR_M)
    np.testing.assert_array_equal(fast.valid, ref.valid)
    np.testing.assert_array_equal(fast.box[fast.valid], ref.box[ref.valid])
    assert 100 < fast.valid.sum() < n - 100  # both: centres outside whose footprints reach in, and not


def test_depth_sort_matches_stable_argsort():
    rng = np.random.default_rng(4)
    n = 5000
    # few distinct depths: many ties, which must keep input order; and a narrow range, in which the
    # radix sort skips digits all keys share
    depth = rng.choice(np.array([0.7, 1.25, 1.2500000001, 3.0]), n) + np.where(rng.random(n) < 0.5, 0.0, 1e-9)
    valid = rng.random(n) < 0.8
    np.testing.assert_array_equal(rc.sort_by_depth(valid, depth), sort_reference(valid, depth))
    depth = rng.uniform(0.05, 50.0, n)
    np.testing.assert_array_equal(rc.sort_by_depth(valid, depth), sort_reference(valid, depth))


@pytest.mark.parametrize("size", [(61, 37), (64, 48)])
def test_tile_binning_matches_reference(size):
    w, h = size
    proj = rc.project_gaussians(*_scene(400, 2), rc.view_from_pose(T_WC, K, w, h))
    order = rc.sort_by_depth(proj.valid, proj.depth)
    _, box = rc.gather_sorted(order, proj.feat, proj.box)
    bins = rc.bin_tiles(box, w, h)
    start, ids = bin_tiles_reference(box, w, h)
    assert bins.n_tiles == len(start) - 1 and bins.tiles_x == -(-w // rc.TILE_SIZE)
    np.testing.assert_array_equal(bins.tile_start, start)
    np.testing.assert_array_equal(bins.tile_ids, ids)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compositing_matches_reference(seed):
    """Same sorted, binned Gaussians through the compiled tile loop and the float64 reference.

    The compiled loop accumulates in float32 and uses a polynomial exp (2e-6 relative): per pixel
    the errors add up to a few 1e-6 in alpha and in relative depth (measured: under 1e-6), so 1e-5
    bounds them. A colour may round to the neighbouring level. A threshold (alpha 1/255,
    transmittance 1e-4 or 0.5) crossed differently would show as a larger difference at a pixel;
    these inputs have none.
    """
    sp = rc.prepare_splats(*_scene(800, seed), _view())
    rgb, depth_m, alpha, median = composite_tiles(sp, BACKGROUND)
    rgb_r, depth_r, alpha_r, median_r = composite_reference(sp.feat.astype(np.float64), sp.box, W, H, BACKGROUND)
    assert (alpha_r > 1 - rc.T_MIN).any() and (alpha_r < 0.5).any()  # some pixels terminate, some see through
    np.testing.assert_allclose(alpha, alpha_r, rtol=0, atol=1e-5)
    assert np.abs(rgb.astype(int) - rgb_r.astype(int)).max() <= 1
    np.testing.assert_array_equal(depth_m > 0, depth_r > 0)
    np.testing.assert_allclose(depth_m, depth_r, rtol=1e-5, atol=0)
    np.testing.assert_allclose(median, median_r, rtol=1e-6, atol=0)  # one Gaussian's z, float32 vs float64


def test_prepare_splats_is_none_when_nothing_is_drawn():
    g = _scene(10, 0)
    behind = (g[0] * 0 - np.array([0.0, 0.0, 5.0], np.float32),) + g[1:]
    assert rc.prepare_splats(*behind, rc.view_from_pose(np.eye(4), K, W, H)) is None


# --------------------------------------------------------------------------------------------
# Intrinsics scaling: one convention (pixel centres at integer coordinates)
# --------------------------------------------------------------------------------------------


def test_scale_intrinsics_keeps_pixel_centres_and_edges():
    Kf = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    Ks = rc.scale_intrinsics(Kf, 0.5)
    # the image centre (319.5, 239.5) at full size is the centre (159.5, 119.5) at half size
    np.testing.assert_allclose(Ks, [[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    # the left/top image edge (-0.5) stays the edge for any scale, per axis
    Ka = rc.scale_intrinsics(Kf, 0.3, 0.7)
    assert (Ka[0, 2] + 0.5) / Ka[0, 0] == pytest.approx((Kf[0, 2] + 0.5) / Kf[0, 0])
    assert (Ka[1, 2] + 0.5) / Ka[1, 1] == pytest.approx((Kf[1, 2] + 0.5) / Kf[1, 1])


def test_scale_camera_sizes_and_per_axis_ratios():
    Kf = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    assert rc.scaled_image_size(640, 480, 0.5) == (320, 240)
    assert rc.scaled_image_size(641, 481, 0.33, multiple=2) == (212, 158)
    w, h, Ks = rc.scale_camera(Kf, 641, 481, 0.33, multiple=2)
    np.testing.assert_allclose(Ks, rc.scale_intrinsics(Kf, 212 / 641, 158 / 481))
    # the far image edges meet too: the same field of view, edge to edge
    assert (w - 0.5 - Ks[0, 2]) / Ks[0, 0] == pytest.approx((641 - 0.5 - Kf[0, 2]) / Kf[0, 0])
    assert (h - 0.5 - Ks[1, 2]) / Ks[1, 1] == pytest.approx((481 - 0.5 - Kf[1, 2]) / Kf[1, 1])


def _alpha_centroid(alpha: np.ndarray) -> np.ndarray:
    ys, xs = np.mgrid[: alpha.shape[0], : alpha.shape[1]]
    a = alpha.astype(np.float64)
    return np.array([(a * xs).sum(), (a * ys).sum()]) / a.sum()


# The half-size and the box-averaged full-size splat differ in width (the 0.3 px^2 low-pass acts at
# each size) but not in position; sampling and the 1/255 cut move the centroid by ~0.005 px
# (measured). A quarter-pixel shift, the error of scaling K by s alone, is 8x this tolerance.
CENTROID_TOL_PX = 0.03


@pytest.mark.parametrize("pos", [(0.13, -0.07, 2.0), (0.1317, -0.0523, 2.0), (-0.2, 0.11, 2.5)])
def test_half_size_render_is_not_shifted(pos):
    wf, hf = 96, 64
    Kf = np.array([[100.0, 0, 47.5], [0, 100.0, 31.5], [0, 0, 1]])
    g = (np.array([pos], np.float32), np.full((1, 3), 0.04, np.float32), np.array([[0, 0, 0, 1.0]], np.float32),
         np.array([[255, 255, 255]], np.uint8), np.array([0.8], np.float32))
    full = render_gaussians(*g, np.eye(4), Kf, wf, hf).alpha
    boxed = full.reshape(hf // 2, 2, wf // 2, 2).mean(axis=(1, 3))  # 2x2 box average
    w, h, Ks = rc.scale_camera(Kf, wf, hf, 0.5)
    assert (w, h) == (wf // 2, hf // 2)
    half = render_gaussians(*g, np.eye(4), Ks, w, h).alpha
    offset = _alpha_centroid(half) - _alpha_centroid(boxed)
    assert np.all(np.abs(offset) < CENTROID_TOL_PX), offset
    # the test sees a quarter-pixel shift: K scaled without the pixel-centre correction
    naive = Kf.copy()
    naive[:2] *= 0.5
    shifted = _alpha_centroid(render_gaussians(*g, np.eye(4), naive, w, h).alpha) - _alpha_centroid(boxed)
    assert np.all(np.abs(shifted) > 0.2), shifted


def test_video_size_uses_the_raster_convention():
    from atlas_pipeline.viz.demo import _render_size

    Kf = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    for scale in (0.5, 0.37, 1.0):
        w, h, Ks = _render_size(640, 480, Kf, scale)
        assert w % 2 == 0 and h % 2 == 0
        ew, eh, eK = rc.scale_camera(Kf, 640, 480, scale, multiple=2)
        assert (w, h) == (ew, eh)
        np.testing.assert_array_equal(Ks, eK)


def test_colour_fit_uses_the_raster_convention(monkeypatch):
    from atlas_pipeline.gaussian_world import refine
    from atlas_pipeline.gaussian_world.field import GaussianField

    seen = []

    def record(field, colors, image, T_world_cam, K_view, width, height):
        seen.append((K_view, width, height, image.shape))
        n = len(field)
        return np.zeros((n, 3)), np.zeros(n), 0.0

    monkeypatch.setattr(refine, "_accumulate_view", record)
    g = _scene(3, 0)
    field = GaussianField(g[0], g[1], g[2], g[3].astype(np.uint8), g[4], np.arange(3, dtype=np.uint64))
    Kf = np.array([[120.0, 0, 79.5], [0, 120.0, 59.5], [0, 0, 1]])
    refine.refine_colours(field, [np.zeros((120, 160, 3), np.uint8)], [np.eye(4)], Kf, iterations=1, scale=0.5)
    (K_view, w, h, shape), = seen
    assert (w, h) == (80, 60) and shape == (60, 80, 3)
    np.testing.assert_allclose(K_view, rc.scale_intrinsics(Kf, 0.5))


# --------------------------------------------------------------------------------------------
# One core
# --------------------------------------------------------------------------------------------


def test_no_private_names_cross_modules():
    """The renderer and the fits use the raster core's public functions only."""
    folder = Path(rc.__file__).parent
    for path in folder.glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and "gaussian_world" in node.module:
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path.name} imports private {private} from {node.module}"
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in {"raster", "render", "R", "rc"} and node.attr.startswith("_")):
                pytest.fail(f"{path.name}:{node.lineno} uses private {node.value.id}.{node.attr}")

"""Photometric evaluation: PSNR, SSIM, depth L1 on tiny seeded images, and held-out views."""

import numpy as np
import pytest

from atlas_pipeline.gaussian_world.evaluation import PhotometricReport, depth_l1, preview_image, psnr, ssim


def test_psnr_known_values():
    a = np.zeros((8, 8, 3), np.uint8)
    b = a.copy()
    assert psnr(a, b) == float("inf")
    b[:] = 255
    assert psnr(a, b) == pytest.approx(0.0)
    b[:] = 1  # MSE 1 -> 20 log10(255)
    assert psnr(a, b) == pytest.approx(48.1308, abs=1e-3)


def test_ssim_identity_noise_and_symmetry():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:64, 0:64]
    a = np.repeat(((xx + yy) * 1.5 + 30)[..., None], 3, axis=2).astype(np.uint8)  # a smooth ramp
    assert ssim(a, a) == pytest.approx(1.0)
    noisy = np.clip(a + rng.normal(0, 30, a.shape), 0, 255).astype(np.uint8)
    s = ssim(a, noisy)
    assert 0.0 < s < 0.9 and s == pytest.approx(ssim(noisy, a))
    # A constant shift of the mean hurts less than noise of the same MSE.
    shifted = np.clip(a.astype(int) + 30, 0, 255).astype(np.uint8)
    assert ssim(a, shifted) > s
    skimage = pytest.importorskip("skimage.metrics")  # when scikit-image is around: same definition
    luma = lambda x: x.astype(np.float64) @ np.array([0.299, 0.587, 0.114])  # noqa: E731
    ref = skimage.structural_similarity(luma(a), luma(noisy), data_range=255, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False)
    assert s == pytest.approx(ref, abs=2e-3)


def test_depth_l1_over_pixels_both_have():
    sensor = np.array([[1.0, 2.0], [0.0, 3.0]])
    rendered = np.array([[1.1, 0.0], [1.0, 2.5]])
    l1, cover = depth_l1(rendered, sensor)
    assert l1 == pytest.approx((0.1 + 0.5) / 2) and cover == pytest.approx(2 / 3)


def test_preview_and_report_roundtrip(tmp_path):
    real = np.full((4, 6, 3), 200, np.uint8)
    img = preview_image(real, real // 2, np.full((4, 6), 1.02), np.ones((4, 6)))
    assert img.shape == (4, 18, 3) and img.dtype == np.uint8
    rep = PhotometricReport("d", "m", "estimated", np.array([3, 5]), np.array([20.0, 22.0]), np.array([25.0, np.nan]),
                            np.array([0.8, 0.9]), np.array([0.01, np.nan]), np.array([0.9, 0.0]), b"\x89PNG")
    rep.save(tmp_path)
    back = PhotometricReport.load(tmp_path)
    assert back.summary["mean_psnr_db"] == pytest.approx(21.0) and back.summary["mean_psnr_masked_db"] == 25.0
    assert np.isnan(back.depth_l1_m[1]) and back.preview_png == b"\x89PNG"


@pytest.mark.slow
def test_colour_refinement_recovers_colours_from_views(small_manifest):
    """Gaussians of the small synthetic world with wrong colours: fitting them to keyframe-like views
    rendered with the right colours brings a held-out view back."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.gaussian_world.field import GaussianField
    from atlas_pipeline.gaussian_world.refine import refine_colours
    from atlas_pipeline.gaussian_world.render import render_gaussians
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    cfg = load_profile("default")
    fused = fuse(small_manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(small_manifest, fused, cfg), cfg)
    f = world.field
    cam = small_manifest.camera
    poses = small_manifest.T_world_cam_gt

    def view(field, i):
        return render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                                poses[i], cam.K, cam.width, cam.height).rgb

    train = [0, 2, 4, 6, 8, 10]
    images = [view(f, i) for i in train]
    rng = np.random.default_rng(0)
    wrong = GaussianField(f.positions, f.scales, f.rotations_xyzw,
                          np.clip(f.colors.astype(int) + rng.integers(-60, 60, f.colors.shape), 0, 255),
                          f.opacities, f.ids)
    fixed = refine_colours(wrong, images, poses[train], cam.K, iterations=4, scale=1.0)
    assert psnr(view(f, 5), view(fixed, 5)) > psnr(view(f, 5), view(wrong, 5)) + 5.0
    again = refine_colours(wrong, images, poses[train], cam.K, iterations=4, scale=1.0)
    assert again.equals(fixed)  # deterministic

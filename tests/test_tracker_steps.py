"""The tracker's named Gauss-Newton steps (kiss-icp's Registration.cpp split) against plain NumPy:
association (projective, gated; photometric with occlusion gate and bilinear samples), the linear
system (point-to-plane + intensity, Huber and depth-noise weights), and the update."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from atlas_pipeline.geometry import so3_exp
from atlas_pipeline.localization import _kernels as kn
from atlas_pipeline.localization.normal_equations import SPLIT_MIN_POINTS
from atlas_pipeline.localization.normal_equations import normal_equations as split_normal_equations
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS, TrackerConstants
from atlas_pipeline.localization.tracker import apply_update, converged, solve_update

# Tiny pinhole views (~2.5 cm pixels at 1 m): a 40 x 30 model view and a 48 x 36 reference image.
MODEL_W, MODEL_H, MODEL_F = 40, 30, 40.0
REF_W, REF_H, REF_F = 48, 36, 48.0
PLANE_SLOPE = 0.1  # the scene: the plane z = 1 + 0.1 x in the model camera frame


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rotvec, float))
    T[:3, 3] = t
    return T


def _plane_model_view(T_world_model: np.ndarray) -> kn.ModelView:
    """The plane rendered into the model view: exact points and camera-facing normals; two holes."""
    cx, cy = (MODEL_W - 1) / 2.0, (MODEL_H - 1) / 2.0
    v, u = np.mgrid[0:MODEL_H, 0:MODEL_W].astype(float)
    xn, yn = (u - cx) / MODEL_F, (v - cy) / MODEL_F
    z = 1.0 / (1.0 - PLANE_SLOPE * xn)  # ray (xn, yn, 1) z on z = 1 + slope x
    pts = np.stack([xn * z, yn * z, z], axis=-1)
    n = np.array([PLANE_SLOPE, 0.0, -1.0]) / np.hypot(PLANE_SLOPE, 1.0)  # facing the camera
    nrm = np.broadcast_to(n, pts.shape).copy()
    pts[12, 13] = nrm[12, 13] = np.nan
    pts[20, 27] = nrm[20, 27] = np.nan
    behind = np.full_like(pts, np.nan)  # no surface behind the plane
    return kn.ModelView(pts, nrm, np.ascontiguousarray(T_world_model), MODEL_F, MODEL_F, cx, cy, behind, behind.copy())


def _reference(T_world_ref: np.ndarray, distortion) -> kn.ReferenceImage:
    """A smooth intensity image with its gradients, and the plane's depth (one pixel without)."""
    v, u = np.mgrid[0:REF_H, 0:REF_W].astype(float)
    inten = (0.5 + 0.3 * np.sin(0.2 * u) * np.cos(0.15 * v)).astype(np.float32)
    gx, gy = kn.image_gradients(inten)
    cx, cy = (REF_W - 1) / 2.0, (REF_H - 1) / 2.0
    depth = (1.0 / (1.0 - PLANE_SLOPE * (u - cx) / REF_F)).astype(np.float32)
    depth[16, 20] = 0.0
    return kn.ReferenceImage(inten, gx, gy, depth, np.ascontiguousarray(T_world_ref), REF_F, REF_F, cx, cy,
                             np.asarray(distortion, float))


def _params(**kw) -> kn.Params:
    C = TRACKER_CONSTANTS
    base = dict(max_distance_m=0.03, huber_depth_m=0.005, photometric_weight=0.04, huber_intensity=C.huber_intensity,
                occlusion_gate_m=C.occlusion_gate_m, min_view_depth_m=C.min_view_depth_m, noise_a_m=C.depth_noise_a_m,
                noise_b_per_m=C.depth_noise_b_per_m, noise_z0_m=C.depth_noise_z0_m,
                noise_reference_sigma_m=C.depth_noise_reference_sigma_m)
    base.update(kw)
    return kn.Params(**base)


@pytest.fixture(scope="module")
def scene():
    """Frame points near the plane (noisy, a few far off it, one behind the camera), seen from a
    camera a little off the model view; the reference is a third camera with lens distortion."""
    rng = np.random.default_rng(3)
    T_world_model = _pose([0.05, -0.1, 0.02], [0.2, -0.1, 0.3])
    T_world_cam = T_world_model @ _pose([0.01, 0.02, -0.01], [0.01, -0.02, 0.005])
    T_world_ref = T_world_model @ _pose([-0.02, 0.01, 0.0], [-0.03, 0.01, 0.02])
    # points on the plane (model camera frame), some beyond the view's edge, then noise / outliers
    x = rng.uniform(-0.7, 0.7, 60)
    y = rng.uniform(-0.5, 0.5, 60)
    p_model = np.stack([x, y, 1.0 + PLANE_SLOPE * x], axis=1)
    p_model[:, 2] += rng.normal(scale=0.004, size=60)
    p_model[::7, 2] += 0.1  # off the surface: gated out
    p_model[5] = (0.0, 0.0, -1.0)  # behind both cameras
    T_cam_model = np.linalg.inv(T_world_cam) @ T_world_model
    p_cam = p_model @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
    frame = kn.FramePoints(np.ascontiguousarray(p_cam), rng.uniform(0.2, 0.8, 60))
    return (frame, np.ascontiguousarray(T_world_cam), _plane_model_view(T_world_model),
            _reference(T_world_ref, [0.05, -0.01, 0.001, -0.002, 0.0]))


# ---- NumPy references ---------------------------------------------------------------------------


def _np_to_camera(T, p):
    """R^T (p - t), element by element in the kernel's order (so the rounding is the same)."""
    R, t = T[:3, :3], T[:3, 3]
    d = p - t
    return np.stack([R[0, 0] * d[:, 0] + R[1, 0] * d[:, 1] + R[2, 0] * d[:, 2],
                     R[0, 1] * d[:, 0] + R[1, 1] * d[:, 1] + R[2, 1] * d[:, 2],
                     R[0, 2] * d[:, 0] + R[1, 2] * d[:, 1] + R[2, 2] * d[:, 2]], axis=1)


def _np_to_world(T, p):
    R, t = T[:3, :3], T[:3, 3]
    return np.stack([R[i, 0] * p[:, 0] + R[i, 1] * p[:, 1] + R[i, 2] * p[:, 2] + t[i] for i in range(3)], axis=1)


def _np_bilinear(img, x, y):
    h, w = img.shape
    if not (0.0 <= x < w - 1 and 0.0 <= y < h - 1):
        return np.nan
    i, j = int(y), int(x)
    a, b = x - j, y - i
    return ((1 - a) * (1 - b) * img[i, j] + a * (1 - b) * img[i, j + 1]
            + (1 - a) * b * img[i + 1, j] + a * b * img[i + 1, j + 1])


def _np_associate(frame, T, model, ref, params):
    """Reference association: ``(p_world, outcome, (u, v), x_model, photometric, x_ref, samples)``."""
    pw = _np_to_world(T, frame.points_cam)
    xm = _np_to_camera(model.T_world_cam, pw)
    n = len(pw)
    outcome = np.full(n, kn.MATCH_NONE)
    uv = np.zeros((n, 2), int)
    mh, mw = model.points_cam.shape[:2]
    for i in range(n):
        if xm[i, 2] <= params.min_view_depth_m:
            continue
        u = int(model.fx * xm[i, 0] / xm[i, 2] + model.cx + 0.5)  # int(): truncation, as the kernel
        v = int(model.fy * xm[i, 1] / xm[i, 2] + model.cy + 0.5)
        if not (0 <= u < mw and 0 <= v < mh) or np.isnan(model.points_cam[v, u, 2]):
            continue
        uv[i] = u, v
        dist2 = np.sum((xm[i] - model.points_cam[v, u]) ** 2)
        in_front = xm[i, 2] < model.points_cam[v, u, 2]
        outcome[i] = (kn.MATCH_OK if dist2 < params.max_distance_m ** 2
                      else kn.MATCH_IN_FRONT if in_front else kn.MATCH_GATED)
    xr = _np_to_camera(ref.T_world_cam, pw)
    found = np.zeros(n, bool)
    samples = np.zeros((n, 3))
    k1, k2, p1, p2, k3 = ref.distortion
    for i in range(n):
        xk, yk, zk = xr[i]
        if zk <= params.min_view_depth_m:
            continue
        xn, yn = xk / zk, yk / zk
        r2 = xn * xn + yn * yn
        rad = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = xn * rad + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * rad + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        uf, vf = ref.fx * xd + ref.cx, ref.fy * yd + ref.cy
        ui, vi = int(uf + 0.5), int(vf + 0.5)
        h, w = ref.depth_m.shape
        dref = float(ref.depth_m[vi, ui]) if 0 <= ui < w and 0 <= vi < h else 0.0
        if not (dref > 0.0 and abs(dref - zk) < params.occlusion_gate_m):
            continue
        s = [_np_bilinear(img, uf, vf) for img in (ref.intensity, ref.grad_x, ref.grad_y)]
        if np.all(np.isfinite(s)):
            found[i] = True
            samples[i] = s
    return pw, outcome, uv, xm, found, xr, samples


def _np_linear_system(frame, model, ref, params, assoc):
    """Reference normal equations: stacked Jacobian rows ``[dr/dv, p x dr/dv]``, weights, residuals."""
    pw, outcome, uv, xm, found, xr, samples = assoc
    rows, weights, residuals = [], [], []
    sq = 0.0
    for i in np.flatnonzero(outcome == kn.MATCH_OK):
        u, v = uv[i]
        n_cam = model.normals_cam[v, u]
        r = float(n_cam @ (xm[i] - model.points_cam[v, u]))
        a = model.T_world_cam[:3, :3] @ n_cam
        z = frame.points_cam[i, 2]
        sigma = params.noise_a_m + params.noise_b_per_m * max(z - params.noise_z0_m, 0.0) ** 2
        ratio = params.noise_reference_sigma_m / sigma
        delta = params.huber_depth_m / ratio
        huber = 1.0 if abs(r) <= delta else delta / abs(r)
        rows.append(np.concatenate([a, np.cross(pw[i], a)]))
        weights.append(huber * ratio ** 2)
        residuals.append(r)
        sq += r * r
    n_geometric = len(rows)
    for i in np.flatnonzero(found):
        xk, yk, zk = xr[i]
        i_ref, gx, gy = samples[i]
        r = i_ref - frame.intensity[i]
        d = np.array([gx * ref.fx / zk, gy * ref.fy / zk, -(gx * ref.fx * xk + gy * ref.fy * yk) / zk ** 2])
        a = ref.T_world_cam[:3, :3] @ d
        huber = 1.0 if abs(r) <= params.huber_intensity else params.huber_intensity / abs(r)
        rows.append(np.concatenate([a, np.cross(pw[i], a)]))
        weights.append(params.photometric_weight * huber)
        residuals.append(r)
    J, w, r = np.array(rows), np.array(weights), np.array(residuals)
    H = J.T @ (w[:, None] * J)
    g = J.T @ (w * r)
    return H, g, n_geometric, sq


# ---- tests ----------------------------------------------------------------------------------------


def test_associate_matches_numpy(scene):
    frame, T, model, ref = scene
    params = _params()
    corr = kn.associate(0, len(frame.points_cam), frame, T, model, ref, params)
    pw, outcome, uv, xm, found, xr, samples = _np_associate(frame, T, model, ref, params)
    # the scene exercises every branch: correspondences, gated, off the view / behind, photometric both ways
    assert {kn.MATCH_NONE, kn.MATCH_GATED, kn.MATCH_OK} <= set(outcome.tolist())
    assert 0 < found.sum() < len(found)
    np.testing.assert_array_equal(corr.geometric, outcome)
    on = outcome != kn.MATCH_NONE
    np.testing.assert_array_equal(corr.model_pixel[on], uv[on])
    np.testing.assert_allclose(corr.points_world, pw, rtol=0, atol=1e-12)
    np.testing.assert_allclose(corr.points_model, xm, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(corr.photometric, found)
    np.testing.assert_allclose(corr.points_ref[found], xr[found], rtol=0, atol=1e-12)
    np.testing.assert_allclose(corr.ref_samples[found], samples[found], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(corr.depth_cam_m, frame.points_cam[:, 2])
    np.testing.assert_array_equal(corr.intensity, frame.intensity)


def test_associate_without_photometric_term_finds_no_photometric_correspondence(scene):
    frame, T, model, ref = scene
    corr = kn.associate(0, len(frame.points_cam), frame, T, model, ref, _params(photometric_weight=0.0))
    assert not corr.photometric.any()
    assert (corr.geometric == kn.MATCH_OK).any()


@pytest.mark.parametrize("photometric_weight", [0.0, 0.04])
def test_build_linear_system_matches_numpy(scene, photometric_weight):
    frame, T, model, ref = scene
    params = _params(photometric_weight=photometric_weight)
    corr = kn.associate(0, len(frame.points_cam), frame, T, model, ref, params)
    H, g, stats = kn.build_linear_system(corr, model, ref, params)
    assoc = _np_associate(frame, T, model, ref, params)
    H_ref, g_ref, n_geometric, sq = _np_linear_system(frame, model, ref, params, assoc)
    np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-12)
    assert np.array_equal(H, H.T)
    assert stats.n_points == len(frame.points_cam)
    assert stats.n_geometric == n_geometric
    assert stats.n_on_model == int(np.count_nonzero((assoc[1] == kn.MATCH_GATED) | (assoc[1] == kn.MATCH_OK)))
    assert stats.n_photometric == (int(assoc[4].sum()) if photometric_weight else 0)
    assert stats.geometric_sq_m2 == pytest.approx(sq, rel=1e-12)
    assert stats.rmse_m == pytest.approx(np.sqrt(sq / n_geometric), rel=1e-12)
    assert stats.inlier_fraction == n_geometric / len(frame.points_cam)
    assert stats.agreement == n_geometric / stats.n_on_model


def test_normal_equations_sums_the_steps_over_chunks(scene):
    """The parallel driver = associate + build_linear_system over all points (chunk sums differ
    only in rounding), and its result does not depend on the thread count (fixed chunk order)."""
    frame, T, model, ref = scene
    params = _params()
    H, g, stats = kn.normal_equations(frame, T, model, ref, params)
    corr = kn.associate(0, len(frame.points_cam), frame, T, model, ref, params)
    H1, g1, stats1 = kn.build_linear_system(corr, model, ref, params)
    np.testing.assert_allclose(H, H1, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(g, g1, rtol=1e-12, atol=1e-15)
    assert stats[:4] == stats1[:4]
    np.testing.assert_allclose(stats[4:], stats1[4:], rtol=1e-12)
    H2, g2, stats2 = kn.normal_equations(frame, T, model, ref, params)
    assert np.array_equal(H, H2) and np.array_equal(g, g2) and stats == stats2


@pytest.mark.parametrize("threads", [2, 3, 5, kn.N_CHUNKS, 64])
def test_normal_equations_are_the_same_on_any_number_of_threads(scene, threads):
    """The tracker's call splits the chunks between threads; the sums come out bit for bit as on
    the calling thread alone, and the worker threads did run a share."""
    import time

    frame, T, model, ref = scene
    params = _params()
    H, g, stats = kn.normal_equations(frame, T, model, ref, params)
    caller = threading.current_thread().name
    ran_on = set()
    original = kn.normal_equation_chunks

    def spy(*args):
        name = threading.current_thread().name
        ran_on.add(name)
        if name == caller:
            time.sleep(0.05)  # a slow share here: the workers start theirs before it could take them back
        return original(*args)

    kn.normal_equation_chunks = spy
    try:
        H2, g2, stats2 = split_normal_equations(frame, T, model, ref, params, threads=threads)
    finally:
        kn.normal_equation_chunks = original
    assert np.array_equal(H, H2) and np.array_equal(g, g2) and stats == stats2
    assert caller in ran_on and len(ran_on) >= 2


def test_normal_equations_take_back_the_chunks_a_busy_worker_has_not_started(scene, monkeypatch):
    """A worker held up elsewhere does not hold the call up: the calling thread runs the chunks
    it handed out and the worker never started, with the same sums."""
    from atlas_pipeline.localization import normal_equations as ne

    frame, T, model, ref = scene
    params = _params()
    H, g, stats = kn.normal_equations(frame, T, model, ref, params)
    monkeypatch.setattr(ne, "_workers", None)  # a pool of one worker, of this test's own
    release = threading.Event()
    pool = ne._pool(1)
    blocker = pool.submit(release.wait, 30.0)  # the only worker, busy
    out = []
    call = threading.Thread(target=lambda: out.append(split_normal_equations(frame, T, model, ref, params, threads=2)))
    try:
        call.start()
        call.join(10.0)
        assert not call.is_alive() and not blocker.done()  # done while the worker was still busy
    finally:
        release.set()
        call.join()
        pool.shutdown()
    H2, g2, stats2 = out[0]
    assert np.array_equal(H, H2) and np.array_equal(g, g2) and stats == stats2


def test_normal_equations_of_few_points_stay_on_the_calling_thread(scene):
    frame, T, model, ref = scene
    assert len(frame.points_cam) < SPLIT_MIN_POINTS
    ran_on = []
    original = kn.normal_equations
    kn.normal_equations = lambda *a: ran_on.append(threading.current_thread().name) or original(*a)
    try:
        split_normal_equations(frame, T, model, ref, _params())
    finally:
        kn.normal_equations = original
    assert ran_on == [threading.current_thread().name]


def test_stats_of_no_correspondence():
    s = kn.Stats(0, 0, 0, 0, 0.0, 0.0, 0.0, 0)
    assert s.inlier_fraction == 0.0 and s.agreement == 0.0 and np.isnan(s.rmse_m)


def test_solve_update_damps_and_limits_the_step():
    H = np.eye(6)
    g = -np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.001])
    xi = solve_update(H.copy(), g, max_step_m=0.02, max_step_rad=0.02)
    assert np.linalg.norm(xi[:3]) == pytest.approx(0.02)  # trust region: scaled down to the step limit
    assert xi[5] / xi[0] == pytest.approx(0.001)  # direction kept
    small = solve_update(H.copy(), -np.full(6, 1e-3), max_step_m=0.02, max_step_rad=0.02)
    C = TRACKER_CONSTANTS
    np.testing.assert_allclose(small, 1e-3 / (1.0 + C.levenberg_damping + C.diagonal_floor), rtol=1e-12)
    assert solve_update(np.zeros((6, 6)), np.full(6, np.nan), 0.02, 0.02) is None


def test_apply_update_is_a_left_world_frame_increment():
    T = _pose([0.1, 0.2, -0.3], [1.0, 2.0, 3.0])
    xi = np.array([0.01, -0.02, 0.03, 0.002, -0.001, 0.003])
    dT = _pose(xi[3:], xi[:3])
    np.testing.assert_allclose(apply_update(xi, T), dT @ T, rtol=0, atol=1e-15)
    assert converged(np.full(6, 1e-7)) and not converged(xi)


def test_gauss_newton_steps_recover_a_small_offset(scene):
    """associate + build_linear_system + solve + apply from a perturbed pose: geometry-only on a
    plane pins three of six degrees of freedom, so the check is the point-to-plane residual."""
    frame, T_true, model, ref = scene
    params = _params(photometric_weight=0.0, noise_a_m=0.0)
    T = _pose([0.0, 0.01, 0.0], [0.0, 0.0, 0.015]) @ T_true
    rmse0 = kn.normal_equations(frame, T, model, ref, params)[2].rmse_m
    for _ in range(5):
        H, g, stats = kn.normal_equations(frame, T, model, ref, params)
        T = apply_update(solve_update(H, g, 0.02, 0.02), T)
    rmse = kn.normal_equations(frame, T, model, ref, params)[2].rmse_m
    assert rmse < 0.5 * rmse0
    assert rmse < 0.006  # the points' own noise is 4 mm


def test_tracker_constants_are_frozen_and_derived_values_follow():
    C = TrackerConstants()
    with pytest.raises(AttributeError):
        C.max_step_m = 1.0  # type: ignore[misc]
    assert C.huber_intensity == C.sigma_intensity * C.huber_intensity_sigmas
    assert C.photometric_scale == (C.sigma_depth_m / C.sigma_intensity) ** 2
    assert C.depth_noise_reference_sigma_m == pytest.approx(
        C.depth_noise_a_m + C.depth_noise_b_per_m * (C.depth_noise_reference_m - C.depth_noise_z0_m) ** 2)


# ---- model view: splatting ------------------------------------------------------------------------

SPLAT_W, SPLAT_H, SPLAT_F = 64, 48, 60.0
LAYER_DEPTH_M = 2.0  # the plane z = 2 m the noisy layer scatters around
LAYER_SIGMA_M = 0.006  # the depth noise a Kinect-class sensor has at 2 m (TrackerConstants' model)


def _noisy_layer(depth_m: float, sigma_m: float, spacing_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Fronto-parallel disks on a grid ``spacing_m`` apart at ``depth_m``, each moved along the
    view axis by N(0, sigma_m): a wall fused from a few noisy frames. ``(centres, normals) [N, 3]``."""
    xs = np.arange(-1.2, 1.2, spacing_m)
    ys = np.arange(-0.9, 0.9, spacing_m)
    gx, gy = np.meshgrid(xs, ys)
    rng = np.random.default_rng(seed)
    c = np.stack([gx.ravel(), gy.ravel(), depth_m + rng.normal(0.0, sigma_m, gx.size)], axis=1)
    return c, np.tile([0.0, 0.0, -1.0], (len(c), 1))


def _splat(centres, normals, radius_m, blend_sigmas: float, blend_floor_m: float):
    C = TRACKER_CONSTANTS
    params = kn.SplatParams(C.splat_max_radius_px, C.min_view_depth_m, C.splat_min_incidence_cos, blend_sigmas,
                            blend_floor_m, C.depth_noise_a_m, C.depth_noise_b_per_m, C.depth_noise_z0_m)
    view = kn.PinholeView(np.eye(4), SPLAT_F, SPLAT_F, (SPLAT_W - 1) / 2.0, (SPLAT_H - 1) / 2.0, SPLAT_W, SPLAT_H)
    return kn.splat_surfels(np.ascontiguousarray(centres), np.ascontiguousarray(normals), radius_m, view, params, True,
                            kn.NO_CULLING)[:2]


def test_a_splat_reuses_its_k_buffer_and_leaves_nothing_of_the_last_view_in_the_next():
    """The k-buffer is kept between splats of one size and not cleared: a view drawn after a
    denser one (more hits a pixel, in the same buffer) is the image a fresh buffer gives."""
    C = TRACKER_CONSTANTS
    sparse = _noisy_layer(LAYER_DEPTH_M, LAYER_SIGMA_M, spacing_m=0.03, seed=5)
    dense = _noisy_layer(LAYER_DEPTH_M - 0.3, LAYER_SIGMA_M, spacing_m=0.005, seed=6)
    kn._splat_scratches.by_size = {}  # a fresh buffer
    first = _splat(*sparse, 0.016, C.splat_blend_sigmas, 0.02)
    buffers = kn._splat_scratch(SPLAT_H, SPLAT_W)
    _splat(*dense, 0.016, C.splat_blend_sigmas, 0.02)  # fills every pixel's k-buffer
    again = _splat(*sparse, 0.016, C.splat_blend_sigmas, 0.02)
    assert kn._splat_scratch(SPLAT_H, SPLAT_W)[0] is buffers[0]  # the same buffer all along
    for a, b in zip(first, again):
        assert np.array_equal(a, b, equal_nan=True)
    assert np.isfinite(first[0][..., 2]).mean() > 0.5


def test_splatting_averages_a_noisy_layer_instead_of_taking_its_front():
    """Overlapping disks of a noisy layer: the nearest alone sits about a sigma in front of the
    surface (the bias that pulled each frame after a keyframe towards its camera); the visibility
    band's mean sits on it."""
    c, n = _noisy_layer(LAYER_DEPTH_M, LAYER_SIGMA_M, spacing_m=0.01, seed=3)
    radius = 0.016  # 0.8 voxels of 2 cm: each pixel's ray meets several disks
    C = TRACKER_CONSTANTS
    nearest, _ = _splat(c, n, radius, 0.0, 0.0)
    blended, nrm = _splat(c, n, radius, C.splat_blend_sigmas, 0.02)
    z_near = np.nanmean(nearest[..., 2])
    z_blend = np.nanmean(blended[..., 2])
    assert LAYER_DEPTH_M - z_near > 0.5 * LAYER_SIGMA_M  # the front of the layer
    assert abs(z_blend - LAYER_DEPTH_M) < 0.15 * LAYER_SIGMA_M  # its middle
    faced = nrm[np.isfinite(nrm[..., 2])]
    np.testing.assert_allclose(faced, np.broadcast_to([0.0, 0.0, -1.0], faced.shape), atol=1e-12)
    # Every pixel holds a point on its own ray.
    v, u = np.nonzero(np.isfinite(blended[..., 2]))
    np.testing.assert_allclose(blended[v, u, 0], (u - (SPLAT_W - 1) / 2.0) / SPLAT_F * blended[v, u, 2], atol=1e-12)


def test_splatting_band_keeps_occluded_surfaces_out():
    """A surface farther behind than the band stays hidden: the view holds the front one alone,
    and its pixels match the nearest-hit render exactly where the front surface is flat."""
    front, n1 = _noisy_layer(1.0, 0.0, spacing_m=0.01, seed=0)
    back, n2 = _noisy_layer(1.3, 0.0, spacing_m=0.01, seed=0)
    c, n = np.concatenate([back, front]), np.concatenate([n2, n1])
    C = TRACKER_CONSTANTS
    blended, _ = _splat(c, n, 0.016, C.splat_blend_sigmas, 0.02)
    nearest, _ = _splat(c, n, 0.016, 0.0, 0.0)
    hit = np.isfinite(blended[..., 2])
    assert hit.mean() > 0.9
    np.testing.assert_allclose(blended[hit, 2], 1.0, atol=1e-12)
    np.testing.assert_allclose(blended[hit], nearest[hit], atol=1e-12)


def _splat_reference(centres, normals, radius_m, params, w, h, f):
    """Plain NumPy :func:`kn.splat_surfels` (every disk hit of every pixel, then the band mean)."""
    c = (w - 1) / 2.0, (h - 1) / 2.0
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - c[0]) / f, (v - c[1]) / f, np.ones_like(u)], axis=-1)  # [h, w, 3]
    hits_z = []
    hits_n = []
    for ctr, nrm in zip(centres, normals):
        if ctr[2] < params.min_depth_m:
            continue
        n = -nrm if nrm @ ctr > 0 else nrm  # facing the camera
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n @ ctr) / denom
        on_disk = np.sum((rays * z[..., None] - ctr) ** 2, axis=-1) <= radius_m ** 2
        # A disk's footprint is capped at max_radius_px pixels from its centre's projection.
        u0, v0 = f * ctr[0] / ctr[2] + c[0], f * ctr[1] / ctr[2] + c[1]
        in_cap = (np.abs(u - u0) <= params.max_radius_px) & (np.abs(v - v0) <= params.max_radius_px)
        ok = (denom <= -params.min_incidence_cos) & (z > 0) & on_disk & in_cap
        hits_z.append(np.where(ok, z, np.inf))
        hits_n.append(n)
    Z = np.stack(hits_z)  # [N, h, w]
    N = np.stack(hits_n)  # [N, 3]
    z0 = Z.min(axis=0)
    dz = np.maximum(z0 - params.noise_z0_m, 0.0)
    band = np.maximum(params.blend_floor_m, params.blend_sigmas * (params.noise_a_m + params.noise_b_per_m * dz ** 2))
    inside = np.isfinite(Z) & (Z <= z0 + band)
    cnt = inside.sum(axis=0)
    zmean = np.where(cnt > 0, np.where(inside, Z, 0.0).sum(axis=0) / np.maximum(cnt, 1), np.nan)
    nsum = np.einsum("khw,kc->hwc", inside.astype(float), N)
    nn = np.linalg.norm(nsum, axis=-1, keepdims=True)
    return rays * zmean[..., None], np.where(cnt[..., None] > 0, nsum / np.where(nn > 0, nn, 1.0), np.nan)


def test_splatting_matches_a_numpy_reference():
    """A noisy layer, a tilted one in front of it and a sphere of disks (every orientation, some
    back-facing or grazing) against the NumPy reference: the k-buffer keeps every hit in the band."""
    rng = np.random.default_rng(11)
    wall, wn = _noisy_layer(2.0, 0.01, spacing_m=0.04, seed=5)
    tilt_n = np.array([0.4, 0.0, -1.0]) / np.hypot(0.4, 1.0)
    gx, gy = np.meshgrid(np.arange(-0.3, 0.3, 0.03), np.arange(-0.3, 0.3, 0.03))
    tilted = np.stack([gx.ravel() - 0.4, gy.ravel(), 1.5 + 0.4 * gx.ravel()], axis=1)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sphere = np.array([0.5, 0.2, 1.2]) + 0.15 * d
    centres = np.concatenate([wall, tilted, sphere])
    normals = np.concatenate([wn, np.tile(tilt_n, (len(tilted), 1)), d])
    C = TRACKER_CONSTANTS
    radius = 0.03
    params = kn.SplatParams(C.splat_max_radius_px, C.min_view_depth_m, C.splat_min_incidence_cos, C.splat_blend_sigmas,
                            0.02, C.depth_noise_a_m, C.depth_noise_b_per_m, C.depth_noise_z0_m)
    got_p, got_n = _splat(centres, normals, radius, C.splat_blend_sigmas, 0.02)
    ref_p, ref_n = _splat_reference(centres, normals, radius, params, SPLAT_W, SPLAT_H, SPLAT_F)
    hit = np.isfinite(ref_p[..., 2])
    assert hit.mean() > 0.5
    np.testing.assert_array_equal(np.isfinite(got_p[..., 2]), hit)
    np.testing.assert_allclose(got_p[hit], ref_p[hit], atol=1e-9)
    np.testing.assert_allclose(got_n[hit], ref_n[hit], atol=1e-9)


def test_the_view_keeps_the_surface_behind_the_first():
    """Two copies of a wall 6 cm apart (drift between passes): the view's first layer is the front
    copy, its layer behind the back copy, both with their normals."""
    front, n1 = _noisy_layer(1.0, 0.0, spacing_m=0.01, seed=0)
    back, n2 = _noisy_layer(1.06, 0.0, spacing_m=0.01, seed=0)
    C = TRACKER_CONSTANTS
    params = kn.SplatParams(C.splat_max_radius_px, C.min_view_depth_m, C.splat_min_incidence_cos, C.splat_blend_sigmas,
                            0.02, C.depth_noise_a_m, C.depth_noise_b_per_m, C.depth_noise_z0_m)
    view = kn.PinholeView(np.eye(4), SPLAT_F, SPLAT_F, (SPLAT_W - 1) / 2.0, (SPLAT_H - 1) / 2.0, SPLAT_W, SPLAT_H)
    pts, nrm, behind, behind_nrm = kn.splat_surfels(np.concatenate([back, front]), np.concatenate([n2, n1]), 0.016,
                                                    view, params, True, kn.NO_CULLING)
    hit = np.isfinite(pts[..., 2]) & np.isfinite(behind[..., 2])
    assert hit.mean() > 0.9
    np.testing.assert_allclose(pts[hit, 2], 1.0, atol=1e-12)
    np.testing.assert_allclose(behind[hit, 2], 1.06, atol=1e-12)
    np.testing.assert_allclose(behind_nrm[hit], np.broadcast_to([0.0, 0.0, -1.0], behind_nrm[hit].shape), atol=1e-12)
    alone, _, none_behind, _ = kn.splat_surfels(np.ascontiguousarray(front), np.ascontiguousarray(n1), 0.016, view,
                                                params, True, kn.NO_CULLING)
    assert np.isnan(none_behind).all() and np.isfinite(alone[..., 2]).mean() > 0.9


def test_a_point_on_the_surface_behind_is_a_correspondence(scene):
    """A frame that lies on the copy behind the first surface agrees with the map: its points match
    the layer behind (MATCH_BEHIND) and pull towards it; with one layer they are gated out."""
    frame, T, model, ref = scene
    params = _params(photometric_weight=0.0)
    shift = np.array([0.0, 0.0, 0.06])  # the whole map surface 6 cm farther, as a second copy
    behind = model.points_cam + shift
    two = model._replace(points_behind_cam=behind, normals_behind_cam=model.normals_cam.copy())
    T_back = T.copy()
    T_back[:3, 3] += model.T_world_cam[:3, :3] @ shift  # the frame aligned to the copy behind
    one = kn.associate(0, len(frame.points_cam), frame, T_back, model, ref, params)
    both = kn.associate(0, len(frame.points_cam), frame, T_back, two, ref, params)
    aligned = kn.associate(0, len(frame.points_cam), frame, T, model, ref, params)  # the frame on the first surface
    n_aligned = int((aligned.geometric == kn.MATCH_OK).sum())
    assert (one.geometric == kn.MATCH_OK).sum() == 0 and (both.geometric == kn.MATCH_BEHIND).sum() >= n_aligned // 2
    _, _, stats_one = kn.build_linear_system(one, model, ref, params)
    _, _, stats_two = kn.build_linear_system(both, two, ref, params)
    assert stats_one.agreement == 0.0 and stats_two.agreement > 0.5 and stats_two.rmse_m < 0.02

"""Mapping has its own, longer depth range than tracking.

The small synthetic room is 6 x 5 m and the camera circles 0.8 m from its walls, so the far walls
lie 4-5 m away: past the tracking (fusion) range of 4 m, within the mapping range of 8 m.
"""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.gaussian_world.builder import GaussianWorld, VoxelGaussianBuilder
from atlas_pipeline.mapping import mapper
from atlas_pipeline.perception.rgbd import fuse

TRACKING_MAX_M = 4.0  # the default fusion.max_depth_m


def _cfg(map_max_m: float, **more):
    over = {"mapping.pose_source": "ground_truth", "mapping.max_depth_m": map_max_m,
            "mapping.fit.epochs": 0, "mapping.colour_refinement.iterations": 0, **more}
    return load_profile("default").with_overrides(over)


def _world(manifest, cfg):
    fused = fuse(manifest, cfg)
    kf = mapper.select_keyframes_stage(manifest, fused, cfg)
    return mapper.build_gaussian_world(fused, kf, cfg, manifest=manifest)


@pytest.fixture(scope="module")
def worlds(small_manifest):
    """The room mapped to the tracking range (4 m) and to the default mapping range (8 m), no fit."""
    return {r: _world(small_manifest, _cfg(r)) for r in (TRACKING_MAX_M, 8.0)}


def _farthest_seen_m(world: GaussianWorld, pts: np.ndarray) -> np.ndarray:
    """``[N]`` the nearest depth at which any keyframe had ``pts [N, 3]`` in front of it."""
    best = np.full(len(pts), np.inf)
    for T in world.T_world_cam_keyframes:
        z = (pts - T[:3, 3]) @ T[:3, 2]  # depth along the camera's optical axis
        best = np.minimum(best, np.where(z > 0, z, np.inf))
    return best


def test_far_walls_get_gaussians_on_the_walls(worlds):
    from atlas_pipeline.sensors.synthetic import build_scene

    near, far = worlds[TRACKING_MAX_M], worlds[8.0]
    assert len(far.field) > len(near.field)
    depth = _farthest_seen_m(far, far.field.positions)
    beyond = far.field.positions[depth > TRACKING_MAX_M + 0.05]
    # a fair share of the map lies where no keyframe saw it within the tracking range
    assert len(beyond) > 0.05 * len(far.field), (len(beyond), len(far.field))
    # and it lies on the room's surfaces (noise-free synthetic depth: within a voxel or two)
    clearance = build_scene(0).clearance_m(beyond)
    assert np.median(np.abs(clearance)) < 0.02 and np.quantile(np.abs(clearance), 0.9) < 0.05
    # the tracking-range world has nothing there
    assert (_farthest_seen_m(near, near.field.positions) < TRACKING_MAX_M + 0.05).all()


def test_held_out_views_cover_more_and_score_higher(small_manifest, worlds):
    """Held-out frames rendered from ground truth: more pixels drawn and a higher full-frame PSNR
    with the longer mapping range (the masked PSNR counts pixels within the tracking range only)."""
    from atlas_pipeline.gaussian_world.evaluation import evaluate_views
    from atlas_pipeline.gaussian_world.render import render_gaussians

    cam = small_manifest.camera
    held = np.setdiff1d(np.arange(small_manifest.n_frames), worlds[8.0].keyframe_indices)
    assert len(held) >= 2
    T = small_manifest.T_world_cam_gt
    res, drawn = {}, {}
    for r, w in worlds.items():
        res[r] = evaluate_views(w.field, small_manifest, T, held, "ground_truth", w.map_id, (0.1, TRACKING_MAX_M))
        drawn[r] = np.mean([render_gaussians(w.field.positions, w.field.scales, w.field.rotations_xyzw,
                                             w.field.colors, w.field.opacities, T[i], cam.K, cam.width,
                                             cam.height).alpha.mean() for i in held])
    assert drawn[8.0] > drawn[TRACKING_MAX_M] + 0.03, drawn
    psnr = {r: float(np.nanmean(res[r].psnr_db)) for r in res}
    assert psnr[8.0] > psnr[TRACKING_MAX_M] + 0.5, psnr


def test_tracking_map_keeps_the_fusion_range(worlds):
    """The tracking map (the world's voxel statistics localization tracks against) is the same,
    bit for bit, whatever the mapping range; only the Gaussians' own statistics reach further."""
    a, b = worlds[TRACKING_MAX_M].tracking_voxels, worlds[8.0].tracking_voxels
    for name in ("ids", "count", "sum_xyz", "sum_rgb", "sum_sq", "n_keyframes", "weight"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert len(worlds[8.0].map_voxels) > len(b)


def test_tracker_depth_range_is_the_fusion_range(small_manifest, worlds, monkeypatch):
    """SLAM (estimated poses) and localization hand the tracker the fusion range, never the mapping one."""
    from atlas_pipeline.localization import localizer, sequence
    from atlas_pipeline.mapping.keyframes import slam_poses

    seen = []
    init = sequence.SequenceTracker.__init__

    def spy(self, camera, cfg, depth_range_m, *args, **kwargs):
        seen.append(tuple(float(v) for v in depth_range_m))
        init(self, camera, cfg, depth_range_m, *args, **kwargs)

    monkeypatch.setattr(sequence.SequenceTracker, "__init__", spy)
    cfg = _cfg(8.0, **{"mapping.loop_closure": False})
    fused = fuse(small_manifest, cfg)
    slam_poses(small_manifest, cfg.mapping, cfg.localization, (fused.min_depth_m, fused.max_depth_m), fused.stride,
               frames=[(small_manifest.read_rgb(i), small_manifest.read_depth_m(i)) for i in range(4)])
    captured = []
    real = localizer.localize_sequence

    def spy_localize(*args, **kwargs):
        captured.append(kwargs["depth_range_m"])
        raise RuntimeError("stop here")  # the range is what this test is about

    monkeypatch.setattr(localizer, "localize_sequence", spy_localize)
    with pytest.raises(RuntimeError, match="stop here"):
        localizer.localize(small_manifest, worlds[8.0], cfg)
    assert real is not spy_localize
    assert seen and all(r == (0.1, TRACKING_MAX_M) for r in seen), seen
    assert captured == [(0.1, TRACKING_MAX_M)]
    assert fused.max_depth_m == TRACKING_MAX_M and cfg.mapping.max_depth_m == 8.0


def test_a_far_noisy_point_moves_a_voxel_less_than_a_near_one():
    """Inverse-variance merging: the same 1 cm outlier added to a voxel of near points shifts its
    mean a lot less when it was measured at 7 m than at 1 m (unweighted, both shift it equally)."""
    v = 0.02
    rng = np.random.default_rng(0)
    base = 0.01 + 0.002 * rng.standard_normal((20, 3))  # a voxel's worth of points, near its centre
    base_w = mapper.depth_weight(np.full(len(base), 1.0), v)
    outlier = np.array([[0.019, 0.019, 0.019]])

    def mean_after(outlier_depth_m: float | None) -> np.ndarray:
        b = VoxelGaussianBuilder(v)
        b.integrate(base, np.zeros((len(base), 3)), base_w)
        if outlier_depth_m is not None:
            b.integrate(outlier, np.zeros((1, 3)), mapper.depth_weight(np.array([outlier_depth_m]), v))
        return b.to_field().positions[0]

    m0 = mean_after(None)
    shift_near = np.linalg.norm(mean_after(1.0) - m0)
    shift_far = np.linalg.norm(mean_after(7.0) - m0)
    assert shift_far < 0.25 * shift_near, (shift_near, shift_far)
    # the weights follow the sensor model: ~1 while the noise is below a voxel, 1/sigma^2 beyond
    w = mapper.depth_weight(np.array([0.5, 1.0, 2.0, 4.0, 8.0]), v)
    assert (np.diff(w) < 0).all() and w[0] > 0.99 and w[1] > 0.99 and w[-1] < 0.05


def test_weighted_builder_matches_unweighted_when_weights_are_equal():
    """Equal weights change nothing (the weighted sums divide by their weight), and a weighted
    builder moved by ``merge`` matches integrating its points at the new pose."""
    from atlas_pipeline.geometry import rotmat_to_quat_xyzw  # noqa: F401 (imported by to_field)

    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.2, 0.2, (500, 3))
    pts[:, 2] *= 0.05  # a thin slab: real shapes
    cols = rng.integers(0, 256, (500, 3))
    a, b = VoxelGaussianBuilder(0.02), VoxelGaussianBuilder(0.02)
    a.integrate(pts, cols)
    b.integrate(pts, cols, np.full(len(pts), 0.3))
    fa, fb = a.to_field(), b.to_field()
    np.testing.assert_allclose(fa.positions, fb.positions, atol=1e-12)
    np.testing.assert_allclose(fa.scales, fb.scales, rtol=1e-5, atol=1e-7)
    assert np.array_equal(fa.colors, fb.colors)
    w = rng.uniform(0.01, 1.0, len(pts))
    c, d = VoxelGaussianBuilder(0.02), VoxelGaussianBuilder(0.02)
    c.integrate(pts, cols, w)
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]  # a translation by whole voxels keeps every voxel whole
    d.merge(c, T)
    moved = VoxelGaussianBuilder(0.02)
    moved.integrate(pts + T[:3, 3], cols, w)
    np.testing.assert_allclose(d.to_field().positions, moved.to_field().positions, atol=1e-9)
    with pytest.raises(ValueError, match="weights"):
        c.integrate(pts, cols, np.zeros(len(pts)))


def test_sensor_model_is_the_synthetic_kinects():
    """The noise model the mapper and the tracker weight with is the one the synthetic Kinect v1
    writes depth with."""
    from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as C
    from atlas_pipeline.sensors import depth_noise
    from atlas_pipeline.sensors.synthetic import KINECT_V1_SENSOR

    assert depth_noise.DEPTH_NOISE_A_M == KINECT_V1_SENSOR["depth_noise_a_m"]
    assert depth_noise.DEPTH_NOISE_B_PER_M == KINECT_V1_SENSOR["depth_noise_b_per_m"]
    assert (C.depth_noise_a_m, C.depth_noise_b_per_m, C.depth_noise_z0_m) == (
        depth_noise.DEPTH_NOISE_A_M, depth_noise.DEPTH_NOISE_B_PER_M, depth_noise.DEPTH_NOISE_Z0_M)
    np.testing.assert_allclose(mapper.depth_sigma_m(np.array([1.0, 3.0])), [0.001884, 0.0140444], rtol=1e-4)
    w = mapper.depth_loss_weight(np.array([[0.0, 1.0, 8.0]]), 0.02)
    assert w[0, 0] == 0.0 and w[0, 1] > 0.99 and 0.1 < w[0, 2] < 0.25


def test_depth_loss_weight_scales_the_depth_term_only():
    """The fit's per-pixel depth weights scale the depth L1 term pixel by pixel; pixels without a
    reading add nothing however they are weighted."""
    from atlas_pipeline.gaussian_world.optimize import LossWeights, render_loss_and_gradients
    from atlas_pipeline.gaussian_world.raster import GaussianArrays

    rng = np.random.default_rng(2)
    n = 40
    pos = np.c_[rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(1.5, 2.5, n)]
    scl = np.full((n, 3), 0.08)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    col = rng.uniform(0, 1, (n, 3))
    op = np.full(n, 0.9)
    K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    img = rng.uniform(0, 1, (24, 32, 3))
    dep = np.where(rng.uniform(size=(24, 32)) < 0.7, 2.2, 0.0)

    def loss(w_depth, wmap=None):
        return render_loss_and_gradients(GaussianArrays(pos, scl, q, col, op), np.eye(4), K, img, dep,
                                         LossWeights(1.0, w_depth), depth_weight_map=wmap)[0]

    base, full = loss(0.0), loss(1.0)
    assert full > base
    half = loss(1.0, np.full(dep.shape, 0.5, np.float32))
    assert half - base == pytest.approx(0.5 * (full - base), rel=1e-4)
    # weight where there is no reading: no effect
    junk = np.where(dep > 0, 1.0, 7.0).astype(np.float32)
    assert loss(1.0, junk) == pytest.approx(full, rel=1e-6)


def test_mapping_range_must_cover_the_tracking_range():
    with pytest.raises(ConfigError, match="mapping.max_depth_m must be >= fusion.max_depth_m"):
        load_profile("default").with_overrides({"mapping.max_depth_m": 3.0})
    assert load_profile("default").mapping.max_depth_m == 8.0
    assert load_profile("demo").mapping.max_depth_m == 8.0


def test_world_roundtrip_keeps_the_mapping_statistics(tmp_path, worlds):
    w = worlds[8.0]
    w.save(tmp_path / "w")
    back = GaussianWorld.load(tmp_path / "w")
    for name in ("ids", "count", "weight", "sum_xyz", "sum_sq", "sum_rgb", "n_keyframes"):
        assert np.array_equal(getattr(back.map_voxels, name), getattr(w.map_voxels, name)), name
        assert np.array_equal(getattr(back.tracking_voxels, name), getattr(w.tracking_voxels, name)), name
    # a world saved before mapping had its own range: no mapping statistics, the tracking ones serve
    old = GaussianWorld(w.field, w.tracking_voxels, w.keyframe_indices, w.T_world_cam_keyframes, w.pose_source, w.history)
    old.save(tmp_path / "old")
    back_old = GaussianWorld.load(tmp_path / "old")
    assert back_old.map_voxels is None and back_old.field_voxels is back_old.tracking_voxels


def test_extending_a_world_extends_its_map_too(small_manifest):
    cfg = _cfg(8.0)
    fused = fuse(small_manifest, cfg)
    kf = mapper.select_keyframes_stage(small_manifest, fused, cfg)
    half = len(kf.indices) // 2
    from dataclasses import replace

    first = mapper.build_world(fused, replace(kf, indices=kf.indices[:half]), cfg.mapping, manifest=small_manifest)
    n_map, n_track = len(first.map_voxels), len(first.tracking_voxels)
    both = mapper.extend_world(first, fused, replace(kf, indices=kf.indices[half:]), cfg.mapping,
                               manifest=small_manifest)
    whole = mapper.build_world(fused, kf, cfg.mapping, manifest=small_manifest)
    assert len(both.map_voxels) > n_map and len(both.tracking_voxels) > n_track
    assert np.array_equal(both.map_voxels.ids, whole.map_voxels.ids)
    np.testing.assert_allclose(both.map_voxels.sum_xyz, whole.map_voxels.sum_xyz, rtol=1e-12)


@pytest.mark.slow
def test_fitted_world_scores_higher_full_frame(small_manifest):
    """With the keyframe fit on, the longer mapping range still gives the held-out views a higher
    full-frame PSNR, and the fit's densification reaches the far Gaussians (its depth weights are
    < 1 there, never 0)."""
    from atlas_pipeline.gaussian_world.evaluation import evaluate_views

    fit = {"mapping.fit.epochs": 6, "mapping.fit.max_steps": 36,
           "mapping.colour_refinement.iterations": 1}
    held = None
    psnr = {}
    for r in (TRACKING_MAX_M, 8.0):
        w = _world(small_manifest, _cfg(r, **fit))
        if held is None:
            held = np.setdiff1d(np.arange(small_manifest.n_frames), w.keyframe_indices)
        rep = evaluate_views(w.field, small_manifest, small_manifest.T_world_cam_gt, held, "ground_truth", w.map_id,
                             (0.1, TRACKING_MAX_M))
        psnr[r] = float(np.nanmean(rep.psnr_db))
        assert w.fit["steps"] > 0
    assert psnr[8.0] > psnr[TRACKING_MAX_M] + 0.3, psnr


def test_mapping_range_reruns_the_world_only():
    """``mapping.max_depth_m`` is a setting of gaussian_world (which reads it), not of keyframes or
    fused_frames (the tracker and the fused points keep the fusion range)."""
    from assets.versioning import stage_settings

    a, b = load_profile("default"), load_profile("default").with_overrides({"mapping.max_depth_m": 6.0})
    changed = [s for s in ("fused_frames", "keyframes", "gaussian_world", "localization_report", "render_evaluation")
               if stage_settings(a, s) != stage_settings(b, s)]
    assert changed == ["gaussian_world"]
    assert stage_settings(b, "gaussian_world")["mapping.max_depth_m"] == 6.0


def test_noise_cells_grow_with_depth_noise():
    from atlas_pipeline.mapping.mapper import MAX_NOISE_CELL_VOXELS, depth_sigma_m, noise_cell_voxels

    z = np.array([0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 20.0])
    cells = noise_cell_voxels(z, 0.02)
    assert list(cells) == sorted(cells) and cells[0] == cells[1] == cells[2] == 1 and cells[-1] == MAX_NOISE_CELL_VOXELS
    sigma = depth_sigma_m(z)
    ok = sigma / 0.02 <= MAX_NOISE_CELL_VOXELS
    # the smallest power of two covering the noise: no smaller cell would
    assert (cells[ok] * 0.02 >= sigma[ok] - 1e-12).all() and ((cells[ok] // 2) * 0.02 < np.maximum(sigma[ok], 0.02)).all()


def test_a_noise_cell_is_one_wide_gaussian_under_its_first_voxels_id():
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder, pack_voxel_ids

    v = 0.02
    rng = np.random.default_rng(0)
    # points spread over the 4x4x4-voxel cell whose first voxel is (-4, 0, 4) (below zero on x: floor)
    pts = rng.uniform([-0.08, 0.0, 0.08], [-0.0001, 0.08, 0.16], (400, 3))
    cells = VoxelGaussianBuilder(v)
    cells.integrate(pts, np.full((400, 3), 128), cell_voxels=np.full(400, 4))
    fine = VoxelGaussianBuilder(v)
    fine.integrate(pts, np.full((400, 3), 128))
    assert len(cells) == 1 and cells.ids[0] == pack_voxel_ids(np.array([[-4, 0, 4]]))[0] and len(fine) > 30
    g = cells.to_field()
    assert np.allclose(g.positions[0], pts.mean(axis=0)) and g.scales[0].min() > 1.5 * v  # as wide as the cell (fine voxels stop at 0.75 v)


def test_hole_fill_takes_the_nearest_reading_within_reach():
    """A pixel without a reading gets the nearest reading's depth when one lies within
    ``HOLE_FILL_MAX_FRACTION`` of the width; readings, far holes and out-of-range depth do not."""
    depth = np.zeros((40, 100), np.float32)
    depth[10:, :50] = 2.0
    depth[10:, 50:] = 3.0
    depth[30:, 90:] = 9.0  # past the range: a hole too
    reach = mapper.HOLE_FILL_MAX_FRACTION * depth.shape[1]  # 5 px
    filled = mapper.hole_fill_depth(depth, 0.1, 8.0)
    assert (filled[10:30, :90] == 0).all()  # readings are not holes
    assert (filled[5:10, :50] == 2.0).all() and (filled[5:10, 50:90] == 3.0).all()  # the band above them
    assert (filled[: 10 - int(reach) - 1] == 0).all()  # out of reach
    assert (filled[35:, 95:] == 0).all() and (filled[30:, 90:93] == 3.0).all()  # 9 m is no reading
    assert (mapper.hole_fill_depth(np.zeros((8, 8), np.float32), 0.1, 8.0) == 0).all()  # nothing to copy


def test_depth_holes_get_gaussians_only_when_filled(small_manifest, monkeypatch):
    """Keyframes whose top rows have no depth (as a registered depth image's border band): with
    hole filling the map holds Gaussians there and a keyframe's view of the band is drawn;
    without it the band renders as background."""
    from atlas_pipeline.gaussian_world.render import render_gaussians

    band = 6
    read = small_manifest.read_depth_m

    def holed(i, **kw):
        d = read(i, **kw).copy()
        d[:band] = 0.0
        return d

    monkeypatch.setattr(small_manifest, "read_depth_m", holed)
    cam = small_manifest.camera
    cover = {}
    for fill in (False, True):
        cfg = _cfg(8.0, **{"mapping.fill_depth_holes": fill})
        world = _world(small_manifest, cfg)
        T = world.T_world_cam_keyframes[0]
        f = world.field
        r = render_gaussians(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, T, cam.K,
                             cam.width, cam.height)
        pc = (f.positions - T[:3, 3]) @ T[:3, :3]  # camera frame
        front = pc[:, 2] > 0.1
        v = cam.fy * pc[front, 1] / pc[front, 2] + cam.cy
        u = cam.fx * pc[front, 0] / pc[front, 2] + cam.cx
        in_band = int(((v >= 0) & (v < band) & (u >= 0) & (u < cam.width)).sum())
        cover[fill] = (float((r.alpha[:band] > 0.5).mean()), in_band)
    # Gaussians in the band: a few from other keyframes' lower rows without filling, many with it;
    # and the band is drawn (without the fit, voxel Gaussians of a 160x120 view cover 60 % of a frame).
    assert cover[True][1] > 5 * cover[False][1], cover
    assert cover[False][0] == 0.0 and cover[True][0] > 0.1, cover

"""One copy of each surface in the tracking map, and a motion prior where the surfaces leave the
camera free: what lets a world localize the frames it was built from after drift."""

from dataclasses import replace

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.localization.tracker import (
    SurfelModel,
    add_motion_prior,
    solve_update,
)
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS
from atlas_pipeline.mapping import mapper
from atlas_pipeline.perception.rgbd import fuse
from atlas_pipeline.mapping import consistency
from atlas_pipeline.mapping.consistency import CONFLICT_MIN_M, conflict_tolerance_m, disagreeing_points
from atlas_pipeline.sensors.camera import CameraIntrinsics
from tests.conftest import InlinePool

CAMERA = CameraIntrinsics(width=160, height=120, fx=120.0, fy=120.0, cx=79.5, cy=59.5)
VOXEL_M = 0.02


def _wall_model(z_m: float = 2.0, half_m: float = 0.5) -> SurfelModel:
    """Surfels of a square wall at depth ``z_m`` in front of a camera at the origin."""
    g = np.arange(-half_m, half_m, VOXEL_M / 3)
    x, y = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z_m)], axis=1)
    pts = np.concatenate([pts, pts + [0.0, 0.0, 0.004]])  # a little thickness for the normals
    return SurfelModel.from_field(pts, VOXEL_M)


def test_points_off_the_mapped_surface_disagree_and_new_or_matching_points_do_not():
    model = _wall_model()
    assert len(model) > 100
    pts = np.array([
        [0.0, 0.0, 2.0],     # on the wall: a second look
        [0.1, 0.05, 2.02],   # within the noise tolerance
        [0.0, 0.1, 1.9],     # 10 cm in front of it: a copy drift put there
        [-0.1, 0.0, 2.1],    # 10 cm behind it
        [1.0, 0.0, 2.0],     # beside the wall, where the map has nothing: new surface
        [0.0, 0.0, -1.0],    # behind the camera
    ])
    got = disagreeing_points(model, pts, np.eye(4), CAMERA)
    assert got.tolist() == [False, False, True, True, False, False]
    # the same points seen from a camera moved 10 cm towards the wall: nothing changes
    T = np.eye(4)
    T[2, 3] = 0.1
    assert disagreeing_points(model, pts - [0.0, 0.0, 0.1], T, CAMERA).tolist() == got.tolist()


def test_the_tolerance_grows_with_the_depth_noise():
    tol = conflict_tolerance_m(np.array([0.5, 1.0, 4.0, 8.0]))
    assert tol[0] == CONFLICT_MIN_M and np.all(np.diff(tol) >= 0) and tol[-1] > 0.1


@pytest.fixture(scope="module")
def small_inputs(small_manifest):
    cfg = load_profile("default")
    fused = fuse(small_manifest, cfg)
    kf = mapper.select_keyframes_stage(small_manifest, fused, cfg)
    return cfg, fused, kf


def _drifted(kf, shift_m: float):
    """The keyframes with the second half's poses moved ``shift_m`` along the first camera's
    optical axis, as drift before a loop would leave them."""
    T = np.array(kf.T_world_cam)
    later = kf.indices[len(kf.indices) // 2:]
    T[later, :3, 3] += shift_m * T[kf.indices[0], :3, 2]
    return replace(kf, T_world_cam=T)


def test_a_drifted_return_does_not_double_the_tracking_map(small_manifest, small_inputs, monkeypatch):
    cfg, fused, kf = small_inputs
    assert len(kf.indices) >= 4
    drifted = _drifted(kf, 0.08)
    exact = mapper.build_world(fused, kf, cfg.mapping, manifest=small_manifest)
    kept = mapper.build_world(fused, drifted, cfg.mapping, manifest=small_manifest)
    with monkeypatch.context() as m:  # every point merged, as before the check
        m.setattr(consistency, "disagreeing_points", lambda model, pts, T, camera: np.zeros(len(pts), bool))
        exact_all = mapper.build_world(fused, kf, cfg.mapping, manifest=small_manifest)
        doubled = mapper.build_world(fused, drifted, cfg.mapping, manifest=small_manifest)
    # With the right poses the check leaves out almost nothing (edges and noise only) ...
    assert len(exact.tracking_voxels) >= 0.97 * len(exact_all.tracking_voxels)
    # ... while 8 cm of drift would add a second copy of what the later keyframes see again.
    extra_doubled = len(doubled.tracking_voxels) - len(exact_all.tracking_voxels)
    extra_kept = len(kept.tracking_voxels) - len(exact.tracking_voxels)
    assert extra_doubled > 0.1 * len(exact_all.tracking_voxels)
    assert extra_kept < 0.25 * extra_doubled
    # The Gaussians (the rendered map) are not touched by the check.
    assert np.array_equal(kept.map_voxels.ids, doubled.map_voxels.ids)
    np.testing.assert_array_equal(kept.map_voxels.sum_xyz, doubled.map_voxels.sum_xyz)


def _two_planes_H() -> np.ndarray:
    """``[6, 6]`` point-to-plane normal matrix of a floor and a wall (normals z and x): the
    camera may slide along y."""
    rng = np.random.default_rng(1)
    normals = np.repeat(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), 400, axis=0)
    points = rng.uniform(-1.0, 1.0, (len(normals), 3)) + [0.0, 0.0, 2.0]
    J = np.concatenate([normals, np.cross(points, normals)], axis=1)  # d(n.p)/d(v, omega)
    return J.T @ J


def test_the_motion_prior_holds_a_free_direction_and_leaves_a_pinned_one_to_the_data():
    C = TRACKER_CONSTANTS
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 1.0]
    pred = T[:3, 3].copy()
    # the data pull 1 cm along the free direction (y) and 1 cm along a pinned one (x)
    H = _two_planes_H()
    xi_true = np.array([0.01, 0.01, 0.0, 0.0, 0.0, 0.0])
    g = -H @ xi_true
    g[1] -= 0.05 * H[0, 0] * 0.01  # a weak pull along y, as a doubled surface's few points give
    free = solve_update(H.copy(), g.copy(), 1.0, 1.0)
    H2, g2 = H.copy(), g.copy()
    add_motion_prior(H2, g2, T, pred, C.motion_prior_share)
    held = solve_update(H2, g2, 1.0, 1.0)
    assert abs(free[1]) > 0.01  # without the prior the camera slides
    assert abs(held[1]) < 0.25 * abs(free[1])
    assert held[0] == pytest.approx(0.01, rel=0.1)  # the pinned direction follows the data
    # With every direction pinned the prior changes the step little (more than its share: a
    # sideways move of the camera is partly confounded with a turn, so the data pin it less).
    rng = np.random.default_rng(2)
    normals = rng.normal(size=(900, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.uniform(-1.0, 1.0, (900, 3)) + [0.0, 0.0, 2.0]
    J = np.concatenate([normals, np.cross(points, normals)], axis=1)
    H = J.T @ J
    g = -H @ xi_true
    plain = solve_update(H.copy(), g.copy(), 1.0, 1.0)
    H3, g3 = H.copy(), g.copy()
    add_motion_prior(H3, g3, T, pred, C.motion_prior_share)
    with_prior = solve_update(H3, g3, 1.0, 1.0)
    assert np.linalg.norm(with_prior[:3] - plain[:3]) < 0.1 * np.linalg.norm(plain[:3])


def test_a_session_extending_a_world_keeps_one_copy_of_its_surfaces(small_manifest, small_inputs):
    """``build --extend`` merges its keyframes through the tracker: a keyframe placed 8 cm off the
    surfaces the saved world has must not add a second copy of them."""
    import copy

    from atlas_pipeline.localization.sequence import SequenceTracker

    cfg, fused, kf = small_inputs
    world = mapper.build_world(fused, kf, cfg.mapping, manifest=small_manifest)
    k = int(kf.indices[len(kf.indices) // 2])
    T = np.array(kf.T_world_cam[k])
    T[:3, 3] += 0.08 * T[:3, 2]  # drift along the optical axis: every mapped wall seen 8 cm off
    added, refused = {}, {}
    for one_surface in (False, True):
        tracking = copy.deepcopy(world.tracking_voxels)
        st = SequenceTracker(small_manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                             builder=tracking, prior_poses=world.T_world_cam_keyframes, one_surface=one_surface)
        fp = st.tracker.prepare(small_manifest.read_rgb(k), small_manifest.read_depth_m(k))
        st._integrate(k, fp, T)
        added[one_surface] = len(tracking) - len(world.tracking_voxels)
        refused[one_surface] = st.n_refused_points
    # Merged as it comes, the drifted keyframe adds a second copy of a third of the map ...
    assert refused[False] == 0 and added[False] > 0.2 * len(world.tracking_voxels)
    # ... checked, what it adds is what lies along the surfaces (edges, grazing floor), a third of that.
    assert refused[True] > 0 and added[True] < 0.4 * added[False]


@pytest.mark.parametrize("with_images", [True, False])
def test_the_two_maps_merged_on_two_threads_equal_one_after_the_other(small_manifest, small_inputs, monkeypatch,
                                                                      with_images):
    """The Gaussians' statistics take each keyframe on a worker thread while the tracking map
    takes it here: the same world, bit for bit, as every step on one thread in keyframe order.
    Without the recording's images both threads read the fused points, chunk by chunk."""
    from atlas_pipeline.perception.rgbd import fuse_frames

    cfg, _, kf = small_inputs
    fused = fuse_frames(small_manifest, cfg.fusion, chunk_frames=2)  # many chunks: the threads read different ones
    manifest = small_manifest if with_images else None
    threaded = mapper.build_world(fused, kf, cfg.mapping, manifest=manifest)
    monkeypatch.setattr(mapper, "ThreadPoolExecutor", InlinePool)
    serial = mapper.build_world(fused, kf, cfg.mapping, manifest=manifest)
    for name in ("tracking_voxels", "map_voxels"):
        a, b = getattr(threaded, name), getattr(serial, name)
        assert np.array_equal(a.ids, b.ids), name
        for stat in ("count", "sum_xyz", "sum_rgb", "sum_sq", "weight"):
            assert np.array_equal(getattr(a, stat), getattr(b, stat)), (name, stat)
    assert np.array_equal(threaded.history, serial.history)
    assert len(threaded.history) == len(kf.indices) and threaded.history[-1] == len(threaded.map_voxels)
    assert fused.n_chunks > 2 and len(kf.indices) >= 4

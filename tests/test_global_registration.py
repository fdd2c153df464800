"""Global registration (localization/global_registration.py, _ransac.py): repeatable RANSAC over
feature matches, graded by the frame's points on the map, and point-to-plane ICP."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from scipy.spatial import cKDTree

from atlas_pipeline.geometry import so3_exp
from atlas_pipeline.localization import global_registration as gr
from atlas_pipeline.localization._ransac import RansacParams, fit_rigid, iterations_needed, ransac_batch
from atlas_pipeline.localization._voxel_hash import table_of_points
from atlas_pipeline.localization.tracker import pose_change


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rotvec, np.float64))
    T[:3, 3] = t
    return T


def _room(rng: np.random.Generator, step_m: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[M, 3]`` and normals of a floor, two walls and two boxes of different sizes: no
    symmetry maps it onto itself."""
    pts, nrm = [], []

    def plane(origin, u, v, nu, nv, normal):
        a, b = np.meshgrid(np.arange(nu) * step_m, np.arange(nv) * step_m, indexing="ij")
        p = np.asarray(origin) + a.reshape(-1, 1) * np.asarray(u) + b.reshape(-1, 1) * np.asarray(v)
        pts.append(p)
        nrm.append(np.tile(normal, (len(p), 1)))

    plane([0, 0, 0], [1, 0, 0], [0, 1, 0], 150, 100, [0, 0, 1.0])  # floor 3 x 2 m
    plane([0, 0, 0], [1, 0, 0], [0, 0, 1], 150, 60, [0, 1.0, 0])  # wall y = 0
    plane([0, 0, 0], [0, 1, 0], [0, 0, 1], 100, 60, [1.0, 0, 0])  # wall x = 0
    for (x, y), (w, d, h) in (((1.0, 0.8), (0.4, 0.3, 0.5)), ((2.2, 1.3), (0.25, 0.6, 0.3))):
        plane([x, y, h], [1, 0, 0], [0, 1, 0], int(w / step_m), int(d / step_m), [0, 0, 1.0])
        plane([x, y, 0], [1, 0, 0], [0, 0, 1], int(w / step_m), int(h / step_m), [0, -1.0, 0])
        plane([x, y, 0], [0, 1, 0], [0, 0, 1], int(d / step_m), int(h / step_m), [-1.0, 0, 0])
    p = np.concatenate(pts) + rng.normal(0, 0.001, (sum(len(q) for q in pts), 3))
    return p, np.concatenate(nrm)


def _matches(rng, n_true: int, n_false: int, T: np.ndarray, extent_m: float = 3.0):
    """``src, dst [n, 3]``: ``n_true`` exact pairs under ``T`` mixed with ``n_false`` random ones."""
    src = rng.uniform(0, extent_m, (n_true + n_false, 3))
    dst = src @ T[:3, :3].T + T[:3, 3]
    dst[n_true:] = rng.uniform(0, extent_m, (n_false, 3))
    order = rng.permutation(len(src))
    return np.ascontiguousarray(src[order]), np.ascontiguousarray(dst[order])


def test_fit_rigid_recovers_a_rotation_and_translation_and_never_a_reflection():
    rng = np.random.default_rng(0)
    T = _pose([0.3, -0.2, 0.9], [0.5, -1.0, 2.0])
    src = rng.normal(size=(20, 3))
    got = fit_rigid(src, src @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(got[:, :3], T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(got[:, 3], T[:3, 3], atol=1e-9)
    mirrored = src * np.array([1.0, 1.0, -1.0])  # the best proper rotation, not the mirror
    assert np.linalg.det(fit_rigid(src, mirrored)[:, :3]) == pytest.approx(1.0)


def test_ransac_finds_the_pose_behind_a_tenth_of_the_matches_and_ranks_it_by_the_points_it_explains():
    rng = np.random.default_rng(1)
    T = _pose([0.1, 0.2, -0.4], [0.3, 0.2, -0.1])
    cloud = rng.uniform(0, 3.0, (3000, 3))
    table = table_of_points(cloud @ T[:3, :3].T + T[:3, 3], 0.075)
    src, dst = _matches(rng, 40, 360, T)
    found = gr.ransac_poses(src, dst, cloud, table, RansacParams(0.075, 0.9, 0), n_poses=3)
    assert found, "no pose found"
    dt, dr = pose_change(found[0], T)
    assert dt < 0.01 and dr < 0.5, (dt, dr)


def test_ransac_gives_the_same_poses_on_every_run_and_any_number_of_threads():
    rng = np.random.default_rng(2)
    T = _pose([0.0, 0.3, 0.1], [1.0, 0.0, 0.5])
    cloud = rng.uniform(0, 3.0, (2000, 3))
    table = table_of_points(cloud @ T[:3, :3].T + T[:3, 3], 0.075)
    src, dst = _matches(rng, 30, 570, T)
    params = RansacParams(0.075, 0.9, 7)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = ransac_batch(src, dst, cloud, table, 0, 5000, params)
    finally:
        numba.set_num_threads(threads)
    many = ransac_batch(src, dst, cloud, table, 0, 5000, params)
    again = ransac_batch(src, dst, cloud, table, 0, 5000, params)
    for a, b, c in zip(one, many, again):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(b, c)
    # A later batch continues the sequence rather than repeating it; another seed draws others.
    later = ransac_batch(src, dst, cloud, table, 5000, 5000, params)
    other = ransac_batch(src, dst, cloud, table, 0, 5000, params._replace(seed=8))
    assert not np.array_equal(later[0], many[0]) and not np.array_equal(other[0], many[0])


def test_iterations_needed_follows_the_ransac_formula():
    assert iterations_needed(0.5, 0.99) == pytest.approx(np.log(0.01) / np.log(1 - 0.125))
    assert iterations_needed(0.0, 0.99) == float("inf")
    assert iterations_needed(1.0, 0.99) == 1.0


def test_mutual_matches_keep_the_pairs_that_choose_each_other():
    src = np.array([[0.0, 0.0], [1.0, 1.0], [5.0, 5.0], [5.1, 5.1]] + [[9.0 + k, 0.0] for k in range(9)])
    dst = np.array([[0.1, 0.0], [1.0, 1.1], [5.03, 5.03]] + [[9.0 + k, 0.1] for k in range(9)])
    m = gr.mutual_matches(src, dst, cKDTree(dst))
    pairs = {tuple(p) for p in m}
    assert (0, 0) in pairs and (1, 1) in pairs
    # Frame points 2 and 3 both choose map point 2, which chooses only one of them.
    assert sum((i, 2) in pairs for i in (2, 3)) == 1
    assert len(m) == len(src) - 1


def test_icp_point_to_plane_undoes_a_small_offset_of_a_frame_in_a_room():
    rng = np.random.default_rng(3)
    pts, nrm = _room(rng)
    T_true = _pose([0.02, -0.03, 0.2], [0.4, 0.3, 0.1])
    frame = (pts[::7] - T_true[:3, 3]) @ T_true[:3, :3]  # map points in the "camera" frame
    T_guess = _pose([0.0, 0.0, 0.25], [0.45, 0.27, 0.12])
    got = gr.icp_point_to_plane(frame, T_guess, cKDTree(pts), pts, nrm, (0.2, 0.1, 0.05))
    dt, dr = pose_change(got, T_true)
    assert dt < 0.005 and dr < 0.3, (dt, dr)


def test_global_registration_places_part_of_a_room_with_no_initial_pose_the_same_way_twice():
    rng = np.random.default_rng(4)
    pts, nrm = _room(rng)
    T_true = _pose([0.1, -0.05, 2.0], [1.2, 0.9, 0.6])
    seen = pts[(pts[:, 0] < 2.0) & (pts[:, 1] < 1.6)]  # one corner of the room, both boxes' sides
    frame = (seen - T_true[:3, 3]) @ T_true[:3, :3]
    reg = gr.GlobalRegistration(pts, nrm, voxel_m=0.05, seed=0)
    first = reg.hypotheses(frame, 3)
    assert first, "no hypothesis"
    dt, dr = min(pose_change(T, T_true) for T in first)
    assert dt < 0.03 and dr < 2.0, (dt, dr)
    again = gr.GlobalRegistration(pts, nrm, voxel_m=0.05, seed=0).hypotheses(frame, 3)
    assert len(again) == len(first)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)


def test_global_registration_returns_nothing_for_a_frame_with_too_few_points():
    rng = np.random.default_rng(5)
    pts, nrm = _room(rng)
    reg = gr.GlobalRegistration(pts, nrm, voxel_m=0.05)
    assert reg.hypotheses(np.zeros((5, 3)), 3) == []

"""Culling a surfel map by chunk: the splat of a view is the same image, at the cost of what it sees."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.geometry import so3_exp
from atlas_pipeline.localization import _kernels as kn
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as C
from atlas_pipeline.localization.culling import ChunkGrid
from atlas_pipeline.localization.tracker import SurfelModel, _level_view, splat_params
from atlas_pipeline.sensors.camera import CameraIntrinsics

CAMERA = CameraIntrinsics(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
ROOMS_M = np.array([16.0, 9.0, 3.0])  # a floor of rooms, larger than one view sees
RADIUS_M = C.surfel_radius_voxels * 0.04  # a 4 cm voxel's disk


def _map(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` surfels on the floor, ceiling and a grid of walls of ``ROOMS_M`` (``[n, 3]`` each)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.0, 1.0, (n, 3)) * ROOMS_M
    normals = np.zeros((n, 3))
    kind = rng.integers(0, 3, n)
    c[kind == 0, 2] = rng.choice([0.0, ROOMS_M[2]], int((kind == 0).sum()))  # floor / ceiling
    normals[kind == 0, 2] = 1.0
    c[kind == 1, 0] = np.round(c[kind == 1, 0] / 4.0) * 4.0  # walls every 4 m along x
    normals[kind == 1, 0] = 1.0
    c[kind == 2, 1] = np.round(c[kind == 2, 1] / 3.0) * 3.0  # and every 3 m along y
    normals[kind == 2, 1] = 1.0
    return np.ascontiguousarray(c), normals


def _poses(n: int, seed: int = 1) -> list[np.ndarray]:
    """Cameras inside the rooms, looking anywhere (level, up, down, along the walls)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        T = np.eye(4)
        T[:3, :3] = so3_exp(rng.normal(size=3) * 1.5)
        T[:3, 3] = rng.uniform(0.2, 0.8, 3) * ROOMS_M
        out.append(T)
    return out


def _splat(centres, normals, view, culling):
    return kn.splat_surfels(centres, normals, RADIUS_M, view, splat_params(RADIUS_M), True, culling)


def test_culled_splat_is_the_same_image_and_skips_most_of_a_large_map():
    centres, normals = _map(40_000)
    grid = ChunkGrid.build(centres)
    params = splat_params(RADIUS_M)
    seen_share = []
    for level in (0, 1):
        for T in _poses(12):
            view = _level_view(T, CAMERA, level)
            seen = grid.seen(view, params)
            culled = _splat(centres, normals, view, kn.SplatCulling(grid.chunk_of, seen))
            whole = _splat(centres, normals, view, kn.NO_CULLING)
            for a, b in zip(culled, whole):
                np.testing.assert_array_equal(a, b)  # NaN where nothing is hit, in both
            seen_share.append(seen[grid.chunk_of].mean())
    assert np.median(seen_share) < 0.6, seen_share  # the test culls: most views see a part of the map


def test_a_chunk_is_seen_when_one_surfel_of_it_lands_just_inside_the_image_edge():
    """A surfel whose disk reaches the image by its largest footprint alone, its centre off the
    image by just under ``splat_max_radius_px``: its chunk stays in."""
    view = _level_view(np.eye(4), CAMERA, 0)
    z = 2.0
    u = -C.splat_max_radius_px + 0.5  # centre left of the image, disk reaching in
    x = (u - view.cx) * z / view.fx
    centres = np.array([[x, 0.0, z], [x - 5.0, 0.0, z], [0.0, 0.0, -3.0]])  # + one far left, one behind
    grid = ChunkGrid.build(centres, chunk_m=0.5)
    seen = grid.seen(view, splat_params(RADIUS_M))
    assert seen[grid.chunk_of].tolist() == [True, False, False]


def test_only_occupied_chunks_are_indexed_and_a_long_map_gets_coarser_ones():
    far_apart = ChunkGrid.build(np.array([[0.0, 0.0, 0.0], [5000.0, 3000.0, 40.0]]))
    assert far_apart.n_chunks == 2 and far_apart.chunk_of.tolist() == [0, 1]
    corridor = np.stack([np.arange(0.0, 200.0, 0.25), np.zeros(800), np.zeros(800)], 1)  # 200 m
    grid = ChunkGrid.build(corridor, max_chunks=64)
    assert 32 < grid.n_chunks <= 64  # 4 m chunks: the first doubling that fits
    lo, hi = grid.corners_w.min(axis=1), grid.corners_w.max(axis=1)  # [O, 3] each
    inside = (corridor >= lo[grid.chunk_of]) & (corridor <= hi[grid.chunk_of])
    assert inside.all()  # every surfel lies in its chunk's cube


def test_a_growing_map_keeps_its_chunks_and_culls_as_a_fresh_grid_does():
    """The surfel cache numbers the chunks of what each keyframe adds and keeps the rest: the
    chunks it gives the model hold the same surfels as a grid built from the whole map."""
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.localization.tracker import SurfelCache

    centres, _ = _map(60_000, seed=9)
    builder = VoxelGaussianBuilder(0.04)
    cache = SurfelCache(builder)
    order = np.argsort(centres[:, 0], kind="stable")  # a camera moving along x: the map grows
    for part in np.array_split(order, 6):
        builder.integrate(centres[part], np.zeros((len(part), 3)))
        model = cache.model()
    fresh = ChunkGrid.build(model.centres)
    kept = model._chunks
    assert kept is not None and len(kept.chunk_of) == len(model)
    # the same partition of the surfels into chunks, under other numbers
    pairs = np.unique(np.stack([kept.chunk_of, fresh.chunk_of], 1), axis=0)
    assert len(pairs) == fresh.n_chunks == len(np.unique(kept.chunk_of))
    params = splat_params(model.radius_m)
    for T in _poses(6, seed=10):
        view = _level_view(T, CAMERA, 1)
        culled = kn.splat_surfels(model.centres, model.normals, model.radius_m, view, params, False,
                                  kn.SplatCulling(kept.chunk_of, kept.seen(view, params)))
        whole = kn.splat_surfels(model.centres, model.normals, model.radius_m, view, params, False, kn.NO_CULLING)
        for a, b in zip(culled, whole):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("n", [0, 1])
def test_an_empty_or_one_surfel_map_culls_without_error(n):
    centres = np.zeros((n, 3))
    grid = ChunkGrid.build(centres)
    seen = grid.seen(_level_view(np.eye(4), CAMERA, 0), splat_params(RADIUS_M))
    assert len(grid.chunk_of) == n and seen.shape == (grid.n_chunks,)


def test_the_surfel_model_renders_a_large_map_culled_and_the_same():
    centres, normals = _map(C.min_surfels_to_cull + 5_000, seed=3)
    model = SurfelModel(centres, normals, RADIUS_M)
    for T in _poses(4, seed=4):
        pts, nrm = model.render(T, CAMERA, 1)
        whole = _splat(model.centres, model.normals, _level_view(T, CAMERA, 1), kn.NO_CULLING)
        np.testing.assert_array_equal(pts, whole[0])
        np.testing.assert_array_equal(nrm, whole[1])


def test_surfels_the_view_cannot_see_change_nothing_wherever_they_sit_in_the_map():
    """Pass 1 keeps the visible surfels in map order: a wall rendered alone and the same wall
    shuffled among surfels behind the camera and beside the view give the same image."""
    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.arange(-1.0, 1.0, 0.02), np.arange(-0.8, 0.8, 0.02))
    wall = np.stack([u.ravel(), v.ravel(), 2.0 + rng.normal(0.0, 0.003, u.size)], 1)  # z = 2 m ahead
    wall_n = np.tile([0.0, 0.0, 1.0], (len(wall), 1))
    behind = wall[:3000] * [1.0, 1.0, -1.0]  # behind the camera
    beside = wall[:3000] + [9.0, 0.0, 0.0]  # off the image
    hidden = np.concatenate([behind, beside])
    mixed = np.concatenate([wall, hidden])
    mixed_n = np.concatenate([wall_n, np.tile([0.0, 0.0, 1.0], (len(hidden), 1))])
    # interleave: the wall's surfels keep their relative order, the others fall anywhere
    slots = np.sort(rng.choice(len(mixed), len(wall), replace=False))
    rest = np.setdiff1d(np.arange(len(mixed)), slots)
    centres, normals = np.empty_like(mixed), np.empty_like(mixed_n)
    centres[slots], normals[slots] = wall, wall_n
    centres[rest], normals[rest] = hidden, mixed_n[len(wall):]
    view = _level_view(np.eye(4), CAMERA, 1)
    alone = _splat(np.ascontiguousarray(wall), wall_n, view, kn.NO_CULLING)
    shuffled = _splat(np.ascontiguousarray(centres), np.ascontiguousarray(normals), view, kn.NO_CULLING)
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(alone, shuffled))
    hit = np.isfinite(alone[0][..., 2])
    assert hit.mean() > 0.5 and np.abs(alone[0][..., 2][hit] - 2.0).max() < 0.02  # the wall, where it is


def test_a_far_clip_drops_only_what_lies_beyond_it_and_culls_those_chunks_too():
    """Surfels farther than ``max_depth_m`` are not drawn; everything nearer renders as before,
    and chunk culling with the clip stays conservative (the same image as the clipped whole map)."""
    centres, normals = _map(40_000, seed=5)
    grid = ChunkGrid.build(centres)
    far_m = 3.0
    clipped_params = splat_params(RADIUS_M, far_m)
    n_seen, n_seen_clipped = 0, 0
    for T in _poses(8, seed=6):
        view = _level_view(T, CAMERA, 1)
        seen = grid.seen(view, clipped_params)
        culled = kn.splat_surfels(centres, normals, RADIUS_M, view, clipped_params, True,
                                  kn.SplatCulling(grid.chunk_of, seen))
        whole = kn.splat_surfels(centres, normals, RADIUS_M, view, clipped_params, True, kn.NO_CULLING)
        for a, b in zip(culled, whole):
            np.testing.assert_array_equal(a, b)
        unclipped = _splat(centres, normals, view, kn.NO_CULLING)
        z, z_all = culled[0][..., 2], unclipped[0][..., 2]
        assert not (z > far_m + RADIUS_M).any()  # nothing drawn beyond the clip (a disk's edge at most)
        near = np.isfinite(z_all) & (z_all < far_m - 0.5)  # well inside: the same surface, bit for bit
        np.testing.assert_array_equal(z[near], z_all[near])
        n_seen += int(grid.seen(view, splat_params(RADIUS_M)).sum())
        n_seen_clipped += int(seen.sum())
    assert n_seen_clipped < 0.8 * n_seen  # the clip also skips whole chunks


def test_tracking_within_range_gives_the_same_pose_as_the_whole_view():
    """A tracking view holds only the map the frame's depth can reach: the correspondences, the
    pose and the judgement are those of the whole view; only the count of points in front of
    the unreachable far surfaces goes."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.localization.tracker import RGBDTracker

    centres, normals = _map(C.min_surfels_to_cull + 60_000, seed=7)
    model = SurfelModel(centres, normals, RADIUS_M)
    tracker = RGBDTracker(CAMERA, load_profile("default").localization, (0.1, 3.0))
    compared = 0
    for T in _poses(6, seed=8):
        pts, _ = model.render(T, CAMERA, 0)
        depth_m = np.nan_to_num(pts[..., 2], nan=0.0).astype(np.float32)
        if (depth_m > 0).mean() < 0.3:
            continue
        frame = tracker.prepare(None, depth_m)
        T0 = T.copy()
        T0[:3, 3] += [0.01, -0.01, 0.01]
        whole = tracker.align(frame, model, T0)
        ranged = tracker.align(frame, model, T0, within_range=True)
        np.testing.assert_array_equal(ranged.T_world_cam, whole.T_world_cam)
        assert (ranged.inlier_fraction, ranged.agreement, ranged.ok) == (whole.inlier_fraction, whole.agreement, whole.ok)
        assert ranged.in_front <= whole.in_front
        compared += 1
    assert compared >= 3

"""A saved world's far part drawn from a coarser level: fewer disks, the same near image."""

from __future__ import annotations

import math

import numpy as np

from atlas_pipeline.localization import _kernels as kn
from atlas_pipeline.localization.constants import TRACKER_CONSTANTS as C
from atlas_pipeline.localization.tracker import SurfelModel, far_level
from atlas_pipeline.geometry import so3_exp
from tests.test_culling import CAMERA

VOXEL_M = 0.02
RADIUS_M = C.surfel_radius_voxels * VOXEL_M
DETAIL_M = 3.0  # where the far level takes over in the view tests
# A pixel's first surface this much nearer than DETAIL_M is out of reach of every far disk
# (their hits lie within a radius of their centre, beyond DETAIL_M) and of the blending band.
NEAR_MARGIN_M = 0.2


def _grid(n_u: int, n_v: int, origin, u, v, normal) -> tuple[np.ndarray, np.ndarray]:
    """Surfels at the voxel centres of a ``n_u x n_v`` patch of plane (``[n_u n_v, 3]`` each)."""
    i, j = np.meshgrid(np.arange(n_u) + 0.5, np.arange(n_v) + 0.5, indexing="ij")
    c = np.asarray(origin, float) + VOXEL_M * (i.reshape(-1, 1) * np.asarray(u, float) + j.reshape(-1, 1) * np.asarray(v, float))
    return c, np.tile(np.asarray(normal, float), (len(c), 1))


HALL_M = (8.0, 3.0, 2.6)  # a long room: a camera at one end sees its far half beyond DETAIL_M


def _hall() -> tuple[np.ndarray, np.ndarray]:
    """Surfels at a 2 cm pitch on the floor, the ceiling and the four walls of ``HALL_M``, as the
    voxel map makes them (``[M, 3]`` each)."""
    lx, ly, lz = (round(x / VOXEL_M) for x in HALL_M)
    parts = [_grid(lx, ly, (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)), _grid(lx, ly, (0, 0, HALL_M[2]), (1, 0, 0), (0, 1, 0), (0, 0, 1)),
             _grid(lx, lz, (0, 0, 0), (1, 0, 0), (0, 0, 1), (0, 1, 0)), _grid(lx, lz, (0, HALL_M[1], 0), (1, 0, 0), (0, 0, 1), (0, 1, 0)),
             _grid(ly, lz, (0, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 0)), _grid(ly, lz, (HALL_M[0], 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 0))]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _looking_down_the_hall(yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """``T_world_cam`` at the hall's near end, 1.2 m up, its optical axis along +x turned by the angles."""
    T = np.eye(4)
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: x_cam, y_cam (down), z_cam
    T[:3, :3] = so3_exp(np.array([0.0, 0.0, yaw_rad])) @ so3_exp(np.array([0.0, pitch_rad, 0.0])) @ R
    T[:3, 3] = (0.3, HALL_M[1] / 2, 1.2)
    return T


def _rows(a: np.ndarray) -> set[tuple[float, ...]]:
    return {tuple(r) for r in np.round(a, 9)}


def test_flat_cells_become_one_disk_each_while_corners_and_specks_keep_their_surfels():
    floor_c, floor_n = _grid(16, 16, (0.0, 0.0, 0.0), (1, 0, 0), (0, 1, 0), (0, 0, 1))  # 32 cm square
    floor_c[:, 2] = 0.5 * VOXEL_M
    # a wall along the floor's x = 0 edge: the cells it shares with the floor hold two directions
    wall_c, wall_n = _grid(16, 15, (0.0, 0.0, VOXEL_M), (0, 1, 0), (0, 0, 1), (1, 0, 0))
    wall_c[:, 0] = 0.5 * VOXEL_M
    speck_c, speck_n = np.array([[5.0, 5.0, 5.0]]), np.array([[0.0, 0.0, 1.0]])
    c = np.concatenate([floor_c, wall_c, speck_c])
    n = np.concatenate([floor_n, wall_n, speck_n])
    level = far_level(c, n, RADIUS_M, DETAIL_M)
    first = level.depth_lo_m == DETAIL_M  # the first band, (DETAIL_M, 2 DETAIL_M]: cells of 4 voxels, then 2
    np.testing.assert_array_equal(level.depth_hi_m[first], 2 * DETAIL_M)
    far = {k: getattr(level, k)[first] for k in ("centres", "normals", "radius_m")}

    coarse = far["radius_m"] > RADIUS_M
    assert len(far["centres"]) < len(c) // 3  # most of the map merged
    assert len(level.chunk_of) == len(level.centres)
    # the speck and the surfels right in the corner (floor and wall in one 4 cm cell) stay as they were
    kept = _rows(far["centres"][~coarse])
    assert tuple(np.round(speck_c[0], 9)) in kept
    corner = (floor_c[:, 0] < 2 * VOXEL_M) & (floor_c[:, 2] < 2 * VOXEL_M)
    assert _rows(floor_c[corner]) <= kept
    np.testing.assert_array_equal(far["radius_m"][~coarse], RADIUS_M)
    # a merged floor disk: the mean of its cell's surfels, the floor's normal, reaching its members
    on_floor = coarse & (np.abs(far["centres"][:, 2] - 0.5 * VOXEL_M) < 1e-9)
    assert on_floor.sum() >= 9
    np.testing.assert_allclose(np.abs(far["normals"][on_floor, 2]), 1.0, atol=1e-9)
    cell_m = C.far_level_cell_voxels * VOXEL_M
    full = on_floor & (far["centres"][:, 0] > cell_m)  # cells of 4 x 4 surfels clear of the wall
    assert full.any()
    np.testing.assert_allclose(far["centres"][full, :2] % cell_m, cell_m / 2)
    reach = math.hypot(1.5 * VOXEL_M, 1.5 * VOXEL_M) + RADIUS_M  # the cell's corner surfel's disk
    np.testing.assert_allclose(far["radius_m"][full], min(reach, C.far_level_cell_voxels * RADIUS_M))
    # farther bands: coarser cells, fewer disks; the last band is unbounded
    counts = [int((level.depth_lo_m == lo).sum()) for lo, _, _ in level.bands]
    assert len(counts) == C.far_level_bands and counts == sorted(counts, reverse=True) and counts[-1] < counts[0]
    assert level.bands[-1][1] == math.inf
    # the same input, the same level
    again = far_level(c, n, RADIUS_M, DETAIL_M)
    for a, b in zip(level[:6], again[:6]):
        np.testing.assert_array_equal(a, b)


def test_a_saved_world_draws_its_far_part_from_the_far_level_and_its_near_part_exactly():
    centres, normals = _hall()
    assert len(centres) >= C.far_level_min_surfels
    fixed = SurfelModel(centres, normals, RADIUS_M, fixed=True)
    whole = SurfelModel(centres, normals, RADIUS_M)
    for yaw, pitch in ((0.0, 0.0), (0.3, -0.2), (-0.25, 0.15)):
        T = _looking_down_the_hall(yaw, pitch)
        a = fixed.model_view(T, CAMERA, 1, True, math.inf, DETAIL_M)
        b = whole.model_view(T, CAMERA, 1, True, math.inf, DETAIL_M)  # a map that may change: no far level
        z = b.points_cam[..., 2]
        near = z < DETAIL_M - NEAR_MARGIN_M
        far = z > DETAIL_M + NEAR_MARGIN_M
        assert near.sum() > 1000 and far.sum() > 1000
        np.testing.assert_array_equal(a.points_cam[near], b.points_cam[near])
        np.testing.assert_array_equal(a.normals_cam[near], b.normals_cam[near])
        za = a.points_cam[..., 2][far]  # far pixels: covered alike, at about the same depth
        assert np.isfinite(za).mean() > 0.99
        assert np.nanmedian(np.abs(za - z[far])) < VOXEL_M
    assert fixed._far is not None
    first_band = (fixed._far.depth_lo_m == DETAIL_M).sum()
    assert first_band < len(centres) / 4 and len(fixed._far.centres) < 2 * first_band
    assert whole._far is None


def test_a_view_clipped_before_the_far_level_is_the_full_detail_view():
    centres, normals = _hall()
    fixed = SurfelModel(centres, normals, RADIUS_M, fixed=True)
    whole = SurfelModel(centres, normals, RADIUS_M)
    T = _looking_down_the_hall(0.1, 0.0)
    a = fixed.model_view(T, CAMERA, 1, True, DETAIL_M, DETAIL_M)
    b = whole.model_view(T, CAMERA, 1, True, DETAIL_M)
    for x, y in zip(a[:2] + a[-2:], b[:2] + b[-2:]):
        np.testing.assert_array_equal(x, y)
    assert fixed._far is None  # never made: nothing beyond DETAIL_M is drawn


def test_the_splat_keeps_its_per_surfel_memory_between_views():
    centres, normals = _hall()
    model = SurfelModel(centres, normals, RADIUS_M)
    T = _looking_down_the_hall(0.0, 0.0)
    kn._splat_scratches.footprints = None
    first = model.model_view(T, CAMERA, 1, True)
    kept = kn._splat_scratches.footprints
    assert kept is not None
    small = SurfelModel(centres[:5_000], normals[:5_000], RADIUS_M).model_view(T, CAMERA, 1, True)
    assert kn._splat_scratches.footprints[0] is kept[0]  # a smaller view reuses it
    again = model.model_view(T, CAMERA, 1, True)  # after the smaller view wrote into it
    for x, y in zip(first[:2] + first[-2:], again[:2] + again[-2:]):
        np.testing.assert_array_equal(x, y)
    assert np.isfinite(small.points_cam[..., 2]).sum() < np.isfinite(first.points_cam[..., 2]).sum()


def test_an_empty_map_has_an_empty_far_level():
    level = far_level(np.zeros((0, 3)), np.zeros((0, 3)), RADIUS_M, DETAIL_M)
    assert len(level.centres) == len(level.chunk_of) == 0 and len(level.bands) == C.far_level_bands


def test_a_session_in_a_saved_world_makes_its_far_level_before_the_first_frame():
    from atlas_pipeline.config import LocalizationConfig
    from atlas_pipeline.localization.sequence import SequenceTracker

    centres, normals = _hall()
    fixed = SurfelModel(centres, normals, RADIUS_M, fixed=True)
    session = SequenceTracker(CAMERA, LocalizationConfig(), (0.1, 2.5), model=fixed)
    assert fixed._far is not None and fixed._far.from_m == session.tracker.tracking_far_m
    assert fixed._chunks is not None
    T = _looking_down_the_hall(0.0, 0.0)
    made = fixed._far
    fixed.model_view(T, CAMERA, 1, True, math.inf, session.tracker.tracking_far_m)
    assert fixed._far is made  # the first view uses it, not a new one
    changing = SurfelModel(centres, normals, RADIUS_M)
    SequenceTracker(CAMERA, LocalizationConfig(), (0.1, 2.5), model=changing)
    assert changing._far is None

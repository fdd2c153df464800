"""The voxel hash table answers every lookup as a binary search of the sorted ids does."""

import numpy as np
import pytest

from atlas_pipeline.gaussian_world.builder import _OFFSET, pack_voxel_ids
from atlas_pipeline.localization.tracker import MIN_APPEARANCE_PAIRS, VoxelAppearance


def _searchsorted_index(ids: np.ndarray, points: np.ndarray, voxel_m: float) -> np.ndarray:
    """The reference: ``floor(x / voxel)`` packed, then a binary search of the sorted ``ids``."""
    out = np.full(len(points), -1, np.int64)
    finite = np.isfinite(points).all(axis=1)
    ijk = np.zeros((len(points), 3), np.int64)
    ijk[finite] = np.floor(points[finite] / voxel_m).astype(np.int64)
    inside = np.flatnonzero(finite & (np.abs(ijk) < _OFFSET).all(axis=1))
    keys = pack_voxel_ids(ijk[inside])
    pos = np.minimum(np.searchsorted(ids, keys), len(ids) - 1)
    hit = ids[pos] == keys
    out[inside[hit]] = pos[hit]
    return out


@pytest.mark.parametrize("n_voxels", [1, 37, 20_000])
def test_lookups_match_a_binary_search_of_the_sorted_ids(n_voxels):
    rng = np.random.default_rng(n_voxels)
    voxel_m = 0.02
    ijk = np.unique(rng.integers(-60, 60, (n_voxels, 3)), axis=0)
    ids = np.sort(pack_voxel_ids(ijk))
    app = VoxelAppearance(ids, rng.uniform(0, 1, len(ids)).astype(np.float32), voxel_m)
    # points inside mapped voxels, on voxel faces (where floor decides), in empty space, far out
    # of the addressable range, and not finite
    inside = (ijk[rng.integers(0, len(ijk), 500)] + rng.uniform(0, 1, (500, 3))) * voxel_m
    faces = ijk[rng.integers(0, len(ijk), 200)] * voxel_m
    empty = rng.uniform(-2.0, 2.0, (2000, 3))
    far = np.array([[1e9, 0.0, 0.0], [0.0, -1e9, 0.0], [0.0, 0.0, _OFFSET * voxel_m]])
    bad = np.array([[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0, -np.inf]])
    points = np.concatenate([inside, faces, empty, far, bad])
    got = app.voxel_index(points)
    expected = _searchsorted_index(ids, points, voxel_m)
    assert np.array_equal(got, expected)
    assert (got[:500] >= 0).mean() > 0.9 and (got[-6:] == -1).all()  # not vacuous: hits and misses both
    grey = app.grey_at(points)
    assert np.array_equal(np.isnan(grey), expected < 0)
    assert np.array_equal(grey[expected >= 0], app.grey[expected[expected >= 0]])


def test_an_empty_map_finds_nothing_and_correlation_needs_pairs():
    empty = VoxelAppearance(np.zeros(0, np.uint64), np.zeros(0, np.float32), 0.02)
    assert np.isnan(empty.grey_at(np.zeros((4, 3)))).all()
    assert empty.correlation(np.zeros((4, 3)), np.zeros(4)) == (pytest.approx(np.nan, nan_ok=True), 0)
    ijk = np.array([[0, 0, 0]])
    one = VoxelAppearance(pack_voxel_ids(ijk), np.array([0.5], np.float32), 0.02)
    pts = np.full((MIN_APPEARANCE_PAIRS - 1, 3), 0.01)
    ncc, pairs = one.correlation(pts, np.linspace(0, 1, len(pts)))
    assert np.isnan(ncc) and pairs == MIN_APPEARANCE_PAIRS - 1

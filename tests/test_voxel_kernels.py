"""The voxel map's row insertion: what ``numpy.insert`` gives, for every array the map keeps."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.gaussian_world._voxel_kernels import insert_rows


@pytest.mark.parametrize("shape, dtype", [((50,), np.uint64), ((50, 3), np.float64), ((50, 6), np.float64),
                                          ((50,), np.int32), ((0, 3), np.float64), ((1,), np.int64)])
@pytest.mark.parametrize("n_new", [0, 1, 7, 60])
def test_insert_rows_is_numpy_insert_for_ascending_positions(shape, dtype, n_new):
    rng = np.random.default_rng(n_new)
    old = (rng.random(shape) * 100).astype(dtype)
    at = np.sort(rng.integers(0, shape[0] + 1, n_new))  # repeats included: several new rows in one gap
    values = (rng.random((n_new,) + shape[1:]) * 100).astype(dtype)
    for fill in (values, 0):
        ours, ref = insert_rows(old, at, fill), np.insert(old, at, fill, axis=0)
        assert ours.dtype == ref.dtype and ours.shape == ref.shape
        np.testing.assert_array_equal(ours, ref)

"""The keyframe fit's coverage band from the depth noise model (mapping/mapper.py coverage_band_m)."""

import numpy as np
import pytest

from atlas_pipeline.mapping.mapper import COVERAGE_BAND_SIGMAS, coverage_band_m, depth_sigma_m


def test_coverage_band_is_a_few_sigma_of_the_position_error_and_zero_without_a_reading():
    d = np.array([[0.0, 1.0], [3.0, 8.0]])
    band = coverage_band_m(d, 0.02)
    assert band.dtype == np.float32 and band.shape == d.shape
    assert band[0, 0] == 0.0  # no reading: no surface to be opaque at
    expect = COVERAGE_BAND_SIGMAS * np.sqrt(depth_sigma_m(d[d > 0]) ** 2 + 0.02 ** 2)
    np.testing.assert_allclose(band[d > 0], expect, rtol=1e-6)
    # the map's resolution dominates near, the sensor's noise far (6 cm at 1 m, 34 cm at 8 m)
    assert band[0, 1] == pytest.approx(0.06, abs=0.002) and band[1, 1] == pytest.approx(0.34, abs=0.01)
    assert np.all(np.diff(band[d > 0]) > 0)

"""The depth-noise model mapping and tracking share: one sensor, one set of constants.

Axial depth noise of a Kinect v1-class structured-light camera (TUM RGB-D, 7-Scenes, ScanNet):
Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction and Tracking",
3DIMPVT 2012: ``sigma_z = a + b (z - z0)^2`` metres (1.9 mm at 1 m, 1.4 cm at 3 m, 11 cm at 8 m;
Khoshelham & Elberink 2012 measured the same z^2 growth, ~4 cm at 5 m). The synthetic Kinect
(:data:`atlas_pipeline.sensors.synthetic_kinect.KINECT_V1_SENSOR`) uses the same constants; a test
keeps them equal.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DEPTH_NOISE_A_M", "DEPTH_NOISE_B_PER_M", "DEPTH_NOISE_Z0_M", "depth_sigma_m"]

DEPTH_NOISE_A_M = 0.0012
DEPTH_NOISE_B_PER_M = 0.0019  # m per m^2 of (z - z0)^2
DEPTH_NOISE_Z0_M = 0.4


def depth_sigma_m(depth_m: np.ndarray) -> np.ndarray:
    """Axial noise std (metres) of a depth reading ``depth_m`` (any shape)."""
    z = np.asarray(depth_m, np.float64)
    return DEPTH_NOISE_A_M + DEPTH_NOISE_B_PER_M * (z - DEPTH_NOISE_Z0_M) ** 2

"""A frame's fit to a model view with each point judged within the depth noise at its range.

A surface mapped by the same sensor from another pose differs from a new reading of it by the
noise of two readings, ``sqrt(2) sigma(z)`` (:func:`atlas_pipeline.sensors.depth_noise.depth_sigma_m`):
under 1 cm within 2 m, 4 cm at 3 m, 7 cm at 4 m with a Kinect-like sensor. A fixed gate of a few
centimetres counts much of a true fit at range as disagreement. Loop verification
(:mod:`atlas_pipeline.mapping.loop_closure`) and tracking (:meth:`RGBDTracker.align
<atlas_pipeline.localization.tracker.RGBDTracker.align>`) grade a frame's agreement this way.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from atlas_pipeline.geometry import invert_se3
from atlas_pipeline.sensors.depth_noise import depth_sigma_m

__all__ = ["NOISE_FIT_SIGMAS", "NoiseFit", "noise_tolerance_m", "fit_within_noise"]

# Standard deviations of the difference of two readings within which a point fits: two hold 95 %
# of a true fit's points.
NOISE_FIT_SIGMAS = 2.0


class NoiseFit(NamedTuple):
    """How a frame at a pose fits a model view, each point judged within the depth noise at its
    range (:func:`fit_within_noise`): ``inlier_fraction`` of the frame's points fit the surface;
    ``agreement``: the fitting points over those that land on the surface or behind it (as
    :class:`TrackResult` counts them)."""

    inlier_fraction: float
    agreement: float


def noise_tolerance_m(depth_m: np.ndarray, floor_m: float, n_sigmas: float = NOISE_FIT_SIGMAS) -> np.ndarray:
    """How far (m) a point at depth ``depth_m`` (any shape) may lie from a surface mapped by the
    same sensor and still fit it: ``n_sigmas`` standard deviations of the difference of two
    readings (``sqrt(2) sigma(z)``), at least ``floor_m``."""
    return np.maximum(floor_m, n_sigmas * math.sqrt(2.0) * depth_sigma_m(depth_m))


def fit_within_noise(points_cam: np.ndarray, T_world_cam: np.ndarray, view, floor_m: float,
                     min_view_depth_m: float = 0.05, n_sigmas: float = NOISE_FIT_SIGMAS) -> NoiseFit:
    """Grade the frame points ``points_cam`` ``[N, 3]`` (its own camera, metres) at the pose
    ``T_world_cam`` ``[4, 4]`` against a model ``view`` (:class:`ModelView`: ``points_cam``
    ``[h, w, 3]`` NaN where empty, its pose and pinhole), each point associated with the view's
    pixel it projects to as the tracker associates it, and fitting when within
    :func:`noise_tolerance_m` (``floor_m``: the tracker's grading gate; ``n_sigmas`` 0: that gate
    alone) of its own depth. A point in front of the surface beyond it is free space the frame
    sees through the old geometry: neither fitting nor landing. Pure."""
    n = len(points_cam)
    if n == 0:
        return NoiseFit(0.0, 0.0)
    T_view_cam = invert_se3(np.asarray(view.T_world_cam, np.float64)) @ np.asarray(T_world_cam, np.float64)
    p = points_cam @ T_view_cam[:3, :3].T + T_view_cam[:3, 3]
    z = p[:, 2]
    h, w = view.points_cam.shape[:2]
    lands = z > min_view_depth_m
    zs = np.where(lands, z, 1.0)
    # nearest pixel, truncated towards zero as the tracker's association kernel rounds it
    u = np.trunc(view.fx * p[:, 0] / zs + view.cx + 0.5).astype(np.int64)
    v = np.trunc(view.fy * p[:, 1] / zs + view.cy + 0.5).astype(np.int64)
    lands &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    q = np.full((n, 3), np.nan)
    q[lands] = view.points_cam[v[lands], u[lands]]
    lands &= np.isfinite(q[:, 2])
    e = p - q
    dist = np.sqrt(np.einsum("ij,ij->i", e, e))
    fits = lands & (dist < noise_tolerance_m(points_cam[:, 2], floor_m, n_sigmas))
    on = int(np.count_nonzero(lands & (fits | (e[:, 2] >= 0.0))))
    n_fit = int(np.count_nonzero(fits))
    return NoiseFit(n_fit / n, n_fit / on if on else 0.0)

"""RANSAC over putative point correspondences, repeatable and parallel.

The minimal sample of iteration ``i`` is drawn from a counter-based generator (SplitMix64 of
``seed`` and ``i``), not from a shared random state, so iterations run in any order on any number of
threads and the result is the same bit for bit. Each iteration's pose and its counts are kept, so
the caller can take several distinct poses, not only the best (a symmetric room has a twin pose
that explains the frame almost as well).

Shapes: ``src [C, 3]``, ``dst [C, 3]`` (correspondence ``c`` pairs ``src[c]`` with ``dst[c]``),
poses ``[n, 3, 4]`` (``R | t`` mapping src to dst).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.localization._voxel_hash import lookup_point

__all__ = ["RansacParams", "ransac_batch", "fit_rigid", "iterations_needed", "SAMPLE_SIZE"]

SAMPLE_SIZE = 3
_SPLITMIX_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_SPLITMIX_M1 = np.uint64(0xBF58476D1CE4E5B9)
_SPLITMIX_M2 = np.uint64(0x94D049BB133111EB)
# A sample whose points are nearly collinear has no stable rotation.
_MIN_SAMPLE_EDGE_M = 1e-6


class RansacParams(NamedTuple):
    """What makes a sample and an inlier."""

    inlier_m: float  # a correspondence is an inlier when the pose maps src within this of dst
    edge_ratio: float  # each pair's distance in src and in dst agree to this ratio (0.9: 10 %)
    seed: int


@njit(cache=True, inline="always")
def _splitmix(x):
    z = x + _SPLITMIX_GAMMA
    z = (z ^ (z >> np.uint64(30))) * _SPLITMIX_M1
    z = (z ^ (z >> np.uint64(27))) * _SPLITMIX_M2
    return z ^ (z >> np.uint64(31))


@njit(cache=True)
def fit_rigid(src, dst):
    """``[3, 4]`` rotation and translation minimising ``sum |R src + t - dst|^2`` (Kabsch, no
    reflection) over ``src, dst [n, 3]``, n >= 3."""
    n = src.shape[0]
    cs = np.zeros(3)
    cd = np.zeros(3)
    for k in range(n):
        for a in range(3):
            cs[a] += src[k, a] / n
            cd[a] += dst[k, a] / n
    H = np.zeros((3, 3))
    for k in range(n):
        for a in range(3):
            for b in range(3):
                H[a, b] += (src[k, a] - cs[a]) * (dst[k, b] - cd[b])
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    if np.linalg.det(Vt.T @ U.T) < 0:
        D[2, 2] = -1.0
    R = Vt.T @ D @ U.T
    out = np.zeros((3, 4))
    out[:, :3] = R
    out[:, 3] = cd - R @ cs
    return out


@njit(cache=True, inline="always")
def _dist(p, i, j):
    dx = p[i, 0] - p[j, 0]
    dy = p[i, 1] - p[j, 1]
    dz = p[i, 2] - p[j, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, inline="always")
def _residual(pose, src, dst, c):
    s = 0.0
    for a in range(3):
        e = pose[a, 0] * src[c, 0] + pose[a, 1] * src[c, 1] + pose[a, 2] * src[c, 2] + pose[a, 3] - dst[c, a]
        s += e * e
    return math.sqrt(s)


@njit(cache=True, parallel=True)
def ransac_batch(src, dst, cloud, table, first, count, params):
    """Iterations ``first .. first + count`` over the matches ``src``/``dst``: ``(poses [count, 3, 4],
    support [count], agreeing [count])``, int64, -1 for a sample the edge-length or distance check
    rejects (Open3D's ``CorrespondenceCheckerBasedOnEdgeLength`` and ``...BasedOnDistance``).

    ``support`` counts the points of ``cloud [N, 3]`` (the whole frame, not only its matched
    points) the pose puts in a voxel of ``table`` (the map's occupied voxels): with ambiguous
    features the true pose often has fewer agreeing matches than a wrong one but explains far
    more of the frame. ``agreeing`` counts the matches the pose maps within ``params.inlier_m``;
    their share drives the stopping test (as in Open3D)."""
    C = src.shape[0]
    inlier_m, edge_ratio = params.inlier_m, params.edge_ratio
    poses = np.zeros((count, 3, 4))
    support = np.full(count, -1, np.int64)
    agreeing = np.full(count, -1, np.int64)
    for it in prange(count):
        state = _splitmix(np.uint64(params.seed) * _SPLITMIX_GAMMA + np.uint64(first + it))
        idx = np.empty(SAMPLE_SIZE, np.int64)
        k = 0
        draws = 0
        while k < SAMPLE_SIZE and draws < 64:
            state = _splitmix(state)
            draws += 1
            c = np.int64(state % np.uint64(C))
            fresh = True
            for q in range(k):
                if idx[q] == c:
                    fresh = False
            if fresh:
                idx[k] = c
                k += 1
        if k < SAMPLE_SIZE:
            continue
        s = np.empty((SAMPLE_SIZE, 3))
        d = np.empty((SAMPLE_SIZE, 3))
        for q in range(SAMPLE_SIZE):
            s[q] = src[idx[q]]
            d[q] = dst[idx[q]]
        good = True
        for a in range(SAMPLE_SIZE):
            for b in range(a + 1, SAMPLE_SIZE):
                ls = _dist(s, a, b)
                ld = _dist(d, a, b)
                if ls < _MIN_SAMPLE_EDGE_M or ld < _MIN_SAMPLE_EDGE_M or ls < edge_ratio * ld or ld < edge_ratio * ls:
                    good = False
        if not good:
            continue
        pose = fit_rigid(s, d)
        for q in range(SAMPLE_SIZE):
            if _residual(pose, src, dst, idx[q]) > inlier_m:
                good = False
        if not good:
            continue
        n_in = 0
        for c in range(C):
            if _residual(pose, src, dst, c) <= inlier_m:
                n_in += 1
        n_on = 0
        for m in range(cloud.shape[0]):
            x = pose[0, 0] * cloud[m, 0] + pose[0, 1] * cloud[m, 1] + pose[0, 2] * cloud[m, 2] + pose[0, 3]
            y = pose[1, 0] * cloud[m, 0] + pose[1, 1] * cloud[m, 1] + pose[1, 2] * cloud[m, 2] + pose[1, 3]
            z = pose[2, 0] * cloud[m, 0] + pose[2, 1] * cloud[m, 1] + pose[2, 2] * cloud[m, 2] + pose[2, 3]
            if lookup_point(table, x, y, z) >= 0:
                n_on += 1
        poses[it] = pose
        support[it] = n_on
        agreeing[it] = n_in
    return poses, support, agreeing


def iterations_needed(inlier_ratio: float, confidence: float) -> float:
    """Iterations after which an all-inlier sample has been drawn with probability ``confidence``."""
    w = inlier_ratio ** SAMPLE_SIZE
    if w <= 0.0:
        return math.inf
    if w >= 1.0:
        return 1.0
    return math.log(1.0 - confidence) / math.log(1.0 - w)

"""Compiled per-voxel statistics (Numba): least-variance axes over voxel neighbourhoods, and the
insertion of new voxels' rows among the sorted old ones.

Shared by the Gaussian builder (orientation of sparse voxels) and the tracker (surfel normals).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["insert_rows", "neighbourhood_surfels", "neighbourhood_surfels_subset"]


@njit(cache=True)
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (closed form:
    trigonometric eigenvalues, then the best-conditioned cross product of two rows of A - l I)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-30:
        return 0.0, 0.0, 1.0  # isotropic: any direction
    p = math.sqrt(p2 / 6.0)
    c00, c11, c22 = b00 / p, b11 / p, b22 / p
    c01, c02, c12 = a01 / p, a02 / p, a12 / p
    detb = (c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02) + c02 * (c01 * c12 - c11 * c02))
    r = min(max(detb / 2.0, -1.0), 1.0)
    phi = math.acos(r) / 3.0
    lam = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)  # the smallest of the three
    m00, m11, m22 = a00 - lam, a11 - lam, a22 - lam
    # rows r0 = (m00, a01, a02), r1 = (a01, m11, a12), r2 = (a02, a12, m22)
    x0 = a01 * a12 - a02 * m11
    y0 = a02 * a01 - m00 * a12
    z0 = m00 * m11 - a01 * a01
    x1 = a01 * m22 - a02 * a12
    y1 = a02 * a02 - m00 * m22
    z1 = m00 * a12 - a01 * a02
    x2 = m11 * m22 - a12 * a12
    y2 = a12 * a02 - a01 * m22
    z2 = a01 * a12 - m11 * a02
    n0 = x0 * x0 + y0 * y0 + z0 * z0
    n1 = x1 * x1 + y1 * y1 + z1 * z1
    n2 = x2 * x2 + y2 * y2 + z2 * z2
    if n0 >= n1 and n0 >= n2 and n0 > 0:
        s = 1.0 / math.sqrt(n0)
        return x0 * s, y0 * s, z0 * s
    if n1 >= n2 and n1 > 0:
        s = 1.0 / math.sqrt(n1)
        return x1 * s, y1 * s, z1 * s
    if n2 > 0:
        s = 1.0 / math.sqrt(n2)
        return x2 * s, y2 * s, z2 * s
    return 0.0, 0.0, 1.0


def neighbourhood_surfels(ids, ijk, count, sum_xyz, sum_sq, offset, bits):
    """Per voxel: the mean of its points and the least-variance axis of the points of the voxel and
    its 26 neighbours, with the neighbourhood's point count.

    Args:
        ids: ``[N]`` sorted uint64 voxel ids (``bits`` per axis, coordinates shifted by ``offset``);
        ijk: ``[N, 3]`` int64 voxel coordinates; count ``[N]``; sum_xyz ``[N, 3]``; sum_sq ``[N, 6]``.
    Returns:
        ``(centres [N, 3], normals [N, 3], support [N])``.
    """
    return neighbourhood_surfels_subset(ids, ijk, count, sum_xyz, sum_sq, offset, bits,
                                        np.arange(len(ids), dtype=np.int64))


@njit(cache=True, parallel=True)
def neighbourhood_surfels_subset(ids, ijk, count, sum_xyz, sum_sq, offset, bits, subset):
    """:func:`neighbourhood_surfels` for the voxels ``subset [S]`` (int64 positions in ``ids``)
    only, ``ijk [S, 3]`` their coordinates: ``(centres [S, 3], normals [S, 3], support [S])``.
    Each voxel's result depends on its neighbourhood alone, so a map that grew recomputes only
    the voxels near what was added (and unpacks only their coordinates)."""
    n = ids.shape[0]
    ns = subset.shape[0]
    centres = np.empty((ns, 3))
    normals = np.empty((ns, 3))
    support = np.zeros(ns, np.int64)
    lim = (1 << (bits - 1))
    for s_i in prange(ns):
        k = subset[s_i]
        s_n = 0.0
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        # scalars, not a small array: an allocation per voxel dominated this loop
        q0 = 0.0
        q1 = 0.0
        q2 = 0.0
        q3 = 0.0
        q4 = 0.0
        q5 = 0.0
        c_lo = max(ijk[s_i, 2] - 1, -lim)
        c_hi = min(ijk[s_i, 2] + 1, lim - 1)
        for di in range(-1, 2):
            for dj in range(-1, 2):
                a = ijk[s_i, 0] + di
                b = ijk[s_i, 1] + dj
                if a < -lim or a >= lim or b < -lim or b >= lim:
                    continue
                # The (up to) three neighbours along the last axis are consecutive ids: one search
                # for the first, then a scan, in the order (dk = -1, 0, 1) the sums always had.
                ab = (np.uint64(a + offset) << np.uint64(2 * bits)) | (np.uint64(b + offset) << np.uint64(bits))
                id_lo = ab | np.uint64(c_lo + offset)
                id_hi = ab | np.uint64(c_hi + offset)
                j = np.searchsorted(ids, id_lo)
                while j < n and ids[j] <= id_hi:
                    s_n += count[j]
                    s0 += sum_xyz[j, 0]
                    s1 += sum_xyz[j, 1]
                    s2 += sum_xyz[j, 2]
                    q0 += sum_sq[j, 0]
                    q1 += sum_sq[j, 1]
                    q2 += sum_sq[j, 2]
                    q3 += sum_sq[j, 3]
                    q4 += sum_sq[j, 4]
                    q5 += sum_sq[j, 5]
                    j += 1
        cnt = count[k]
        centres[s_i, 0] = sum_xyz[k, 0] / cnt
        centres[s_i, 1] = sum_xyz[k, 1] / cnt
        centres[s_i, 2] = sum_xyz[k, 2] / cnt
        support[s_i] = int(s_n)
        m0, m1, m2 = s0 / s_n, s1 / s_n, s2 / s_n
        nx, ny, nz = _smallest_eigenvector(q0 / s_n - m0 * m0, q1 / s_n - m0 * m1, q2 / s_n - m0 * m2,
                                           q3 / s_n - m1 * m1, q4 / s_n - m1 * m2, q5 / s_n - m2 * m2)
        normals[s_i, 0] = nx
        normals[s_i, 1] = ny
        normals[s_i, 2] = nz
    return centres, normals, support


def insert_rows(old: np.ndarray, at: np.ndarray, values) -> np.ndarray:
    """``numpy.insert(old, at, values, axis=0)`` for ascending ``at [M]`` (int, each in ``[0, N]``):
    ``old [N, ...]`` with ``values`` (``[M, ...]``, or one value for every new row) placed before
    the rows ``at``. One pass of block copies: a map of a million voxels takes a keyframe's new
    voxels in a few milliseconds per array, where ``numpy.insert`` sorts and masks every row."""
    n, m, k = old.shape[0], len(at), int(np.prod(old.shape[1:], dtype=np.int64))
    out = np.empty((n + m,) + old.shape[1:], old.dtype)
    new = np.empty((m,) + old.shape[1:], old.dtype)
    new[...] = values
    _insert_rows(np.ascontiguousarray(old).reshape(n, k), np.ascontiguousarray(at, np.int64),
                 new.reshape(m, k), out.reshape(n + m, k))
    return out


@njit(cache=True)
def _insert_rows(old, at, new, out):
    """Kernel of :func:`insert_rows` on 2-D views: ``old [N, K]``, ``new [M, K]``, ``out [N + M, K]``."""
    start = 0
    for j in range(at.shape[0]):
        a = at[j]
        out[start + j:a + j] = old[start:a]
        out[a + j] = new[j]
        start = a
    out[start + at.shape[0]:] = old[start:]

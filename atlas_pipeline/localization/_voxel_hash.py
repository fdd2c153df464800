"""A hash table over a map's packed voxel ids, for the per-pixel voxel lookups of the tracker.

A frame's photometric reference looks up the voxel under every pixel of the model view (tens of
thousands per frame) among a map's million voxels. A sorted-id binary search costs ~20 probes of a
large array per lookup; open addressing with linear probing at load factor at most one half costs
one or two. The table holds, per slot, the index of an id in the caller's ``ids`` array (-1: empty),
so a lookup answers exactly what ``searchsorted`` on the sorted ids answers.

Ids are :func:`atlas_pipeline.gaussian_world.builder.pack_voxel_ids` of ``floor(x / voxel)``
(21 bits per axis, offset to be non-negative). Shapes: ``ids [V]`` uint64, ``slots [S]`` int64 (S a
power of two), ``points [M, 3]`` float64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from atlas_pipeline.gaussian_world.builder import _BITS, _OFFSET, pack_voxel_ids

__all__ = ["VoxelTable", "table_bits", "build_slots", "lookup_point", "lookup_points", "table_of_points"]

# Fibonacci hashing: multiply by 2^64 / golden ratio, keep the top bits (Knuth, TAOCP 6.4).
_GOLDEN_64 = np.uint64(0x9E3779B97F4A7C15)
# Slots per id at least this: linear probing stays near one probe per lookup below half full.
_SLOTS_PER_ID = 2
_MIN_TABLE_BITS = 4


class VoxelTable(NamedTuple):
    """The kernel's view of a hashed voxel set."""

    ids: np.ndarray  # [V] uint64 distinct packed voxel ids
    slots: np.ndarray  # [2^bits] int64 index into ids, -1 = empty slot
    bits: int  # log2 of the table size
    voxel_size_m: float


def table_bits(n_ids: int) -> int:
    """log2 of the table size for ``n_ids`` ids (at least :data:`_SLOTS_PER_ID` slots per id)."""
    return max(_MIN_TABLE_BITS, int(math.ceil(math.log2(max(1, _SLOTS_PER_ID * n_ids)))))


@njit(cache=True, inline="always")
def _slot(key, shift):
    return np.int64((key * _GOLDEN_64) >> shift)


@njit(cache=True)
def build_slots(ids, bits):
    """``[2^bits]`` int64: the index of each of ``ids [V]`` (distinct uint64) at its slot, -1 elsewhere."""
    size = 1 << bits
    mask = size - 1
    shift = np.uint64(64 - bits)
    slots = np.full(size, -1, np.int64)
    for i in range(ids.shape[0]):
        s = _slot(ids[i], shift)
        while slots[s] >= 0:
            s = (s + 1) & mask
        slots[s] = i
    return slots


@njit(cache=True, inline="always")
def lookup_point(table, x, y, z):
    """Index into ``table.ids`` of the voxel the world point ``(x, y, z)`` (m) falls in
    (``floor(x / voxel_size_m)``, as the map's ids were made); -1 where the map has none, the
    point is not finite, or it lies outside the addressable range."""
    ids, slots, voxel = table.ids, table.slots, table.voxel_size_m
    mask = slots.shape[0] - 1
    key = np.uint64(0)
    for v in (x, y, z):
        c = math.floor(v / voxel) if math.isfinite(v) else float(_OFFSET)
        if not (-_OFFSET < c < _OFFSET):
            return -1
        key = (key << np.uint64(_BITS)) | np.uint64(np.int64(c) + _OFFSET)
    s = _slot(key, np.uint64(64 - table.bits))
    while slots[s] >= 0:
        i = slots[s]
        if ids[i] == key:
            return i
        s = (s + 1) & mask
    return -1


@njit(cache=True)
def lookup_points(table, points):
    """``[M]`` int64: :func:`lookup_point` of each of ``points [M, 3]`` (world, m)."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    for m in range(n):
        out[m] = lookup_point(table, points[m, 0], points[m, 1], points[m, 2])
    return out


def table_of_points(points: np.ndarray, voxel_size_m: float) -> VoxelTable:
    """The hashed set of voxels (edge ``voxel_size_m``) that ``points [M, 3]`` (world, m) occupy."""
    ijk = np.floor(np.asarray(points, np.float64).reshape(-1, 3) / voxel_size_m)
    ids = np.unique(pack_voxel_ids(ijk[np.isfinite(ijk).all(axis=1)]))
    bits = table_bits(len(ids))
    return VoxelTable(ids, build_slots(ids, bits), bits, float(voxel_size_m))

"""Place recognition over a map's keyframes: which viewpoints could a frame have been taken from?

Relocalization without a guess used to try every viewpoint prior and a global feature
registration against the whole map: seconds per attempt, growing with the map. A place index
answers the same question in microseconds and leaves the tracker a handful of hypotheses to verify
(:meth:`atlas_pipeline.localization.relocalize.Relocalizer.relocalize_fast`).

Each entry is a *depth layout*: the map rendered from a viewpoint (a keyframe pose, and the same
pose turned left and right about the camera's vertical axis, so a frame taken facing another way
from the same spot is found too), reduced to a coarse grid of block-mean log depths (the "small
blurry image" of Klein & Murray's PTAM relocalizer and of Glocker et al.'s randomized ferns, in
depth). Depth is what a second visit at another time of day still shares with the first: it does
not change with exposure or lighting. A frame's own depth image, reduced the same way, is compared
with every entry over the blocks valid in both (RMS log-depth difference, plus a penalty for blocks
valid in only one); the nearest entries are the hypotheses.

Entries come from the map itself, so any world with keyframe poses (built, extended, reloaded)
has an index without storing images; the index grows by one keyframe's entries at a time while
mapping. A world bundle stores its index (``places.npz``, :meth:`PlaceIndex.save`) so a later session
starts relocalizing at once instead of rendering every keyframe's views again; the stored index
carries a key (:func:`map_key`) of the map, viewpoints, camera and layout it was made from, and is
used only where the key matches (same entries, bit for bit, as an index built then).
Shapes: ``T_*`` ``[4, 4]`` camera-to-world.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from atlas_pipeline.geometry import so3_exp

__all__ = ["PlaceIndex", "PlaceMatch", "CoverageMap", "place_index", "depth_layout", "map_key", "adopt_stored", "DESCRIPTOR_GRID",
           "VIEW_YAWS_DEG", "PLACES_FILE"]

logger = logging.getLogger(__name__)

PLACES_FILE = "places.npz"  # a world bundle's stored place index
# Bumped whenever what an entry holds changes (layout, views, rendering): an index of another
# version has another key and is rebuilt, never misread.
PLACES_VERSION = 1
MAX_LEVEL = 16  # pyramid levels a stored index may name (a 640 px image has 10)
_PLACES_MEMBERS = {"codes": ("f", 2), "T_world_cam": ("f", 3), "keyframe": ("iu", 1), "level": ("iu", 0),
                   "key": (np.uint8, 1)}

# Blocks of a depth layout (rows, columns): 192 numbers, coarse enough that a viewpoint 20 cm or
# 10 degrees away still matches, fine enough to tell the walls of one room from another's.
DESCRIPTOR_GRID = (12, 16)
# A block counts when at least this share of its pixels has depth.
MIN_BLOCK_VALID_FRACTION = 0.5
# Views indexed per keyframe: the keyframe itself and turned about the camera's vertical axis.
VIEW_YAWS_DEG = (0.0, -15.0, 15.0, -30.0, 30.0, -45.0, 45.0)
# Layouts are made at the coarsest pyramid level at least this wide (80 px at 640 or 320).
DESCRIPTOR_MIN_WIDTH_PX = 64
# Fewer blocks valid in both than this share of the grid: no comparison (blank wall, no depth).
MIN_COMMON_BLOCKS_FRACTION = 0.3
# Weight of the share of blocks valid in only one layout, against the RMS log-depth difference:
# a block missing on one side is as bad as a 30 % depth error.
MISMATCH_PENALTY = 0.3


class PlaceMatch(NamedTuple):
    """One hypothesis: ``T_world_cam [4, 4]`` of the entry, its distance, its keyframe number."""

    T_world_cam: np.ndarray
    distance: float
    keyframe: int


def descriptor_level(width_px: int, n_levels: int) -> int:
    """The pyramid level layouts are made at (``DESCRIPTOR_MIN_WIDTH_PX``), below ``n_levels``."""
    level = 0
    while level + 1 < n_levels and width_px // 2 ** (level + 1) >= DESCRIPTOR_MIN_WIDTH_PX:
        level += 1
    return level


def depth_layout(depth_m: np.ndarray) -> np.ndarray:
    """``[B]`` float32 block-mean log depth of ``depth_m [h, w]`` (0 or NaN = none) on
    :data:`DESCRIPTOR_GRID`; NaN for blocks with too little depth."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, 0.0).astype(np.float64)
    gh, gw = DESCRIPTOR_GRID
    h, w = d.shape
    rows = (np.arange(h) * gh) // h  # block of each pixel row / column
    cols = (np.arange(w) * gw) // w
    valid = (d > 0).astype(np.float64)
    logd = np.where(d > 0, np.log(np.maximum(d, 1e-6)), 0.0)
    s = np.zeros((gh, gw))
    c = np.zeros((gh, gw))
    np.add.at(s, (rows[:, None], cols[None, :]), logd)
    np.add.at(c, (rows[:, None], cols[None, :]), valid)
    size = np.zeros((gh, gw))
    np.add.at(size, (rows[:, None], cols[None, :]), 1.0)
    out = np.where(c >= MIN_BLOCK_VALID_FRACTION * size, s / np.maximum(c, 1.0), np.nan)
    return out.ravel().astype(np.float32)


def _turned(T_world_cam: np.ndarray, yaw_deg: float) -> np.ndarray:
    """The pose turned by ``yaw_deg`` about its own vertical (image y) axis, centre kept."""
    if yaw_deg == 0.0:
        return np.array(T_world_cam, np.float64)
    T = np.array(T_world_cam, np.float64)
    T[:3, :3] = T[:3, :3] @ so3_exp(np.array([0.0, math.radians(yaw_deg), 0.0]))
    return T


class PlaceIndex:
    """Depth layouts of a map's viewpoints (module docstring), searched by :meth:`query`.

    Args:
        model: the map (:class:`~atlas_pipeline.localization.tracker.SurfelModel`) the entries are
            rendered from; ``camera`` and ``level`` fix the view they are rendered at.
    """

    def __init__(self, camera, level: int, key: str | None = None):
        self.camera = camera
        self.level = level
        self.key = key  # map_key of what the entries were made from (None: not recorded)
        self._codes: list[np.ndarray] = []  # [B] each
        self._poses: list[np.ndarray] = []
        self._keyframe: list[int] = []
        self._stack: np.ndarray | None = None

    def save(self, path: str | Path) -> Path:
        """``places.npz``: ``codes [E, B]`` float32 (NaN = no depth), ``T_world_cam [E, 4, 4]``,
        ``keyframe [E]`` int32, ``level`` and the 32-byte ``key``; no pickled objects, and equal
        indexes give equal bytes."""
        from atlas_pipeline.io_utils import atomic_path
        from atlas_pipeline.safe_arrays import save_npz_deterministic

        if self.key is None:
            raise ValueError("a place index is saved with the key of the map it was made from")
        n_blocks = DESCRIPTOR_GRID[0] * DESCRIPTOR_GRID[1]
        codes = np.stack(self._codes).astype(np.float32) if self._codes else np.zeros((0, n_blocks), np.float32)
        poses = np.stack(self._poses) if self._poses else np.zeros((0, 4, 4))
        with atomic_path(Path(path)) as tmp:
            with open(tmp, "wb") as fh:
                save_npz_deterministic(fh, codes=codes, T_world_cam=np.asarray(poses, np.float64),
                                       keyframe=np.asarray(self._keyframe, np.int32), level=np.int64(self.level),
                                       key=np.frombuffer(bytes.fromhex(self.key), np.uint8))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path, camera) -> "PlaceIndex":
        """Read :meth:`save`'s file (entries to be rendered later use ``camera``); a malformed one
        raises ``BundleFormatError`` naming the file and the member. Whether it fits a map is
        :func:`map_key`'s to say."""
        from atlas_pipeline.errors import BundleFormatError
        from atlas_pipeline.safe_arrays import load_npz_checked

        path = Path(path)
        z = load_npz_checked(path, _PLACES_MEMBERS)
        codes, poses, keyframe, key = z["codes"], z["T_world_cam"], z["keyframe"], z["key"]
        n = len(codes)
        n_blocks = DESCRIPTOR_GRID[0] * DESCRIPTOR_GRID[1]
        if codes.shape[1:] != (n_blocks,):
            raise BundleFormatError(path, f"codes is {list(codes.shape)}, expected [E, {n_blocks}]")
        if poses.shape != (n, 4, 4) or not np.isfinite(poses).all():
            raise BundleFormatError(path, f"T_world_cam must be [{n}, 4, 4] finite (one per entry), got {list(poses.shape)}")
        if keyframe.shape != (n,) or (n and keyframe.min() < 0):
            raise BundleFormatError(path, f"keyframe must be [{n}] non-negative numbers, got {list(keyframe.shape)}")
        if key.shape != (32,):
            raise BundleFormatError(path, f"key must be 32 bytes, got {list(key.shape)}")
        if n and not np.allclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0]):
            raise BundleFormatError(path, "T_world_cam rows must end in [0, 0, 0, 1] (camera-to-world 4x4)")
        if np.isinf(codes).any():
            raise BundleFormatError(path, "codes hold infinite log depths (NaN marks a block without depth)")
        level = int(z["level"])
        if not 0 <= level < MAX_LEVEL:
            raise BundleFormatError(path, f"level {level} is not a pyramid level (0..{MAX_LEVEL - 1})")
        index = cls(camera, level, bytes(key.tobytes()).hex())
        index._codes = list(np.asarray(codes, np.float32))
        index._poses = list(np.asarray(poses, np.float64))
        index._keyframe = [int(k) for k in keyframe]
        return index

    def __len__(self) -> int:
        return len(self._codes)

    def add_keyframe(self, model, T_world_cam: np.ndarray, keyframe: int) -> None:
        """Index the map ``model`` as seen from ``T_world_cam`` and its turned views. The index no
        longer is what its key describes (:func:`place_index` keys it once it is complete)."""
        self.key = None
        # The whole map, as far as it reaches: a coarser map or one clipped to the sensor's reach
        # renders faster but reorders the candidates, and on the suite both made a second visit's
        # extension worse (docs/benchmarks.md).
        for yaw in VIEW_YAWS_DEG:
            T = _turned(T_world_cam, yaw)
            pts, _ = model.render(T, self.camera, self.level)
            code = depth_layout(pts[..., 2])
            if np.isfinite(code).sum() < MIN_COMMON_BLOCKS_FRACTION * code.size:
                continue  # nothing to recognise (looking into empty space)
            self._codes.append(code)
            self._poses.append(T)
            self._keyframe.append(int(keyframe))
        self._stack = None

    def query(self, depth_m: np.ndarray, k: int) -> list[PlaceMatch]:
        """The ``k`` entries nearest the layout of ``depth_m [h, w]`` (the frame at ``level``),
        nearest first, at most one per keyframe; empty when the frame has too little depth."""
        if not self._codes:
            return []
        q = depth_layout(depth_m)
        qv = np.isfinite(q)
        if qv.sum() < MIN_COMMON_BLOCKS_FRACTION * q.size:
            return []
        if self._stack is None:
            self._stack = np.stack(self._codes)  # [E, B]
        E = self._stack
        ev = np.isfinite(E)
        both = ev & qv[None, :]
        n_both = both.sum(axis=1)
        diff = np.where(both, E - q[None, :], 0.0)
        rms = np.sqrt((diff * diff).sum(axis=1) / np.maximum(n_both, 1))
        only_one = (ev ^ qv[None, :]).sum(axis=1) / q.size
        dist = rms + MISMATCH_PENALTY * only_one
        dist = np.where(n_both >= MIN_COMMON_BLOCKS_FRACTION * q.size, dist, np.inf)
        out: list[PlaceMatch] = []
        seen: set[int] = set()
        for e in np.argsort(dist, kind="stable"):
            if not np.isfinite(dist[e]) or len(out) >= k:
                break
            if self._keyframe[e] in seen:
                continue
            seen.add(self._keyframe[e])
            out.append(PlaceMatch(self._poses[e], float(dist[e]), self._keyframe[e]))
        return out


def adopt_stored(stored: PlaceIndex | None, model, poses: np.ndarray, camera, n_levels: int) -> PlaceIndex | None:
    """``stored`` (a bundle's index) made ready for a session with this map ``model``, viewpoints
    ``poses [K, 4, 4]``, ``camera`` and pyramid of ``n_levels``, when its key says it was made from
    exactly these; None otherwise (logged), and the session renders its own."""
    if stored is None:
        return None
    level = descriptor_level(camera.width, n_levels)
    if stored.key is None or stored.key != map_key(model, poses, camera, level):
        logger.info("the stored place index is of another map, camera or layout: indexing the map's "
                    "%d viewpoints again", len(np.asarray(poses).reshape(-1, 4, 4)))
        return None
    stored.camera, stored.level = camera, level
    return stored


def map_key(model, poses: np.ndarray, camera, level: int) -> str:
    """SHA-256 (hex) of what a place index over ``model`` seen from ``poses [K, 4, 4]`` depends on:
    the surfels as stored (float32), the poses, the camera's pinhole, the pyramid level, the splat's
    limits (:meth:`SurfelModel.render`'s) and this module's layout and thresholds (grid, turned
    views, block and comparison shares, :data:`PLACES_VERSION`)."""
    from atlas_pipeline.localization.tracker import splat_params

    poses = np.ascontiguousarray(np.asarray(poses, np.float64).reshape(-1, 4, 4))
    centres = np.ascontiguousarray(model.centres, np.float32)
    normals = np.ascontiguousarray(model.normals, np.float32)
    h = hashlib.sha256()
    h.update(f"atlas-gs places v{PLACES_VERSION} grid {DESCRIPTOR_GRID} yaws {VIEW_YAWS_DEG} "
             f"min width {DESCRIPTOR_MIN_WIDTH_PX} level {int(level)} block {MIN_BLOCK_VALID_FRACTION} "
             f"common {MIN_COMMON_BLOCKS_FRACTION} splat {tuple(splat_params(model.radius_m))} "
             f"surfels {len(centres)} poses {len(poses)};".encode())
    h.update(np.array([camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy], np.float64).tobytes())
    h.update(np.float64(model.radius_m).tobytes())
    for a in (centres, normals, poses):
        h.update(a.tobytes())
    return h.hexdigest()


def place_index(model, camera, n_levels: int, poses: np.ndarray) -> PlaceIndex:
    """A :class:`PlaceIndex` of ``model`` seen from ``poses [K, 4, 4]`` (a world's keyframes), at
    the level pyramids of ``n_levels`` give, keyed by :func:`map_key`."""
    level = descriptor_level(camera.width, n_levels)
    index = PlaceIndex(camera, level)
    for k, T in enumerate(np.asarray(poses, np.float64).reshape(-1, 4, 4)):
        index.add_keyframe(model, T, k)
    index.key = map_key(model, poses, camera, level)
    return index


# Cells of the coverage map (m): coarse enough that a surface sampled every few centimetres (far
# walls, stride-2 points) fills its cells, fine enough that a new wall or object is new cells.
COVERAGE_CELL_M = 0.1


class CoverageMap:
    """Which coarse cells of space hold mapped surface (hashed voxels, :data:`COVERAGE_CELL_M`).

    What a keyframe adds is the share of its points in cells the map has never seen: robust to a
    sparse or noisy map where "lands on a rendered surfel" is not, and its cost per frame depends
    on the frame's points only (a sorted-array lookup), not on how much has been mapped.
    """

    def __init__(self, cell_m: float = COVERAGE_CELL_M):
        self.cell_m = float(cell_m)
        self._cells = np.zeros(0, np.uint64)  # sorted unique cell ids

    def __len__(self) -> int:
        return len(self._cells)

    def _ids(self, points_world: np.ndarray) -> np.ndarray:
        from atlas_pipeline.gaussian_world.builder import pack_voxel_ids

        return pack_voxel_ids(np.floor(np.asarray(points_world, np.float64) / self.cell_m).astype(np.int64))

    def add(self, points_world: np.ndarray) -> None:
        """Mark the cells of ``points_world [M, 3]`` as mapped."""
        if len(points_world):
            self._cells = np.union1d(self._cells, self._ids(points_world))

    def add_voxels(self, builder) -> None:
        """Mark the cells of every voxel of a :class:`VoxelGaussianBuilder` (a saved map)."""
        from atlas_pipeline.gaussian_world.builder import unpack_voxel_ids

        if len(builder.ids):
            centres = (unpack_voxel_ids(builder.ids) + 0.5) * builder.voxel_size_m
            self.add(centres)

    def new_share(self, points_world: np.ndarray) -> float:
        """Share of ``points_world [M, 3]`` in cells not mapped yet (1.0 for an empty map; NaN with no points)."""
        if not len(points_world):
            return float("nan")
        if not len(self._cells):
            return 1.0
        ids = self._ids(points_world)
        pos = np.minimum(np.searchsorted(self._cells, ids), len(self._cells) - 1)
        return float(np.mean(self._cells[pos] != ids))


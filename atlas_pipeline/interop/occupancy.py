"""A 2D occupancy grid for navigation, written as a ROS ``map_server`` map (PGM + YAML) that Nav2's
map server loads.

1. *Floor*, from the map: "up" is the mean normal of the flat Gaussians lying within 35 degrees of
   the cameras' mean up axis (-y of an OpenCV camera held upright); the Gaussians' heights along it
   are histogrammed; the lowest height holding at least
   :data:`FLOOR_MIN_SHARE` of them, below the cameras, is the floor, refined by a least-squares
   plane through the Gaussians near it (twice: the plane's normal becomes "up").
2. *Map frame*: z the floor's normal (towards the cameras), x the world's x projected onto the floor
   (y where x is nearly vertical), the origin the world origin's projection onto the floor; heights
   are measured from the floor. ``occupancy.json`` gives ``T_world_map`` (4x4).
3. *Floor, region by region* (:func:`fit_floor`): real depth does not lie on one plane (a pose a
   fraction of a degree off, a depth bias growing with range lift the far floor by centimetres per
   metre). The frames' depth points near the plane vote, one vote per 5-cm cell, for the floor's
   height in regions of :data:`FLOOR_TILE_M` (the lowest strong peak of their heights, smoothed by
   the depth noise model); each frame's own tilt against that floor is fitted and taken out, and
   the floor fitted again.
4. *Obstacles*: a depth point whose height above that floor (as its frame sees it) lies in the band
   from :func:`obstacle_min_height_m` (:data:`OBSTACLE_MIN_HEIGHT_M` near the camera, rising with
   the depth noise model's std, ``sensors.depth_noise``: 3 std, 12 cm at 5 m) to
   :data:`OBSTACLE_MAX_HEIGHT_M` is a hit. A cell is occupied with :data:`MIN_OBSTACLE_HITS` hits
   that are at least :data:`OBSTACLE_MIN_SHARE` of its readings, from two frames where two read it
   (:meth:`CellEvidence.occupied`).
5. *Free space*, from the camera rays: every cell a ray from a camera to its depth point crosses
   below the band's top, and every cell whose floor was seen, is observed; observed cells that
   are not occupied are free. The rest is unknown.

Frames are read through :func:`keyframe_depths` alone (depth without lens distortion, at the
export source's poses).

The map's cells are ``resolution_m`` wide (default :data:`OCCUPANCY_RESOLUTION_M`, 5 cm: Nav2's
usual costmap resolution). The PGM (binary P5) holds 0 for occupied, 254 for free and 205 for
unknown, its first row the map's far (+y) edge; the YAML says ``mode: trinary``, ``negate: 0``,
``occupied_thresh: 0.65`` and ``free_thresh: 0.19`` (map_server: occupancy ``(255 - p) / 255``, so 205 stays unknown),
and ``origin``: the map-frame pose ``[x, y, yaw]`` of the lower-left pixel.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from atlas_pipeline.config import MappingConfig
from atlas_pipeline.errors import ArtifactError, AtlasError, ConfigError
from atlas_pipeline.interop.frames import ExportSource
from atlas_pipeline.io_utils import atomic_path, write_json_atomic, write_text_atomic
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.depth_noise import depth_sigma_m

logger = logging.getLogger(__name__)

__all__ = ["OCCUPANCY_RESOLUTION_M", "OccupancyGrid", "occupancy_grid", "find_floor", "map_frame", "grid_evidence",
           "cell_evidence", "CellEvidence", "FloorSurface", "FramePoints", "fit_floor", "fit_floor_surface",
           "fit_frame_tilts", "obstacle_min_height_m", "keyframe_depths", "frame_points", "write_ros_map", "read_pgm",
           "OccupancyMap", "FREE", "OCCUPIED", "UNKNOWN", "check_resolution"]

OCCUPANCY_RESOLUTION_M = 0.05
MIN_RESOLUTION_M, MAX_RESOLUTION_M = 0.01, 1.0
OBSTACLE_MIN_HEIGHT_M = 0.05  # the band's bottom at close range, where the depth noise is millimetres
OBSTACLE_NOISE_SIGMAS = 3.0  # farther, the bottom is 3 std of the depth noise: 0.1 % of floor points above it
OBSTACLE_MAX_HEIGHT_M = 2.0  # a person-sized robot; the ceiling (and lamps) stay out
MIN_OBSTACLE_HITS = 2  # one stray depth point does not block a cell
MIN_OBSTACLE_FRAMES = 2  # nor one frame's stray cluster, where other frames read the cell too
# A floor cell's readings above the band are the noise's tail: 0.1 % of them at 3 std if it were
# Gaussian, a few % on real structured-light depth (a heavier tail); an obstacle is most of its cell's.
OBSTACLE_MIN_SHARE = 0.1
FLOOR_MIN_SHARE = 0.03  # of the map's Gaussians in one floor height bin
FLOOR_BIN_M = 0.02
FLOOR_BAND_M = 0.04  # Gaussians within this of the floor height fit its plane
FLOOR_BELOW_CAMERAS_M = 0.3  # the floor is at least this far below the lowest camera
MIN_FLOOR_OPACITY = 0.3
FLAT_SCALE_RATIO = 0.5  # a Gaussian is flat (has a normal) when its shortest axis is under half the next
HORIZONTAL_MAX_TILT_DEG = 35.0
# The floor, region by region: a tilted pose or a depth bias that grows with range lifts the far
# floor off the plane by centimetres per metre; regions of 0.5 m follow that, and the 1.5-m window
# each is fitted over sees floor beside anything a robot must drive around.
FLOOR_TILE_M = 0.5
FLOOR_MAX_DEPARTURE_M = 0.3  # farther from the plane is another level (a step, a table), not this floor
FLOOR_HIST_BIN_M = 0.01
FLOOR_PEAK_SHARE = 0.3  # the floor's peak holds this much of the window's strongest height
FLOOR_CELL_M = 0.05  # the points vote for the floor's height one cell of this size at a time
FLOOR_MIN_CELLS = 20  # floor cells in a window (of 900) for its floor to be fitted
FLOOR_MIN_SIGMA_M = 0.005  # the floor's own unevenness, under the sensor's noise at close range
FLOOR_INLIER_SIGMAS = 2.0
FLOOR_AGREE_SIGMAS = 3.0  # a region's floor within this many std of its neighbours' median
FLOOR_MIN_NEIGHBOURS = 3
TILT_MIN_POINTS = 200  # floor points of a frame to fit its tilt (3 parameters) to
TILT_ITERATIONS = 4
TILT_MIN_SPREAD_M = FLOOR_TILE_M  # the floor points' std across their narrowest direction, for slopes
MAD_TO_SIGMA = 1.4826  # a normal distribution's std per median absolute deviation
OCCUPANCY_MAX_DEPTH_M = MappingConfig().max_depth_m  # the map's own depth range
ORIGIN_DECIMALS = 9  # nanometres: the origin is a whole number of cells, free of float residue
HIT_STRIDE_PX = 2  # obstacle and floor points from every 2nd pixel
RAY_STRIDE_PX = 8  # free-space rays from every 8th pixel (each crosses many cells)
GRID_MARGIN_CELLS = 2
# ROS map_server values (trinary): occupancy = (255 - p) / 255 with negate 0
FREE, OCCUPIED, UNKNOWN = 0, 100, -1  # the grid's cell states (nav_msgs/OccupancyGrid's values)
PGM_FREE, PGM_OCCUPIED, PGM_UNKNOWN = 254, 0, 205
# unknown (205) reads (255 - 205) / 255 = 0.196: free_thresh must stay below it or unknown loads as free
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.19
_PREVIEW_SCALE = 4  # preview pixels per cell
_PREVIEW_COLOURS = {FREE: (255, 255, 255), OCCUPIED: (20, 20, 20), UNKNOWN: (170, 170, 180)}
_CAMERA_COLOUR = (220, 40, 40)
_RAY_CHUNK = 1 << 14


def check_resolution(resolution_m: float, option: str = "--resolution") -> float:
    r = float(resolution_m)
    if not (np.isfinite(r) and MIN_RESOLUTION_M <= r <= MAX_RESOLUTION_M):
        raise ConfigError(f"{option} must be a number of metres in [{MIN_RESOLUTION_M}, {MAX_RESOLUTION_M}], "
                          f"got {resolution_m}")
    return r


def _horizontal_up(field, opaque: np.ndarray, up: np.ndarray) -> np.ndarray:
    """"Up" refined from the flat Gaussians whose normal (shortest axis) is within
    :data:`HORIZONTAL_MAX_TILT_DEG` of ``up`` (floor, ceiling, table tops): the mean of those
    normals. Cameras look down at a floor, so their up axes alone are tilted by tens of degrees."""
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    s = field.scales[opaque]
    order = np.sort(s, axis=1)
    flat = order[:, 0] < FLAT_SCALE_RATIO * order[:, 1]
    if flat.sum() < 3:
        return up
    R = quat_xyzw_to_rotmat(field.rotations_xyzw[opaque][flat].astype(np.float64))  # [M, 3, 3]
    n = R[np.arange(len(R)), :, np.argmin(s[flat], axis=1)]  # [M, 3] shortest axis in the world
    n *= np.sign(n @ up)[:, None]
    level = n @ up >= np.cos(np.radians(HORIZONTAL_MAX_TILT_DEG))
    if level.sum() < 3:
        return up
    m = n[level].mean(axis=0)
    return m / np.linalg.norm(m)


def find_floor(field, T_world_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """The floor plane ``(unit normal [3] towards the cameras, offset)``, ``n . p = offset`` on the
    floor, from the map's Gaussians and the cameras ``[K, 4, 4]`` (module docstring, step 1)."""
    up = -np.asarray(T_world_cam, np.float64)[:, :3, 1].mean(axis=0)
    if np.linalg.norm(up) < 1e-6:
        raise AtlasError("the cameras' up axes cancel out: no floor direction")
    up /= np.linalg.norm(up)
    opaque = field.opacities >= MIN_FLOOR_OPACITY
    if opaque.sum() < 3:
        opaque = np.ones(len(field), bool)
    up = _horizontal_up(field, opaque, up)
    p = field.positions[opaque].astype(np.float64)
    offset = 0.0
    for _ in range(2):
        h = p @ up
        cam_h = np.asarray(T_world_cam, np.float64)[:, :3, 3] @ up
        below = h < cam_h.min() - FLOOR_BELOW_CAMERAS_M
        if below.sum() < 3:
            raise AtlasError("no map points below the cameras: the floor was not seen")
        edges = np.arange(h[below].min(), h[below].max() + 2 * FLOOR_BIN_M, FLOOR_BIN_M)
        counts, edges = np.histogram(h[below], bins=edges)
        strong = np.flatnonzero(counts >= FLOOR_MIN_SHARE * len(p))
        if not len(strong):
            raise AtlasError(f"no height below the cameras holds {FLOOR_MIN_SHARE:.0%} of the map: no floor found")
        b = strong[0]
        # the peak may straddle two bins: the floor is fitted to the points near it
        near = below & (np.abs(h - (edges[b] + edges[b + 1]) / 2) <= FLOOR_BAND_M)
        q = p[near]
        c = q.mean(axis=0)
        n = np.linalg.svd(q - c, full_matrices=False)[2][-1]
        up = n if n @ up > 0 else -n
        offset = float(c @ up)
    return up, offset


def map_frame(normal: np.ndarray, offset: float) -> np.ndarray:
    """``T_world_map`` ``[4, 4]`` of the floor ``normal . p = offset`` (module docstring, step 2)."""
    z = np.asarray(normal, np.float64)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = offset * z  # the world origin's projection onto the floor
    return T


@dataclass
class GridSpec:
    """Cells ``resolution_m`` wide; cell ``(row, col)`` spans ``x0 + col * r`` and ``y0 + row * r``
    in the map frame (row 0 at the lowest y)."""

    origin_xy: np.ndarray
    resolution_m: float
    shape: tuple[int, int]

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(rows, cols, inside)`` of map-frame points ``[N, 2]``."""
        c = np.floor((xy - self.origin_xy) / self.resolution_m).astype(np.int64)
        inside = (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < self.shape[1]) & (c[:, 1] < self.shape[0])
        return c[:, 1], c[:, 0], inside


def grid_around(xy: np.ndarray, resolution_m: float) -> GridSpec:
    """The grid holding the map-frame points ``xy`` ``[N, 2]`` with :data:`GRID_MARGIN_CELLS` to
    spare, its origin a whole number of cells."""
    lo = np.floor(xy.min(axis=0) / resolution_m - GRID_MARGIN_CELLS) * resolution_m
    hi = np.ceil(xy.max(axis=0) / resolution_m + GRID_MARGIN_CELLS) * resolution_m
    shape = (int(round((hi[1] - lo[1]) / resolution_m)), int(round((hi[0] - lo[0]) / resolution_m)))
    return GridSpec(lo, resolution_m, shape)


def written_origin_xy(grid: GridSpec) -> list[float]:
    """The grid's origin as the YAML and JSON give it: rounded to :data:`ORIGIN_DECIMALS` (a whole
    number of cells reads ``-8.45``, not ``-8.450000000000001``)."""
    return [round(float(v), ORIGIN_DECIMALS) for v in grid.origin_xy]


# ---- frames ------------------------------------------------------------------------------------


def keyframe_depths(src: ExportSource) -> Iterator[tuple[np.ndarray, np.ndarray, CameraIntrinsics]]:
    """Per frame of ``src``: ``(T_world_cam [4, 4], depth_m [H, W] float32 without lens distortion,
    its pinhole camera)``, each frame read from its own recording (an extended world's keyframes
    come from several). The one place this module reads frames."""
    for k, T in enumerate(src.T_world_cam):
        yield T, src.pinhole_depth_m(k), src.camera


@dataclass
class FramePoints:
    """One frame's depth points in the map frame: the camera centre ``[3]``, the points ``[M, 3]``
    and each point's depth reading ``depth_m`` ``[M]`` (what its noise grows with)."""

    centre: np.ndarray
    points: np.ndarray
    depth_m: np.ndarray
    # the frame's own floor error ``[3]``: offset (m) at the camera, slopes along map x and y
    # (m/m), fitted by :func:`fit_frame_tilts` (a pose a fraction of a degree off lifts the far floor)
    tilt: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def heights(self, floor: "FloorSurface", xyz: np.ndarray | None = None) -> np.ndarray:
        """Heights ``[N]`` above ``floor`` as this frame sees it, of its points or of ``xyz`` ``[N, 3]``."""
        p = self.points if xyz is None else xyz
        dx, dy = p[:, 0] - self.centre[0], p[:, 1] - self.centre[1]
        return p[:, 2] - floor.height_at(p[:, :2]) - (self.tilt[0] + self.tilt[1] * dx + self.tilt[2] * dy)


def frame_points(T_map_cam: np.ndarray, depth_m: np.ndarray, camera: CameraIntrinsics, stride: int,
                 max_depth_m: float = OCCUPANCY_MAX_DEPTH_M) -> FramePoints:
    """Every ``stride``-th pixel's depth point of ``depth_m`` ``[H, W]`` (readings in
    ``(0, max_depth_m]``) in the map frame, the camera at ``T_map_cam`` ``[4, 4]``."""
    v, u = np.mgrid[0:depth_m.shape[0]:stride, 0:depth_m.shape[1]:stride]
    d = depth_m[v, u].astype(np.float64)
    ok = (d > 0) & (d <= max_depth_m)
    d = d[ok]
    p_cam = np.stack([(u[ok] - camera.cx) / camera.fx * d, (v[ok] - camera.cy) / camera.fy * d, d], axis=1)
    return FramePoints(T_map_cam[:3, 3].copy(), p_cam @ T_map_cam[:3, :3].T + T_map_cam[:3, 3], d)


def _as_frame_points(frames) -> list[FramePoints]:
    """``FramePoints``, or ``(centre, points)`` pairs of an ideal sensor (depth noise 0)."""
    out = []
    for f in frames:
        if isinstance(f, FramePoints):
            out.append(f)
        else:
            centre, pts = f
            out.append(FramePoints(np.asarray(centre, np.float64), np.asarray(pts, np.float64), np.zeros(len(pts))))
    return out


# ---- the floor, region by region ---------------------------------------------------------------


@dataclass
class FloorSurface:
    """The floor's height above the map frame's ``z = 0`` plane, region by region: ``height_m``
    ``[Ht, Wt]`` at the centres of tiles ``tile_m`` wide (tile ``(0, 0)`` from ``origin_xy``),
    bilinear between them (constant beyond the outer centres); ``fitted`` ``[Ht, Wt]`` marks the
    tiles whose floor was seen (the others are filled in from them)."""

    origin_xy: np.ndarray
    tile_m: float
    height_m: np.ndarray
    fitted: np.ndarray

    @classmethod
    def flat(cls) -> "FloorSurface":
        """The plane ``z = 0`` itself."""
        return cls(np.zeros(2), 1.0, np.zeros((1, 1)), np.ones((1, 1), bool))

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """The floor's height ``[N]`` under map-frame points ``xy`` ``[N, 2]``."""
        h = self.height_m
        f = (np.asarray(xy, np.float64) - self.origin_xy) / self.tile_m - 0.5  # in tile centres
        fx = np.clip(f[:, 0], 0, h.shape[1] - 1)
        fy = np.clip(f[:, 1], 0, h.shape[0] - 1)
        x0 = np.minimum(np.floor(fx).astype(np.int64), max(h.shape[1] - 2, 0))
        y0 = np.minimum(np.floor(fy).astype(np.int64), max(h.shape[0] - 2, 0))
        x1, y1 = np.minimum(x0 + 1, h.shape[1] - 1), np.minimum(y0 + 1, h.shape[0] - 1)
        ax, ay = fx - x0, fy - y0
        return ((1 - ay) * ((1 - ax) * h[y0, x0] + ax * h[y0, x1]) + ay * ((1 - ax) * h[y1, x0] + ax * h[y1, x1]))

    def summary(self) -> dict[str, Any]:
        fitted = self.height_m[self.fitted]
        return {"tile_m": self.tile_m, "tiles_fitted": int(self.fitted.sum()), "tiles": int(self.fitted.size),
                "height_range_m": [round(float(fitted.min()), 4), round(float(fitted.max()), 4)] if len(fitted)
                else [0.0, 0.0]}


def _box3(a: np.ndarray) -> np.ndarray:
    """Sums over the 3 x 3 tiles around each tile of ``a`` ``[Ht, Wt, ...]`` (zero outside)."""
    p = np.pad(a, [(1, 1), (1, 1)] + [(0, 0)] * (a.ndim - 2))
    return sum(p[i:i + a.shape[0], j:j + a.shape[1]] for i in range(3) for j in range(3))


def _lowest_peak(density: np.ndarray) -> int:
    """The lowest bin of ``density`` ``[B]`` that is a local maximum holding at least
    :data:`FLOOR_PEAK_SHARE` of the highest (the floor lies under whatever stands on it)."""
    d = np.concatenate([[-1.0], density, [-1.0]])
    peak = (d[1:-1] >= d[:-2]) & (d[1:-1] >= d[2:]) & (density >= FLOOR_PEAK_SHARE * density.max())
    return int(np.flatnonzero(peak)[0])


def _cell_medians(pts: np.ndarray, sig: np.ndarray, lo: np.ndarray, cell_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per floor cell (``cell_m`` wide from ``lo``) holding points ``[N, 3]`` (x, y, height):
    ``(cell [C, 2] int64 column and row, median height [C], the noise std of that point [C])``."""
    cell = np.floor((pts[:, :2] - lo) / cell_m).astype(np.int64)
    key = cell[:, 1] * (int(cell[:, 0].max()) + 1) + cell[:, 0]
    order = np.lexsort((pts[:, 2], key))
    k = key[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    counts = np.diff(np.r_[starts, len(k)])
    mid = order[starts + (counts - 1) // 2]
    return cell[mid], pts[mid, 2], sig[mid]


def fit_floor_surface(frames: list[FramePoints], tile_m: float = FLOOR_TILE_M) -> FloorSurface:
    """The floor's height region by region, from the depth points within
    :data:`FLOOR_MAX_DEPARTURE_M` of the map's floor plane (each frame's tilt taken out).

    The points vote by :data:`FLOOR_CELL_M` cell, each cell its median height: a wall holds many
    points but few cells, the floor many cells. Per tile, over the window of it and its 8
    neighbours, the cells' heights are histogrammed (:data:`FLOOR_HIST_BIN_M` bins) and smoothed by
    the depth noise model's std (the window's median); the lowest strong peak is the floor there
    (whatever stands on the floor is above it), refined to the mean of the cells within
    :data:`FLOOR_INLIER_SIGMAS` std of it (each weighted by its ``1 / sigma^2``). A tile's floor
    that departs from the median of its fitted neighbours by more than the noise allows (a low
    platform, a wall's foot taken for floor) is dropped; tiles with no floor take their
    neighbours' (repeated 3 x 3 averaging), or the plane's where none was seen.
    """
    if not frames:
        return FloorSurface.flat()
    flat = FloorSurface.flat()
    pts = np.concatenate([np.column_stack([f.points[:, :2], f.heights(flat)]) for f in frames])
    dep = np.concatenate([f.depth_m for f in frames])
    near = np.abs(pts[:, 2]) <= FLOOR_MAX_DEPARTURE_M
    pts, sig = pts[near], np.maximum(depth_sigma_m(dep[near]), FLOOR_MIN_SIGMA_M)
    if len(pts) == 0:
        return FloorSurface.flat()
    lo = np.floor(pts[:, :2].min(axis=0) / tile_m) * tile_m
    cell, h, sig = _cell_medians(pts, sig, lo, FLOOR_CELL_M)
    t = (cell * FLOOR_CELL_M + FLOOR_CELL_M / 2) // tile_m  # the tile of each cell's centre
    t = t.astype(np.int64)
    shape = (int(t[:, 1].max()) + 1, int(t[:, 0].max()) + 1)
    n_bins = int(round(2 * FLOOR_MAX_DEPARTURE_M / FLOOR_HIST_BIN_M)) + 1
    b = np.clip(np.rint((h + FLOOR_MAX_DEPARTURE_M) / FLOOR_HIST_BIN_M).astype(np.int64), 0, n_bins - 1)
    tile = t[:, 1] * shape[1] + t[:, 0]
    hist = np.bincount(tile * n_bins + b, minlength=shape[0] * shape[1] * n_bins).reshape(*shape, n_bins)
    window = _box3(hist.astype(np.float64))  # [Ht, Wt, B] cells per height bin
    height = np.zeros(shape)
    tile_sigma = np.zeros(shape)
    fitted = np.zeros(shape, bool)
    centres = np.arange(n_bins) * FLOOR_HIST_BIN_M - FLOOR_MAX_DEPARTURE_M
    kernel_m = np.arange(-n_bins + 1, n_bins) * FLOOR_HIST_BIN_M
    order = np.argsort(tile, kind="stable")
    starts = np.searchsorted(tile[order], np.arange(shape[0] * shape[1] + 1))
    for r, c in zip(*np.nonzero(window.sum(axis=2) >= FLOOR_MIN_CELLS)):
        idx = np.concatenate([order[starts[rr * shape[1] + cc]:starts[rr * shape[1] + cc + 1]]
                              for rr in range(max(r - 1, 0), min(r + 2, shape[0]))
                              for cc in range(max(c - 1, 0), min(c + 2, shape[1]))])
        s = float(np.median(sig[idx]))  # the window's noise
        density = np.convolve(window[r, c], np.exp(-0.5 * (kernel_m / s) ** 2))[n_bins - 1:2 * n_bins - 1]
        peak = centres[_lowest_peak(density)]
        w = 1.0 / sig[idx] ** 2
        inl = np.abs(h[idx] - peak) <= FLOOR_INLIER_SIGMAS * np.maximum(sig[idx], s)
        if inl.sum() < FLOOR_MIN_CELLS:
            continue
        height[r, c] = float((h[idx][inl] * w[inl]).sum() / w[inl].sum())
        tile_sigma[r, c] = s
        fitted[r, c] = True
    # a tile's floor agrees with its fitted neighbours' median, within the noise of both
    keep = fitted.copy()
    for r, c in zip(*np.nonzero(fitted)):
        nb = [(rr, cc) for rr in range(max(r - 1, 0), min(r + 2, shape[0]))
              for cc in range(max(c - 1, 0), min(c + 2, shape[1])) if (rr, cc) != (r, c) and fitted[rr, cc]]
        if len(nb) >= FLOOR_MIN_NEIGHBOURS:
            med = np.median([height[x] for x in nb])
            if abs(height[r, c] - med) > FLOOR_AGREE_SIGMAS * tile_sigma[r, c]:
                keep[r, c] = False
    fitted = keep
    filled = np.where(fitted, height, 0.0)
    have = fitted.astype(np.float64)
    for _ in range(max(shape)):
        if have.all():
            break
        s_h, s_n = _box3(filled * (have > 0)), _box3((have > 0).astype(np.float64))
        grow = (have == 0) & (s_n > 0)
        if not grow.any():
            break
        filled[grow] = s_h[grow] / s_n[grow]
        have[grow] = 1.0
    return FloorSurface(lo, tile_m, filled, fitted)


def fit_frame_tilts(frames: list[FramePoints], floor: FloorSurface) -> None:
    """Each frame's own floor error (:attr:`FramePoints.tilt`), a plane through its floor points'
    heights above ``floor``: the points below the obstacle band's bottom, refitted
    :data:`TILT_ITERATIONS` times to those within :data:`FLOOR_INLIER_SIGMAS` std (the depth noise
    model's, or the residuals' own robust std where larger) of the plane. A frame with under
    :data:`TILT_MIN_POINTS` floor points keeps a zero tilt; one whose floor points spread less than
    :data:`TILT_MIN_SPREAD_M` across gets an offset alone."""
    for f in frames:
        f.tilt = np.zeros(3)
        e = f.heights(floor)
        sig = np.maximum(depth_sigma_m(f.depth_m), FLOOR_MIN_SIGMA_M)
        inl = np.abs(e) < obstacle_min_height_m(f.depth_m)
        if inl.sum() < TILT_MIN_POINTS:
            continue
        A = np.stack([np.ones(len(e)), f.points[:, 0] - f.centre[0], f.points[:, 1] - f.centre[1]], axis=1)
        # a slope needs floor spread out along it: a small patch's slope would tip the far points
        spread = np.sqrt(np.linalg.eigvalsh(np.cov(A[inl, 1:].T)).min())
        if spread < TILT_MIN_SPREAD_M:
            A[:, 1:] = 0.0
        coef = np.zeros(3)
        for _ in range(TILT_ITERATIONS):
            w = 1.0 / sig[inl]
            coef = np.linalg.lstsq(A[inl] * w[:, None], e[inl] * w, rcond=None)[0]
            res = e - A @ coef
            scale = MAD_TO_SIGMA * float(np.median(np.abs(res[inl])))
            inl = np.abs(res) <= FLOOR_INLIER_SIGMAS * np.maximum(sig, scale)
            if inl.sum() < TILT_MIN_POINTS:
                break
        else:
            f.tilt = coef


def fit_floor(frames: list[FramePoints]) -> FloorSurface:
    """The floor region by region (:func:`fit_floor_surface`) and each frame's own tilt against it
    (:func:`fit_frame_tilts`), twice: the second floor is fitted to the points with their frame's
    tilt taken out, so one frame's error does not lift the others' floor."""
    floor = fit_floor_surface(frames)
    fit_frame_tilts(frames, floor)
    floor = fit_floor_surface(frames)
    fit_frame_tilts(frames, floor)
    return floor


# ---- evidence ----------------------------------------------------------------------------------


def obstacle_min_height_m(depth_m: np.ndarray, band_bottom_m: float = OBSTACLE_MIN_HEIGHT_M) -> np.ndarray:
    """The lowest height above the floor ``[N]`` at which a point of depth reading ``depth_m``
    ``[N]`` is an obstacle: ``band_bottom_m``, or :data:`OBSTACLE_NOISE_SIGMAS` times the depth noise
    model's std where that is more (a floor point read with that noise stays below it)."""
    d = np.asarray(depth_m, np.float64)
    return np.where(d > 0, np.maximum(band_bottom_m, OBSTACLE_NOISE_SIGMAS * depth_sigma_m(d)), band_bottom_m)


@dataclass
class CellEvidence:
    """Per cell ``[H, W]``: ``hits`` (int64), the depth points in the obstacle band; ``readings``
    (int64), the depth points below the band's top (floor and obstacle); ``hit_frames`` and
    ``reading_frames`` (int64), the frames with a hit, a reading there; ``seen`` (bool), observed
    (a reading, or a camera ray below the band's top, crossed it)."""

    hits: np.ndarray
    readings: np.ndarray
    hit_frames: np.ndarray
    reading_frames: np.ndarray
    seen: np.ndarray

    def occupied(self) -> np.ndarray:
        """``[H, W]`` bool: at least :data:`MIN_OBSTACLE_HITS` hits, at least
        :data:`OBSTACLE_MIN_SHARE` of the cell's readings, and from two frames unless one frame
        alone read the cell. A frame's noise is correlated over a few pixels (the sensor's matching
        window), so its stray readings come in clusters; another frame's are independent of them."""
        agreed = (self.hit_frames >= MIN_OBSTACLE_FRAMES) | (self.reading_frames < MIN_OBSTACLE_FRAMES)
        return (self.hits >= MIN_OBSTACLE_HITS) & (self.hits >= OBSTACLE_MIN_SHARE * self.readings) & agreed


def cell_evidence(hits_frames, ray_frames, grid: GridSpec, band_m: tuple[float, float],
                  floor: FloorSurface | None = None) -> CellEvidence:
    """The evidence of map-frame depth points (:class:`FramePoints`, or ``(centre [3], points [M,
    3])`` pairs of an ideal sensor) on ``grid``'s cells: a point is an obstacle hit when its height
    above ``floor`` (default the plane ``z = 0``; with its frame's tilt taken out) lies in the band
    from :func:`obstacle_min_height_m` (``band_m[0]``, or the depth noise's where more) to
    ``band_m[1]``; rays from each camera to its points (sampled every half cell, below the band's
    top) mark the cells they cross as seen. ``ray_frames[k]`` is ``hits_frames[k]`` at another
    stride (its tilt is taken from there)."""
    floor = floor or FloorSurface.flat()
    hit_frames, rays = _as_frame_points(hits_frames), _as_frame_points(ray_frames)
    hits = np.zeros(grid.shape, np.int64)
    readings = np.zeros(grid.shape, np.int64)
    n_hit_frames = np.zeros(grid.shape, np.int64)
    n_reading_frames = np.zeros(grid.shape, np.int64)
    seen = np.zeros(grid.shape, bool)
    lo, hi = band_m
    # the floor under each cell's centre: it changes by millimetres across a cell
    rows, cols = np.mgrid[0:grid.shape[0], 0:grid.shape[1]]
    centres_xy = grid.origin_xy + (np.stack([cols.ravel(), rows.ravel()], axis=1) + 0.5) * grid.resolution_m
    floor_cells = floor.height_at(centres_xy).reshape(grid.shape)

    def heights(f: FramePoints, p: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Heights of ``p`` ``[N, 3]`` (inside the grid, in cells ``r``, ``c``) as frame ``f`` sees them."""
        return p[:, 2] - floor_cells[r, c] - (f.tilt[0] + f.tilt[1] * (p[:, 0] - f.centre[0])
                                              + f.tilt[2] * (p[:, 1] - f.centre[1]))

    for f in hit_frames:
        r, c, ok = grid.cells(f.points[:, :2])
        h = np.full(len(f.points), np.inf)
        h[ok] = heights(f, f.points[ok], r[ok], c[ok])
        below_top = ok & (h <= hi)
        obstacle = below_top & (h >= obstacle_min_height_m(f.depth_m, lo))
        np.add.at(hits, (r[obstacle], c[obstacle]), 1)
        np.add.at(readings, (r[below_top], c[below_top]), 1)
        hit_cell = np.zeros(grid.shape, bool)
        hit_cell[r[obstacle], c[obstacle]] = True
        n_hit_frames += hit_cell
        read_cell = np.zeros(grid.shape, bool)
        read_cell[r[below_top], c[below_top]] = True
        n_reading_frames += read_cell
        seen |= read_cell
    step = grid.resolution_m / 2
    for k, f in enumerate(rays):
        tilted = FramePoints(f.centre, f.points, f.depth_m, hit_frames[k].tilt if k < len(hit_frames) else f.tilt)
        centre = f.centre
        for s in range(0, len(f.points), _RAY_CHUNK):
            end = f.points[s:s + _RAY_CHUNK]
            d = end - centre
            length = np.linalg.norm(d[:, :2], axis=1)  # cells are crossed in the floor's plane
            n = np.maximum(1, np.ceil(length / step).astype(np.int64))
            ray = np.repeat(np.arange(len(end)), n)
            t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)  # [0, 1) along each ray
            q = centre + d[ray] * t[:, None]
            r, c, ok = grid.cells(q[:, :2])
            r, c, q = r[ok], c[ok], q[ok]
            keep = heights(tilted, q, r, c) <= hi
            seen[r[keep], c[keep]] = True
    return CellEvidence(hits, readings, n_hit_frames, n_reading_frames, seen)


def grid_evidence(hits_frames, ray_frames, grid: GridSpec, band_m: tuple[float, float],
                  floor: FloorSurface | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(obstacle hits [H, W] int64, observed [H, W] bool)`` of :func:`cell_evidence`."""
    ev = cell_evidence(hits_frames, ray_frames, grid, band_m, floor)
    return ev.hits, ev.seen


@dataclass
class OccupancyGrid:
    """``state`` ``[H, W]`` int8 (:data:`FREE`, :data:`OCCUPIED`, :data:`UNKNOWN`), row 0 at the
    map frame's lowest y; ``grid``; ``T_world_map`` ``[4, 4]``; the floor plane, the band (its
    bottom at close range: it rises with the depth noise), the floor region by region."""

    state: np.ndarray
    grid: GridSpec
    T_world_map: np.ndarray
    floor_normal: np.ndarray
    floor_offset_m: float
    band_m: tuple[float, float]
    cameras_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [K, 2] map frame
    floor: FloorSurface = field(default_factory=FloorSurface.flat)


def occupancy_grid(src: ExportSource, resolution_m: float = OCCUPANCY_RESOLUTION_M,
                   band_m: tuple[float, float] = (OBSTACLE_MIN_HEIGHT_M, OBSTACLE_MAX_HEIGHT_M),
                   log: Callable[[str], None] | None = None) -> OccupancyGrid:
    """The occupancy grid of ``src``'s world and frames (module docstring)."""
    log = log or logger.info
    resolution_m = check_resolution(resolution_m)
    normal, offset = find_floor(src.field, src.T_world_cam)
    T_world_map = map_frame(normal, offset)
    T_map_world = np.linalg.inv(T_world_map)
    hit_frames, ray_frames = [], []
    for T_world_cam, depth_m, cam in keyframe_depths(src):
        T_map_cam = T_map_world @ T_world_cam
        hit_frames.append(frame_points(T_map_cam, depth_m, cam, HIT_STRIDE_PX))
        ray_frames.append(frame_points(T_map_cam, depth_m, cam, RAY_STRIDE_PX))
    cameras_xy = np.array([f.centre[:2] for f in hit_frames])
    grid = grid_around(np.concatenate([f.points[:, :2] for f in hit_frames] + [cameras_xy]), resolution_m)
    floor = fit_floor(hit_frames)
    ev = cell_evidence(hit_frames, ray_frames, grid, band_m, floor)
    state = np.full(grid.shape, UNKNOWN, np.int8)
    state[ev.seen] = FREE
    state[ev.occupied()] = OCCUPIED
    fs = floor.summary()
    log(f"occupancy: {grid.shape[1]}x{grid.shape[0]} cells of {resolution_m} m, {int((state == FREE).sum())} free, "
        f"{int((state == OCCUPIED).sum())} occupied; floor fitted in {fs['tiles_fitted']} regions of "
        f"{floor.tile_m} m, {fs['height_range_m'][0]:+.3f}..{fs['height_range_m'][1]:+.3f} m off its plane")
    return OccupancyGrid(state, grid, T_world_map, normal, offset, tuple(band_m), cameras_xy, floor)


def write_ros_map(occ: OccupancyGrid, directory: Path, stem: str = "map") -> list[Path]:
    """``<stem>.pgm`` and ``<stem>.yaml`` (map_server's format, module docstring) into ``directory``."""
    h, w = occ.state.shape
    pgm = np.full((h, w), PGM_UNKNOWN, np.uint8)
    pgm[occ.state == FREE] = PGM_FREE
    pgm[occ.state == OCCUPIED] = PGM_OCCUPIED
    pgm_path = directory / f"{stem}.pgm"
    with atomic_path(pgm_path) as tmp:
        tmp.write_bytes(f"P5\n# Atlas-GS occupancy grid, {occ.grid.resolution_m} m/cell\n{w} {h}\n255\n".encode()
                        + pgm[::-1].tobytes())  # the image's first row is the map's far (+y) edge
    x0, y0 = written_origin_xy(occ.grid)
    yaml_path = write_text_atomic(directory / f"{stem}.yaml", (
        f"image: {stem}.pgm\nmode: trinary\nresolution: {occ.grid.resolution_m!r}\n"
        f"origin: [{x0!r}, {y0!r}, 0.0]\nnegate: 0\noccupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n"))
    return [pgm_path, yaml_path]


def read_pgm(path: Path) -> np.ndarray:
    """``[H, W]`` uint8 of a binary (P5) PGM of maxval 255, first row first (as stored)."""
    data = Path(path).read_bytes()
    fields: list[bytes] = []
    pos = 0
    while len(fields) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[pos:end])
        pos = end
    if fields[0] != b"P5" or fields[3] != b"255":
        raise ArtifactError(f"{path}: not a binary 8-bit PGM")
    w, h = int(fields[1]), int(fields[2])
    return np.frombuffer(data[pos + 1:pos + 1 + w * h], np.uint8).reshape(h, w)


def occupancy_preview_png(occ: OccupancyGrid) -> bytes:
    """The grid as a PNG, :data:`_PREVIEW_SCALE` pixels per cell, +y up, cameras in red."""
    from PIL import Image

    img = np.zeros((*occ.state.shape, 3), np.uint8)
    for s, col in _PREVIEW_COLOURS.items():
        img[occ.state == s] = col
    r, c, ok = occ.grid.cells(occ.cameras_xy)
    img[r[ok], c[ok]] = _CAMERA_COLOUR
    img = np.repeat(np.repeat(img[::-1], _PREVIEW_SCALE, axis=0), _PREVIEW_SCALE, axis=1)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def occupancy_info(occ: OccupancyGrid, src: ExportSource) -> dict[str, Any]:
    return {"resolution_m": occ.grid.resolution_m, "width": occ.state.shape[1], "height": occ.state.shape[0],
            "origin_xy_m": written_origin_xy(occ.grid), "T_world_map": occ.T_world_map.tolist(),
            "floor": {"normal": occ.floor_normal.tolist(), "offset_m": occ.floor_offset_m,
                      "regions": occ.floor.summary()},
            # the band's bottom at close range; farther it is this many std of the depth noise model
            "obstacle_band_m": list(occ.band_m), "obstacle_band_noise_sigmas": OBSTACLE_NOISE_SIGMAS,
            "n_free": int((occ.state == FREE).sum()),
            "n_occupied": int((occ.state == OCCUPIED).sum()), "n_unknown": int((occ.state == UNKNOWN).sum()),
            "map_id": src.map_id, "dataset": src.manifest.dataset, "pose_source": src.pose_source,
            "frame_indices": [int(i) for i in src.frame_indices],
            "recordings": src.recordings_summary(), "frame_recordings": [int(j) for j in src.frame_recording]}


@dataclass
class OccupancyMap:
    """The ``occupancy_map`` asset's artifact: ``map.pgm``, ``map.yaml``, ``occupancy.json``,
    ``preview.png``."""

    grid: OccupancyGrid | None
    info: dict[str, Any]
    preview_png: bytes = b""

    def save(self, directory: Path) -> list[Path]:
        if self.grid is None:
            raise ArtifactError("a loaded OccupancyMap holds only its summary; compute it again to write it")
        paths = write_ros_map(self.grid, directory)
        with atomic_path(directory / "preview.png") as tmp:
            tmp.write_bytes(self.preview_png or occupancy_preview_png(self.grid))
        return [*paths, directory / "preview.png", write_json_atomic(directory / "occupancy.json", self.info)]

    @classmethod
    def load(cls, directory: Path) -> "OccupancyMap":
        from atlas_pipeline.safe_arrays import load_json_object_checked

        if not (directory / "occupancy.json").is_file() or not (directory / "map.pgm").is_file():
            raise ArtifactError(f"{directory}: occupancy.json or map.pgm missing")
        return cls(None, load_json_object_checked(directory / "occupancy.json"))

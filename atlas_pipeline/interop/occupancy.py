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
3. *Obstacles*: the frames' depth points (at the frames' poses) whose height lies in the band
   ``[OBSTACLE_MIN_HEIGHT_M, OBSTACLE_MAX_HEIGHT_M]`` (above floor noise, below a ceiling) mark
   their cell; :data:`MIN_OBSTACLE_HITS` marks make it occupied.
4. *Free space*, from the camera rays: every cell a ray from a camera to its depth point crosses
   below the band's top, and every cell whose floor was seen, is observed; observed cells that
   are not occupied are free. The rest is unknown.

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
from typing import Any, Callable

import numpy as np

from atlas_pipeline.errors import ArtifactError, AtlasError, ConfigError
from atlas_pipeline.interop.frames import ExportSource, undistorted_depth_m
from atlas_pipeline.io_utils import atomic_path, write_json_atomic, write_text_atomic

logger = logging.getLogger(__name__)

__all__ = ["OCCUPANCY_RESOLUTION_M", "OccupancyGrid", "occupancy_grid", "find_floor", "map_frame", "grid_evidence",
           "write_ros_map", "read_pgm", "OccupancyMap", "FREE", "OCCUPIED", "UNKNOWN", "check_resolution"]

OCCUPANCY_RESOLUTION_M = 0.05
MIN_RESOLUTION_M, MAX_RESOLUTION_M = 0.01, 1.0
OBSTACLE_MIN_HEIGHT_M = 0.05  # above the floor's depth noise and the Gaussians' thickness there
OBSTACLE_MAX_HEIGHT_M = 2.0  # a person-sized robot; the ceiling (and lamps) stay out
MIN_OBSTACLE_HITS = 2  # one stray depth point does not block a cell
FLOOR_MIN_SHARE = 0.03  # of the map's Gaussians in one floor height bin
FLOOR_BIN_M = 0.02
FLOOR_BAND_M = 0.04  # Gaussians within this of the floor height fit its plane
FLOOR_BELOW_CAMERAS_M = 0.3  # the floor is at least this far below the lowest camera
MIN_FLOOR_OPACITY = 0.3
FLAT_SCALE_RATIO = 0.5  # a Gaussian is flat (has a normal) when its shortest axis is under half the next
HORIZONTAL_MAX_TILT_DEG = 35.0
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


def _frame_points(src: ExportSource, T_map_world: np.ndarray, stride: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame: ``(camera centre [3], depth points [M, 3])`` in the map frame."""
    cam = src.manifest.camera
    v, u = np.mgrid[0:cam.height:stride, 0:cam.width:stride]
    out = []
    for i, T in zip(src.frame_indices.tolist(), src.T_world_cam):
        d = undistorted_depth_m(src.manifest.read_depth_m(i, allow_empty=True), cam)[v, u].astype(np.float64)
        ok = d > 0
        p_cam = np.stack([(u[ok] - cam.cx) / cam.fx * d[ok], (v[ok] - cam.cy) / cam.fy * d[ok], d[ok]], axis=1)
        T_map_cam = T_map_world @ T
        out.append((T_map_cam[:3, 3], p_cam @ T_map_cam[:3, :3].T + T_map_cam[:3, 3]))
    return out


def grid_evidence(hits_frames: list[tuple[np.ndarray, np.ndarray]], ray_frames: list[tuple[np.ndarray, np.ndarray]],
                  grid: GridSpec, band_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """``(obstacle hits [H, W] int64, observed [H, W] bool)`` from map-frame depth points: hits
    of points in the height ``band_m``; observed where such a hit, a floor point, or a ray from a
    camera to a point (sampled every half cell, below the band's top) lies."""
    hits = np.zeros(grid.shape, np.int64)
    seen = np.zeros(grid.shape, bool)
    lo, hi = band_m
    for _, pts in hits_frames:
        h = pts[:, 2]
        r, c, ok = grid.cells(pts[:, :2])
        obstacle = ok & (h >= lo) & (h <= hi)
        np.add.at(hits, (r[obstacle], c[obstacle]), 1)
        seen[r[ok & (h <= hi)], c[ok & (h <= hi)]] = True
    step = grid.resolution_m / 2
    for centre, pts in ray_frames:
        for s in range(0, len(pts), _RAY_CHUNK):
            end = pts[s:s + _RAY_CHUNK]
            d = end - centre
            length = np.linalg.norm(d[:, :2], axis=1)  # cells are crossed in the floor's plane
            n = np.maximum(1, np.ceil(length / step).astype(np.int64))
            ray = np.repeat(np.arange(len(end)), n)
            t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)  # [0, 1) along each ray
            q = centre + d[ray] * t[:, None]
            keep = q[:, 2] <= hi
            r, c, ok = grid.cells(q[keep, :2])
            seen[r[ok], c[ok]] = True
    return hits, seen


@dataclass
class OccupancyGrid:
    """``state`` ``[H, W]`` int8 (:data:`FREE`, :data:`OCCUPIED`, :data:`UNKNOWN`), row 0 at the
    map frame's lowest y; ``grid``; ``T_world_map`` ``[4, 4]``; the floor plane and the band."""

    state: np.ndarray
    grid: GridSpec
    T_world_map: np.ndarray
    floor_normal: np.ndarray
    floor_offset_m: float
    band_m: tuple[float, float]
    cameras_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [K, 2] map frame


def occupancy_grid(src: ExportSource, resolution_m: float = OCCUPANCY_RESOLUTION_M,
                   band_m: tuple[float, float] = (OBSTACLE_MIN_HEIGHT_M, OBSTACLE_MAX_HEIGHT_M),
                   log: Callable[[str], None] | None = None) -> OccupancyGrid:
    """The occupancy grid of ``src``'s world and frames (module docstring)."""
    log = log or logger.info
    resolution_m = check_resolution(resolution_m)
    f = src.field
    normal, offset = find_floor(f, src.T_world_cam)
    T_world_map = map_frame(normal, offset)
    T_map_world = np.linalg.inv(T_world_map)
    hit_frames = _frame_points(src, T_map_world, HIT_STRIDE_PX)
    ray_frames = _frame_points(src, T_map_world, RAY_STRIDE_PX)
    xy = np.concatenate([p[:, :2] for _, p in hit_frames] + [np.array([c[:2] for c, _ in hit_frames])])
    lo = np.floor(xy.min(axis=0) / resolution_m - GRID_MARGIN_CELLS) * resolution_m
    hi = np.ceil(xy.max(axis=0) / resolution_m + GRID_MARGIN_CELLS) * resolution_m
    shape = (int(round((hi[1] - lo[1]) / resolution_m)), int(round((hi[0] - lo[0]) / resolution_m)))
    grid = GridSpec(lo, resolution_m, shape)
    hits, seen = grid_evidence(hit_frames, ray_frames, grid, band_m)
    state = np.full(shape, UNKNOWN, np.int8)
    state[seen] = FREE
    state[hits >= MIN_OBSTACLE_HITS] = OCCUPIED
    log(f"occupancy: {shape[1]}x{shape[0]} cells of {resolution_m} m, {int((state == FREE).sum())} free, "
        f"{int((state == OCCUPIED).sum())} occupied")
    return OccupancyGrid(state, grid, T_world_map, normal, offset, tuple(band_m),
                         np.array([c[:2] for c, _ in hit_frames]))


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
    x0, y0 = (float(v) for v in occ.grid.origin_xy)
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
            "origin_xy_m": [float(v) for v in occ.grid.origin_xy], "T_world_map": occ.T_world_map.tolist(),
            "floor": {"normal": occ.floor_normal.tolist(), "offset_m": occ.floor_offset_m},
            "obstacle_band_m": list(occ.band_m), "n_free": int((occ.state == FREE).sum()),
            "n_occupied": int((occ.state == OCCUPIED).sum()), "n_unknown": int((occ.state == UNKNOWN).sum()),
            "map_id": src.map_id, "dataset": src.manifest.dataset, "pose_source": src.pose_source,
            "frame_indices": [int(i) for i in src.frame_indices]}


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

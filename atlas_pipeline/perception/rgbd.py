"""RGB-D back-projection: depth pixels to coloured 3D points in the camera frame (paper section 5.1).

``p_cam = depth_m * K^-1 [u, v, 1]^T``, with lens distortion removed from the pixel rays first when
the camera has distortion coefficients (TUM freiburg1/2), so points are metrically right across the
whole image, not only near the centre.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.config import FusionConfig, PipelineConfig
from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.progress import Progress
from atlas_pipeline.safe_arrays import is_finite_number, load_json_object_checked, load_npz_checked
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["pixel_rays", "backproject", "FusedFrames", "fuse_frames", "fuse", "iter_rgbd"]


def _undistort_normalized(xd: np.ndarray, yd: np.ndarray, dist: tuple[float, ...], iters: int = 10):
    """Invert the Brown-Conrady model (k1 k2 p1 p2 [k3]) by fixed-point iteration, as OpenCV does."""
    k1, k2, p1, p2 = dist[:4]
    k3 = dist[4] if len(dist) > 4 else 0.0
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


@functools.lru_cache(maxsize=16)
def pixel_rays(camera: CameraIntrinsics, stride: int = 1) -> np.ndarray:
    """Undistorted viewing rays with z = 1 for every ``stride``-th pixel: ``[H/stride, W/stride, 3]`` float32.

    Cached per (camera, stride): computing the inverse distortion is the expensive part.
    """
    v, u = np.mgrid[0:camera.height:stride, 0:camera.width:stride].astype(np.float64)
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    if camera.distortion:
        x, y = _undistort_normalized(x, y, camera.distortion)
    rays = np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float32)
    rays.setflags(write=False)  # shared through the cache
    return rays


def backproject(
    depth_m: np.ndarray,
    rgb: np.ndarray | None,
    camera: CameraIntrinsics,
    stride: int = 1,
    min_depth_m: float = 0.1,
    max_depth_m: float = 4.0,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Valid depth pixels to camera-frame points.

    Args:
        depth_m: ``[H, W]`` float32 metres, 0 = invalid.
        rgb: ``[H, W, 3]`` uint8 or None.
        stride: use every ``stride``-th pixel in u and v.

    Returns:
        ``(points_cam [M, 3] float32, colors [M, 3] uint8 or None)``.
    """
    rays = pixel_rays(camera, stride)
    z = depth_m[::stride, ::stride]
    valid = (z > min_depth_m) & (z < max_depth_m) & np.isfinite(z)
    pts = rays[valid] * z[valid][:, None]
    cols = rgb[::stride, ::stride][valid] if rgb is not None else None
    return pts.astype(np.float32, copy=False), cols


def iter_rgbd(manifest: FrameManifest, indices=None):
    """Yield ``(frame_index, rgb [H, W, 3] uint8, depth_m [H, W] float32)``, one frame in memory at a time."""
    for i in range(manifest.n_frames) if indices is None else indices:
        rgb = manifest.read_rgb(i)
        depth = manifest.read_depth_m(i)
        yield i, rgb, depth


# fused.npz members: (dtype kinds or exact dtype, ndim); shapes in FusedFrames.
_FUSED_MEMBERS = {"points_cam": ("f", 2), "colors": (np.uint8, 2), "offsets": ("iu", 1), "valid_fraction": ("f", 1)}


@dataclass
class FusedFrames:
    """Coloured camera-frame points of every frame, concatenated.

    Points stay in the camera frame so this artifact does not depend on which poses (ground truth
    or estimated) the mapper uses later.

    Attributes:
        points_cam: ``[M, 3]`` float32, metres, camera frame of the frame they came from.
        colors: ``[M, 3]`` uint8 RGB.
        offsets: ``[N + 1]`` int64; frame ``i`` owns rows ``offsets[i]:offsets[i+1]``.
        valid_fraction: ``[N]`` float32 share of sampled pixels with usable depth.
        stride, min_depth_m, max_depth_m: the settings that produced them.
    """

    points_cam: np.ndarray
    colors: np.ndarray
    offsets: np.ndarray
    valid_fraction: np.ndarray
    stride: int
    min_depth_m: float
    max_depth_m: float

    @property
    def n_frames(self) -> int:
        return len(self.offsets) - 1

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(points_cam [Mi, 3], colors [Mi, 3])`` of frame ``i`` (views, no copy)."""
        a, b = self.offsets[i], self.offsets[i + 1]
        return self.points_cam[a:b], self.colors[a:b]

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "fused.npz"
        with atomic_path(path) as tmp:
            np.savez(tmp, points_cam=self.points_cam, colors=self.colors, offsets=self.offsets,
                     valid_fraction=self.valid_fraction)
        meta = write_json_atomic(directory / "fused.json", {
            "n_frames": self.n_frames, "n_points": int(len(self.points_cam)), "stride": self.stride,
            "min_depth_m": self.min_depth_m, "max_depth_m": self.max_depth_m,
        })
        return [path, meta]

    @classmethod
    def load(cls, directory: Path) -> "FusedFrames":
        """Read :meth:`save`'s folder; arrays are checked (dtype, shape, offsets that partition the
        points, finite points) and a malformed file raises ``ArtifactError`` naming it."""
        path, meta_path = directory / "fused.npz", directory / "fused.json"
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: fused frames missing fused.npz or fused.json")
        meta = load_json_object_checked(meta_path)
        stride, lo, hi = meta.get("stride"), meta.get("min_depth_m"), meta.get("max_depth_m")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ArtifactError(f"{meta_path}: stride must be an integer >= 1, got {stride!r}")
        if not (is_finite_number(lo) and is_finite_number(hi)):
            raise ArtifactError(f"{meta_path}: min_depth_m and max_depth_m must be finite numbers, got {lo!r}, {hi!r}")
        z = load_npz_checked(path, _FUSED_MEMBERS, error_type=ArtifactError)
        pts, cols, offsets, valid = z["points_cam"], z["colors"], z["offsets"], z["valid_fraction"]
        n = len(valid)
        if pts.shape[1:] != (3,) or cols.shape != pts.shape or offsets.shape != (n + 1,):
            raise ArtifactError(f"{path}: points_cam {list(pts.shape)}, colors {list(cols.shape)}, offsets "
                                f"{list(offsets.shape)} and valid_fraction {list(valid.shape)} must be "
                                "[M, 3], [M, 3], [N + 1], [N]")
        if offsets[0] != 0 or int(offsets[-1]) != len(pts) or (np.diff(offsets.astype(np.int64)) < 0).any():
            raise ArtifactError(f"{path}: offsets must rise from 0 to the number of points ({len(pts)})")
        if not np.isfinite(pts).all():
            raise ArtifactError(f"{path}: points_cam has NaN or infinite values")
        if not (np.isfinite(valid).all() and (valid >= 0).all() and (valid <= 1).all()):
            raise ArtifactError(f"{path}: valid_fraction must lie in [0, 1]")
        return cls(points_cam=pts.astype(np.float32), colors=cols, offsets=offsets.astype(np.int64),
                   valid_fraction=valid.astype(np.float32), stride=stride, min_depth_m=float(lo), max_depth_m=float(hi))


def fuse_frames(manifest: FrameManifest, cfg: FusionConfig,
                log: Callable[[str], None] | None = None) -> FusedFrames:
    """Back-project every frame of ``manifest`` with the settings of ``cfg``."""
    progress = Progress("fusing frames", manifest.n_frames, log)
    pts_list, col_list, counts, valid = [], [], [], []
    n_sampled = len(range(0, manifest.camera.height, cfg.stride)) * len(range(0, manifest.camera.width, cfg.stride))
    for i, rgb, depth in iter_rgbd(manifest):
        pts, cols = backproject(depth, rgb, manifest.camera, cfg.stride, cfg.min_depth_m, cfg.max_depth_m)
        pts_list.append(pts)
        col_list.append(cols)
        counts.append(len(pts))
        valid.append(len(pts) / n_sampled)
        progress.update()
    offsets = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return FusedFrames(
        points_cam=np.concatenate(pts_list).astype(np.float32),
        colors=np.concatenate(col_list).astype(np.uint8),
        offsets=offsets,
        valid_fraction=np.asarray(valid, dtype=np.float32),
        stride=cfg.stride, min_depth_m=cfg.min_depth_m, max_depth_m=cfg.max_depth_m,
    )


def fuse(manifest: FrameManifest, cfg: PipelineConfig, log: Callable[[str], None] | None = None) -> FusedFrames:
    """The fusion stage: :func:`fuse_frames` with the pipeline config's ``fusion`` section."""
    return fuse_frames(manifest, cfg.fusion, log)

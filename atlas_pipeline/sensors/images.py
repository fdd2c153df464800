"""Reading one RGB-D frame from disk, with checks that name the file on failure."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.camera import CameraIntrinsics

__all__ = ["read_rgb", "read_depth_m"]


def _read(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(path, "image file not found")
    try:
        return iio.imread(path)
    except Exception as exc:  # imageio raises many types for corrupt files
        raise DatasetError(path, f"cannot decode image ({exc})") from exc


def read_rgb(path: Path, camera: CameraIntrinsics) -> np.ndarray:
    """RGB image ``[H, W, 3]`` uint8; an alpha channel is dropped."""
    img = _read(path)
    if img.ndim != 3 or img.shape[2] not in (3, 4) or img.dtype != np.uint8:
        raise DatasetError(path, f"expected an 8-bit RGB image, got shape {img.shape} dtype {img.dtype}")
    if img.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            path, f"image is {img.shape[1]}x{img.shape[0]}, camera expects {camera.width}x{camera.height}"
        )
    return np.ascontiguousarray(img[..., :3])


def read_depth_m(path: Path, camera: CameraIntrinsics, allow_empty: bool = False) -> np.ndarray:
    """Depth image ``[H, W]`` float32 in metres (0 = no reading).

    Raises DatasetError for a wrong size or type, or an image with no valid pixel at all (a
    sensor dropout that would otherwise poison tracking silently) unless ``allow_empty``.
    """
    raw = _read(path)
    if raw.ndim != 2 or raw.dtype not in (np.uint16, np.int32, np.uint32):
        raise DatasetError(path, f"expected a 16-bit single-channel depth image, got shape {raw.shape} dtype {raw.dtype}")
    if raw.shape != (camera.height, camera.width):
        raise DatasetError(
            path, f"image is {raw.shape[1]}x{raw.shape[0]}, camera expects {camera.width}x{camera.height}"
        )
    if not allow_empty and not np.any(raw):
        raise DatasetError(path, "depth image has no valid pixel (all zero)")
    return raw.astype(np.float32) / np.float32(camera.depth_scale)

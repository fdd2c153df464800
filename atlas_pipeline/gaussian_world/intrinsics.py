"""Intrinsics of a resampled image, in the raster core's pixel convention (pixel centres at
integer coordinates: pixel ``i`` covers ``[i - 0.5, i + 0.5)``). Re-exported by
:mod:`atlas_pipeline.gaussian_world.raster`."""

from __future__ import annotations

import numpy as np

__all__ = ["scale_intrinsics", "scaled_image_size", "scale_camera"]


def scale_intrinsics(
    K: np.ndarray,  # [3, 3]
    scale_x: float,
    scale_y: float | None = None,
) -> np.ndarray:
    """``[3, 3]`` intrinsics of the image resampled by ``scale_x`` (and ``scale_y``, default the same).

    With pixel centres at integer coordinates pixel ``i`` covers ``[i - 0.5, i + 0.5)``, so the
    image edges ``-0.5`` and ``W - 0.5`` map to ``-0.5`` and ``s W - 0.5``: ``u' = s (u + 0.5) - 0.5``
    (a plain ``s u`` would shift the view by ``(1 - s) / 2`` pixels: a quarter pixel at half size).
    """
    if scale_y is None:
        scale_y = scale_x
    Ks = np.asarray(K, np.float64).copy()
    Ks[0, 0] *= scale_x
    Ks[1, 1] *= scale_y
    Ks[0, 2] = (Ks[0, 2] + 0.5) * scale_x - 0.5
    Ks[1, 2] = (Ks[1, 2] + 0.5) * scale_y - 0.5
    return Ks


def scaled_image_size(width: int, height: int, scale: float, multiple: int = 1) -> tuple[int, int]:
    """``(w, h)`` of an image scaled by ``scale``, rounded, then down to a multiple of ``multiple``
    (2 for yuv420p video)."""
    return (int(round(width * scale)) // multiple * multiple,
            int(round(height * scale)) // multiple * multiple)


def scale_camera(
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
    scale: float,
    multiple: int = 1,
) -> tuple[int, int, np.ndarray]:
    """``(w, h, K_scaled [3, 3])`` of the image scaled by about ``scale`` (``scaled_image_size``).

    The intrinsics use the exact per-axis ratios ``w / width`` and ``h / height``, so the scaled
    image shows the same field of view as the full one, edge to edge.
    """
    w, h = scaled_image_size(width, height, scale, multiple)
    return w, h, scale_intrinsics(K, w / width, h / height)

"""The keyframe fit's images at each scale, within a memory budget.

Working copies of one level (float32 image, depth, depth weight and coverage band per keyframe)
are held while they fit in ``LEVEL_MEMORY_BUDGET_BYTES``; above it (hundreds of keyframes) each
view's copy is made when its step needs it (one image decode and box filter per step), so the
fit's memory does not grow with the sequence.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Callable

import numpy as np

from atlas_pipeline.gaussian_world import raster

__all__ = ["LEVEL_MEMORY_BUDGET_BYTES", "OnDemandViews", "FitLevel", "reciprocal_factor"]

def _downsample(img: np.ndarray, f: int) -> np.ndarray:
    """Box filter by an integer factor ``f`` (crops a remainder)."""
    if f == 1:
        return img
    h, w = img.shape[0] // f, img.shape[1] // f
    img = img[: h * f, : w * f]
    return img.reshape(h, f, w, f, *img.shape[2:]).mean(axis=(1, 3))


def _downsample_depth(depth: np.ndarray, f: int) -> np.ndarray:
    """Mean of the valid readings of each ``f x f`` block; 0 where a block has fewer than half."""
    if f == 1:
        return depth
    h, w = depth.shape[0] // f, depth.shape[1] // f
    blocks = depth[: h * f, : w * f].reshape(h, f, w, f)
    ok = blocks > 0
    n = ok.sum(axis=(1, 3))
    s = np.where(ok, blocks, 0.0).sum(axis=(1, 3))
    return np.where(n * 2 >= f * f, s / np.maximum(n, 1), 0.0)


def reciprocal_factor(scale: float, name: str) -> int:
    f = int(round(1.0 / scale)) if scale > 0 else 0
    if f < 1 or abs(1.0 / f - scale) > 1e-9:
        raise ValueError(f"optimisation {name} must be 1/n for an integer n, got {scale}")
    return f


LEVEL_MEMORY_BUDGET_BYTES = 384 << 20
_LEVEL_BYTES_PER_PIXEL = (3 + 1 + 1 + 1) * 4  # float32 RGB, depth, depth weight, coverage band


class OnDemandViews(Sequence):
    """A read-only sequence of ``n`` arrays made by ``make(k)`` at each access, the last one kept
    (a fit step reads one view's image, depth and weight in turn; nothing else is held). Used for
    the keyframes of long sequences: the fit's levels here, its inputs in ``mapping/mapper.py``."""

    def __init__(self, n: int, make: Callable[[int], np.ndarray]) -> None:
        self.n, self.make, self._last = n, make, (None, None)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self.n))]
        if not -self.n <= k < self.n:
            raise IndexError(k)
        k %= self.n
        if self._last[0] != k:
            self._last = (k, self.make(k))
        return self._last[1]


class FitLevel:
    """The keyframes at one image scale (float32 images in [0, 1], depths, depth-term weights,
    coverage bands (None when not given), intrinsics): held, or made per view on access when they
    would exceed ``LEVEL_MEMORY_BUDGET_BYTES``."""

    def __init__(self, name: str, f: int, images, depths_m, K: np.ndarray, depth_weights=None,
                 coverage_bands=None) -> None:
        self.name, self.f, self.scale = name, f, 1.0 / f
        h0, w0 = np.shape(images[0])[:2]
        n = len(images)

        def image(k):
            return np.ascontiguousarray(_downsample(np.asarray(images[k], np.float64) / 255.0, f), np.float32)

        def depth(k):
            return np.ascontiguousarray(_downsample_depth(np.asarray(depths_m[k], np.float64), f), np.float32)

        def per_reading(maps, k):  # the mean of the readings' values each block averages (same validity rule)
            d = np.asarray(depths_m[k])
            return np.ascontiguousarray(
                _downsample_depth(np.where(d > 0, np.asarray(maps[k], np.float64), 0.0), f), np.float32)

        def weight(k):
            if depth_weights is None:
                return np.ones(((h0 // f), (w0 // f)), np.float32)  # the shape _downsample_depth gives
            return per_reading(depth_weights, k)

        def band(k):
            return per_reading(coverage_bands, k)

        if n * (h0 // f) * (w0 // f) * _LEVEL_BYTES_PER_PIXEL <= LEVEL_MEMORY_BUDGET_BYTES:
            self.images = [image(k) for k in range(n)]
            self.depths = [depth(k) for k in range(n)]
            self.depth_w = [weight(k) for k in range(n)]
            self.bands = None if coverage_bands is None else [band(k) for k in range(n)]
        else:
            self.images, self.depths, self.depth_w = (OnDemandViews(n, image), OnDemandViews(n, depth),
                                                      OnDemandViews(n, weight))
            self.bands = None if coverage_bands is None else OnDemandViews(n, band)
        self.K = raster.scale_intrinsics(K, 1.0 / f)
        self.height, self.width = self.images[0].shape[:2]

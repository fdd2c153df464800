"""Image pyramid kernels of the RGB-D tracker: depth and intensity halved level by level, and the
intensity gradients of the photometric term."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["downsample_depth", "downsample_mean", "image_gradients"]


@njit(cache=True)
def downsample_depth(depth_m, max_jump_m, max_jump_fraction):
    """2x2 mean of valid depths ``[h, w]`` -> ``[h/2, w/2]``; a block whose readings spread more
    than ``max_jump_m`` + ``max_jump_fraction`` of its depth straddles an edge and is left invalid
    (0) so no flying point is made between foreground and background. At least 2 of the 4 readings
    must be valid."""
    h, w = depth_m.shape[0] // 2, depth_m.shape[1] // 2
    out = np.zeros((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            s = 0.0
            n = 0
            lo = math.inf
            hi = 0.0
            for di in range(2):
                for dj in range(2):
                    d = depth_m[2 * i + di, 2 * j + dj]
                    if d > 0.0:
                        s += d
                        n += 1
                        lo = min(lo, d)
                        hi = max(hi, d)
            if n >= 2 and hi - lo < max_jump_m + max_jump_fraction * lo:
                out[i, j] = s / n
    return out


@njit(cache=True)
def downsample_mean(img):
    """2x2 block mean of a float image ``[h, w]`` -> ``[h/2, w/2]``."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    out = np.empty((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            out[i, j] = 0.25 * (img[2 * i, 2 * j] + img[2 * i + 1, 2 * j] + img[2 * i, 2 * j + 1] + img[2 * i + 1, 2 * j + 1])
    return out


@njit(cache=True)
def image_gradients(img):
    """Central-difference gradients ``(gx, gy)`` of ``[h, w]`` (zero on the border)."""
    h, w = img.shape
    gx = np.zeros((h, w), np.float32)
    gy = np.zeros((h, w), np.float32)
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            gx[i, j] = 0.5 * (img[i, j + 1] - img[i, j - 1])
            gy[i, j] = 0.5 * (img[i + 1, j] - img[i - 1, j])
    return gx, gy

"""Colour refinement: fit each Gaussian's colour to the keyframe images it is seen in.

A voxel's mean colour averages every observation, near and far, and ignores how neighbouring
Gaussians blend in the image. Rendering the keyframes and moving each colour by the weighted mean
of the residuals it contributes to (a Jacobi / Gauss-Newton step on
``sum_pixels |render - image|^2`` with colours as the only unknowns) makes the blend match the
images. Only keyframes are used, so held-out frames still measure generalisation.

The backward pass runs on the forward render's own projection, sorting and tiling
(:mod:`atlas_pipeline.gaussian_world.raster`), and visits the same Gaussians front to back with the
same alpha, so the weights are exactly those of the forward image.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Sequence

import numpy as np
from numba import njit, prange

from atlas_pipeline.gaussian_world import raster
from atlas_pipeline.gaussian_world.composite import composite_tiles
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.gaussian_world.raster import T_MIN, pixel_alpha, tile_pixel_bounds

logger = logging.getLogger(__name__)

__all__ = ["refine_colours"]

_N_WORKERS = 4  # fixed, so the sums (and the refined world) do not depend on the machine's cores


@njit(cache=True)
def _backward_tiles(worker, n_workers, bins, feat, box, width, height, residual, gsum, wsum):
    """Tiles ``worker, worker + n_workers, ...`` of ``bins`` (:class:`raster.TileBins`):
    ``gsum[k] += w_k(p) residual(p)``, ``wsum[k] += w_k(p)`` over the pixels ``p`` of each Gaussian
    row ``k``, with ``w = alpha T`` as in the forward pass."""
    t_min = T_MIN
    tile_start, tile_ids, tiles_x, n_tiles = bins
    for t in range(worker, n_tiles, n_workers):
        px0, py0, px1, py1 = tile_pixel_bounds(t, tiles_x, width, height)
        for py in range(py0, py1 + 1):
            for px in range(px0, px1 + 1):
                T = 1.0
                r0, r1, r2 = residual[py, px, 0], residual[py, px, 1], residual[py, px, 2]
                for k in range(tile_start[t], tile_start[t + 1]):
                    g = tile_ids[k]
                    alpha = pixel_alpha(feat, box, g, px, py)[0]
                    if alpha == 0.0:
                        continue
                    w = alpha * T
                    gsum[g, 0] += w * r0
                    gsum[g, 1] += w * r1
                    gsum[g, 2] += w * r2
                    wsum[g] += w
                    T *= 1.0 - alpha
                    if T < t_min:
                        break


@njit(cache=True, parallel=True)
def _backward(bins, feat, box, width, height, residual, n_workers):
    m = feat.shape[0]
    gs = np.zeros((n_workers, m, 3))
    ws = np.zeros((n_workers, m))
    for w in prange(n_workers):
        _backward_tiles(w, n_workers, bins, feat, box, width, height, residual, gs[w], ws[w])
    g = np.zeros((m, 3))
    wsum = np.zeros(m)
    for w in range(n_workers):  # fixed order: deterministic
        g += gs[w]
        wsum += ws[w]
    return g, wsum


def _accumulate_view(field: GaussianField, colors: np.ndarray, image: np.ndarray, T_world_cam: np.ndarray,
                     K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Forward render with ``colors`` ``[N, 3]`` float (black background), then the backward sums for
    one view on the same projected, sorted and binned Gaussians."""
    inp = raster.validate_inputs(field.positions, field.scales, field.rotations_xyzw, colors, field.opacities,
                                 T_world_cam, K, width, height, (0, 0, 0), raster.NEAR_M)
    view = raster.view_from_pose(inp.T_world_cam, inp.K, inp.width, inp.height)
    sp = raster.prepare_splats(inp.positions, inp.scales, inp.rotations_xyzw, inp.colors, inp.opacities, view,
                               inp.near_m)
    n = len(field)
    if sp is None:
        return np.zeros((n, 3)), np.zeros(n), float("nan")
    rgb = composite_tiles(sp, inp.background)[0]
    # Residual of the unrounded colour image would be slightly better; the uint8 one is within 0.5.
    residual = rgb.astype(np.float32) - image.astype(np.float32)
    bins = raster.TileBins(sp.tile_start, sp.tile_ids, sp.tiles_x, sp.n_tiles)
    g_s, w_s = _backward(bins, sp.feat, sp.box, sp.width, sp.height, residual, _N_WORKERS)
    g = np.zeros((n, 3))
    w = np.zeros(n)
    g[sp.order] = g_s
    w[sp.order] = w_s
    return g, w, float(np.sqrt(np.mean(residual.astype(np.float64) ** 2)))


def refine_colours(field: GaussianField, images: Sequence[np.ndarray], poses: Sequence[np.ndarray], K: np.ndarray,
                   iterations: int = 3, scale: float = 0.5, log: Callable[[str], None] | None = None) -> GaussianField:
    """A copy of ``field`` whose colours best reproduce ``images`` (``[H, W, 3]`` uint8) seen from
    ``poses`` (``[4, 4]`` each): ``iterations`` Jacobi steps, each over every view, at ``scale``
    times the image size. Gaussians no view sees keep their colour."""
    if len(images) != len(poses):
        raise ValueError("one pose per image")
    if not images or len(field) == 0 or iterations < 1:
        return field
    h0, w0 = images[0].shape[:2]
    w, h, Ks = raster.scale_camera(K, w0, h0, scale)  # pixel centres kept (see raster.scale_intrinsics)
    small = [img if (w, h) == (w0, h0) else _resize(img, w, h) for img in images]
    if field.sh_degree:
        logger.warning("colour refinement renders and fits degree-0 colour only: the SH coefficients of degree %d "
                       "(view-dependent colour) are kept unchanged", field.sh_degree)
    colors = field.colors.astype(np.float64)
    for it in range(iterations):
        g = np.zeros((len(field), 3))
        ws = np.zeros(len(field))
        rms = []
        for img, T in zip(small, poses):
            gi, wi, r = _accumulate_view(field, colors, img, T, Ks, w, h)
            g += gi
            ws += wi
            rms.append(r)
        seen = ws > 1e-3
        colors[seen] = np.clip(colors[seen] - g[seen] / ws[seen, None], 0.0, 255.0)
        msg = f"colour refinement {it + 1}/{iterations}: image RMS residual before the step {np.mean(rms):.2f}"
        (log or logger.info)(msg)
    # degree 0: only the base colour is refined; SH coefficients, if any, are kept (said once, above)
    return dataclasses.replace(field, colors=np.rint(colors).astype(np.uint8))


def _resize(img: np.ndarray, w: int, h: int) -> np.ndarray:
    """Box-filter downsample by an integer factor (the common case), else nearest neighbour: the
    source pixel under each new pixel's centre (pixel centres at integer coordinates, as
    ``raster.scale_intrinsics``)."""
    H, W = img.shape[:2]
    if W % w == 0 and H % h == 0:
        fx, fy = W // w, H // h
        return img.reshape(h, fy, w, fx, -1).mean(axis=(1, 3)).round().astype(np.uint8)
    ys = ((np.arange(h) + 0.5) * H / h).astype(int)
    xs = ((np.arange(w) + 0.5) * W / w).astype(int)
    return img[ys][:, xs]

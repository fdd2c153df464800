"""CPU rasteriser of anisotropic 3D Gaussians (the 3D Gaussian Splatting forward pass).

The image model is the one of Kerbl et al. 2023 / gsplat (EWA splatting):

1. Means go to the camera frame (OpenCV: x right, y down, z forward). Gaussians with ``z < near_m``
   are dropped.
2. The world covariance ``Sigma = R S S^T R^T`` becomes the pixel covariance
   ``cov2d = J W Sigma W^T J^T + 0.3 I`` with ``W`` the world-to-camera rotation and ``J`` the
   perspective Jacobian at the mean (its x/z, y/z clamped to 1.3x the half field of view, as in
   gsplat, so Gaussians far outside the image do not get huge footprints). The 0.3 px^2 low-pass
   makes even sub-pixel Gaussians cover a pixel.
3. ``radius = ceil(3 sqrt(lambda_max(cov2d)))``; a Gaussian touches only the pixels whose centres
   lie in the square of half-side ``radius`` around its projected mean (its "3-sigma box").
   Gaussians whose box misses the image are dropped. (The compiled path further trims the box to
   the ellipse outside of which ``alpha < 1/255``; those pixels would be skipped anyway, so the
   image is the same.)
4. Per pixel, front to back in camera depth (ties keep input order):
   ``alpha_i = min(0.99, opacity_i exp(-0.5 d^T conic_i d))``, skipped when ``alpha_i < 1/255``;
   ``C += T alpha_i c_i``, ``D += T alpha_i z_i``, ``T *= 1 - alpha_i``; a pixel stops as soon as
   ``T < 1e-4`` (early termination; the contribution that crosses the threshold is kept).
5. ``rgb = round(C + T background)``, ``alpha = 1 - T``, ``depth = D / alpha`` where
   ``alpha >= 0.5``, else 0.

Pixel centres are at integer pixel coordinates, so a point projecting to ``(u, v) = K p / z``
lands in the centre of pixel ``(round(u), round(v))`` (the convention of ``CameraIntrinsics``).
Skew in ``K`` is ignored.

``render_gaussians`` is the fast path: the compiled stages of :mod:`atlas_pipeline.gaussian_world.raster`
(tiled: 16x16 pixel tiles, per-tile lists of Gaussians in depth order; multi-threaded over tiles),
which the colour and keyframe fits share. ``render_gaussians_reference`` chains the plain NumPy
references of the same stages (:mod:`atlas_pipeline.gaussian_world._raster_reference`) to check it.
The constants of the model (``TILE_SIZE``, ``ALPHA_MAX``, ...) live in ``raster``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from atlas_pipeline.gaussian_world import raster
from atlas_pipeline.gaussian_world._raster_reference import composite_reference, project_reference, sort_reference
from atlas_pipeline.gaussian_world.raster import TILE_SIZE

__all__ = ["RenderResult", "render_gaussians", "render_gaussians_reference", "TILE_SIZE"]

logger = logging.getLogger(__name__)


@dataclass
class RenderResult:
    """One rendered view.

    Attributes:
        rgb: ``[H, W, 3]`` uint8 colour, background blended in where the Gaussians are transparent.
        depth_m: ``[H, W]`` float32 expected depth (alpha-weighted camera z, normalised by the
            accumulated alpha); 0 where ``alpha < 0.5``.
        alpha: ``[H, W]`` float32 accumulated opacity in ``[0, 1]``.
        depth_median_m: ``[H, W]`` float32 depth at which the accumulated opacity crosses 0.5
            (the first surface that hides what lies behind it; not pulled towards the background
            at silhouettes or through half-transparent Gaussians as the expected depth is); 0
            where it never does.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    alpha: np.ndarray
    depth_median_m: np.ndarray | None = None


def _empty_result(width: int, height: int, bg: np.ndarray) -> RenderResult:
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    rgb[:] = np.clip(np.floor(bg + 0.5), 0, 255).astype(np.uint8)
    return RenderResult(
        rgb=rgb,
        depth_m=np.zeros((height, width), dtype=np.float32),
        alpha=np.zeros((height, width), dtype=np.float32),
        depth_median_m=np.zeros((height, width), dtype=np.float32),
    )


def render_gaussians(
    positions: np.ndarray,
    scales: np.ndarray,
    rotations_xyzw: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = raster.NEAR_M,
) -> RenderResult:
    """Render Gaussians into one view (numba-compiled, tiled, multi-threaded).

    Args:
        positions: ``[N, 3]`` world-frame means (metres).
        scales: ``[N, 3]`` standard deviations (metres) along each Gaussian's local axes, ``>= 0``.
        rotations_xyzw: ``[N, 4]`` quaternions (x, y, z, w), local -> world; normalised here.
        colors: ``[N, 3]`` RGB in ``[0, 255]`` (uint8 or any numeric dtype).
        opacities: ``[N]`` (or ``[N, 1]``) in ``[0, 1]``.
        T_world_cam: ``[4, 4]`` camera-to-world pose (OpenCV camera axes).
        K: ``[3, 3]`` pinhole intrinsics.
        width, height: image size in pixels.
        background: RGB shown where the Gaussians are transparent.
        near_m: Gaussians whose mean has camera ``z < near_m`` are not drawn.

    Returns:
        ``RenderResult`` with rgb ``[H, W, 3]`` uint8, depth_m and alpha ``[H, W]`` float32.

    Raises:
        ValueError: malformed shapes, non-finite values or values out of range.
    """
    inp = raster.validate_inputs(positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width,
                                 height, background, near_m)
    view = raster.view_from_pose(inp.T_world_cam, inp.K, inp.width, inp.height)
    splats = raster.prepare_splats(inp.positions, inp.scales, inp.rotations_xyzw, inp.colors, inp.opacities,
                                   view, inp.near_m)
    if splats is None:
        return _empty_result(inp.width, inp.height, inp.background)
    rgb, depth_m, alpha, depth_median_m = raster.composite_tiles(splats, inp.background)
    return RenderResult(rgb=rgb, depth_m=depth_m, alpha=alpha, depth_median_m=depth_median_m)


def render_gaussians_reference(
    positions: np.ndarray,
    scales: np.ndarray,
    rotations_xyzw: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = raster.NEAR_M,
) -> RenderResult:
    """Straightforward NumPy splat of the same model (no tiling, no compiled code).

    Used as the correctness and speed reference of ``render_gaussians``: the NumPy reference of each
    raster stage, each Gaussian drawn over its whole 3-sigma box (the compiled path cuts the box to
    the visible ellipse). Slow (seconds for 10^5 Gaussians) but easy to check. Same arguments and
    result.
    """
    inp = raster.validate_inputs(positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width,
                                 height, background, near_m)
    if inp.positions.shape[0] == 0:
        return _empty_result(inp.width, inp.height, inp.background)
    proj = project_reference(inp.positions, inp.scales, inp.rotations_xyzw, inp.colors, inp.opacities,
                             inp.T_world_cam, inp.K, inp.width, inp.height, inp.near_m)
    order = sort_reference(proj.valid, proj.depth)
    rgb, depth_m, alpha, depth_median_m = composite_reference(
        proj.feat[order], proj.box_3sigma[order], inp.width, inp.height, inp.background)
    return RenderResult(rgb=rgb, depth_m=depth_m, alpha=alpha, depth_median_m=depth_median_m)

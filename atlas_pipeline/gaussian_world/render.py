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

``render_field`` renders a ``GaussianField`` with its view-dependent colour: before step 1, each
Gaussian's colour is its spherical harmonics evaluated along the ray from the camera centre to its
mean (:mod:`atlas_pipeline.gaussian_world.sh`; 3DGS's ``eval_sh`` + 0.5, clamped at 0), a chunk at
a time inside the bounded-memory projection. A degree-0 field renders exactly as ``render_gaussians``.

Pixel centres are at integer pixel coordinates, so a point projecting to ``(u, v) = K p / z``
lands in the centre of pixel ``(round(u), round(v))`` (the convention of ``CameraIntrinsics``).
Skew in ``K`` is ignored.

``render_gaussians`` is the fast path: the compiled stages of :mod:`atlas_pipeline.gaussian_world.raster`
(tiled: 16x16 pixel tiles, per-tile lists of Gaussians in depth order; multi-threaded over tiles),
which the colour and keyframe fits share. ``render_gaussians_reference`` chains the plain NumPy
references of the same stages (:mod:`atlas_pipeline.gaussian_world._raster_reference`) to check it.
The constants of the model (``TILE_SIZE``, ``ALPHA_MAX``, ...) live in ``raster``.

Memory (big worlds): ``render_gaussians`` runs the raster stages in bounded memory (see
``raster``): only the drawn Gaussians are kept, sorted in place, and the (tile, Gaussian) pairs are
listed a batch of tiles at a time (at most ``max_tile_pairs``), so a view of N Gaussians needs at
most ``render_peak_bytes(N, W, H)`` beyond the caller's arrays::

    4 N      validation temporaries (the caller's float32 / uint8 arrays are used in place)
    72 M     drawn Gaussians (M <= N): feature row, box, depth (64) and the sort's order (8)
    4 P_b    one batch of (tile, Gaussian) pairs, P_b <= max(max_tile_pairs, M)
    32 T     per-tile pair counts and offsets (T tiles of 16x16 pixels)
    15 W H   the result (rgb, depth, alpha, median depth)
    + ~21 MB per-chunk projection buffers (raster.PROJECT_CHUNK), the radix sort's histogram,
      per-thread tile buffers

with the worst case M = N (every Gaussian in view): at most 76 bytes per Gaussian. The image is the
same bit for bit as the one-pass stages the fits use (``raster.prepare_splats`` /
``composite.composite_tiles``; ``tests/test_big_world.py``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from atlas_pipeline.gaussian_world import raster, raster_bounded
from atlas_pipeline.gaussian_world.composite import composite_tile_batch
from atlas_pipeline.gaussian_world._raster_reference import (
    composite_reference, project_reference, sort_reference, view_colors_reference,
)
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.gaussian_world.raster import TILE_SIZE
from atlas_pipeline.gaussian_world.sh import check_sh_rest

__all__ = ["RenderResult", "render_gaussians", "render_gaussians_reference", "render_field", "render_field_reference",
           "TILE_SIZE", "render_peak_bytes",
           "RENDER_BYTES_PER_GAUSSIAN", "RENDER_BYTES_PER_DRAWN", "RENDER_BYTES_PER_PIXEL",
           "RENDER_FIXED_BYTES"]

logger = logging.getLogger(__name__)

# What one view costs (render_peak_bytes; checked by tests/test_big_world.py and
# benchmarks/bench_big_world.py against measured allocations and RSS):
RENDER_BYTES_PER_GAUSSIAN = 4  # validation temporaries (isfinite masks, quaternion norms), any Gaussian
RENDER_BYTES_PER_DRAWN = 4 * raster.N_FEAT + 16 + 8 + 8  # feature row 40, box 16, depth 8, sort order 8
RENDER_BYTES_PER_PAIR = 4  # one int32 per (tile, Gaussian) pair of the current batch
RENDER_BYTES_PER_PIXEL = 3 + 4 + 4 + 4  # the result: rgb uint8, depth, alpha, median depth float32
# Per-chunk projection outputs (65 bytes per chunk row, counted as 80; render_field's per-view SH
# colours of a chunk add 12), the radix sort's histograms and per-thread tile buffers, with room
# for allocator rounding.
RENDER_FIXED_BYTES = 80 * raster.PROJECT_CHUNK + (4 << 20)


def render_peak_bytes(n_gaussians: int, width: int, height: int,
                      max_tile_pairs: int | None = raster.MAX_TILE_PAIRS) -> int:
    """Upper bound on the memory ``render_gaussians`` allocates for one ``width x height`` view of
    ``n_gaussians`` (every Gaussian drawn, the worst case), beyond the caller's arrays (which must
    be float32, or uint8 colours, as a ``GaussianField`` holds them; other dtypes are converted
    first, 40 bytes per Gaussian more). With ``max_tile_pairs=None`` (one batch) the pairs of the
    whole view are listed at once, which no formula in N bounds usefully (a Gaussian may cover
    every tile): the bound then assumes that worst case."""
    n = int(n_gaussians)
    tiles = -(-int(width) // TILE_SIZE) * -(-int(height) // TILE_SIZE)
    pairs = max(int(max_tile_pairs), n) if max_tile_pairs is not None else n * tiles
    return (RENDER_BYTES_PER_GAUSSIAN * n + RENDER_BYTES_PER_DRAWN * n + RENDER_BYTES_PER_PAIR * pairs
            + 32 * (tiles + 1) + RENDER_BYTES_PER_PIXEL * int(width) * int(height) + RENDER_FIXED_BYTES)


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
    max_tile_pairs: int | None = raster.MAX_TILE_PAIRS,
) -> RenderResult:
    """Render Gaussians into one view (numba-compiled, tiled, multi-threaded, bounded memory:
    ``render_peak_bytes``).

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
        max_tile_pairs: (tile, Gaussian) pairs listed at once; the tiles are drawn in batches of
            at most this many pairs (None: all at once). The image does not depend on it.

    Returns:
        ``RenderResult`` with rgb ``[H, W, 3]`` uint8, depth_m and alpha ``[H, W]`` float32.

    Raises:
        ValueError: malformed shapes, non-finite values or values out of range.
    """
    inp = raster.validate_inputs(positions, scales, rotations_xyzw, colors, opacities, T_world_cam, K, width,
                                 height, background, near_m, float_colors=False)
    return _render_checked(inp, None, max_tile_pairs)


def render_field(
    field: GaussianField,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = raster.NEAR_M,
    max_tile_pairs: int | None = raster.MAX_TILE_PAIRS,
) -> RenderResult:
    """Render a :class:`GaussianField` into one view, its view-dependent colour included: each
    Gaussian's colour is its spherical harmonics (``field.sh_rest``, :mod:`~atlas_pipeline.gaussian_world.sh`)
    evaluated along the ray from the camera centre to its mean, as 3DGS does. A degree-0 field gives
    exactly ``render_gaussians`` of its arrays. Arguments and result as ``render_gaussians``."""
    if not field.sh_degree:
        return render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                                T_world_cam, K, width, height, background, near_m, max_tile_pairs)
    inp = raster.validate_inputs(field.positions, field.scales, field.rotations_xyzw, field.colors,
                                 field.opacities, T_world_cam, K, width, height, background, near_m,
                                 float_colors=False)
    return _render_checked(inp, check_sh_rest(field.sh_rest, len(field)), max_tile_pairs)


def _render_checked(inp: raster.RasterInputs, sh_rest: np.ndarray | None,
                    max_tile_pairs: int | None) -> RenderResult:
    """The fast path on checked inputs; ``sh_rest`` ``[N, K, 3]`` float32 or None (colours as given)."""
    if max_tile_pairs is not None and int(max_tile_pairs) < 1:
        raise ValueError(f"max_tile_pairs must be a positive integer or None, got {max_tile_pairs!r}")
    view = raster.view_from_pose(inp.T_world_cam, inp.K, inp.width, inp.height)
    vis = raster_bounded.project_visible(inp.positions, inp.scales, inp.rotations_xyzw, inp.colors, inp.opacities,
                                         view, inp.near_m, sh_rest=sh_rest)
    if len(vis.depth) == 0:
        return _empty_result(inp.width, inp.height, inp.background)
    bg = inp.background
    del inp  # the converted copies (if any) are not needed past the projection
    raster_bounded.sort_visible(vis)
    h, w = view.height, view.width
    out = (np.empty((h, w, 3), np.uint8), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
           np.empty((h, w), np.float32))
    counts = raster_bounded.tile_pair_counts(vis.box, w, h)  # [n_tiles]
    batches = raster_bounded.tile_batches(counts, max_tile_pairs)
    biggest = max(int(counts[t0:t1].sum()) for t0, t1 in batches)
    buf = np.empty(biggest, np.int32)  # reused by every batch
    for t0, t1 in batches:
        tile_start, tile_ids = raster_bounded.bin_tile_batch(vis.box, counts, w, t0, t1, buf)
        composite_tile_batch(vis.feat, vis.box, tile_start, tile_ids, t0, bg, out)
    rgb, depth_m, alpha, depth_median_m = out
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
    return _render_reference_checked(inp, None)


def render_field_reference(
    field: GaussianField,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    background: tuple[int, int, int] = (0, 0, 0),
    near_m: float = raster.NEAR_M,
) -> RenderResult:
    """``render_field`` by the NumPy references of the stages (the SH stage ``view_colors_reference``
    included): the check of ``render_field``, as ``render_gaussians_reference`` is of ``render_gaussians``."""
    inp = raster.validate_inputs(field.positions, field.scales, field.rotations_xyzw, field.colors,
                                 field.opacities, T_world_cam, K, width, height, background, near_m)
    return _render_reference_checked(inp, check_sh_rest(field.sh_rest, len(field)) if field.sh_degree else None)


def _render_reference_checked(inp: raster.RasterInputs, sh_rest: np.ndarray | None) -> RenderResult:
    if inp.positions.shape[0] == 0:
        return _empty_result(inp.width, inp.height, inp.background)
    colors = inp.colors if sh_rest is None else view_colors_reference(inp.positions, inp.colors, sh_rest,
                                                                      inp.T_world_cam[:3, 3])
    proj = project_reference(inp.positions, inp.scales, inp.rotations_xyzw, colors, inp.opacities,
                             inp.T_world_cam, inp.K, inp.width, inp.height, inp.near_m)
    order = sort_reference(proj.valid, proj.depth)
    rgb, depth_m, alpha, depth_median_m = composite_reference(
        proj.feat[order], proj.box_3sigma[order], inp.width, inp.height, inp.background)
    return RenderResult(rgb=rgb, depth_m=depth_m, alpha=alpha, depth_median_m=depth_median_m)

"""Plain-NumPy references of the raster core's stages (as gsplat keeps them in ``_torch_impl.py``).

Each function is a direct, vectorised float64 transcription of one stage of
:mod:`atlas_pipeline.gaussian_world.raster`, written for reading, not speed: the compiled stages are
tested against these (``tests/test_raster.py``), and ``render.render_gaussians_reference`` chains
them into a whole renderer. The one deliberate difference: ``ReferenceProjection.box_3sigma`` is the
model's full ``SIGMA_EXTENT``-sigma footprint, which the reference renderer draws, so comparing it
with the compiled renderer also checks the compiled box cut to the visible ellipse.

``view_colors_reference`` (from :mod:`atlas_pipeline.gaussian_world.sh`) is the stage before the
projection for a field with view-dependent colour: each Gaussian's spherical harmonics evaluated
along the ray from the camera centre, the reference of the compiled ``sh.view_colors`` that
``raster_bounded.project_visible`` runs per chunk.

``fit_gradients_reference`` is the keyframe fit's forward and image-space backward pass in the
textbook prefix-sum form (``tests/test_optimize.py`` checks the compiled tile kernels against it).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from atlas_pipeline.geometry import invert_se3, quat_xyzw_to_rotmat
from atlas_pipeline.gaussian_world.raster import (
    ALPHA_MAX,
    ALPHA_MIN,
    BOX_SLACK_PX,
    COLOR_LEVELS,
    DEPTH_MIN_ALPHA,
    FEAT_BLUE,
    FEAT_CONIC_A,
    FEAT_CONIC_B,
    FEAT_CONIC_C,
    FEAT_GREEN,
    FEAT_OPACITY,
    FEAT_RED,
    FEAT_U,
    FEAT_V,
    FEAT_Z,
    FRUSTUM_MARGIN,
    LOW_PASS_PX2,
    MEDIAN_DEPTH_T,
    N_FEAT,
    NEAR_M,
    PLANE_FLATNESS,
    PLANE_MAX_SLOPE,
    SIGMA_EXTENT,
    T_MIN,
    TILE_SIZE,
)
from atlas_pipeline.gaussian_world.sh import view_colors_reference

__all__ = ["ReferenceProjection", "project_reference", "sort_reference", "bin_tiles_reference",
           "composite_reference", "plane_slopes_reference", "fit_gradients_reference", "visible_reference",
           "tile_pair_counts_reference", "bin_tile_batch_reference",
           "view_colors_reference"]


class ReferenceProjection(NamedTuple):
    """Every Gaussian projected into one view (rows in input order), float64."""

    valid: np.ndarray  # [N] bool, as raster.Projection.valid
    depth: np.ndarray  # [N] float64 camera z
    feat: np.ndarray  # [N, N_FEAT] float64 (u, v, conic a, b, c, opacity, r, g, b, z)
    box: np.ndarray  # [N, 4] int64 (x0, x1, y0, y1), cut to the visible ellipse, as the compiled box
    box_3sigma: np.ndarray  # [N, 4] int64, the uncut SIGMA_EXTENT-sigma square
    jw: np.ndarray  # [N, 2, 3] float64 J W, the clamped perspective Jacobian times the camera rotation
    cov2d: np.ndarray  # [N, 2, 2] float64 pixel covariance (low-pass included)
    slopes: np.ndarray  # [N, 2] float64 (dz/du, dz/dv) of each Gaussian's plane (plane_slopes_reference)


def project_reference(
    positions: np.ndarray,  # [N, 3] world (metres)
    scales: np.ndarray,  # [N, 3] standard deviations (metres)
    rotations_xyzw: np.ndarray,  # [N, 4]
    colors: np.ndarray,  # [N, 3]
    opacities: np.ndarray,  # [N]
    T_world_cam: np.ndarray,  # [4, 4] camera-to-world
    K: np.ndarray,  # [3, 3]
    width: int,
    height: int,
    near_m: float = NEAR_M,
) -> ReferenceProjection:
    """Reference of ``raster.project_gaussians``: matrix products ``cov2d = J W R S S^T R^T W^T J^T``
    with the clamped Jacobian. Rows that are not valid hold unspecified values."""
    n = positions.shape[0]
    Km = np.asarray(K, np.float64)
    fx, fy, cx, cy = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]
    T_cw = invert_se3(T_world_cam)
    W = T_cw[:3, :3]
    p_cam = np.asarray(positions).astype(np.float64) @ W.T + T_cw[:3, 3]
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    opa = np.asarray(opacities).astype(np.float64)
    keep = z >= near_m
    zs = np.where(keep, z, 1.0)  # placeholder depth for culled ones avoids division warnings

    R = quat_xyzw_to_rotmat(rotations_xyzw)
    M = R * np.asarray(scales).astype(np.float64)[:, None, :]  # R S
    Sigma = M @ np.swapaxes(M, 1, 2)

    # Jacobian clamp: x/z, y/z within the image plus FRUSTUM_MARGIN of the half field of view
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_x = (cx / fx + FRUSTUM_MARGIN * tan_x, (width - cx) / fx + FRUSTUM_MARGIN * tan_x)
    lim_y = (cy / fy + FRUSTUM_MARGIN * tan_y, (height - cy) / fy + FRUSTUM_MARGIN * tan_y)
    txz = np.clip(x / zs, -lim_x[0], lim_x[1])
    tyz = np.clip(y / zs, -lim_y[0], lim_y[1])
    J = np.zeros((n, 2, 3))
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * txz / zs
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * tyz / zs
    JW = J @ W
    cov2d = JW @ Sigma @ np.swapaxes(JW, 1, 2)
    cov2d[:, 0, 0] += LOW_PASS_PX2
    cov2d[:, 1, 1] += LOW_PASS_PX2
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
    keep &= det > 0
    dets = np.where(keep, det, 1.0)
    mid = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
    lam_max = mid + np.sqrt(np.maximum(0.0, mid**2 - det))
    radius = np.ceil(SIGMA_EXTENT * np.sqrt(np.maximum(lam_max, 0.0)))
    u = fx * x / zs + cx
    v = fy * y / zs + cy

    def pixel_box(ex, ey):
        return np.stack([np.maximum(0, np.ceil(u - ex)), np.minimum(width - 1, np.floor(u + ex)),
                         np.maximum(0, np.ceil(v - ey)), np.minimum(height - 1, np.floor(v + ey))], axis=1)

    box_3sigma = pixel_box(radius, radius)
    # the ellipse d^T conic d <= 2 ln(opacity / ALPHA_MIN), outside of which alpha < ALPHA_MIN
    visible = opa * COLOR_LEVELS >= 1.0
    thr = 2.0 * np.log(COLOR_LEVELS * np.where(visible, opa, 1.0))
    box = pixel_box(np.minimum(radius, np.sqrt(thr * cov2d[:, 0, 0]) + BOX_SLACK_PX),
                    np.minimum(radius, np.sqrt(thr * cov2d[:, 1, 1]) + BOX_SLACK_PX))
    valid = keep & visible & (box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3])

    feat = np.empty((n, N_FEAT))
    feat[:, FEAT_U] = u
    feat[:, FEAT_V] = v
    feat[:, FEAT_CONIC_A] = cov2d[:, 1, 1] / dets
    feat[:, FEAT_CONIC_B] = -cov2d[:, 0, 1] / dets
    feat[:, FEAT_CONIC_C] = cov2d[:, 0, 0] / dets
    feat[:, FEAT_OPACITY] = opa
    feat[:, [FEAT_RED, FEAT_GREEN, FEAT_BLUE]] = np.asarray(colors).astype(np.float64)
    feat[:, FEAT_Z] = z
    slopes = plane_slopes_reference(R, np.asarray(scales).astype(np.float64), W, p_cam, fx, fy)
    return ReferenceProjection(valid, np.where(valid, z, 0.0), feat, box.astype(np.int64),
                               box_3sigma.astype(np.int64), JW, cov2d, slopes)


def plane_slopes_reference(
    R: np.ndarray,  # [N, 3, 3] Gaussian rotations (local axes to world)
    scales: np.ndarray,  # [N, 3]
    W: np.ndarray,  # [3, 3] world -> camera rotation
    p_cam: np.ndarray,  # [N, 3] camera-frame means
    fx: float,
    fy: float,
) -> np.ndarray:
    """Reference of ``raster.plane_depth_slopes``: ``[N, 2]`` ``(dz/du, dz/dv)`` of the plane through
    each mean normal to its shortest axis, from ``z(u, v) = (n . mu) / (n . ray(u, v))`` with
    ``ray = ((u - cx) / fx, (v - cy) / fy, 1)`` differentiated at the mean's pixel; 0 where the
    Gaussian is not flat (shortest scale over ``PLANE_FLATNESS`` times the middle one) or seen
    edge-on, clamped at ``PLANE_MAX_SLOPE * z / f``."""
    n = len(scales)
    srt = np.sort(scales, axis=1)
    shortest = np.argmin(scales, axis=1)  # first of equal minima, as the compiled test
    normal_cam = (R[np.arange(n), :, shortest]) @ W.T  # [N, 3]
    z = p_cam[:, 2]
    c = np.einsum("ij,ij->i", normal_cam, p_cam)
    ok = (srt[:, 0] <= PLANE_FLATNESS * srt[:, 1]) & (np.abs(c) >= 1e-9)
    cs = np.where(ok, c, 1.0)
    # d/du of c / (n . ray) at the mean (where n . ray = c / z): -c nx / (fx (c / z)^2) = -z^2 nx / (fx c)
    su = -z * z * normal_cam[:, 0] / (fx * cs)
    sv = -z * z * normal_cam[:, 1] / (fy * cs)
    lim_u, lim_v = PLANE_MAX_SLOPE * z / fx, PLANE_MAX_SLOPE * z / fy
    return np.where(ok[:, None], np.stack([np.clip(su, -lim_u, lim_u), np.clip(sv, -lim_v, lim_v)], axis=1), 0.0)


def fit_gradients_reference(
    feat: np.ndarray,  # [M, N_FEAT] sorted front to back (colours in [0, 1])
    slopes: np.ndarray,  # [M, 2] depth slopes in that order
    box: np.ndarray,  # [M, 4] (x0, x1, y0, y1)
    image: np.ndarray,  # [H, W, 3] in [0, 1]
    depth_obs: np.ndarray,  # [H, W] metres, 0 = no reading
    w_rgb: float,
    w_depth: float,
    w_cover: float,
    background: np.ndarray = np.zeros(3),  # [3] in [0, 1]
    depth_limit: np.ndarray | None = None,  # [H, W] metres; None = no limit
) -> tuple[float, np.ndarray]:
    """Reference of the keyframe fit's forward and image-space backward pass
    (``fit_kernels.forward_tiles`` / ``backward_tiles`` / the slot sums): ``(loss, g2d [M, 10])``.

    ``loss = sum_p w_rgb |f(p) - image(p)|_1 + w_depth |D(p) / acc(p) - depth(p)|`` (over pixels with
    a reading and ``acc >= DEPTH_MIN_ALPHA``) ``+ w_cover T_s(p)`` (pixels with a reading; ``T_s`` the
    product of ``1 - alpha`` over the Gaussians whose depth at ``p`` is at most ``depth_limit(p)``,
    ``T_final`` without a limit), with
    ``f`` and ``D`` composited as ``composite_reference`` does and each Gaussian's depth at a pixel
    ``z + s_u dx + s_v dy``. ``g2d`` rows are ``d loss / d (u, v, conic a, b, c, opacity, r, g, b, z)``
    from the textbook form: a second front-to-back pass with prefix sums ``P`` of colour and depth,
    ``d f / d alpha_i = T_i c_i - (f - P_i - w_i c_i) / (1 - alpha_i)`` (what lies behind), float64
    with ``np.exp``; a capped alpha (``ALPHA_MAX``) moves with nothing but colour and depth.
    """
    height, width = image.shape[:2]
    bg = np.asarray(background, np.float64)
    m = feat.shape[0]

    def footprint(g: int, Tr: np.ndarray):
        u, v, ca, cb, cc, opa = feat[g, [FEAT_U, FEAT_V, FEAT_CONIC_A, FEAT_CONIC_B, FEAT_CONIC_C, FEAT_OPACITY]]
        ys = slice(int(box[g, 2]), int(box[g, 3]) + 1)
        xs = slice(int(box[g, 0]), int(box[g, 1]) + 1)
        dx = np.arange(xs.start, xs.stop)[None, :] - u
        dy = np.arange(ys.start, ys.stop)[:, None] - v
        gauss = np.exp(-0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy)
        raw = opa * gauss
        alpha = np.minimum(ALPHA_MAX, raw)
        ok = (alpha >= ALPHA_MIN) & (Tr[ys, xs] >= T_MIN)
        zp = feat[g, FEAT_Z] + slopes[g, 0] * dx + slopes[g, 1] * dy
        return ys, xs, dx, dy, gauss, raw, np.where(ok, alpha, 0.0), ok, zp

    lim = np.full((height, width), np.inf) if depth_limit is None else np.asarray(depth_limit, np.float64)
    Tr = np.ones((height, width))
    Ts = np.ones((height, width))
    C = np.zeros((height, width, 3))
    D = np.zeros((height, width))
    for g in range(m):
        ys, xs, _, _, _, _, a, _, zp = footprint(g, Tr)
        w = a * Tr[ys, xs]
        C[ys, xs] += w[..., None] * feat[g, [FEAT_RED, FEAT_GREEN, FEAT_BLUE]]
        D[ys, xs] += w * zp
        Tr[ys, xs] *= 1.0 - a
        Ts[ys, xs] *= np.where(zp <= lim[ys, xs], 1.0 - a, 1.0)
    f = C + Tr[..., None] * bg
    res = f - image
    loss = w_rgb * np.abs(res).sum()
    G = w_rgb * np.sign(res)  # d loss / d f
    acc = 1.0 - Tr
    seen = depth_obs > 0
    use_d = seen & (acc >= DEPTH_MIN_ALPHA)
    dn = np.where(use_d, D / np.where(use_d, acc, 1.0), 0.0)
    loss += w_depth * np.abs(dn - depth_obs)[use_d].sum()
    GD = np.where(use_d, w_depth * np.sign(dn - depth_obs) / np.where(use_d, acc, 1.0), 0.0)  # d loss / d D
    gcov = np.where(seen, -w_cover * Ts, 0.0) if w_cover > 0 else np.zeros((height, width))
    loss += w_cover * Ts[seen].sum() if w_cover > 0 else 0.0
    Tf = Tr

    g2d = np.zeros((m, 10))
    T = np.ones((height, width))
    P = np.zeros((height, width, 3))
    Pd = np.zeros((height, width))
    for g in range(m):
        ys, xs, dx, dy, gauss, raw, a, ok, zp = footprint(g, T)
        Tp = T[ys, xs]
        w = a * Tp
        inv = 1.0 / (1.0 - a)
        c = feat[g, [FEAT_RED, FEAT_GREEN, FEAT_BLUE]]
        df = Tp[..., None] * c - (f[ys, xs] - P[ys, xs] - w[..., None] * c) * inv[..., None]
        dD = Tp * zp - (D[ys, xs] - Pd[ys, xs] - w * zp) * inv
        dacc = Tf[ys, xs] * inv  # d acc / d alpha = T_final / (1 - alpha)
        # d T_s / d alpha = -T_s / (1 - alpha) for the Gaussians within the limit
        ga = ((G[ys, xs] * df).sum(axis=2) + GD[ys, xs] * (dD - dn[ys, xs] * dacc)
              + np.where(zp <= lim[ys, xs], gcov[ys, xs] * inv, 0.0))
        gs = np.where(ok & (raw < ALPHA_MAX), ga, 0.0)
        gp = gs * np.minimum(ALPHA_MAX, raw)
        ca, cb, cc = feat[g, [FEAT_CONIC_A, FEAT_CONIC_B, FEAT_CONIC_C]]
        gz = w * GD[ys, xs]
        g2d[g] = [(gp * (ca * dx + cb * dy)).sum() - slopes[g, 0] * gz.sum(),
                  (gp * (cc * dy + cb * dx)).sum() - slopes[g, 1] * gz.sum(),
                  -0.5 * (gp * dx * dx).sum(), -(gp * dx * dy).sum(), -0.5 * (gp * dy * dy).sum(),
                  (gs * gauss).sum(), *(w[..., None] * G[ys, xs]).sum(axis=(0, 1)), gz.sum()]
        P[ys, xs] += w[..., None] * c
        Pd[ys, xs] += w * zp
        T[ys, xs] = Tp * (1.0 - a)
    return float(loss), g2d


def sort_reference(
    valid: np.ndarray,  # [N] bool
    depth: np.ndarray,  # [N] camera z
) -> np.ndarray:
    """Reference of ``raster.sort_by_depth``: ``[M]`` valid rows front to back, ties in input order."""
    ids = np.flatnonzero(valid)
    return ids[np.argsort(depth[ids], kind="stable")]


def bin_tiles_reference(
    box: np.ndarray,  # [M, 4] (x0, x1, y0, y1) of the sorted Gaussians
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``raster.bin_tiles``: ``(tile_start [n_tiles + 1], tile_ids [P])``, each tile (row
    major) listing the rows whose box overlaps its pixels, in row order."""
    tiles_x = -(-width // TILE_SIZE)
    tiles_y = -(-height // TILE_SIZE)
    lists = []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            x0, y0 = tx * TILE_SIZE, ty * TILE_SIZE
            hit = ((box[:, 0] < x0 + TILE_SIZE) & (box[:, 1] >= x0)
                   & (box[:, 2] < y0 + TILE_SIZE) & (box[:, 3] >= y0))
            lists.append(np.flatnonzero(hit))
    tile_start = np.concatenate([[0], np.cumsum([len(ids) for ids in lists])]).astype(np.int64)
    return tile_start, np.concatenate(lists).astype(np.int64)


def visible_reference(
    valid: np.ndarray,  # [N] bool
    depth: np.ndarray,  # [N] camera z
    feat: np.ndarray,  # [N, N_FEAT]
    box: np.ndarray,  # [N, 4]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference of ``raster_bounded.project_visible`` + ``raster_bounded.sort_visible`` from a whole-view
    projection: ``(feat [M, N_FEAT], box [M, 4], depth [M])`` of the valid rows, front to back."""
    order = sort_reference(valid, depth)
    return feat[order], box[order], depth[order]


def tile_pair_counts_reference(
    box: np.ndarray,  # [M, 4] (x0, x1, y0, y1)
    width: int,
    height: int,
) -> np.ndarray:
    """Reference of ``raster_bounded.tile_pair_counts``: ``[n_tiles]`` boxes overlapping each tile (row major),
    tile by tile."""
    tile_start, _ = bin_tiles_reference(box, width, height)
    return np.diff(tile_start)


def bin_tile_batch_reference(
    box: np.ndarray,  # [M, 4] (x0, x1, y0, y1) of the sorted Gaussians
    width: int,
    height: int,
    t0: int,
    t1: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``raster_bounded.bin_tile_batch``: ``(tile_start [t1 - t0 + 1], tile_ids [P])`` of tiles
    ``t0 .. t1 - 1``, cut out of the whole view's ``bin_tiles_reference``."""
    tile_start, tile_ids = bin_tiles_reference(box, width, height)
    return tile_start[t0:t1 + 1] - tile_start[t0], tile_ids[tile_start[t0]:tile_start[t1]]


def composite_reference(
    feat: np.ndarray,  # [M, N_FEAT] sorted front to back
    box: np.ndarray,  # [M, 4] (x0, x1, y0, y1) pixels each Gaussian may touch
    width: int,
    height: int,
    background: np.ndarray,  # [3] in [0, 255]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference of ``composite.composite_tiles``: one step per Gaussian, front to back, over the pixels
    of its box, in float64 with ``np.exp``. Returns ``(rgb [H, W, 3] uint8, depth_m, alpha,
    depth_median_m [H, W] float32)``."""
    bg = np.asarray(background, np.float64)
    Tr = np.ones((height, width))
    C = np.zeros((height, width, 3))
    D = np.zeros((height, width))
    Dm = np.zeros((height, width))
    for g in range(feat.shape[0]):
        u, v, ca, cb, cc, opa = feat[g, [FEAT_U, FEAT_V, FEAT_CONIC_A, FEAT_CONIC_B, FEAT_CONIC_C, FEAT_OPACITY]]
        z = feat[g, FEAT_Z]
        ys = slice(int(box[g, 2]), int(box[g, 3]) + 1)
        xs = slice(int(box[g, 0]), int(box[g, 1]) + 1)
        dx = np.arange(xs.start, xs.stop)[None, :] - u
        dy = np.arange(ys.start, ys.stop)[:, None] - v
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = np.minimum(ALPHA_MAX, opa * np.exp(power))
        Tp = Tr[ys, xs]
        # pixels already terminated and too-faint contributions are skipped
        alpha = np.where((alpha >= ALPHA_MIN) & (Tp >= T_MIN), alpha, 0.0)
        wgt = alpha * Tp
        C[ys, xs] += wgt[..., None] * feat[g, [FEAT_RED, FEAT_GREEN, FEAT_BLUE]]
        D[ys, xs] += wgt * z
        Tn = Tp * (1.0 - alpha)
        Dm[ys, xs] = np.where((Tp > MEDIAN_DEPTH_T) & (Tn <= MEDIAN_DEPTH_T), z, Dm[ys, xs])
        Tr[ys, xs] = Tn
    acc = 1.0 - Tr
    rgb = np.clip(np.floor(C + Tr[..., None] * bg + 0.5), 0, 255).astype(np.uint8)
    depth_m = np.where(acc >= DEPTH_MIN_ALPHA, D / np.maximum(acc, 1e-12), 0.0)
    return rgb, depth_m.astype(np.float32), acc.astype(np.float32), Dm.astype(np.float32)

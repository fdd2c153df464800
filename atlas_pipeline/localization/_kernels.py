"""Compiled inner loops of the RGB-D tracker (Numba): image pyramids, surfel splatting of the map
into a model view, and the Gauss-Newton normal equations of the hybrid residual.

Inputs and outputs are flat named tuples (:class:`PinholeView`, :class:`SplatParams`,
:class:`FramePoints`, :class:`ModelView`, :class:`ReferenceImage`, :class:`Params`,
:class:`Correspondences`, :class:`Stats`), which Numba passes by value in nopython mode. They are
kept flat: Numba cannot hand a named tuple nested in another to a ``prange`` body. No field may be
named like an array method (``view``, ``T``, ``shape``, ...): Numba reads such a field as the method.

The normal equations are built in the named steps of kiss-icp's ``Registration.cpp``:

1. :func:`associate`: correspondences (projective data association into the model view with a
   distance gate; projection into the reference image with an occlusion gate and bilinear
   sampling), written out as :class:`Correspondences`;
2. :func:`build_linear_system`: residuals, Jacobians and robust (Huber, depth-noise) weights of
   the correspondences summed into ``J^T W J`` and ``J^T W r``;
3. solving and applying the update: the caller's (:mod:`atlas_pipeline.localization.tracker`).

:func:`normal_equation_chunks` runs 1 and 2 per chunk of points, so a chunk's correspondences
are still in cache when they are summed, and :func:`add_chunks` adds the chunks in a fixed order.
(Measured on a TUM frame: as fast as, in fact ~10 % faster than, the single fused loop it
replaced. Per-point helpers inlined into one fused loop were ~30 % slower: each array a
Numba-inlined function binds costs a reference-count update per call, so the per-point helpers
here take scalars only, poses as tuples from :func:`_pose`.)

Conventions: ``T_*`` are 4x4 float64 camera-to-world poses; images are row-major ``[h, w]``; a
level-``l`` pixel ``(i, j)`` covers the full-resolution block starting at ``(s*i, s*j)`` with
``s = 2**l``, so its centre is at ``s*i + (s-1)/2`` full-resolution pixels. Tuning values arrive
as arguments (see :mod:`atlas_pipeline.localization.constants`); the literals left here are
structural (halves of central differences and 2x2 blocks, rounding to the nearest pixel, the 6
unknowns of a pose).
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from atlas_pipeline.localization._pyramid_kernels import downsample_depth, downsample_mean, image_gradients

__all__ = [
    "PinholeView", "SplatParams", "FramePoints", "ModelView", "ReferenceImage", "Params", "Correspondences", "Stats",
    "MATCH_NONE", "MATCH_GATED", "MATCH_OK", "MATCH_IN_FRONT", "MATCH_BEHIND", "N_CHUNKS",
    "downsample_depth", "downsample_mean", "image_gradients", "splat_surfels", "SplatCulling", "NO_CULLING",
    "FarSurfels", "NO_FAR",
    "associate", "build_linear_system", "normal_equations", "ChunkSums", "chunk_sums",
    "normal_equation_chunks", "add_chunks",
]

# Summation layout (not tuning): the points are summed in this many chunks, then the chunks are
# added in chunk order. Changing it changes the rounding of every pose.
N_CHUNKS = 16
# Splatting runs over this many horizontal image bands in parallel (each owns its rows of the z-buffer).
N_SPLAT_BANDS = 4
# Disk hits kept per pixel for the visibility band's mean (the nearest ones). Disks of 0.8 voxels
# overlap a few deep on a surface seen head-on and more at grazing angles: with 8, 28 of 15,626
# pixels of a synthetic-handheld model view had more hits in their band; with 16, none.
SPLAT_HITS_PER_PIXEL = 16

# Outcome of the geometric association of one point (Correspondences.geometric).
MATCH_NONE = 0  # projects outside the model view, or onto an empty pixel
MATCH_GATED = 1  # lands on the model view, but farther from its surface than the gate, behind it
MATCH_OK = 2  # a correspondence
# Lands on the model view farther than the gate *in front of* its surface: a surface the map does
# not have (the far side of an object mapped from one side only, an object moved in): it neither
# agrees nor disagrees with the map, so it counts as unmapped, not as on the model.
MATCH_IN_FRONT = 3
MATCH_BEHIND = 4  # behind the view's first surface, within the gate of the surface behind it: a correspondence


# ---- named inputs and outputs --------------------------------------------------------------------


class PinholeView(NamedTuple):
    """A posed pinhole camera to render into."""

    T_world_cam: np.ndarray  # [4, 4] float64 camera-to-world
    fx: float  # px
    fy: float
    cx: float
    cy: float
    width: int  # px
    height: int


class SplatParams(NamedTuple):
    """Limits of :func:`splat_surfels` (see ``TrackerConstants``)."""

    max_radius_px: int  # largest disk footprint
    min_depth_m: float  # near clip
    min_incidence_cos: float  # grazing rays below this are not splatted
    # Visibility band: hits within max(blend_floor_m, blend_sigmas * sigma(z)) behind a pixel's
    # nearest hit z are averaged with it (sigma(z) = noise_a_m + noise_b_per_m (z - noise_z0_m)^2
    # for z > noise_z0_m); both 0 keep the nearest hit alone.
    blend_sigmas: float
    blend_floor_m: float
    noise_a_m: float
    noise_b_per_m: float
    noise_z0_m: float
    # Far clip: surfels whose centre lies farther along the optical axis are not drawn (inf: none).
    max_depth_m: float = math.inf


class FramePoints(NamedTuple):
    """The frame being tracked, at one pyramid level (unpacks as ``points, intensity``)."""

    points_cam: np.ndarray  # [N, 3] float64 camera-frame points, m
    intensity: np.ndarray  # [N] float64 grey in [0, 1]


class ModelView(NamedTuple):
    """The map splatted into a pinhole view (:func:`splat_surfels`): the geometric reference."""

    points_cam: np.ndarray  # [h, w, 3] float64 surface points in the view's camera frame, NaN = empty
    normals_cam: np.ndarray  # [h, w, 3] float64 unit normals facing the camera
    T_world_cam: np.ndarray  # [4, 4] pose of the view
    fx: float  # px, of the view's pyramid level
    fy: float
    cx: float
    cy: float
    # The next surface behind the first along each pixel's ray (NaN: none): where the map holds
    # two copies of a surface a few cm apart (drift between passes), or an occluder's edge is a
    # pixel off, a frame point behind the first surface is matched to the one it lies on.
    points_behind_cam: np.ndarray  # [h, w, 3] float64
    normals_behind_cam: np.ndarray  # [h, w, 3] float64


class ReferenceImage(NamedTuple):
    """The photometric reference (a keyframe) at one pyramid level; raw (distorted) sensor pixels."""

    intensity: np.ndarray  # [h, w] float32 grey in [0, 1]
    grad_x: np.ndarray  # [h, w] float32 d intensity / d u, per pixel
    grad_y: np.ndarray  # [h, w] float32 d intensity / d v
    depth_m: np.ndarray  # [h, w] float32, 0 = none
    T_world_cam: np.ndarray  # [4, 4] pose of the keyframe
    fx: float  # px, of the level
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray  # [5] float64 (k1, k2, p1, p2, k3); zeros = none


class Params(NamedTuple):
    """Gates (:func:`associate`), robust weights and the depth-noise model (:func:`build_linear_system`)."""

    max_distance_m: float  # geometric association gate: point to model surface point
    huber_depth_m: float  # Huber threshold of the point-to-plane residual (at the reference depth)
    photometric_weight: float  # weight of the intensity residuals; 0 disables the photometric term
    huber_intensity: float  # Huber threshold of the intensity residual (grey levels)
    occlusion_gate_m: float  # reference depth must be this close to the point's depth there
    min_view_depth_m: float  # near clip of the projections into the model view and the reference
    noise_a_m: float  # depth noise sigma(z) = a + b (z - z0)^2 for z > z0; a = 0 disables weighting
    noise_b_per_m: float
    noise_z0_m: float
    noise_reference_sigma_m: float  # sigma(reference depth): residuals with this noise keep full weight


class Correspondences(NamedTuple):
    """Output of :func:`associate` for points ``lo:hi`` of a frame (row ``i`` = point ``lo + i``)."""

    points_world: np.ndarray  # [n, 3] float64 the points at the current pose estimate
    depth_cam_m: np.ndarray  # [n] float64 their depth in their own camera (for the noise model)
    intensity: np.ndarray  # [n] float64 their grey value
    geometric: np.ndarray  # [n] int8 MATCH_NONE / MATCH_GATED / MATCH_OK / MATCH_IN_FRONT / MATCH_BEHIND
    model_pixel: np.ndarray  # [n, 2] int64 (u, v) of the model view pixel the point projects to
    points_model: np.ndarray  # [n, 3] float64 the points in the model view's camera frame
    photometric: np.ndarray  # [n] bool: the reference sees the point (photometric correspondence)
    points_ref: np.ndarray  # [n, 3] float64 the points in the reference camera frame (photometric term on)
    ref_samples: np.ndarray  # [n, 3] float64 reference (intensity, grad_x, grad_y) where ``photometric``


class ChunkSums(NamedTuple):
    """Per-chunk sums of :func:`normal_equation_chunks`, row ``c`` = chunk ``c``."""

    H: np.ndarray  # [N_CHUNKS, 6, 6] float64 J^T W J
    g: np.ndarray  # [N_CHUNKS, 6] float64 J^T W r
    counts: np.ndarray  # [N_CHUNKS, 4] int64 n_on_model, n_in_front, n_geometric, n_photometric
    costs: np.ndarray  # [N_CHUNKS, 3] float64 geometric_cost, photometric_cost, geometric_sq_m2


class Stats(NamedTuple):
    """Counts and sums of :func:`build_linear_system` / :func:`normal_equations`."""

    n_points: int  # frame points tried
    n_on_model: int  # points that land on a non-empty pixel of the model view (not in front of its surface)
    n_geometric: int  # geometric correspondences (within the association gate)
    n_photometric: int  # photometric correspondences
    geometric_cost: float  # sum of Huber-weighted squared point-to-plane residuals, m^2
    photometric_cost: float  # sum of weighted squared intensity residuals
    geometric_sq_m2: float  # sum of unweighted squared point-to-plane residuals, m^2
    n_in_front: int  # points in front of the model view's surface (MATCH_IN_FRONT)

    @property
    def inlier_fraction(self) -> float:
        """Share of the points with a geometric correspondence."""
        return self.n_geometric / self.n_points if self.n_points else 0.0

    @property
    def agreement(self) -> float:
        """Share of the points landing on the model view that are correspondences."""
        return self.n_geometric / self.n_on_model if self.n_on_model else 0.0

    @property
    def rmse_m(self) -> float:
        """RMS point-to-plane residual of the geometric correspondences (NaN: none)."""
        return math.sqrt(self.geometric_sq_m2 / self.n_geometric) if self.n_geometric else float("nan")


# ---- model view ---------------------------------------------------------------------------------


class SplatCulling(NamedTuple):
    """Surfels :func:`splat_surfels` may skip unseen (:mod:`atlas_pipeline.localization.culling`):
    surfel ``k`` is looked at only where ``chunk_seen[chunk_of[k]]``. An empty ``chunk_of`` culls
    nothing."""

    chunk_of: np.ndarray  # [N] int32, or [0]
    chunk_seen: np.ndarray  # [C] bool


NO_CULLING = SplatCulling(np.zeros(0, np.int32), np.zeros(0, np.bool_))


class FarSurfels(NamedTuple):
    """Coarser stand-ins for the map's far part (``tracker.far_level``): in a view given them,
    :func:`splat_surfels` draws each where its centre's depth along the optical axis lies in its
    window ``(depth_lo_m, depth_hi_m]``, and the map's own surfels only up to ``from_m``."""

    centres_w: np.ndarray  # [F, 3] float64
    normals_w: np.ndarray  # [F, 3] float64 unit
    radius_m: np.ndarray  # [F] float64 each disk's radius
    depth_lo_m: np.ndarray  # [F] float64 its depth window (inf: unbounded)
    depth_hi_m: np.ndarray  # [F] float64
    culling: SplatCulling  # of these surfels (NO_CULLING: none)
    from_m: float  # where they take over from the map's surfels (inf: never)


NO_FAR = FarSurfels(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0), NO_CULLING, math.inf)


def splat_surfels(centres_w, normals_w, radius_m, view, params, surface_behind, culling, far=NO_FAR):
    """Render oriented disks (surfels) into a pinhole view with a z-buffer (:func:`_splat_surfels`
    with this thread's scratch k-buffer for the view's size, :func:`_splat_scratch`).

    Args:
        centres_w, normals_w: ``[N, 3]`` float64 surfel centres and unit normals (world).
        radius_m: disk radius.
        view: :class:`PinholeView` to render into.
        params: :class:`SplatParams`.
        surface_behind: also blend the next band of hits behind the first (False: the ``behind``
            pair stays NaN, and costs no blending).
        culling: :class:`SplatCulling` (``NO_CULLING``: every surfel); it must be conservative:
            the image is the same as without it, only cheaper.
        far: :class:`FarSurfels` drawn instead of the map's surfels beyond ``far.from_m``, each
            in its depth window (``NO_FAR``: none).
    Returns:
        ``(points_cam, normals_cam, points_behind_cam, normals_behind_cam)``, each ``[h, w, 3]``
        float64, NaN where nothing was hit; each pixel holds the mean ray / disk-plane
        intersection of the disks in its visibility band (see :class:`SplatParams` and
        :func:`_splat_band`), so the model surface is smooth and point-to-plane residuals against
        it are sub-voxel; the ``behind`` pair, the same of the next band of hits behind it.
    """
    hit_z, hit_k = _splat_scratch(view.height, view.width)
    cand, cand_far = _candidates(centres_w.shape[0], culling), _candidates(far.centres_w.shape[0], far.culling)
    cam, box, visible = _footprint_scratch(cand.shape[0] + cand_far.shape[0])
    return _splat_surfels(centres_w, normals_w, radius_m, view, params, surface_behind, cand, far, cand_far,
                          SplatScratch(hit_z, hit_k, cam, box, visible))


class SplatScratch(NamedTuple):
    """Working memory of :func:`_splat_surfels`, contents undefined on entry (see
    :func:`_splat_scratch`, :func:`_footprint_scratch`)."""

    hit_z: np.ndarray  # [h, w, K] float64 the k-buffer's depths
    hit_k: np.ndarray  # [h, w, K] int64 ... and rows of ``cam``
    cam: np.ndarray  # [>= M, 8] float64 per candidate surfel (pass 1): see VisibleSurfels
    box: np.ndarray  # [>= M, 4] int32 its pixel box
    visible: np.ndarray  # [>= M] bool


# A splat's k-buffer (SPLAT_HITS_PER_PIXEL depths and surfel numbers a pixel) is 20 MB at 320x240.
# Allocated afresh, its pages cost more to map and fill than a tracking view costs to draw; kept per
# thread for the last few view sizes, it is reused without being cleared (each pixel counts its own
# hits). Buffers larger than this are not kept (full-resolution renders are rare).
SPLAT_SCRATCH_MAX_BYTES = 48 << 20
SPLAT_SCRATCH_SIZES = 2  # view sizes kept per thread
_splat_scratches = threading.local()


def _splat_scratch(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``(hit_z [h, w, K] float64, hit_k [h, w, K] int64)`` scratch of this thread, contents undefined."""
    kept = getattr(_splat_scratches, "by_size", None)
    if kept is None:
        kept = _splat_scratches.by_size = {}
    buffers = kept.pop((h, w), None)
    if buffers is None:
        buffers = (np.empty((h, w, SPLAT_HITS_PER_PIXEL)), np.empty((h, w, SPLAT_HITS_PER_PIXEL), np.int64))
    if sum(b.nbytes for b in buffers) <= SPLAT_SCRATCH_MAX_BYTES:
        kept[(h, w)] = buffers  # the most recent last
        while len(kept) > SPLAT_SCRATCH_SIZES:
            del kept[next(iter(kept))]
    return buffers


# Pass 1 of a splat keeps 81 bytes per candidate surfel: 49 MB for the 600,000 a view of a
# multi-room world may hold. Allocated afresh (past the C allocator's 32 MB reuse limit, or after
# it trimmed the heap), its pages are mapped and zeroed at every call, which costs more than the
# pass itself. Kept per thread, growing to the largest view, up to this size.
FOOTPRINT_SCRATCH_MAX_BYTES = 256 << 20
FOOTPRINT_SCRATCH_HEADROOM = 1.25  # grow to this many times what a view needs: fewer regrowths
_FOOTPRINT_BYTES = 8 * 8 + 4 * 4 + 1  # cam, box, visible per candidate


def _footprint_scratch(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(cam [>= m, 8] float64, box [>= m, 4] int32, visible [>= m] bool)`` of this thread,
    contents undefined."""
    kept = getattr(_splat_scratches, "footprints", None)
    if kept is not None and kept[0].shape[0] >= m:
        return kept
    cap = max(m, int(m * FOOTPRINT_SCRATCH_HEADROOM))
    if cap * _FOOTPRINT_BYTES > FOOTPRINT_SCRATCH_MAX_BYTES:
        cap = m
    buffers = (np.empty((cap, 8)), np.empty((cap, 4), np.int32), np.empty(cap, np.bool_))
    if cap * _FOOTPRINT_BYTES <= FOOTPRINT_SCRATCH_MAX_BYTES:
        _splat_scratches.footprints = buffers
    return buffers


@njit(cache=True, parallel=True)
def _splat_surfels(centres_w, normals_w, radius_m, view, params, surface_behind, cand, far, cand_far, scratch):
    """:func:`splat_surfels` of the candidate surfels ``cand`` and far stand-ins ``cand_far``
    (ascending ``[M]``, ``[F]`` int64: :func:`_candidates`) with ``scratch``'s memory
    (:class:`SplatScratch`)."""
    pose = _pose(view.T_world_cam)
    fx, fy, cx, cy, w, h = view.fx, view.fy, view.cx, view.cy, view.width, view.height
    intrinsics = (fx, fy, cx, cy, w, h)
    near_limits = (params.min_depth_m, params.max_radius_px, radius_m, min(params.max_depth_m, far.from_m))
    zbuf = np.full((h, w), np.inf)
    pts = np.full((h, w, 3), np.nan)
    nrm = np.full((h, w, 3), np.nan)
    pts2 = np.full((h, w, 3), np.nan)
    nrm2 = np.full((h, w, 3), np.nan)
    # Pass 1 (parallel over surfels): camera-frame centre, camera-facing normal, pixel box. Only
    # the candidates (surfels of the chunks the view may see) are looked at, and memory is
    # allocated for them, not for the whole map. One parallel loop: waking the threads costs more
    # than the work of a small map. Rows m.. are the far stand-ins, each with its own radius and
    # depth window (tuples are unpacked before the loop: numba's parallel loops take arrays).
    far_c, far_n, far_r, far_lo, far_hi = far.centres_w, far.normals_w, far.radius_m, far.depth_lo_m, far.depth_hi_m
    m, n_cand = cand.shape[0], cand.shape[0] + cand_far.shape[0]
    cam = scratch.cam[:n_cand]  # xc yc zc nx ny nz n.c r^2
    box = scratch.box[:n_cand]  # ulo uhi vlo vhi
    visible = scratch.visible[:n_cand]
    hit_z, hit_k = scratch.hit_z, scratch.hit_k
    for j in prange(n_cand):
        if j < m:
            k = cand[j]
            r = radius_m
            seen, xc, yc, zc, nx, ny, nz, ndotc, ulo, uhi, vlo, vhi = _footprint(
                pose, centres_w[k, 0], centres_w[k, 1], centres_w[k, 2], normals_w[k, 0], normals_w[k, 1],
                normals_w[k, 2], intrinsics, near_limits)
        else:
            k = cand_far[j - m]
            r = far_r[k]
            seen, xc, yc, zc, nx, ny, nz, ndotc, ulo, uhi, vlo, vhi = _footprint(
                pose, far_c[k, 0], far_c[k, 1], far_c[k, 2], far_n[k, 0], far_n[k, 1], far_n[k, 2], intrinsics,
                (params.min_depth_m, params.max_radius_px, r, min(params.max_depth_m, far_hi[k])))
            seen = seen and zc > far_lo[k]
        visible[j] = seen
        if not seen:
            continue
        cam[j, 0], cam[j, 1], cam[j, 2] = xc, yc, zc
        cam[j, 3], cam[j, 4], cam[j, 5], cam[j, 6] = nx, ny, nz, ndotc
        cam[j, 7] = r * r
        box[j, 0], box[j, 1], box[j, 2], box[j, 3] = ulo, uhi, vlo, vhi
    order = np.nonzero(visible)[0]  # the visible candidates, in surfel order
    # Pass 2 (parallel over image bands): each band writes only its own rows, so there is no
    # race on the z-buffer and the result does not depend on the number of threads.
    band_h = (h + N_SPLAT_BANDS - 1) // N_SPLAT_BANDS
    for band in prange(N_SPLAT_BANDS):
        lo, hi = min(h, band * band_h), min(h, (band + 1) * band_h)
        _splat_band(lo, hi, VisibleSurfels(cam, box, order), (fx, fy, cx, cy), params,
                    SplatBuffers(zbuf, pts, nrm, pts2, nrm2), surface_behind, hit_z[lo:hi], hit_k[lo:hi])
    return pts, nrm, pts2, nrm2


@njit(cache=True)
def _candidates(n, culling):
    """``[M]`` int64 ascending: the surfels of the chunks ``culling`` keeps (all ``n`` without culling)."""
    if culling.chunk_of.shape[0] != n:
        return np.arange(n)
    keep = np.empty(n, np.int64)
    m = 0
    for k in range(n):
        if culling.chunk_seen[culling.chunk_of[k]]:
            keep[m] = k
            m += 1
    return keep[:m]


@njit(cache=True, inline="always")
def _footprint(pose, xw, yw, zw, nxw, nyw, nzw, intrinsics, limits):
    """One surfel (centre and unit normal, world) in a view: ``(visible, xc, yc, zc, nx, ny, nz,
    n.c, ulo, uhi, vlo, vhi)``, the camera-frame centre, the normal turned to face the camera,
    and the pixel box of the disk; ``visible`` False when it is outside the near and far clips or
    its box misses the image. ``intrinsics`` = (fx, fy, cx, cy, w, h); ``limits`` = (min depth m,
    max footprint px, disk radius m, max depth m)."""
    fx, fy, cx, cy, w, h = intrinsics
    min_depth_m, max_px, radius_m, max_depth_m = limits
    r00, r01, r02, r10, r11, r12, r20, r21, r22, _, _, _ = pose
    xc, yc, zc = _to_camera(pose, xw, yw, zw)
    if zc < min_depth_m or zc > max_depth_m:
        return False, xc, yc, zc, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0
    nx = r00 * nxw + r10 * nyw + r20 * nzw
    ny = r01 * nxw + r11 * nyw + r21 * nzw
    nz = r02 * nxw + r12 * nyw + r22 * nzw
    ndotc = nx * xc + ny * yc + nz * zc
    if ndotc > 0.0:  # face the camera: a visible surface's normal points back to the viewer
        nx, ny, nz, ndotc = -nx, -ny, -nz, -ndotc
    u0 = fx * xc / zc + cx
    v0 = fy * yc / zc + cy
    # Pixel box of the disk: a ray meets it only if it passes within radius_m of the centre
    # c; a ray through the point c + d of the centre's depth plane passes at least
    # zc |d| / |c + d| from it, so |d| <= radius_m |c| / (zc - radius_m), which is
    # f radius_m |c| / (zc (zc - radius_m)) pixels from the centre's projection; capped at max_px.
    if zc > radius_m:
        reach = radius_m * math.sqrt(xc * xc + yc * yc + zc * zc) / (zc * (zc - radius_m))
        ru = min(fx * reach, float(max_px))
        rv = min(fy * reach, float(max_px))
    else:  # the camera is within a radius of the disk's plane
        ru = rv = float(max_px)
    if u0 + ru < 0.0 or u0 - ru > w - 1 or v0 + rv < 0.0 or v0 - rv > h - 1:
        return False, xc, yc, zc, nx, ny, nz, ndotc, 0, 0, 0, 0
    ulo = max(int(math.ceil(u0 - ru)), 0)
    uhi = min(int(math.floor(u0 + ru)), w - 1)
    vlo = max(int(math.ceil(v0 - rv)), 0)
    vhi = min(int(math.floor(v0 + rv)), h - 1)
    return ulo <= uhi and vlo <= vhi, xc, yc, zc, nx, ny, nz, ndotc, ulo, uhi, vlo, vhi


class VisibleSurfels(NamedTuple):
    """The surfels a view sees, in its camera frame (pass 1 of :func:`splat_surfels`)."""

    cam: np.ndarray  # [M, 8] float64: centre xyz, normal xyz, normal . centre (camera frame), radius^2 (m^2)
    box: np.ndarray  # [M, 4] int32: pixel bounds ulo, uhi, vlo, vhi of each disk's footprint
    order: np.ndarray  # [V] int64: the visible ones, ascending


class SplatBuffers(NamedTuple):
    """What :func:`splat_surfels` writes, per pixel of the view."""

    zbuf: np.ndarray  # [h, w] float64 blended depth (inf: empty)
    points_cam: np.ndarray  # [h, w, 3] float64
    normals_cam: np.ndarray  # [h, w, 3] float64
    points_behind_cam: np.ndarray  # [h, w, 3] float64: the next surface behind (NaN: none)
    normals_behind_cam: np.ndarray  # [h, w, 3] float64


@njit(cache=True, inline="always")
def _ray_hit(k, u, v, cam, fx, fy, cx, cy, min_incidence_cos):
    """Depth along pixel ``(u, v)``'s ray where it meets disk ``k`` (inf: it misses)."""
    rx = (u - cx) / fx
    ry = (v - cy) / fy
    denom = cam[k, 3] * rx + cam[k, 4] * ry + cam[k, 5]
    if denom > -min_incidence_cos:  # grazing or back-facing ray
        return np.inf
    z = cam[k, 6] / denom
    if z <= 0.0:
        return np.inf
    ex = rx * z - cam[k, 0]
    ey = ry * z - cam[k, 1]
    ez = z - cam[k, 2]
    if ex * ex + ey * ey + ez * ez > cam[k, 7]:
        return np.inf
    return z


@njit(cache=True)
def _splat_band(row_lo, row_hi, surfels, intrinsics, params, out, surface_behind, hit_z, hit_k):
    """Surfels ``order`` (visible ones, ascending) into rows ``row_lo:row_hi`` of the buffers (see
    :func:`splat_surfels`); ``hit_z``, ``hit_k`` ``[row_hi - row_lo, w, K]``: scratch.

    Each pixel keeps its :data:`SPLAT_HITS_PER_PIXEL` nearest disk hits (a k-buffer, one sweep
    over the disks); then the hits within the visibility band behind the nearest are averaged,
    depth and normal (surface splatting's blending, Zwicker et al. 2001). A surface seen by few
    noisy frames is a layer of disks as thick as the depth noise; the nearest disk alone lies
    about a sigma in front of it, and a frame aligned to it is pulled towards its camera."""
    cam, box, order = surfels
    fx, fy, cx, cy = intrinsics
    zbuf, pts, nrm, pts2, nrm2 = out
    mic = params.min_incidence_cos
    rows = row_hi - row_lo
    w = zbuf.shape[1]
    kbuf = SPLAT_HITS_PER_PIXEL
    n_hits = np.zeros((rows, w), np.int64)  # the pixel's hits so far: the first n_hits of its k-buffer
    for i in range(order.shape[0]):
        k = order[i]
        if box[k, 3] < row_lo or box[k, 2] >= row_hi:
            continue
        for v in range(max(box[k, 2], row_lo), min(box[k, 3], row_hi - 1) + 1):
            r = v - row_lo
            for u in range(box[k, 0], box[k, 1] + 1):
                z = _ray_hit(k, u, v, cam, fx, fy, cx, cy, mic)
                if not z < np.inf:  # a miss (or a NaN from a non-finite surfel)
                    continue
                n = n_hits[r, u]
                if n < kbuf:
                    j = n
                    n_hits[r, u] = n + 1
                elif z >= hit_z[r, u, kbuf - 1]:  # behind the k nearest
                    continue
                else:
                    j = kbuf - 1
                while j > 0 and hit_z[r, u, j - 1] > z:  # insertion; ties keep the earlier disk first
                    hit_z[r, u, j] = hit_z[r, u, j - 1]
                    hit_k[r, u, j] = hit_k[r, u, j - 1]
                    j -= 1
                hit_z[r, u, j] = z
                hit_k[r, u, j] = k
    for r in range(rows):
        v = row_lo + r
        ry = (v - cy) / fy
        for u in range(w):
            n = n_hits[r, u]
            if n == 0:
                continue
            z, nx, ny, nz, nxt = _blend_band(hit_z[r, u], hit_k[r, u], n, 0, cam, params)
            if not np.isfinite(z):
                continue
            zbuf[v, u] = z
            rx = (u - cx) / fx
            pts[v, u, 0], pts[v, u, 1], pts[v, u, 2] = rx * z, ry * z, z
            nrm[v, u, 0], nrm[v, u, 1], nrm[v, u, 2] = nx, ny, nz
            if surface_behind and nxt < n:
                z, nx, ny, nz, _ = _blend_band(hit_z[r, u], hit_k[r, u], n, nxt, cam, params)
                if np.isfinite(z):
                    pts2[v, u, 0], pts2[v, u, 1], pts2[v, u, 2] = rx * z, ry * z, z
                    nrm2[v, u, 0], nrm2[v, u, 1], nrm2[v, u, 2] = nx, ny, nz


@njit(cache=True, inline="always")
def _blend_band(hit_z, hit_k, n, j0, cam, params):
    """Mean depth and unit normal of the sorted hits ``j0..n-1`` of one pixel (``n`` hits) within
    the visibility band behind hit ``j0`` (``inf`` depth: opposed normals cancelled), and the
    index of the first hit beyond the band (``n``: none)."""
    z0 = hit_z[j0]
    dz = z0 - params.noise_z0_m if z0 > params.noise_z0_m else 0.0
    band = max(params.blend_floor_m, params.blend_sigmas * (params.noise_a_m + params.noise_b_per_m * dz * dz))
    zsum = 0.0
    nx = ny = nz = 0.0
    count = 0
    j = j0
    while j < n:
        z = hit_z[j]
        if z > z0 + band:  # sorted: the rest are farther
            break
        k = hit_k[j]
        zsum += z
        nx += cam[k, 3]
        ny += cam[k, 4]
        nz += cam[k, 5]
        count += 1
        j += 1
    nxt = j
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    if nn <= 0.0:  # opposed normals cancelled: no surface orientation to offer
        return np.inf, 0.0, 0.0, 0.0, nxt
    return zsum / count, nx / nn, ny / nn, nz / nn, nxt


@njit(cache=True)
def frame_surface(depth_m, rays, intrinsics, jump_m, jump_fraction):
    """A frame's own surface as a model view (``tracker.frame_view``): the points ``rays * depth``
    with normals from central differences, moved onto the pinhole grid, the nearest kept per pixel.

    Args:
        depth_m: ``[h, w]`` float64 (0 = none); rays: ``[h, w, 3]`` float64 undistorted, z = 1;
        intrinsics: (fx, fy, cx, cy) of the grid; jump_m, jump_fraction: a neighbour further
            than ``2 (jump_m + jump_fraction z)`` from the pixel's depth is across an occluding edge.
    Returns:
        ``(points_cam [h, w, 3], normals_cam [h, w, 3])`` float64, NaN where nothing lands; the
        normals face the camera. Border pixels, pixels by an edge or an invalid reading have none.
    """
    h, w = depth_m.shape
    fx, fy, cx, cy = intrinsics
    out_p = np.full((h, w, 3), np.nan)
    out_n = np.full((h, w, 3), np.nan)
    zbuf = np.full((h, w), np.inf)
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            zc = depth_m[i, j]
            zr, zl, zd, zu = depth_m[i, j + 1], depth_m[i, j - 1], depth_m[i + 1, j], depth_m[i - 1, j]
            if not (zc > 0.0 and zr > 0.0 and zl > 0.0 and zd > 0.0 and zu > 0.0):
                continue
            jump = 2.0 * (jump_m + jump_fraction * zc)
            if max(abs(zr - zc), abs(zl - zc), abs(zd - zc), abs(zu - zc)) > jump:
                continue
            dx0 = rays[i, j + 1, 0] * zr - rays[i, j - 1, 0] * zl
            dx1 = rays[i, j + 1, 1] * zr - rays[i, j - 1, 1] * zl
            dx2 = rays[i, j + 1, 2] * zr - rays[i, j - 1, 2] * zl
            dy0 = rays[i + 1, j, 0] * zd - rays[i - 1, j, 0] * zu
            dy1 = rays[i + 1, j, 1] * zd - rays[i - 1, j, 1] * zu
            dy2 = rays[i + 1, j, 2] * zd - rays[i - 1, j, 2] * zu
            n0 = dx1 * dy2 - dx2 * dy1
            n1 = dx2 * dy0 - dx0 * dy2
            n2 = dx0 * dy1 - dx1 * dy0
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if not norm > 0.0:
                continue
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            px, py, pz = rays[i, j, 0] * zc, rays[i, j, 1] * zc, rays[i, j, 2] * zc
            if n0 * px + n1 * py + n2 * pz > 0.0:  # face the camera
                n0, n1, n2 = -n0, -n1, -n2
            u = int(np.rint(fx * px / pz + cx))
            v = int(np.rint(fy * py / pz + cy))
            if u < 0 or u >= w or v < 0 or v >= h or pz > zbuf[v, u]:
                continue  # ties: the later pixel wins
            zbuf[v, u] = pz
            out_p[v, u, 0], out_p[v, u, 1], out_p[v, u, 2] = px, py, pz
            out_n[v, u, 0], out_n[v, u, 1], out_n[v, u, 2] = n0, n1, n2
    return out_p, out_n


# ---- small helpers --------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _pose(T_world_cam):
    """A ``[4, 4]`` pose as a tuple of 12 floats ``(R row-major, t)``: scalars, so the per-point
    helpers below take no array (an array bound in an inlined helper costs a reference count
    update per call)."""
    T = T_world_cam
    return (T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2],
            T[0, 3], T[1, 3], T[2, 3])


@njit(cache=True, inline="always")
def _to_world(pose, x, y, z):
    """``R p + t``: a camera-frame point into the world (``pose`` of :func:`_pose`)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2 = pose
    return (r00 * x + r01 * y + r02 * z + t0,
            r10 * x + r11 * y + r12 * z + t1,
            r20 * x + r21 * y + r22 * z + t2)


@njit(cache=True, inline="always")
def _to_camera(pose, px, py, pz):
    """``R^T (p - t)``: a world point into the camera frame of ``pose``."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2 = pose
    dx, dy, dz = px - t0, py - t1, pz - t2
    return (r00 * dx + r10 * dy + r20 * dz,
            r01 * dx + r11 * dy + r21 * dz,
            r02 * dx + r12 * dy + r22 * dz)


@njit(cache=True, inline="always")
def _rotate(pose, x, y, z):
    """``R v`` for a direction ``v``."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, _, _, _ = pose
    return (r00 * x + r01 * y + r02 * z,
            r10 * x + r11 * y + r12 * z,
            r20 * x + r21 * y + r22 * z)


@njit(cache=True)
def _bilinear(img, x, y):
    """Bilinear sample of ``img`` at (x, y); NaN outside or next to an invalid (<= 0 for depth) sample."""
    h, w = img.shape
    if not (x >= 0.0 and y >= 0.0 and x < w - 1 and y < h - 1):
        return np.nan
    i = int(y)
    j = int(x)
    a = x - j
    b = y - i
    return ((1 - a) * (1 - b) * img[i, j] + a * (1 - b) * img[i, j + 1]
            + (1 - a) * b * img[i + 1, j] + a * b * img[i + 1, j + 1])


@njit(cache=True, inline="always")
def _huber_weight(abs_residual, delta):
    """IRLS weight of the Huber loss: 1 inside ``delta``, ``delta / |r|`` outside."""
    return 1.0 if abs_residual <= delta else delta / abs_residual


@njit(cache=True, inline="always")
def _depth_noise_ratio(z_cam_m, params):
    """``sigma(reference) / sigma(z)`` of the depth-noise model (1 when it is disabled)."""
    if params.noise_a_m > 0.0:
        dz = z_cam_m - params.noise_z0_m if z_cam_m > params.noise_z0_m else 0.0
        return params.noise_reference_sigma_m / (params.noise_a_m + params.noise_b_per_m * dz * dz)
    return 1.0


@njit(cache=True, inline="always")
def _add_to_normal_equations(H, g, J, px, py, pz, ax, ay, az, weight, r):
    """Add one weighted residual ``r`` whose gradient w.r.t. its world-frame point ``p`` is ``a``
    to ``H`` (upper triangle) and ``g``: for ``T <- exp(xi) T``, ``dr/dv = a`` and
    ``dr/domega = p x a``. ``J`` ``[6]`` is scratch."""
    J[0], J[1], J[2] = ax, ay, az
    J[3] = py * az - pz * ay
    J[4] = pz * ax - px * az
    J[5] = px * ay - py * ax
    for a in range(6):
        g[a] += weight * J[a] * r
        for b in range(a, 6):
            H[a, b] += weight * J[a] * J[b]


# ---- step 1: association --------------------------------------------------------------------------


@njit(cache=True)
def associate(lo, hi, frame, T_world_cam, model, ref, params):
    """Correspondences of points ``lo:hi`` of ``frame`` at the pose ``T_world_cam`` ``[4, 4]``.

    Geometric (projective data association, as KinectFusion): the point is moved into the model
    view's camera frame and rounded to its nearest pixel; the surface point ``q`` the view holds
    there is its correspondence when ``|x - q| < params.max_distance_m``.

    Photometric (only with ``params.photometric_weight > 0``): the point is moved into the
    reference camera frame, distorted and projected; the reference depth at the nearest pixel must
    be within ``params.occlusion_gate_m`` of the point's depth there (else the reference sees
    another surface, or none), and the bilinear samples of intensity and gradient must lie inside
    the image.

    Returns:
        :class:`Correspondences` ``[hi - lo]``.
    """
    n = hi - lo
    points_world = np.empty((n, 3))
    depth_cam_m = np.empty(n)
    intensity = np.empty(n)
    geometric = np.zeros(n, np.int8)  # MATCH_NONE
    model_pixel = np.zeros((n, 2), np.int64)
    points_model = np.empty((n, 3))
    photometric = np.zeros(n, np.bool_)
    points_ref = np.empty((n, 3))
    ref_samples = np.zeros((n, 3))
    pose = _pose(T_world_cam)
    model_pose = _pose(model.T_world_cam)
    ref_pose = _pose(ref.T_world_cam)
    pts = frame.points_cam
    model_pts = model.points_cam
    behind_pts = model.points_behind_cam
    mh, mw = model_pts.shape[0], model_pts.shape[1]
    mfx, mfy, mcx, mcy = model.fx, model.fy, model.cx, model.cy
    gate2 = params.max_distance_m * params.max_distance_m
    min_depth = params.min_view_depth_m
    use_photometric = params.photometric_weight > 0.0
    ref_I, ref_gx, ref_gy, ref_D = ref.intensity, ref.grad_x, ref.grad_y, ref.depth_m
    rh, rw = ref_D.shape[0], ref_D.shape[1]
    pfx, pfy, pcx, pcy = ref.fx, ref.fy, ref.cx, ref.cy
    k1, k2, p1, p2, k3 = ref.distortion[0], ref.distortion[1], ref.distortion[2], ref.distortion[3], ref.distortion[4]
    has_distortion = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    for i in range(n):
        k = lo + i
        px, py, pz = _to_world(pose, pts[k, 0], pts[k, 1], pts[k, 2])
        points_world[i, 0], points_world[i, 1], points_world[i, 2] = px, py, pz
        depth_cam_m[i] = pts[k, 2]
        intensity[i] = frame.intensity[k]
        # --- geometric: the model view's pixel
        xm, ym, zm = _to_camera(model_pose, px, py, pz)
        points_model[i, 0], points_model[i, 1], points_model[i, 2] = xm, ym, zm
        if zm > min_depth:
            # int() truncates towards zero, so x + 0.5 in (-1, 0) lands on pixel 0 too (kept as it was).
            u = int(mfx * xm / zm + mcx + 0.5)
            v = int(mfy * ym / zm + mcy + 0.5)
            if 0 <= u < mw and 0 <= v < mh and model_pts[v, u, 2] == model_pts[v, u, 2]:
                model_pixel[i, 0], model_pixel[i, 1] = u, v
                ex = xm - model_pts[v, u, 0]
                ey = ym - model_pts[v, u, 1]
                ez = zm - model_pts[v, u, 2]
                if ex * ex + ey * ey + ez * ez < gate2:
                    geometric[i] = MATCH_OK
                elif ez < 0.0:
                    geometric[i] = MATCH_IN_FRONT
                else:
                    geometric[i] = MATCH_GATED
                    bz = behind_pts[v, u, 2]
                    if bz == bz:
                        ex = xm - behind_pts[v, u, 0]
                        ey = ym - behind_pts[v, u, 1]
                        ez = zm - bz
                        if ex * ex + ey * ey + ez * ez < gate2:
                            geometric[i] = MATCH_BEHIND
        if not use_photometric:
            continue
        # --- photometric: where the reference image sees the point
        xk, yk, zk = _to_camera(ref_pose, px, py, pz)
        points_ref[i, 0], points_ref[i, 1], points_ref[i, 2] = xk, yk, zk
        if zk > min_depth:
            xn = xk / zk
            yn = yk / zk
            if has_distortion:  # reference images are raw (distorted) sensor images
                r2 = xn * xn + yn * yn
                rad = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
                xd = xn * rad + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
                yd = yn * rad + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
            else:
                xd = xn
                yd = yn
            uf = pfx * xd + pcx
            vf = pfy * yd + pcy
            ui = int(uf + 0.5)
            vi = int(vf + 0.5)
            dref = ref_D[vi, ui] if 0 <= ui < rw and 0 <= vi < rh else 0.0
            # occlusion / missing depth test: the reference must see this same surface
            if dref == dref and dref > 0.0 and abs(dref - zk) < params.occlusion_gate_m:
                iref = _bilinear(ref_I, uf, vf)
                gxv = _bilinear(ref_gx, uf, vf)
                gyv = _bilinear(ref_gy, uf, vf)
                if iref == iref and gxv == gxv and gyv == gyv:  # NaN: on the image border
                    photometric[i] = True
                    ref_samples[i, 0], ref_samples[i, 1], ref_samples[i, 2] = iref, gxv, gyv
    return Correspondences(points_world, depth_cam_m, intensity, geometric, model_pixel, points_model,
                           photometric, points_ref, ref_samples)


# ---- step 2: linear system -------------------------------------------------------------------------


@njit(cache=True)
def build_linear_system(corr, model, ref, params):
    """Gauss-Newton normal equations of :func:`associate`'s correspondences for a left world-frame
    update ``T <- exp(xi) T`` with ``xi = (v, omega)``.

    Geometric residual: point-to-plane ``r = n . (x - q)`` (``x`` the point, ``q``, ``n`` the
    model view's point and normal at its pixel, all in the view's camera frame), Huber-weighted
    with threshold ``params.huber_depth_m``. Sensor model: with ``params.noise_a_m > 0`` the
    residual is whitened by the point's depth noise relative to a point at the reference depth
    (weight ratio^2, Huber threshold / ratio).

    Photometric residual: ``r = I_ref(pi(x)) - I_cur``, weighted by ``params.photometric_weight``
    times its Huber weight (threshold ``params.huber_intensity``); pinhole Jacobian (the
    distortion's own derivative is neglected: it only slows convergence).

    Returns:
        ``(H [6, 6], g [6], stats)``: ``H = J^T W J`` (symmetric), ``g = J^T W r`` (solve
        ``H xi = -g``), and :class:`Stats`.
    """
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.zeros(6)
    model_pose = _pose(model.T_world_cam)
    ref_pose = _pose(ref.T_world_cam)
    model_pts, model_nrm = model.points_cam, model.normals_cam
    behind_pts, behind_nrm = model.points_behind_cam, model.normals_behind_cam
    pfx, pfy = ref.fx, ref.fy
    huber_depth_m = params.huber_depth_m
    n_on_model = 0
    n_in_front = 0
    n_geometric = 0
    n_photometric = 0
    geometric_cost = 0.0
    photometric_cost = 0.0
    geometric_sq = 0.0
    pw = corr.points_world
    n = pw.shape[0]
    for i in range(n):
        px, py, pz = pw[i, 0], pw[i, 1], pw[i, 2]
        outcome = corr.geometric[i]
        if outcome == MATCH_GATED or outcome == MATCH_OK or outcome == MATCH_BEHIND:
            n_on_model += 1
        elif outcome == MATCH_IN_FRONT:
            n_in_front += 1
        if outcome == MATCH_OK or outcome == MATCH_BEHIND:
            u, v = corr.model_pixel[i, 0], corr.model_pixel[i, 1]
            surf, surf_nrm = (model_pts, model_nrm) if outcome == MATCH_OK else (behind_pts, behind_nrm)
            ex = corr.points_model[i, 0] - surf[v, u, 0]
            ey = corr.points_model[i, 1] - surf[v, u, 1]
            ez = corr.points_model[i, 2] - surf[v, u, 2]
            nrx, nry, nrz = surf_nrm[v, u, 0], surf_nrm[v, u, 1], surf_nrm[v, u, 2]
            r = nrx * ex + nry * ey + nrz * ez
            nwx, nwy, nwz = _rotate(model_pose, nrx, nry, nrz)  # d r / d p: the normal in the world
            ratio = _depth_noise_ratio(corr.depth_cam_m[i], params)
            wgt = _huber_weight(abs(r), huber_depth_m / ratio)
            _add_to_normal_equations(H, g, J, px, py, pz, nwx, nwy, nwz, wgt * ratio * ratio, r)
            geometric_cost += wgt * r * r
            geometric_sq += r * r
            n_geometric += 1
        if corr.photometric[i]:
            xk, yk, zk = corr.points_ref[i, 0], corr.points_ref[i, 1], corr.points_ref[i, 2]
            gx, gy = corr.ref_samples[i, 1], corr.ref_samples[i, 2]
            r = corr.ref_samples[i, 0] - corr.intensity[i]
            wgt = params.photometric_weight * _huber_weight(abs(r), params.huber_intensity)
            # d r / d x (reference camera frame), then into the world
            d0 = gx * pfx / zk
            d1 = gy * pfy / zk
            d2 = -(gx * pfx * xk + gy * pfy * yk) / (zk * zk)
            awx, awy, awz = _rotate(ref_pose, d0, d1, d2)
            _add_to_normal_equations(H, g, J, px, py, pz, awx, awy, awz, wgt, r)
            photometric_cost += wgt * r * r
            n_photometric += 1
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, Stats(n, n_on_model, n_geometric, n_photometric, geometric_cost, photometric_cost, geometric_sq,
                       n_in_front)


# ---- both steps, chunk by chunk -----------------------------------------------------------------------


# The chunks run serially inside one call: a frame's solve calls this ~10 times on 2k-40k points, and
# waking OpenMP threads that sleep at barriers (OMP_WAIT_POLICY=PASSIVE, set by atlas_pipeline)
# costs ~2 ms a call in a VM, more than the work (teddy: 2.4 / 2.6 / 3.6 ms a call on 2k / 10k / 40k
# points in parallel, 0.3 / 0.9 / 2.9 ms serial). Ranges of chunks run on plain threads instead
# (:mod:`atlas_pipeline.localization.normal_equations`; this kernel releases the GIL). The chunked
# sum is what makes the result independent of how the chunks are run.
@njit(cache=True, nogil=True)
def normal_equation_chunks(c_lo, c_hi, frame, T_world_cam, model, ref, params, sums):
    """:func:`associate` then :func:`build_linear_system` for chunks ``c_lo:c_hi`` of the
    :data:`N_CHUNKS` chunks of ``frame``'s points, each written to its row of ``sums``
    (:class:`ChunkSums`, from :func:`chunk_sums`); a chunk's correspondences stay in cache between
    the two steps. Args as :func:`normal_equations`."""
    n_pts = frame.points_cam.shape[0]
    step = (n_pts + N_CHUNKS - 1) // N_CHUNKS
    for c in range(c_lo, c_hi):
        lo = c * step
        hi = min(n_pts, lo + step)
        if lo < hi:
            corr = associate(lo, hi, frame, T_world_cam, model, ref, params)
            H_c, g_c, s = build_linear_system(corr, model, ref, params)
            sums.H[c] = H_c
            sums.g[c] = g_c
            sums.counts[c, 0] = s.n_on_model
            sums.counts[c, 1] = s.n_in_front
            sums.counts[c, 2] = s.n_geometric
            sums.counts[c, 3] = s.n_photometric
            sums.costs[c, 0] = s.geometric_cost
            sums.costs[c, 1] = s.photometric_cost
            sums.costs[c, 2] = s.geometric_sq_m2


@njit(cache=True)
def add_chunks(n_pts, sums):
    """The chunks' rows of ``sums`` added in chunk order (so the sum does not depend on which
    thread ran which chunk): ``(H [6, 6], g [6], Stats)`` of all ``n_pts`` points."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    n_on_model = n_geometric = n_photometric = n_in_front = 0
    geometric_cost = photometric_cost = geometric_sq = 0.0
    for c in range(N_CHUNKS):
        H += sums.H[c]
        g += sums.g[c]
        n_on_model += sums.counts[c, 0]
        n_in_front += sums.counts[c, 1]
        n_geometric += sums.counts[c, 2]
        n_photometric += sums.counts[c, 3]
        geometric_cost += sums.costs[c, 0]
        photometric_cost += sums.costs[c, 1]
        geometric_sq += sums.costs[c, 2]
    return H, g, Stats(n_pts, n_on_model, n_geometric, n_photometric, geometric_cost, photometric_cost,
                       geometric_sq, n_in_front)


def chunk_sums() -> ChunkSums:
    """Zeroed per-chunk sums for :func:`normal_equation_chunks` (a chunk with no points adds zero)."""
    return ChunkSums(np.zeros((N_CHUNKS, 6, 6)), np.zeros((N_CHUNKS, 6)), np.zeros((N_CHUNKS, 4), np.int64),
                     np.zeros((N_CHUNKS, 3)))


def normal_equations(frame, T_world_cam, model, ref, params):
    """:func:`associate` then :func:`build_linear_system` over all points of ``frame`` at the pose
    ``T_world_cam`` ``[4, 4]``, on the calling thread: the hybrid (point-to-plane + photometric)
    Gauss-Newton system.

    Points are split into :data:`N_CHUNKS` chunks, each associated and accumulated in turn, then
    the chunks' sums are added in chunk order.

    Args:
        frame: :class:`FramePoints` ``[N]``; model: :class:`ModelView`; ref:
            :class:`ReferenceImage` (any, with ``params.photometric_weight`` 0); params: :class:`Params`.
    Returns:
        ``(H [6, 6], g [6], stats)`` as :func:`build_linear_system`, for all points.
    """
    sums = chunk_sums()
    normal_equation_chunks(0, N_CHUNKS, frame, T_world_cam, model, ref, params, sums)
    return add_chunks(frame.points_cam.shape[0], sums)

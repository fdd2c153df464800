"""Loop closure: loops found between keyframes, and the keyframe poses corrected by a pose graph.

Frame-to-model tracking (:class:`atlas_pipeline.localization.sequence.SequenceTracker`) drifts
slowly over a long sequence: when the camera returns to a place it mapped long ago, the new
keyframes sit a few centimetres (or degrees) away from the old ones. This module runs after
tracking and mapping:

1. **Detection**: for each keyframe ``i`` (and each loop probe, :func:`loop_probe_frames`: the
   frames that stand in for keyframes where a return over mapped surfaces adds none), earlier
   keyframes ``j`` at least ``min_gap`` keyframes back whose poses are near
   (:func:`loop_candidates`: camera centres within ``radius_m``, optical axes within
   :data:`LOOP_MAX_VIEW_ANGLE_DEG`; the views overlap if the drift is smaller than the radius);
   those whose surfaces keyframe ``i`` sees again from elsewhere
   (:func:`covisible_candidates`: old points landing on ``i``'s depth image, the case of a camera
   returning along another path); and, whatever the drift, those that *look* alike
   (:func:`appearance_candidates`: place recognition by the "small blurry image" of PTAM's
   relocalizer, Klein and Murray 2008, a normalised cross-correlation of 40x30 thumbnails).
2. **Verification** (:func:`verify_loop`): keyframe ``i`` is aligned with the RGB-D tracker to the
   geometry of the candidate and its neighbours as they were mapped (a :class:`SurfelModel` from
   their own points), from the drifted pose and from the candidate's pose; when both fail, the
   :class:`Relocalizer` (no initial pose needed) searches that local map. A loop is accepted only
   when the tracker judges the fit good (``ok``: inlier fraction, agreement, residual) and the
   inlier fraction is at least :data:`LOOP_MIN_INLIER_FRACTION` with :data:`LOOP_MIN_AGREEMENT` of
   what lands on the old geometry fitting it, that agreement counted within the depth noise at
   each point's range (:func:`fit_within_noise`), and only when the matched surfaces pin the
   camera in every direction (:data:`LOOP_MIN_TRANSLATION_CONSTRAINT`) and the two guesses do not
   end in two good fits apart (:data:`LOOP_AMBIGUITY_M`).
3. **Pose graph** (:func:`optimize_pose_graph`): Open3D's ``PoseGraph`` with one odometry edge
   between consecutive keyframes (the tracked relative pose) and one uncertain edge per verified
   loop, solved by ``global_optimization`` (Levenberg-Marquardt with a line process that prunes
   loops inconsistent with the rest, Choi et al. 2015); keyframe 0 stays fixed.
4. **Propagation** (:func:`propagate_correction`): every other frame moves with its nearest earlier
   keyframe or probe (``T_new = T_kf_new @ inv(T_kf_old) @ T_old``).

Probes are nodes of the graph like keyframes (searched, verified, corrected) but never merged into
the map; "keyframe" below means either.

The map is then re-fused from the corrected keyframe poses (:func:`merge_keyframes_at_poses`;
``gaussian_world`` does the same from the corrected :class:`KeyframeSet`).

Conventions (as Open3D's multiway registration): poses ``T_world_cam`` ``[4, 4]`` camera-to-world;
an edge ``(source, target, T)`` measures ``T = inv(T_target) @ T_source`` (source camera to target
camera). Math functions take arrays and do no IO; :func:`close_loops` reads the frames.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from atlas_pipeline.geometry import invert_se3
from atlas_pipeline.localization.noise_fit import NOISE_FIT_SIGMAS, NoiseFit, fit_within_noise, noise_tolerance_m  # noqa: F401

logger = logging.getLogger(__name__)

__all__ = ["LoopEdge", "LoopClosureResult", "CovisibilityView", "NoiseFit", "loop_probe_frames", "loop_candidates",
           "covisible_candidates", "keyframe_reach_m", "keyframe_thumbnail", "appearance_candidates",
           "relative_poses", "optimize_pose_graph",
           "propagate_correction", "trajectory_change", "information_matrix", "noise_tolerance_m",
           "fit_within_noise", "grade_within_noise", "verify_loop", "close_loops", "merge_keyframes_at_poses"]

# Optical axes of two keyframes more than this apart rarely see the same surfaces from the short
# range of an indoor RGB-D camera (a 57-degree field of view): not a candidate.
LOOP_MAX_VIEW_ANGLE_DEG = 45.0
# Candidates tried per keyframe (nearest first): each costs one or two tracker alignments.
LOOP_MAX_CANDIDATES = 3
# The local map a keyframe is verified against: the candidate and this many keyframes either side
# (all older than the gap), so a view a little off the candidate's still overlaps it.
LOOP_MODEL_WINDOW = 2
# A loop edge is added to the graph only when this share of the keyframe's points fit the old
# geometry: stricter than tracking's ``min_fitness`` (a wrong loop bends the whole trajectory).
LOOP_MIN_INLIER_FRACTION = 0.3
# ... and this share of the frame's points that land on the old geometry must fit it: no motion
# prior vouches for a loop, so it must agree better than a tracked frame (min_agreement, 0.6). A
# frame slid along the old surfaces by a few dozen cm still fits with a third of its points, but
# the rest of what lands there disagrees.
LOOP_MIN_AGREEMENT = 0.8
# That agreement counts a point as fitting the old geometry within the depth noise at its range
# (fit_within_noise): within this many standard deviations of the difference of two readings of
# the surface (the frame's and the one it was mapped from: sqrt(2) sigma(z) of sensors.depth_noise),
# or within the tracker's grading gate (localization.min_correspondence_m) where that is wider.
# Two sigmas hold 95 % of a true fit's points. The gate is the wider up to about 2 m, so near
# surfaces are judged as the tracker judges them (the frames slid along old surfaces above stay
# refused); at 3 m a point fits within 4 cm, at 4 m within 7.3 cm, where the sensor's own noise
# (1.4 and 2.6 cm) left a true loop's agreement at 0.6-0.8 against a fixed 2 cm gate. The inlier
# fraction stays the tracker's: far surfaces fit a pose some cm off nearly as well as the true
# one, and on the far loop preset loops let in by a noise-wide inlier fraction moved the
# trajectory about as much as the drift they corrected (docs/tracking.md).
LOOP_NOISE_SIGMAS = NOISE_FIT_SIGMAS
# A loop is verified by geometry alone, so the matched surfaces must pin the camera in every
# direction: a wall and the floor seen through a door let the alignment slide along them with a
# good fit. The least over the largest eigenvalue of the translation block of the point-to-plane
# normal matrix (tracker.translation_constraint) must reach this: a third plane seen over a few
# percent of the view's points.
LOOP_MIN_TRANSLATION_CONSTRAINT = 0.03
# After a keyframe closes a loop, the next this-many keyframes do not search: they would add
# near-duplicate edges, costing time but no information.
LOOP_COOLDOWN_KEYFRAMES = 2
# Place recognition (appearance_candidates): thumbnails of this size, blurred by a Gaussian of this
# sigma (thumbnail pixels) so small shifts still correlate, and a candidate only above this
# normalised cross-correlation (1 = the same image; unrelated indoor views are mostly below 0.6).
# Covisibility (covisible_candidates): an older keyframe is a candidate when its points land on at
# least this share of the keyframe's depth pixels, tested on every COVISIBILITY_STRIDE-th pixel,
# a point counting as on the surface within the tolerance (drift before a loop is a few cm).
LOOP_MIN_COVISIBLE_SHARE = 0.2
COVISIBILITY_STRIDE = 8
COVISIBILITY_DEPTH_TOLERANCE_M = 0.1
THUMBNAIL_SIZE = (40, 30)
THUMBNAIL_BLUR_PX = 1.0
LOOP_MIN_APPEARANCE_NCC = 0.85
# A verified loop is still refused when it would move the keyframe further than tracking can drift
# over the path between the two keyframes: this share of the path length plus a floor (frame-to-
# model RGB-D tracking drifts about 1-3 % of the distance travelled; 10 % leaves a wide margin while
# a look-alike place metres away is caught).
LOOP_MAX_DRIFT_FRACTION = 0.1
LOOP_DRIFT_FLOOR_M = 0.05
# Relocalizer fallback (seconds per try): at most this many per sequence.
LOOP_MAX_RELOCALIZATIONS = 8
# Pose graph: Open3D's line process keeps an uncertain (loop) edge whose error, weighted by its
# information, is within about this distance; edges whose line-process weight ends below the
# prune threshold are dropped as false loops. A floor: close_loops uses the search radius when
# larger (a 40 cm drift with a 5 cm tolerance prunes the true loop: see tests/test_loop_closure.py).
POSE_GRAPH_MAX_CORRESPONDENCE_M = 0.05
POSE_GRAPH_EDGE_PRUNE_THRESHOLD = 0.25
# ... and the distance the line process tolerates is at least this times the largest drift a
# verified loop measured (loops found by appearance may exceed the search radius).
LOOP_DRIFT_TOLERANCE_FACTOR = 1.25
# A frame aligned from two guesses that lands in two good fits further apart than this is
# ambiguous (a room's planes fit the frame from more than one pose): no loop. Two fits of one
# well-pinned frame agree to a few millimetres.
LOOP_AMBIGUITY_M = 0.03
LOOP_AMBIGUITY_DEG = 2.0
# Loop probes (loop_probe_frames): a tracked frame this share of the search radius (or of the
# view-angle limit) away from the last keyframe or probe becomes a probe, so a camera coming back
# over mapped surfaces passes within the search radius of some probe.
LOOP_PROBE_SPACING_FRACTION = 0.5
# Points per keyframe used for the information matrices (Open3D counts correspondences): voxel
# downsampling at twice the map voxel keeps them cheap.
INFO_VOXEL_FACTOR = 2.0


class CovisibilityView(NamedTuple):
    """The keyframe camera as :func:`covisible_candidates` sees it: intrinsics ``fx, fy, cx, cy``
    (pixels of the full image), the subsampling ``stride`` of its depth, and how far (m) a point may
    lie from the measured surface and still count as seen."""

    fx: float
    fy: float
    cx: float
    cy: float
    stride: int
    depth_tolerance_m: float


@dataclass
class LoopEdge:
    """A verified loop: keyframe ``source`` (later) seen again from keyframe ``target`` (earlier).

    Attributes:
        source, target: positions in the list of graph nodes (keyframes and probes, in frame
            order; not frame indices).
        T_target_source: ``[4, 4]`` measured relative pose ``inv(T_target) @ T_source``.
        inlier_fraction, residual_m: the verifying alignment's quality.
        method: ``tracker`` (aligned from a pose guess) or ``relocalizer`` (found with no prior).
        kept: the pose graph kept the edge (False: pruned as inconsistent).
    """

    source: int
    target: int
    T_target_source: np.ndarray
    inlier_fraction: float
    residual_m: float
    method: str = "tracker"
    kept: bool = True


@dataclass
class LoopClosureResult:
    """Outcome of :func:`close_loops`.

    Attributes:
        T_world_cam: ``[N, 4, 4]`` corrected poses of all frames (rows not valid left as given).
        T_keyframes_before, T_keyframes_after: ``[K, 4, 4]`` (keyframes only, not probes).
        node_frames: ``[M]`` frame index of each graph node (keyframes and probes, increasing);
            is_keyframe ``[M]`` bool.
        loops: the verified loops (``kept`` says which the graph kept).
        max_translation_change_m, mean_translation_change_m: how far the correction moved the
            frames' camera centres (valid frames).
        time_s: wall time of detection, verification and optimisation.
    """

    T_world_cam: np.ndarray
    T_keyframes_before: np.ndarray
    T_keyframes_after: np.ndarray
    node_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    is_keyframe: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    loops: list[LoopEdge] = field(default_factory=list)
    max_translation_change_m: float = 0.0
    mean_translation_change_m: float = 0.0
    n_candidates: int = 0
    time_s: float = 0.0

    def record(self) -> dict:
        """A JSON-able summary (frame indices; ``keyframe`` / ``matched_keyframe`` the positions in
        the keyframe list, None for a probe) for artifacts and reports."""
        frames = np.asarray(self.node_frames)
        kf_pos = np.cumsum(self.is_keyframe) - 1

        def keyframe(node: int) -> int | None:
            return int(kf_pos[node]) if self.is_keyframe[node] else None

        return {
            "n_candidates": int(self.n_candidates),
            "n_probes": int(np.count_nonzero(~np.asarray(self.is_keyframe, bool))),
            "n_loops": int(sum(lp.kept for lp in self.loops)),
            "loops": [{"frame": int(frames[lp.source]), "matched_frame": int(frames[lp.target]),
                       "keyframe": keyframe(lp.source), "matched_keyframe": keyframe(lp.target),
                       "inlier_fraction": round(float(lp.inlier_fraction), 4),
                       "residual_m": round(float(lp.residual_m), 5), "method": lp.method, "kept": bool(lp.kept)}
                      for lp in self.loops],
            "max_translation_change_m": round(float(self.max_translation_change_m), 5),
            "mean_translation_change_m": round(float(self.mean_translation_change_m), 5),
        }  # no time: the record is artifact content, which must not change when nothing else does


# -- pure math ---------------------------------------------------------------------------------------

def loop_probe_frames(T_world_cam: np.ndarray, valid: np.ndarray, kf_indices: np.ndarray, spacing_m: float,
                      spacing_deg: float) -> np.ndarray:
    """Frames that stand in for keyframes in the loop search where the map took none.

    Keyframes are chosen by new surface, so a camera coming back over mapped surfaces (the very
    place a loop closes) adds none, and a search over keyframes alone never sees that return.
    Walking the valid frames in order, a frame that moved more than ``spacing_m`` or turned more
    than ``spacing_deg`` from the last keyframe or probe becomes a probe, and so does the last
    valid frame after the last keyframe (a recording often ends where it started).

    Args:
        T_world_cam: ``[N, 4, 4]`` tracked poses; valid ``[N]`` bool; kf_indices ``[K]`` increasing.
    Returns:
        ``[P]`` int64 frame indices, increasing, none of them a keyframe, none before the first.
    """
    from atlas_pipeline.localization.tracker import poses_differ

    kf = np.asarray(kf_indices, np.int64)
    idx = np.flatnonzero(np.asarray(valid, bool))
    if len(kf) == 0 or len(idx) == 0:
        return np.zeros(0, np.int64)
    is_kf = np.zeros(len(T_world_cam), bool)
    is_kf[kf] = True
    probes: list[int] = []
    last = int(kf[0])
    for i in idx[idx > kf[0]]:
        if is_kf[i]:
            last = int(i)
            continue
        if poses_differ(T_world_cam[last], T_world_cam[i], spacing_m, spacing_deg):
            probes.append(int(i))
            last = int(i)
    end = int(idx[-1])
    if end > kf[-1] and end not in probes:
        probes.append(end)
    return np.asarray(probes, np.int64)


def loop_candidates(T_kf: np.ndarray, i: int, min_gap: int, radius_m: float,
                    max_view_angle_deg: float = LOOP_MAX_VIEW_ANGLE_DEG,
                    max_candidates: int = LOOP_MAX_CANDIDATES) -> np.ndarray:
    """Earlier keyframes that may see what keyframe ``i`` sees, nearest first.

    Args:
        T_kf: ``[K, 4, 4]`` keyframe poses (camera-to-world).
        i: the keyframe searching; candidates are ``j <= i - min_gap``.
        radius_m: camera centres at most this far apart; optical axes at most
            ``max_view_angle_deg`` apart.
    Returns:
        ``[C]`` int64 keyframe positions, ``C <= max_candidates``.
    """
    last = i - min_gap
    if last < 0:
        return np.zeros(0, np.int64)
    old = T_kf[: last + 1]
    d = np.linalg.norm(old[:, :3, 3] - T_kf[i, :3, 3], axis=1)
    cos_axes = old[:, :3, 2] @ T_kf[i, :3, 2]
    ok = (d <= radius_m) & (cos_axes >= np.cos(np.radians(max_view_angle_deg))) & np.isfinite(d)
    idx = np.flatnonzero(ok)
    return idx[np.argsort(d[idx], kind="stable")][:max_candidates].astype(np.int64)


def keyframe_reach_m(points_world: list[np.ndarray], T_kf: np.ndarray) -> np.ndarray:
    """``[K]`` the distance (m) from each keyframe's camera centre to the farthest of its points
    ``points_world[k] [M_k, 3]`` (0 for none): a ball no surface it saw lies outside."""
    return np.array([float(np.linalg.norm(p - T[:3, 3], axis=1).max()) if len(p) else 0.0
                     for p, T in zip(points_world, T_kf)])


def _view_reach_m(depth_small: np.ndarray, view: "CovisibilityView") -> float:
    """How far (m) from the camera a point can lie and still land on a pixel of ``depth_small``
    ``[h, w]`` within ``view.depth_tolerance_m`` of its depth: the farthest depth plus the
    tolerance, along the widest ray of the image."""
    h, w = depth_small.shape
    tan_x = max(view.cx, w * view.stride - view.cx) / view.fx
    tan_y = max(view.cy, h * view.stride - view.cy) / view.fy
    return (float(depth_small.max()) + view.depth_tolerance_m) * float(np.sqrt(1.0 + tan_x ** 2 + tan_y ** 2))


def covisible_candidates(points_world: list[np.ndarray], depth_small: np.ndarray, T_kf: np.ndarray, i: int,
                         view: "CovisibilityView", min_gap: int,
                         min_overlap: float = LOOP_MIN_COVISIBLE_SHARE,
                         max_candidates: int = LOOP_MAX_CANDIDATES,
                         reach_m: np.ndarray | None = None) -> np.ndarray:
    """Earlier keyframes that saw the surfaces keyframe ``i`` sees, most overlap first.

    A camera coming back to a mapped place seldom stands where it stood (and keyframes chosen by
    new surface are never taken over mapped space), so nearness of camera centres misses most
    returns. Here an older keyframe's points, moved into keyframe ``i``'s camera by the tracked
    poses, are tested against ``i``'s own depth: a point that lands on ``i``'s measured surface
    (within ``view.depth_tolerance_m``) is seen by both. Points behind a wall land behind the
    measured surface, so rooms do not leak into each other.

    Args:
        points_world: per keyframe ``[M_k, 3]`` world points (a few thousand each).
        depth_small: ``[K, h, w]`` keyframe depths subsampled by ``view.stride`` (0 = none).
        T_kf: ``[K, 4, 4]`` keyframe poses (camera-to-world).
        i: the keyframe searching; candidates are ``j <= i - min_gap``.
        min_overlap: least share of ``i``'s depth pixels that ``j``'s points land on.
        reach_m: ``[K]`` :func:`keyframe_reach_m` of ``points_world`` (None: computed here). A
            keyframe whose ball of points cannot meet the ball ``i``'s depth reaches is not
            looked at: on a long path the search costs the keyframes nearby, not all of them,
            and the result is the same.
    Returns:
        ``[C]`` int64 keyframe positions, ``C <= max_candidates``.
    """
    last = i - min_gap
    if last < 0:
        return np.zeros(0, np.int64)
    depth_i = depth_small[i]
    h, w = depth_i.shape
    n_valid = int(np.count_nonzero(depth_i > 0))
    if n_valid == 0:
        return np.zeros(0, np.int64)
    if reach_m is None:
        reach_m = keyframe_reach_m(points_world[: last + 1], T_kf[: last + 1])
    apart_m = np.linalg.norm(T_kf[: last + 1, :3, 3] - T_kf[i, :3, 3], axis=1)
    near = np.flatnonzero(apart_m <= reach_m[: last + 1] + _view_reach_m(depth_i, view))
    T_cam_world = invert_se3(T_kf[i])
    share = np.zeros(last + 1)
    for j in near:
        p = points_world[j] @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        p = p[p[:, 2] > 0]
        u = np.floor((view.fx * p[:, 0] / p[:, 2] + view.cx) / view.stride).astype(np.int64)
        v = np.floor((view.fy * p[:, 1] / p[:, 2] + view.cy) / view.stride).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z_meas = depth_i[v[inside], u[inside]]
        hit = (z_meas > 0) & (np.abs(z_meas - p[inside, 2]) <= view.depth_tolerance_m)
        # Distinct pixels covered, not points: a dense old keyframe must not count twice.
        share[j] = len(np.unique(v[inside][hit] * w + u[inside][hit])) / n_valid
    idx = np.flatnonzero(share >= min_overlap)
    return idx[np.argsort(-share[idx], kind="stable")][:max_candidates].astype(np.int64)


def keyframe_thumbnail(rgb: np.ndarray | None, depth_m: np.ndarray) -> np.ndarray:
    """A place descriptor: the image (grey; depth when there is no colour) shrunk to
    :data:`THUMBNAIL_SIZE` by area averaging, blurred, zero mean and unit norm. ``[w * h]`` float64.

    Args:
        rgb: ``[H, W, 3]`` uint8 or None; depth_m: ``[H, W]`` (used when ``rgb`` is None).
    """
    img = (np.asarray(rgb, np.float64) @ np.array([0.299, 0.587, 0.114]) if rgb is not None
           else np.asarray(depth_m, np.float64))
    tw, th = THUMBNAIL_SIZE
    H, W = img.shape
    ys = np.minimum((np.arange(H) * th) // H, th - 1)
    xs = np.minimum((np.arange(W) * tw) // W, tw - 1)
    small = np.zeros((th, tw))
    np.add.at(small, (ys[:, None], xs[None, :]), img)
    small /= np.maximum(np.bincount(ys, minlength=th)[:, None] * np.bincount(xs, minlength=tw)[None, :], 1)
    r = int(np.ceil(3 * THUMBNAIL_BLUR_PX))
    g = np.exp(-0.5 * (np.arange(-r, r + 1) / THUMBNAIL_BLUR_PX) ** 2)
    g /= g.sum()
    pad = np.pad(small, r, mode="edge")
    small = np.apply_along_axis(lambda v: np.convolve(v, g, "valid"), 1, pad)
    small = np.apply_along_axis(lambda v: np.convolve(v, g, "valid"), 0, small)
    v = small.ravel() - small.mean()
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def appearance_candidates(thumbs: np.ndarray, i: int, min_gap: int, min_ncc: float = LOOP_MIN_APPEARANCE_NCC,
                          max_candidates: int = LOOP_MAX_CANDIDATES) -> np.ndarray:
    """Earlier keyframes (``j <= i - min_gap``) whose thumbnail correlates with keyframe ``i``'s
    at least ``min_ncc``, best first. ``thumbs``: ``[K, D]`` from :func:`keyframe_thumbnail`.
    Returns ``[C]`` int64, ``C <= max_candidates``."""
    last = i - min_gap
    if last < 0:
        return np.zeros(0, np.int64)
    ncc = thumbs[: last + 1] @ thumbs[i]
    idx = np.flatnonzero(ncc >= min_ncc)
    return idx[np.argsort(-ncc[idx], kind="stable")][:max_candidates].astype(np.int64)


def relative_poses(T_kf: np.ndarray) -> np.ndarray:
    """Odometry measurements between consecutive keyframes: ``[K-1, 4, 4]``, element ``k`` is
    ``inv(T_kf[k + 1]) @ T_kf[k]`` (keyframe k's camera to keyframe k+1's)."""
    return np.einsum("kij,kjl->kil", np.stack([invert_se3(T) for T in T_kf[1:]]), T_kf[:-1]) if len(T_kf) > 1 \
        else np.zeros((0, 4, 4))


def optimize_pose_graph(T_kf: np.ndarray, odometry: np.ndarray, loops: list[tuple[int, int, np.ndarray]],
                        odometry_information: np.ndarray | None = None,
                        loop_information: np.ndarray | None = None,
                        max_correspondence_m: float = POSE_GRAPH_MAX_CORRESPONDENCE_M,
                        edge_prune_threshold: float = POSE_GRAPH_EDGE_PRUNE_THRESHOLD) -> tuple[np.ndarray, list[bool]]:
    """Keyframe poses that best agree with odometry and loop measurements (Open3D's solver).

    Args:
        T_kf: ``[K, 4, 4]`` initial poses (the tracked ones); keyframe 0 stays fixed.
        odometry: ``[K-1, 4, 4]`` edge ``k -> k+1`` measurements (:func:`relative_poses`), certain.
        loops: ``(source, target, T_target_source [4, 4])`` per loop, uncertain (may be pruned).
        odometry_information: ``[K-1, 6, 6]`` (default identity); loop_information ``[L, 6, 6]``.
    Returns:
        ``(T_kf_optimised [K, 4, 4], kept [L])``: ``kept[l]`` is False where the line process
        pruned loop ``l``.
    """
    from atlas_pipeline._open3d import open3d

    o3d = open3d()
    reg = o3d.pipelines.registration
    K = len(T_kf)
    if K < 2 or not loops:
        return np.array(T_kf, np.float64), [True] * len(loops)
    info_o = np.broadcast_to(np.eye(6), (K - 1, 6, 6)) if odometry_information is None else odometry_information
    info_l = np.broadcast_to(np.eye(6), (len(loops), 6, 6)) if loop_information is None else loop_information
    graph = reg.PoseGraph()
    for T in T_kf:
        graph.nodes.append(reg.PoseGraphNode(np.asarray(T, np.float64)))
    for k in range(K - 1):
        graph.edges.append(reg.PoseGraphEdge(k, k + 1, np.asarray(odometry[k], np.float64),
                                             np.asarray(info_o[k], np.float64), uncertain=False))
    for (s, t, T), info in zip(loops, info_l):
        graph.edges.append(reg.PoseGraphEdge(int(s), int(t), np.asarray(T, np.float64),
                                             np.asarray(info, np.float64), uncertain=True))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=max_correspondence_m,
                                          edge_prune_threshold=edge_prune_threshold, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    out = np.stack([np.asarray(n.pose, np.float64) for n in graph.nodes])
    remaining = {(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain}
    kept = [(int(s), int(t)) in remaining for s, t, _ in loops]
    return out, kept


def propagate_correction(T_all: np.ndarray, valid: np.ndarray, kf_indices: np.ndarray,
                         T_kf_old: np.ndarray, T_kf_new: np.ndarray) -> np.ndarray:
    """Move every frame with its nearest earlier keyframe (the first keyframe for frames before it).

    Args:
        T_all: ``[N, 4, 4]`` poses of all frames; valid ``[N]`` bool (others are returned as given).
        kf_indices: ``[K]`` increasing frame indices of the keyframes.
        T_kf_old, T_kf_new: ``[K, 4, 4]`` keyframe poses before and after the correction.
    Returns:
        ``[N, 4, 4]``: ``T_new = T_kf_new @ inv(T_kf_old) @ T_old`` per valid frame (keyframes get
        exactly their new pose).
    """
    out = np.array(T_all, np.float64)
    if len(kf_indices) == 0:
        return out
    corr = np.einsum("kij,kjl->kil", T_kf_new, np.stack([invert_se3(T) for T in T_kf_old]))  # [K, 4, 4]
    which = np.clip(np.searchsorted(kf_indices, np.arange(len(T_all)), side="right") - 1, 0, len(kf_indices) - 1)
    v = np.asarray(valid, bool)
    out[v] = np.einsum("nij,njl->nil", corr[which[v]], out[v])
    out[np.asarray(kf_indices)] = T_kf_new
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    out[~v] = T_all[~v]
    return out


def trajectory_change(T_before: np.ndarray, T_after: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, float]:
    """``(max, mean)`` camera-centre displacement (m) between two ``[N, 4, 4]`` trajectories."""
    d = np.linalg.norm(T_after[:, :3, 3] - T_before[:, :3, 3], axis=1)
    if valid is not None:
        d = d[np.asarray(valid, bool)]
    d = d[np.isfinite(d)]
    return (float(d.max()), float(d.mean())) if len(d) else (0.0, 0.0)


def information_matrix(points_source: np.ndarray, points_target: np.ndarray, T_target_source: np.ndarray,
                       max_correspondence_m: float) -> np.ndarray:
    """Open3D's ``[6, 6]`` information matrix of an edge from the two keyframes' camera-frame
    points ``[M, 3]`` (it grows with the number of correspondences within the distance)."""
    from atlas_pipeline._open3d import open3d, point_cloud

    o3d = open3d()
    src, dst = point_cloud(points_source), point_cloud(points_target)
    return np.asarray(o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        src, dst, max_correspondence_m, np.asarray(T_target_source, np.float64)))


def _voxel_means(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point (the mean) per occupied voxel: ``[M, 3]`` -> ``[V, 3]`` float32."""
    if len(points) == 0:
        return np.zeros((0, 3), np.float32)
    from atlas_pipeline.gaussian_world.builder import pack_voxel_ids

    # One packed integer per voxel: a 1-D unique is several times cheaper than a row-wise one.
    _, inv, counts = np.unique(pack_voxel_ids(np.floor(points / voxel_m)), return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inv, weights=points[:, a], minlength=len(counts)) for a in range(3)], axis=1)
    return (sums / counts[:, None]).astype(np.float32)


# -- verification (tracker) ----------------------------------------------------------------------------

def grade_within_noise(tracker, frame, model, result):
    """``result`` (a :class:`TrackResult` or relocalization result of ``frame`` aligned to
    ``model``) with its agreement counted within the depth noise (:func:`fit_within_noise`
    against the model re-rendered at its pose, as the tracker grades) and ``ok`` judged again
    with it; the inlier fraction and residual stay the tracker's."""
    T = np.asarray(result.T_world_cam, np.float64)
    if not np.isfinite(T).all():
        return result
    view = model.model_view(T, tracker.camera, tracker.model_level, False, math.inf, tracker.tracking_far_m)
    agreement = tracker.agreement_within_noise(frame, view, T)
    ok = (tracker.judge(result.inlier_fraction, result.residual_m, agreement)
          and not getattr(result, "ambiguous", False))
    return dataclasses.replace(result, agreement=agreement, ok=ok)


def verify_loop(tracker, frame, model, guesses: list[np.ndarray], relocalizer_factory=None,
                min_inlier_fraction: float = LOOP_MIN_INLIER_FRACTION, grade=None):
    """Align ``frame`` (a :class:`FramePyramid`) to ``model`` from each guess pose ``[4, 4]``; the
    best good fit, or, when none is good and ``relocalizer_factory`` is given, the relocalizer's.
    ``grade``: maps each alignment's result to the one judged (:func:`grade_within_noise`: the
    agreement within the depth noise; None: as the tracker graded it).

    Returns ``(TrackResult-like with T_world_cam, inlier_fraction, residual_m, method)`` or None.
    """
    from atlas_pipeline.localization.tracker import poses_differ

    def good(r) -> bool:
        return (r.ok and r.inlier_fraction >= min_inlier_fraction and r.agreement >= LOOP_MIN_AGREEMENT
                and r.translation_constraint >= LOOP_MIN_TRANSLATION_CONSTRAINT)

    graded = grade if grade is not None else (lambda r: r)
    best = None
    fits = []
    for g in guesses:
        r = graded(tracker.align(frame, model, g, None))
        if good(r):
            fits.append(r.T_world_cam)
            if best is None or r.inlier_fraction > best.inlier_fraction:
                best = r
    if any(poses_differ(T, fits[0], LOOP_AMBIGUITY_M, LOOP_AMBIGUITY_DEG) for T in fits[1:]):
        # Two starts, two good fits in different places: the geometry fits more than one pose.
        return None
    if best is not None:
        return best.T_world_cam, best.inlier_fraction, best.residual_m, "tracker"
    if relocalizer_factory is not None:
        r = graded(relocalizer_factory().relocalize(frame, guesses))
        if good(r):
            return r.T_world_cam, r.inlier_fraction, r.residual_m, "relocalizer"
    return None


# -- the whole step (reads frames) -------------------------------------------------------------------

def close_loops(manifest, T_world_cam: np.ndarray, valid: np.ndarray, kf_indices: np.ndarray, localization,
                depth_range_m: tuple[float, float], fusion_stride: int, voxel_size_m: float, min_gap: int,
                radius_m: float, use_relocalizer: bool = True, probes: bool = False,
                log: Callable[[str], None] | None = None) -> LoopClosureResult:
    """Detect and verify loops between the keyframes, optimise the pose graph, correct all frames.

    Args:
        manifest: the sequence (:class:`FrameManifest`; frames are read again, graph nodes only).
        T_world_cam: ``[N, 4, 4]`` tracked poses; valid ``[N]`` bool; kf_indices ``[K]`` increasing.
        localization: :class:`LocalizationConfig` (the tracker that verifies loops).
        min_gap: candidates are at least this many keyframes older; radius_m: search radius.
        probes: add :func:`loop_probe_frames` to the graph (half the search radius and view-angle
            limit apart), so returns over mapped surfaces are searched too
            (``mapping.loop_probes``).
    """
    from atlas_pipeline.localization.relocalize import Relocalizer
    from atlas_pipeline.localization.tracker import RGBDTracker, SurfelModel
    from atlas_pipeline.perception.rgbd import backproject

    t0 = time.perf_counter()
    keyframes = np.asarray(kf_indices, np.int64)
    T_keyframes = np.array(T_world_cam[keyframes], np.float64)
    result = LoopClosureResult(np.array(T_world_cam, np.float64), T_keyframes.copy(), T_keyframes.copy(),
                               keyframes.copy(), np.ones(len(keyframes), bool))
    if len(keyframes) < min_gap + 1:
        result.time_s = time.perf_counter() - t0
        return result
    extra = (loop_probe_frames(T_world_cam, valid, keyframes, LOOP_PROBE_SPACING_FRACTION * radius_m,
                               LOOP_PROBE_SPACING_FRACTION * LOOP_MAX_VIEW_ANGLE_DEG)
             if probes else np.zeros(0, np.int64))
    # The graph's nodes: keyframes and probes in frame order ("keyframe" from here on means either).
    kf = np.union1d(keyframes, extra)
    is_kf = np.isin(kf, keyframes)
    result.node_frames, result.is_keyframe = kf, is_kf
    T_kf = np.array(T_world_cam[kf], np.float64)
    K = len(kf)
    # The last node each node may close a loop with: at least min_gap keyframes older.
    kf_rank = np.cumsum(is_kf)
    last_allowed = np.searchsorted(kf_rank, kf_rank - min_gap, side="right") - 1
    gap = np.arange(K) - last_allowed  # in nodes, as the candidate searches count
    tracker = RGBDTracker(manifest.camera, localization, depth_range_m)
    # Camera-frame points of every keyframe, one per map voxel: the local maps and the information
    # matrices are made from these (each a few thousand points; frames are not kept).
    pts: list[np.ndarray] = []
    thumbs = []
    depth_small = []
    for k in kf:
        depth = manifest.read_depth_m(int(k), allow_empty=True)
        p, _ = backproject(depth, None, manifest.camera, fusion_stride, *depth_range_m)
        pts.append(_voxel_means(p.astype(np.float64), voxel_size_m))
        thumbs.append(keyframe_thumbnail(manifest.read_rgb(int(k)), depth))
        d = depth[::COVISIBILITY_STRIDE, ::COVISIBILITY_STRIDE]
        depth_small.append(np.where((d > depth_range_m[0]) & (d < depth_range_m[1]), d, 0.0))
    thumbs = np.stack(thumbs)
    depth_small = np.stack(depth_small)
    points_world = [p.astype(np.float64) @ T[:3, :3].T + T[:3, 3] for p, T in zip(pts, T_kf)]
    cam = manifest.camera
    view = CovisibilityView(cam.fx, cam.fy, cam.cx, cam.cy, COVISIBILITY_STRIDE, COVISIBILITY_DEPTH_TOLERANCE_M)
    reach_m = keyframe_reach_m(points_world, T_kf)

    def local_model(j: int, i: int):
        lo, hi = max(0, j - LOOP_MODEL_WINDOW), min(int(last_allowed[i]), j + LOOP_MODEL_WINDOW)
        world = [pts[m].astype(np.float64) @ T_kf[m, :3, :3].T + T_kf[m, :3, 3] for m in range(lo, hi + 1)]
        return SurfelModel.from_field(np.concatenate(world), voxel_size_m), T_kf[lo:hi + 1]

    loops: list[LoopEdge] = []
    n_reloc = 0
    cooldown = 0
    n_cand = 0
    for i in range(K):
        if cooldown > 0:
            cooldown -= 1
            continue
        if last_allowed[i] < 0:
            continue
        g = int(gap[i])
        near = loop_candidates(T_kf, i, g, radius_m)
        alike = appearance_candidates(thumbs, i, g)
        covisible = covisible_candidates(points_world, depth_small, T_kf, i, view, g, reach_m=reach_m)
        cands = np.array(list(dict.fromkeys([*near.tolist(), *covisible.tolist(), *alike.tolist()])), np.int64)
        if len(cands) == 0:
            continue
        n_cand += len(cands)
        frame = tracker.prepare(manifest.read_rgb(int(kf[i])), manifest.read_depth_m(int(kf[i]), allow_empty=True))
        by_pose = set(near.tolist()) | set(alike.tolist())
        for j in cands:
            model, priors = local_model(int(j), i)
            if len(model) == 0:
                continue
            # A covisible keyframe was found from keyframe i's own pose, so that pose is the
            # guess; the candidate's pose and the prior-free search serve the others (a camera
            # near an old one, or a view that looks alike, wherever the drift put it).
            guesses = [T_kf[i], T_kf[j]] if int(j) in by_pose else [T_kf[i]]
            factory = None
            if use_relocalizer and n_reloc < LOOP_MAX_RELOCALIZATIONS and int(j) in by_pose:
                def factory(model=model, priors=priors):
                    nonlocal n_reloc
                    n_reloc += 1
                    return Relocalizer(tracker, model, priors)
            found = verify_loop(tracker, frame, model, guesses, factory,
                                grade=functools.partial(grade_within_noise, tracker, frame, model))
            if found is None:
                continue
            T_i_in_old, frac, res, method = found
            correction_m = float(np.linalg.norm(T_i_in_old[:3, 3] - T_kf[i, :3, 3]))
            path_m = float(np.sum(np.linalg.norm(np.diff(T_kf[j:i + 1, :3, 3], axis=0), axis=1)))
            if correction_m > LOOP_MAX_DRIFT_FRACTION * path_m + LOOP_DRIFT_FLOOR_M:
                # More drift than tracking makes over that path: a look-alike place, not a loop.
                logger.info("loop candidate keyframe %d -> %d refused: it would move the camera %.2f m after "
                            "%.2f m of travel", i, j, correction_m, path_m)
                continue
            edge = LoopEdge(i, int(j), invert_se3(T_kf[j]) @ T_i_in_old, frac, res, method)
            loops.append(edge)
            logger.info("loop: keyframe %d (frame %d) matches keyframe %d (frame %d), %.2f inliers, %.1f mm, %s",
                        i, kf[i], j, kf[j], frac, 1000 * res, method)
            cooldown = LOOP_COOLDOWN_KEYFRAMES
            break
    result.n_candidates = n_cand
    result.loops = loops
    if not loops:
        result.time_s = time.perf_counter() - t0
        logger.info("loop closure: %d candidates, no loop verified", n_cand)
        return result
    odo = relative_poses(T_kf)
    info_d = INFO_VOXEL_FACTOR * voxel_size_m
    coarse = [_voxel_means(p.astype(np.float64), info_d) for p in pts]
    info_o = np.stack([information_matrix(coarse[k], coarse[k + 1], odo[k], info_d) for k in range(K - 1)])
    info_l = np.stack([information_matrix(coarse[lp.source], coarse[lp.target], lp.T_target_source, info_d)
                       for lp in loops])
    # The line process must tolerate loop errors up to the drift the loops found (at least the
    # search radius); false loops are kept out by the verification.
    drift = max(float(np.linalg.norm((T_kf[lp.target] @ lp.T_target_source)[:3, 3] - T_kf[lp.source, :3, 3]))
                for lp in loops)
    T_new, kept = optimize_pose_graph(T_kf, odo, [(lp.source, lp.target, lp.T_target_source) for lp in loops],
                                      info_o, info_l,
                                      max_correspondence_m=max(radius_m, LOOP_DRIFT_TOLERANCE_FACTOR * drift,
                                                               POSE_GRAPH_MAX_CORRESPONDENCE_M))
    for lp, k in zip(loops, kept):
        lp.kept = bool(k)
    result.T_keyframes_after = T_new[is_kf]
    result.T_world_cam = propagate_correction(T_world_cam, valid, kf, T_kf, T_new)
    result.max_translation_change_m, result.mean_translation_change_m = trajectory_change(
        T_world_cam, result.T_world_cam, valid)
    result.time_s = time.perf_counter() - t0
    msg = (f"loop closure: {sum(kept)} of {len(loops)} loops kept, trajectory moved by "
           f"{100 * result.max_translation_change_m:.1f} cm at most ({100 * result.mean_translation_change_m:.1f} cm "
           f"mean), {result.time_s:.1f} s")
    logger.info(msg)
    if log is not None:
        log(msg)
    return result


def merge_keyframes_at_poses(manifest, kf_indices: np.ndarray, T_kf: np.ndarray, depth_range_m: tuple[float, float],
                     fusion_stride: int, voxel_size_m: float):
    """A new :class:`VoxelGaussianBuilder` with every keyframe's points merged at its (corrected)
    pose ``T_kf [K, 4, 4]``, as :meth:`SequenceTracker._integrate` merges them while tracking."""
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.perception.rgbd import backproject

    builder = VoxelGaussianBuilder(voxel_size_m)
    for k, T in zip(np.asarray(kf_indices), T_kf):
        rgb = manifest.read_rgb(int(k))
        pts, cols = backproject(manifest.read_depth_m(int(k), allow_empty=True), rgb, manifest.camera,
                                fusion_stride, *depth_range_m)
        if cols is None:
            cols = np.full((len(pts), 3), 128, np.uint8)
        builder.integrate(pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3], cols)
    return builder

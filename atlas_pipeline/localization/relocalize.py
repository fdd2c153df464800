"""Relocalization: the pose of a frame with no initial guess, against a map.

Fast path (:meth:`Relocalizer.relocalize_fast`, milliseconds): the place index
(:mod:`atlas_pipeline.localization.places`) proposes the few keyframe viewpoints whose depth layout
looks most like the frame's, and the tracker verifies them. Full path (:meth:`Relocalizer.relocalize`,
seconds, for when the fast one finds nothing): two sources of hypotheses, then one refinement and
one score for all of them:

1. *Global registration* (:mod:`.global_registration`): FPFH features of the frame's points and
   of the map's surfel centres, matched by a repeatable RANSAC, so a frame can be placed anywhere
   in the map.
2. *Viewpoint priors*: the poses the map was built from (its keyframes), the same poses swung
   about the point they look at, and, while tracking, the last good pose.

Every hypothesis is screened with the tracker's geometric alignment on the coarse levels, the best
few are refined on all levels and scored by inlier fraction and residual; the best wins. ``confidence`` is the winner's inlier
fraction scaled down when a runner-up that disagrees scores almost as well (an ambiguous scene).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Iterator, NamedTuple

import numpy as np

from atlas_pipeline.geometry import so3_exp
from atlas_pipeline.localization.global_registration import GlobalRegistration
from atlas_pipeline.localization.places import PlaceIndex
from atlas_pipeline.localization.tracker import FramePyramid, RGBDTracker, SurfelModel, TrackResult, poses_differ

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["RelocalizationResult", "Relocalizer", "Reach", "relocalize_frames", "select_priors", "MAX_PRIOR_VIEWPOINTS"]


@dataclass
class RelocalizationResult:
    """Outcome of relocalizing one frame.

    Attributes:
        T_world_cam: ``[4, 4]`` best pose (NaN when nothing converged).
        ok: the best hypothesis passed the tracker's quality test.
        confidence: in [0, 1]; inlier fraction, discounted by ambiguity.
        inlier_fraction, residual_m: of the best hypothesis.
        source: which hypothesis won (``global``, ``keyframe``, ``previous``).
        n_hypotheses: hypotheses refined.
    """

    T_world_cam: np.ndarray
    ok: bool
    confidence: float
    inlier_fraction: float
    residual_m: float
    source: str
    n_hypotheses: int
    ambiguous: bool = False  # a distinct pose explains the frame almost as well (FAST_MAX_RUNNER_UP_SCORE)
    translation_constraint: float = 0.0  # of the best hypothesis (tracker.translation_constraint)
    agreement: float = float("nan")  # of the best hypothesis (TrackResult.agreement)


class Reach(NamedTuple):
    """Where the camera can be: its position within ``radius_m`` of ``centre_w``."""

    centre_w: np.ndarray  # [3] float64 world frame
    radius_m: float

    def holds(self, T_world_cam: np.ndarray, slack_m: float = 0.0) -> bool:
        """Whether the pose ``T_world_cam`` ``[4, 4]`` lies within reach (plus ``slack_m``)."""
        return bool(np.linalg.norm(T_world_cam[:3, 3] - self.centre_w) <= self.radius_m + slack_m)


# A hypothesis converges up to about this far from where it starts: one beyond the reach by more
# is not screened at all.
REACH_SCREEN_SLACK_M = 1.0


def geometric_score(r: TrackResult) -> float:
    """Higher is better: share of points explained, discounted by their residual."""
    res = r.residual_m if np.isfinite(r.residual_m) else 1.0
    return r.inlier_fraction * float(np.exp(-res / 0.01))


# Bounded cost: every viewpoint prior costs seven coarse alignments (itself and six swung views), so
# a map of hundreds of keyframes would make one relocalization take tens of seconds. At most this
# many priors are tried: half nearest the caller's own guesses, the rest spread over the map.
MAX_PRIOR_VIEWPOINTS = 32
# Fast path: the place index's nearest viewpoints screened (a few ms each), and how many of them
# are refined on every level.
FAST_CANDIDATES = 8
FAST_REFINE = 4
# ... and the winner must be unambiguous: no distinct refined pose scoring this share of its score
# (a flat wall or a corridor fits many poses equally well; such a frame waits for a better one).
FAST_MAX_RUNNER_UP_SCORE = 0.8
# A relocalized pose must put the frame's texture on the map's: normalized cross-correlation of
# grey levels (unchanged by exposure and gain) at least this. True poses correlate at 0.75-0.98
# on the synthetic and TUM frames, poses 20 cm off or in a look-alike place below 0.62.
MIN_APPEARANCE_NCC = 0.65


# Two poses are distinct hypotheses when they differ by more than this (the tracker's basin on the
# finest level is a few centimetres and degrees; closer poses converge to the same answer).
DISTINCT_POSE_M = 0.05
DISTINCT_POSE_DEG = 5.0


def _is_distinct(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    return poses_differ(T_a, T_b, DISTINCT_POSE_M, DISTINCT_POSE_DEG)


def _distinct(screened: list[tuple[float, str, TrackResult]], n: int) -> list[tuple[str, TrackResult]]:
    """The best ``n`` of ``screened`` (best first) whose coarse poses are distinct: hypotheses from
    neighbouring viewpoints usually converge to one pose, and refining it twice would both waste
    the time and keep a look-alike place out of the comparison that tells the frame is ambiguous."""
    out: list[tuple[str, TrackResult]] = []
    for _, src, r in screened:
        if len(out) >= n:
            break
        if all(_is_distinct(r.T_world_cam, o.T_world_cam) for _, o in out):
            out.append((src, r))
    return out


def select_priors(priors: np.ndarray, near: list[np.ndarray], k: int = MAX_PRIOR_VIEWPOINTS) -> np.ndarray:
    """At most ``k`` of ``priors [P, 4, 4]``: the ``k // 2`` whose camera centres are nearest any
    pose in ``near`` (none when it is empty), then farthest-point sampling of the centres (the
    first prior when nothing is chosen yet) for coverage. Deterministic; all when ``P <= k``."""
    P = len(priors)
    if P <= k:
        return priors
    c = priors[:, :3, 3]
    chosen: list[int] = []
    if near:
        d = np.min(np.stack([np.linalg.norm(c - np.asarray(T)[:3, 3], axis=1) for T in near]), axis=0)
        chosen = [int(i) for i in np.argsort(d, kind="stable")[: k // 2]]
    if not chosen:
        chosen = [0]
    dist = np.min(np.stack([np.linalg.norm(c - c[i], axis=1) for i in chosen]), axis=0)
    while len(chosen) < k:
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(c - c[i], axis=1))
    return priors[sorted(chosen)]


def orbit_samples(T_world_cam: np.ndarray, frame: FramePyramid,
                  angles_deg: tuple[float, ...] = (-45.0, -30.0, -15.0, 15.0, 30.0, 45.0)) -> list[np.ndarray]:
    """Poses ``[4, 4]`` made by swinging ``T_world_cam`` about the point it looks at (median depth
    of ``frame`` along the optical axis), around the camera's own vertical (image y) axis."""
    d = frame.depth[-1]
    z = float(np.median(d[d > 0])) if np.any(d > 0) else 1.5
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    pivot = t + R[:, 2] * z
    axis = R[:, 1]
    out = []
    for a in np.radians(angles_deg):
        Ra = so3_exp(axis * a)
        T = np.eye(4)
        T[:3, :3] = Ra @ R
        T[:3, 3] = pivot + Ra @ (t - pivot)
        out.append(T)
    return out


class Relocalizer:
    """Finds a frame's pose in a fixed map (see the module docstring).

    Args:
        tracker: the tracker whose alignment refines the hypotheses.
        model: the map as surfels.
        prior_poses: ``[K, 4, 4]`` viewpoint priors (e.g. the map's keyframe poses); may be empty.
        feature_voxel_m: voxel size for FPFH features (frame and map are downsampled to it).
        use_global: run global registration as well as the priors.
        seed: global registration's RANSAC seed (the same seed, the same poses).
        n_global: at most this many global registration poses per search.
    """

    def __init__(self, tracker: RGBDTracker, model: SurfelModel, prior_poses: np.ndarray | None = None,
                 feature_voxel_m: float = 0.05, use_global: bool = True, seed: int = 0, n_global: int = 6,
                 places: PlaceIndex | None = None):
        self.tracker = tracker
        self.model = model
        self.priors = np.zeros((0, 4, 4)) if prior_poses is None else np.asarray(prior_poses, np.float64).reshape(-1, 4, 4)
        self.priors = self.priors[np.isfinite(self.priors).all(axis=(1, 2))]
        self.voxel = feature_voxel_m
        self.use_global = use_global and len(model) >= 30
        self.seed = seed
        self.n_global = n_global
        self.n_refine = 4
        cfg = tracker.cfg
        # Screening tracker: the same solver on the coarse levels only (a few ms per hypothesis).
        coarse_iters = tuple(cfg.iterations[:-1]) + (0,) if len(cfg.iterations) > 1 else cfg.iterations
        self._coarse = RGBDTracker(tracker.camera, cfg.model_copy(update={"iterations": coarse_iters}), tracker.depth_range_m,
                                   screening=True)
        self._global: GlobalRegistration | None = None
        self.places = places

    def relocalize_fast(self, frame: FramePyramid, extra_priors: list[np.ndarray] | None = None,
                        reach: Reach | None = None) -> RelocalizationResult:
        """Pose of ``frame`` from the place index's nearest viewpoints (and ``extra_priors``, e.g.
        the last good pose), verified by the tracker: a few coarse alignments and at most
        ``FAST_REFINE`` full ones; only poses within ``reach`` (None: anywhere) count. Not ok (NaN
        pose) when no index or no hypothesis passes."""
        hyps: list[tuple[str, np.ndarray]] = [("previous", np.asarray(T, np.float64)) for T in (extra_priors or [])]
        if self.places is not None and len(self.places):
            hyps += [("place", m.T_world_cam) for m in self.places.query(frame.depth[self.places.level], FAST_CANDIDATES)]
        r = self._verify(frame, hyps, FAST_REFINE, reach)
        if r.ok and r.ambiguous:
            return dataclasses.replace(r, ok=False)
        return r

    def _appearance(self, frame: FramePyramid, T_world_cam: np.ndarray) -> float:
        """How well the frame's grey at ``T_world_cam`` correlates with the map's (NCC in [-1, 1];
        1.0 when either side has no colour to compare): geometry alone cannot tell look-alike
        places apart (rooms of one shape, a corridor, a floor of repeating tiles)."""
        appearance = self.model.appearance()
        if appearance is None or frame.rgb is None:
            return 1.0
        level = min(self.tracker.cfg.finest_level + 1, len(frame.depth) - 1)
        pts, grey = frame.points(level)
        ncc, _ = appearance.correlation(pts @ T_world_cam[:3, :3].T + T_world_cam[:3, 3], grey)
        return ncc if np.isfinite(ncc) else 1.0

    def _verify(self, frame: FramePyramid, hyps: list[tuple[str, np.ndarray]], n_refine: int,
                reach: Reach | None = None) -> RelocalizationResult:
        """Screen ``hyps`` (``(source, T_world_cam)``) on the coarse levels, refine the best
        ``n_refine`` on all levels, and return the best, with its confidence. With ``reach``, a
        pose outside it is dropped before it is ranked: a look-alike place farther than the camera
        can have moved neither wins nor makes the true one look ambiguous."""
        if reach is not None:
            hyps = [(src, T) for src, T in hyps if reach.holds(T, REACH_SCREEN_SLACK_M)]
        if not hyps:
            return RelocalizationResult(np.full((4, 4), np.nan), False, 0.0, 0.0, float("nan"), "none", 0)
        screened: list[tuple[float, str, TrackResult]] = []
        for src, T in hyps:
            # The screening score weighs no free space: the map beyond the frame's reach is left out
            # of the view (the same pose and score, a view of what the sensor reaches).
            r = self._coarse.align(frame, self.model, T, None, within_range=True)
            if np.all(np.isfinite(r.T_world_cam)) and (reach is None or reach.holds(r.T_world_cam)):
                screened.append((geometric_score(r), src, r))
        screened.sort(key=lambda x: -x[0])
        results: list[tuple[str, TrackResult]] = []
        for src, rc in _distinct(screened, n_refine):
            r = self.tracker.align(frame, self.model, rc.T_world_cam, None)
            if np.all(np.isfinite(r.T_world_cam)) and (reach is None or reach.holds(r.T_world_cam)):
                results.append((src, r))
        # Geometry and appearance together rank the poses: a look-alike place fits the geometry
        # as well as the true one, but not the texture.
        looks = {id(r): self._appearance(frame, r.T_world_cam) for _, r in results}
        results = [sr for sr in results if looks[id(sr[1])] >= MIN_APPEARANCE_NCC]
        if not results:
            return RelocalizationResult(np.full((4, 4), np.nan), False, 0.0, 0.0, float("nan"), "none", len(hyps))

        def score(r: TrackResult) -> float:
            return geometric_score(r) * looks[id(r)]

        results.sort(key=lambda sr: -score(sr[1]))
        src, best = results[0]
        conf = best.inlier_fraction
        ambiguous = False
        for _, other in results[1:]:
            if _is_distinct(best.T_world_cam, other.T_world_cam):  # another pose explaining the frame almost as well?
                ambiguous = score(other) > FAST_MAX_RUNNER_UP_SCORE * score(best)
                conf *= float(np.clip(1.0 - score(other) / max(score(best), 1e-9), 0.0, 1.0)) ** 0.5 if ambiguous else 1.0
                break
        # No motion prior vouches for the pose: points in front of the map count against it too.
        ok = best.ok and best.strict_agreement >= self.tracker.cfg.min_agreement
        return RelocalizationResult(best.T_world_cam, ok, float(conf), best.inlier_fraction, best.residual_m,
                                    src, len(hyps), ambiguous, best.translation_constraint, best.agreement)

    def _global_hypotheses(self, frame: FramePyramid) -> list[np.ndarray]:
        """Poses from FPFH matches and RANSAC (:mod:`.global_registration`): the best and its
        distinct runners-up (feature matches in man-made scenes are ambiguous, so the best often
        belongs to a symmetric twin), each polished by a coarse-to-fine point-to-plane ICP whose
        wide first gate widens the tracker's basin."""
        if self._global is None:
            self._global = GlobalRegistration(self.model.centres, self.model.normals, self.voxel, self.seed)
        pts, _ = frame.points(self.tracker.cfg.finest_level + 1)
        if len(pts) < 30:
            return []
        return self._global.hypotheses(pts, self.n_global)

    def relocalize(self, frame: FramePyramid, extra_priors: list[np.ndarray] | None = None,
                   reach: Reach | None = None) -> RelocalizationResult:
        """Pose of ``frame`` in the map, with no initial guess needed; only poses within ``reach``
        (None: anywhere) count."""
        hyps: list[tuple[str, np.ndarray]] = [("previous", np.asarray(T, np.float64)) for T in (extra_priors or [])]
        hyps += [("keyframe", T) for T in select_priors(self.priors, [T for _, T in hyps])]
        if self.use_global:
            try:
                hyps += [("global", T) for T in self._global_hypotheses(frame)]
            except RuntimeError as exc:  # Open3D (the features) reports degenerate inputs this way
                logger.debug("global registration failed: %s", exc)
        # Viewpoints around each prior: the camera swung about the point it looks at (an RGB-D
        # session usually circles what it scans), so a later frame from further round is reachable.
        hyps += [("keyframe", T) for _, P in list(hyps) if _ == "keyframe" for T in orbit_samples(P, frame)]
        return self._verify(frame, hyps, self.n_refine, reach)


def relocalize_frames(manifest: FrameManifest, model: SurfelModel, prior_poses: np.ndarray, cfg: PipelineConfig,
                      frames: Iterable[int], places: PlaceIndex | None = None) -> Iterator[tuple[int, RelocalizationResult]]:
    """Each of ``frames`` of a recording placed in the map ``model`` with no initial pose, one at a
    time: the place index over ``prior_poses`` (``[K, 4, 4]``, the map's keyframes) first, in
    milliseconds; the full search (seconds) only where it finds nothing. ``places``: a stored
    index, used where its key matches the map, priors and camera (else one is rendered)."""
    from atlas_pipeline.localization.places import adopt_stored, place_index

    tracker = RGBDTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m))
    places = adopt_stored(places, model, prior_poses, manifest.camera, tracker.n_levels)
    if places is None:
        places = place_index(model, manifest.camera, tracker.n_levels, prior_poses)
    reloc = Relocalizer(tracker, model, prior_poses, places=places)
    for i in frames:
        frame = tracker.prepare(manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True))
        result = reloc.relocalize_fast(frame)
        if not result.ok:
            result = reloc.relocalize(frame)
        yield i, result

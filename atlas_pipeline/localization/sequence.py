"""Tracking a whole sequence: motion model, loss detection, recovery, and (optionally) mapping.

:class:`SequenceTracker` consumes frames one at a time and keeps only what the next frame needs
(the current and reference pyramids, the last poses, the map), so memory does not grow with the
sequence length. With a ``builder`` it is a small RGB-D SLAM system: keyframes (chosen by motion)
are merged into the voxel map, and the surfel model every later frame is tracked against is
rebuilt from it. Without one it localizes against a fixed map.

Per frame the status is one of:

* ``anchor``: the pose was given (where the session starts);
* ``tracked``: aligned to the map from the motion-model guess (or, failing that, the last pose);
  the guess is the frame aligned to the previous one (odometry), and the camera centre is held to
  it where the map's surfaces leave it free (a wall and the floor), so a free direction follows
  that frame's surfaces, not a velocity that carries any error on, nor a slide;
  when mapping, a frame the map does not explain is aligned to the previous frame instead (note
  ``frame-to-frame``); it becomes a keyframe only when enough of it is surface the map lacks (a
  pan into unmapped space), never when it sees mapped surface the map disagrees with (drift on a
  revisit: merging it would double the surface);
* ``relocalized``: tracking failed, and the frame was placed by :class:`Relocalizer`: first from
  the place index's nearest keyframe views (milliseconds, every lost frame), then, with back-off,
  by the full search (seconds). In a saved world a frame more than
  :data:`STALE_POSE_AFTER_FRAMES` after the last placed one is not tracked at all, only
  relocalized (the last pose is one of the hypotheses). While a session goes on, a relocalized
  pose must lie where the camera can have moved since the last placed frame
  (:data:`RELOCALIZATION_MAX_SPEED_M_S`);
* ``lost``: no good alignment (too few correspondences, too large a residual, no valid depth);
  the pose is the motion-model prediction, and the frame never touches the map. After a failed
  relocalization the next tries back off (1, 2, 4 ... frames, at most
  :data:`RELOCALIZATION_BACKOFF_MAX_FRAMES`), so being lost has a bounded cost per frame;
* ``new_map`` (mapping with ``new_map_after_lost_frames``): after that many lost frames in a row,
  a new map is started from the frame, as ORB-SLAM3's Atlas does: its pose is the last placed
  pose (nothing better is known) and tracking goes on in the new map.
* ``not_attempted``: never processed (set by callers such as
  :func:`atlas_pipeline.localization.localizer.localize_sequence` when they stop early); NaN pose.

**Keyframes by covisibility.** While mapping, a frame is a keyframe when it moved
(``keyframe_translation_m`` / ``keyframe_rotation_deg`` from the last keyframe) *and* at least
:data:`KEYFRAME_MIN_NEW_SURFACE` of its points lie in cells of space the map has no surface in
(:class:`~atlas_pipeline.localization.places.CoverageMap`): keyframes grow
with new surface, not with frames, so a slow pan over mapped surfaces adds none and the cost of a
frame does not grow with the recording.

**Multiple maps.** Every frame's estimate carries the ``map_id`` it was tracked in. While a map
other than the first is active, each of its keyframes is aligned to every older map from its own
pose (milliseconds: a brief loss leaves the maps close), and every
:data:`MAP_MERGE_RELOCALIZE_EVERY_KEYFRAMES` keyframes relocalized in them (no prior needed). A fit
the tracker accepts with at least :data:`MAP_MERGE_MIN_INLIER_FRACTION` of the frame's points
merges the active map into the old one: voxel statistics moved exactly
(:meth:`VoxelGaussianBuilder.merge`), keyframes joined, tracking goes on there. Estimates already
returned keep their map's frame; :meth:`SequenceTracker.to_root` maps a ``(map_id, T)`` into the
frame of the map it ended in, and :meth:`SequenceTracker.map_record` says what happened.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from atlas_pipeline.config import LocalizationConfig
from atlas_pipeline.localization.places import CoverageMap, PlaceIndex, adopt_stored, descriptor_level
from atlas_pipeline.localization.relocalize import Reach, Relocalizer
from atlas_pipeline.localization.tracker import (
    RGBDTracker,
    SurfelCache,
    SurfelModel,
    TrackResult,
    frame_view,
    pose_change,
    poses_differ,
    predict_constant_velocity,
)
from atlas_pipeline.mapping.consistency import point_relation
from atlas_pipeline.perception.colour_timing import MAX_COLOUR_DELAY_S, colour_at_depth_time
from atlas_pipeline.perception.rgbd import backproject
from atlas_pipeline.sensors.camera import CameraIntrinsics

logger = logging.getLogger(__name__)

__all__ = ["STATUS_ANCHOR", "STATUS_TRACKED", "STATUS_RELOCALIZED", "STATUS_LOST", "STATUS_NEW_MAP",
           "STATUS_NOT_ATTEMPTED", "PLACED_STATUSES", "NOTE_NO_DEPTH", "FrameEstimate", "MapInfo", "SequenceTracker"]

STATUS_ANCHOR = "anchor"
STATUS_TRACKED = "tracked"
STATUS_RELOCALIZED = "relocalized"
STATUS_LOST = "lost"
STATUS_NEW_MAP = "new_map"  # mapping: the first frame of a new map, started after a loss
STATUS_NOT_ATTEMPTED = "not_attempted"  # a run stopped before this frame (never produced by process())
# Statuses of frames the map itself placed (an anchor's pose is given, so it says nothing about the map).
PLACED_STATUSES = (STATUS_TRACKED, STATUS_RELOCALIZED)

_MIN_VALID_DEPTH = 200  # fewer valid depth pixels than this: nothing to align
NOTE_NO_DEPTH = "no valid depth"  # note of a frame lost without any alignment tried (nothing to align)
NOTE_BACKING_OFF = "relocalization backing off"
NOTE_FRAME_TO_FRAME = "frame-to-frame"  # tracked against the previous frame where the map ended
# Global relocalization costs seconds per frame, tracking milliseconds. After each failed try the
# next one waits twice as many frames (1, 2, 4, ... up to this cap), so a long stretch the map
# cannot explain costs a bounded share of relocalizations instead of one per frame.
RELOCALIZATION_BACKOFF_MAX_FRAMES = 16
# The place index's fast relocalization (milliseconds) is tried on every lost frame; the full
# search (seconds) only after this many lost frames in a row, then with the back-off above. A
# brief loss recovers within a few frames at tracking cost.
FAST_ONLY_ATTEMPTS = 3
# In a saved world, a frame more than this many frames after the last placed one is not tracked
# from that pose: the camera has moved past the tracker's basin, and an alignment from there can
# settle on surfaces that fit at a wrong place. Only a verified relocalization (geometry and
# texture, that pose among its hypotheses) places it.
STALE_POSE_AFTER_FRAMES = 4
# A relocalization while a session goes on must lie where the camera can have moved since the last
# placed frame: within this speed times the time since (a person walking, a robot at speed) plus
# the margin (that frame's own error). A look-alike place farther off (rooms of one plan, a
# repeating corridor) is not taken for it; after a long loss the reach covers any place.
RELOCALIZATION_MAX_SPEED_M_S = 2.0
RELOCALIZATION_REACH_MARGIN_M = 0.5
# Mapping only: the points of the previous frame that a frame is tracked against when the map does
# not cover it (a pan into unmapped space). One point per this many pixels in u and v.
FRAME_TO_FRAME_STRIDE = 2
# Map merging (see the module doc). As strict as a loop edge (mapping/loop_closure.py): a wrong
# merge bends one map onto another for good.
MAP_MERGE_MIN_INLIER_FRACTION = 0.3
# Frames whose time steps differ by less than this factor count as evenly spaced: the motion
# model steps one increment (timestamps jitter by a few ms) ...
EVEN_SPACING_RATIO = 1.5
# ... and past it, the increment is scaled by the time ratio, up to this many frame intervals:
# a USB stream drops 1-3 frames in a row (a ratio of 2-4, and 5 leaves room for timestamp
# jitter); over longer gaps constant velocity is a guess no better than none.
MAX_VELOCITY_EXTRAPOLATION = 5.0
# Relocalization into older maps costs seconds: tried on every this-many keyframes of a new map.
MAP_MERGE_RELOCALIZE_EVERY_KEYFRAMES = 5
# Mapping: a frame that moved is a keyframe only when at least this share of its points lands
# where the map has no surface (one tenth of the view is new).
KEYFRAME_MIN_NEW_SURFACE = 0.1
NOTE_CONFLICT = "frame-to-frame; sees mapped surface the map disagrees with, not merged"
# A session extending a saved world takes a frame's pose from the saved world alone when at least
# this share of its points lands on that world's surfaces: the world is the reference, and the
# session's own surfaces carry whatever error their poses had.
SAVED_WORLD_MIN_OVERLAP = 0.5


@dataclass
class MapInfo:
    """One map of a mapping session: where it started and where it went.

    ``merged_into`` is the map it was joined to (None: still its own), ``T_into_map [4, 4]`` moves
    its coordinates into that map's, ``merged_at_frame`` is the frame that recognised the place.
    """

    id: int
    first_frame: int | None
    merged_into: int | None = None
    T_into_map: np.ndarray = field(default_factory=lambda: np.eye(4))
    merged_at_frame: int | None = None
    method: str = ""


@dataclass
class ParkedMap:
    """A map put aside when tracking was lost, kept until a later keyframe recognises it.

    Attributes:
        builder: its voxel statistics; model: its tracking surfels.
        keyframe_indices, keyframe_poses: its keyframes (frame index, ``T_map_cam [4, 4]``).
        relocalizer: made on the first prior-free search against it (None until then).
    """

    builder: object
    model: object
    keyframe_indices: list[int]
    keyframe_poses: list[np.ndarray]
    relocalizer: object | None = None


@dataclass
class FrameEstimate:
    """One frame's outcome: ``T_world_cam [4, 4]``, status, quality and time (decoding excluded)."""

    index: int
    T_world_cam: np.ndarray
    status: str
    inlier_fraction: float
    residual_m: float
    time_s: float
    keyframe: bool = False
    note: str = ""
    map_id: int = 0
    new_surface: float = float("nan")  # mapping: share of its points in space the map has not seen


class SequenceTracker:
    """Frame-by-frame tracking against a map that is fixed (``model``) or grown (``builder``).

    Args:
        camera: intrinsics of the frames.
        cfg: localization settings.
        depth_range_m: ``(min, max)`` depth used for tracking and merged into the map.
        model: a fixed map (localization only).
        builder: a :class:`VoxelGaussianBuilder` to merge keyframes into (tracking and mapping);
            may already hold a map (a session that extends a saved world).
        keyframe_translation_m, keyframe_rotation_deg: motion between keyframes (mapping).
        fusion_stride: pixel stride of the points merged per keyframe (as the fused frames use).
        prior_poses: ``[K, 4, 4]`` viewpoints for relocalization (e.g. the map's keyframe poses).
        places: a stored place index of ``model`` (or the builder's map) seen from ``prior_poses``
            (a world bundle's ``places.npz``); used only while its key still matches the map, the
            priors and the camera (:func:`~atlas_pipeline.localization.places.map_key`), else the
            index is rendered from the map when first needed.
        new_map_after_lost_frames: mapping only; after this many lost frames in a row (with depth)
            a new map is started; 0 = never (a session inside a saved world keeps to that world).
        one_surface: mapping only; a keyframe's points that contradict a surface already in the
            map are left out (:func:`~atlas_pipeline.mapping.consistency.disagreeing_points`), as
            the world build does, so a session extending a saved world does not double it.
        saved_world: mapping only; a session inside a saved world (an extension): a frame that
            mostly sees the saved world is aligned to it alone (``SAVED_WORLD_MIN_OVERLAP``), a
            keyframe merges only its points on rays where the map has no surface
            (:func:`~atlas_pipeline.mapping.consistency.point_relation`), the world's own colours
            are the photometric reference, and a stale pose is relocalized, not tracked, as along
            a fixed world (localization always is).
    """

    def __init__(self, camera: CameraIntrinsics, cfg: LocalizationConfig, depth_range_m: tuple[float, float],
                 model: SurfelModel | None = None, builder=None, keyframe_translation_m: float = 0.08,
                 keyframe_rotation_deg: float = 8.0, fusion_stride: int = 2, prior_poses: np.ndarray | None = None,
                 new_map_after_lost_frames: int = 0, one_surface: bool = False,
                 saved_world: bool = False, places: PlaceIndex | None = None):
        if model is None and builder is None:
            raise ValueError("SequenceTracker needs a model (localization) or a builder (mapping)")
        self.camera = camera
        self.cfg = cfg
        self.depth_range_m = depth_range_m
        self.tracker = RGBDTracker(camera, cfg, depth_range_m)
        self.builder = builder
        self.kf_t, self.kf_r = keyframe_translation_m, keyframe_rotation_deg
        self.fusion_stride = fusion_stride
        self.one_surface = bool(one_surface)
        self.saved_world = bool(saved_world) or builder is None
        self.n_refused_points = 0  # keyframe points left out by the one-surface check
        self.n_by_saved_world = 0  # an extension's frames placed by the saved world alone
        # Mapping: the surfel map follows the builder incrementally (cost per keyframe, not per map).
        self._surfels = None if builder is None else SurfelCache(builder)
        self.model = model if model is not None else self._surfels.model()
        # An extension's saved world, frozen as it was loaded (colours included): the reference
        # its frames are placed against wherever they see it.
        self._saved_model = None
        if builder is not None and self.saved_world and len(self.model):
            self._saved_model = self.model
            self._saved_model.appearance()
        if builder is None:  # localization: the map's culling (a fixed map's far level too) made before the first frame
            self.model.prepare_views(self.tracker.tracking_far_m)
        self.priors = [] if prior_poses is None else [np.asarray(T, np.float64) for T in prior_poses]
        self.keyframe_indices: list[int] = []
        self.keyframe_poses: list[np.ndarray] = []
        self._relocalizer: Relocalizer | None = None
        self._places: PlaceIndex | None = None  # built lazily; grows with the keyframes
        self._stored_places = places  # adopted by the first use of the index if it still fits
        self._coverage: CoverageMap | None = None  # mapping: cells with surface (covisibility)
        self._n_places = 0  # viewpoints (priors, then keyframes) indexed so far
        self.new_map_after_lost_frames = int(new_map_after_lost_frames)
        self.map_id = 0
        self.maps: list[MapInfo] = [MapInfo(0, None)]
        # Older maps not merged yet: id -> (builder, model, keyframe indices, keyframe poses, relocalizer).
        self._old_maps: dict[int, ParkedMap] = {}
        self._lost_run = 0  # lost frames in a row (with depth)
        self._kf_in_map = 0  # keyframes of the active map since it started (merge relocalization cadence)
        self.reset()

    # -- state ---------------------------------------------------------------------------------
    def reset(self, index: int | None = None, T_world_cam: np.ndarray | None = None) -> None:
        """Forget the motion state (e.g. before tracking backwards from the anchor)."""
        self._last: tuple[int, np.ndarray] | None = None if T_world_cam is None else (index, np.asarray(T_world_cam, np.float64))
        self._prev: tuple[int, np.ndarray] | None = None
        self._t_last: float | None = None
        self._t_prev: float | None = None
        self._ref = None  # (pyramid, pose) of the photometric reference
        self._last_kf_pose: np.ndarray | None = self.keyframe_poses[-1] if self.keyframe_poses else None
        self._last_frame = None  # (pyramid, pose) of the last accepted frame (frame-to-frame fallback)
        self._reloc_failures = 0  # consecutive failed relocalizations
        self._reloc_wait = FAST_ONLY_ATTEMPTS  # lost frames before the next full search

    @property
    def relocalizer(self) -> Relocalizer:
        if self._relocalizer is None:
            self._relocalizer = Relocalizer(self.tracker, self.model, np.array(self.priors + self.keyframe_poses),
                                            places=self.places)
        return self._relocalizer

    @property
    def places(self) -> PlaceIndex:
        """The place index of the active map's viewpoints (priors, then keyframes), brought up
        to date: only viewpoints not indexed yet are rendered."""
        if self._places is None:
            stored = self._adopt_stored_places()
            if stored is not None:  # holds every prior's views already
                self._places, self._n_places = stored, len(self.priors)
            else:
                self._places = PlaceIndex(self.camera, descriptor_level(self.camera.width, self.tracker.n_levels))
                self._n_places = 0
        views = self.priors + self.keyframe_poses
        for k in range(self._n_places, len(views)):
            self._places.add_keyframe(self.model, views[k], k)
        self._n_places = len(views)
        return self._places

    def _adopt_stored_places(self) -> PlaceIndex | None:
        """The stored place index, when it was made from this very map, priors and camera (no
        keyframe mapped since); None otherwise (then it is never looked at again)."""
        stored, self._stored_places = self._stored_places, None
        if self.keyframe_poses:
            return None
        return adopt_stored(stored, self.model, np.array(self.priors).reshape(-1, 4, 4), self.camera,
                            self.tracker.n_levels)

    def _velocity_poses(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``(T_last, T_prev)``, the last two placed frames, when the constant-velocity model
        carries them to frame ``index``: they are consecutive and lead to it (either direction)."""
        if self.cfg.motion_model != "constant_velocity" or self._last is None or self._prev is None:
            return None
        li, lT = self._last
        if self._prev[0] == li - (index - li) and abs(index - li) == 1:
            return lT, self._prev[1]
        return None

    def _predict(self, index: int, timestamp_s: float | None = None) -> np.ndarray:
        """Constant-velocity guess from the last two frames (:meth:`_motion_prediction`), or the
        last pose after a longer gap, a restart after a loss, or frames not in sequence."""
        assert self._last is not None
        moved = self._motion_prediction(index, timestamp_s)
        return self._last[1].copy() if moved is None else moved

    def _motion_prediction(self, index: int, timestamp_s: float | None) -> np.ndarray | None:
        """The last two frames' velocity carried over the time to this one: a frame after dropped
        frames is predicted as far as the velocity takes the camera (up to
        :data:`MAX_VELOCITY_EXTRAPOLATION` frame intervals). None when there is no velocity."""
        base = self._velocity_poses(index)
        if base is None:
            return None
        lT, pT = base
        if timestamp_s is None or self._t_last is None or self._t_prev is None:
            return predict_constant_velocity(lT, pT)
        dt, dt_prev = abs(timestamp_s - self._t_last), abs(self._t_last - self._t_prev)
        if dt_prev > 0:
            ratio = dt / dt_prev
            if 1 / EVEN_SPACING_RATIO <= ratio <= EVEN_SPACING_RATIO:  # timestamp jitter: one step
                return predict_constant_velocity(lT, pT)
            if ratio <= MAX_VELOCITY_EXTRAPOLATION:
                return predict_constant_velocity(lT, pT, ratio)
        return None

    # -- one frame -----------------------------------------------------------------------------
    def _colour_motion(self, index: int, timestamp_s: float | None, colour_delay_s: float) -> np.ndarray | None:
        """The camera's motion from this frame's depth image to its colour image, ``colour_delay_s``
        later: the velocity of the last two frames (as :meth:`_predict`) over that time, as the
        colour camera's pose in the depth camera's frame ``[4, 4]``; None without a velocity."""
        if (not colour_delay_s or not self.cfg.colour_delay_compensation or abs(colour_delay_s) > MAX_COLOUR_DELAY_S
                or timestamp_s is None or self._t_last is None or self._t_prev is None):
            return None
        base = self._velocity_poses(index)
        dt_prev = self._t_last - self._t_prev  # signed: negative when tracking backwards in time
        if base is None or dt_prev == 0:
            return None
        lT, pT = base
        # the camera-frame increment of the last two frames, per second, over colour_delay_s
        return np.linalg.solve(lT, predict_constant_velocity(lT, pT, colour_delay_s / dt_prev))

    def process(self, index: int, rgb: np.ndarray | None, depth_m: np.ndarray,
                T_given: np.ndarray | None = None, timestamp_s: float | None = None,
                colour_delay_s: float = 0.0) -> FrameEstimate:
        """Estimate frame ``index``; ``T_given`` makes it an anchor with that pose.

        Args:
            rgb: ``[H, W, 3]`` uint8 or None (geometry only); depth_m ``[H, W]`` float32.
            timestamp_s: the frame's time (its depth image's); a gap in time switches the motion
                model off for it.
            colour_delay_s: when the colour image was taken after the depth image (TUM fr1: ~15 ms);
                the colour is moved to the depth image's time with the motion model's velocity
                (:func:`~atlas_pipeline.perception.colour_timing.colour_at_depth_time`), for
                tracking and for the map.
        """
        t0 = time.perf_counter()
        if rgb is not None and T_given is None:
            dT = self._colour_motion(index, timestamp_s, colour_delay_s)
            if dT is not None:
                rgb = colour_at_depth_time(rgb, depth_m, self.camera, dT)
        fp = self.tracker.prepare(rgb, depth_m)
        nan = float("nan")
        if T_given is not None:
            est = FrameEstimate(index, np.asarray(T_given, np.float64).copy(), STATUS_ANCHOR, nan, nan, 0.0)
        elif fp.n_valid < _MIN_VALID_DEPTH:
            T = self._predict(index, timestamp_s) if self._last is not None else np.full((4, 4), np.nan)
            est = FrameEstimate(index, T, STATUS_LOST, 0.0, nan, 0.0, note=NOTE_NO_DEPTH)
        elif self._last is None or len(self.model) == 0:
            est = self._relocalize(index, fp, [])
        elif self.saved_world and self.cfg.relocalize and abs(index - self._last[0]) > STALE_POSE_AFTER_FRAMES:
            est = self._relocalize(index, fp, [self._last[1]], reach=self._reach(timestamp_s))
            if not np.isfinite(est.T_world_cam).all():
                est.T_world_cam = self._last[1].copy()  # lost: the last pose, as a prediction
        else:
            moved = self._motion_prediction(index, timestamp_s)
            guess = self._last[1].copy() if moved is None else moved  # as _predict
            use_photo = self.cfg.photometric_weight > 0 and self._ref is not None
            # Along a fixed world (no map being built) a frame may match a surface behind the
            # first: a world can hold two copies of a wall that drift left a few cm apart.
            behind = self.builder is None
            # ... and where its surfaces leave a direction free, the motion model decides it. With
            # no velocity (the first frame after a start, a loss or a gap) the frame is left free,
            # as the last pose is no prediction of motion; a session mapping into a saved world
            # holds it there instead, since a pose slid along a wall would be merged into that world.
            prior = guess if moved is None and self.builder is not None and self.saved_world else moved
            odo = self._odometry(index, fp, guess, prior)
            if odo is not None:
                guess = prior = odo  # odometry runs only where the motion model holds the pose
            res = self._align_to_saved_world(fp, guess, prior, use_photo)
            if res is None:
                # In a saved world (along it, or extending it) the world's own colours are the photometric
                # reference: a keyframe of this session would move with the camera's error.
                res = self.tracker.align(fp, self.model, guess, self._ref if use_photo else None,
                                         surface_behind=behind, motion_prior=prior, map_reference=self.saved_world,
                                         within_range=True)
            if not res.ok:
                # Second try: last good pose, geometry only (blur or a bad prediction misleads the
                # hybrid solve), held to the same prior: it must not slide where the first could not.
                res2 = self.tracker.align(fp, self.model, self._last[1], None, surface_behind=behind,
                                          motion_prior=prior, within_range=True)
                if _better(res2, res):
                    res = res2
            f2f = None
            if not res.ok and self.builder is not None:
                f2f = self._align_to_last_frame(fp, guess)
            if res.ok:
                est = FrameEstimate(index, res.T_world_cam, STATUS_TRACKED, res.inlier_fraction, res.residual_m, 0.0)
            elif f2f is not None:
                est = FrameEstimate(index, f2f.T_world_cam, STATUS_TRACKED, f2f.inlier_fraction, f2f.residual_m, 0.0,
                                    note=NOTE_FRAME_TO_FRAME)
            elif self.cfg.relocalize:
                est = self._relocalize(index, fp, [self._last[1]], fallback=(guess, res), reach=self._reach(timestamp_s))
            else:
                est = FrameEstimate(index, guess, STATUS_LOST, res.inlier_fraction, res.residual_m, 0.0,
                                    note="poor alignment")
        if self.builder is not None and self.new_map_after_lost_frames > 0:
            self._lost_run = self._lost_run + 1 if (est.status == STATUS_LOST and fp.n_valid >= _MIN_VALID_DEPTH) else 0
            if self._lost_run >= self.new_map_after_lost_frames and np.isfinite(est.T_world_cam).all():
                self._start_new_map(index)
                est = FrameEstimate(index, est.T_world_cam, STATUS_NEW_MAP, float("nan"), float("nan"), 0.0,
                                    note=f"new map {self.map_id} after {self._lost_run} lost frames; pose of the last placed frame")
                self._lost_run = 0
        est.map_id = self.map_id
        if est.status != STATUS_LOST:
            if self.builder is not None and np.isfinite(est.T_world_cam).all():  # only frames that may be merged
                est.new_surface = self._new_surface(fp, est.T_world_cam)
                if est.note == NOTE_FRAME_TO_FRAME and est.new_surface < KEYFRAME_MIN_NEW_SURFACE:
                    est.note = NOTE_CONFLICT  # sees mapped space the map disagrees with: drift, not new surface
            self._accept(index, fp, est, timestamp_s)
            if est.keyframe and self._old_maps and est.status != STATUS_NEW_MAP:
                self._try_merge(index, fp, est.T_world_cam)
        est.time_s = time.perf_counter() - t0
        return est

    # -- multiple maps -------------------------------------------------------------------------
    def _start_new_map(self, index: int) -> None:
        """Put the active map aside and start an empty one; the frame becomes its first keyframe."""
        from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder

        self._old_maps[self.map_id] = ParkedMap(self.builder, self.model, self.keyframe_indices, self.keyframe_poses)
        self.map_id = len(self.maps)
        self.maps.append(MapInfo(self.map_id, index))
        logger.info("frame %d: lost for %d frames, starting map %d", index, self._lost_run, self.map_id)
        self.builder = VoxelGaussianBuilder(self.builder.voxel_size_m)
        self._surfels = SurfelCache(self.builder)
        self.model = self._surfels.model()
        self.keyframe_indices, self.keyframe_poses = [], []
        self._relocalizer = None
        self._places = None
        self._coverage = None
        self._kf_in_map = 0
        last = self._last
        self.reset()
        self._last = last  # the new map's first pose is the last placed one

    def _try_merge(self, index: int, fp, T_world_cam: np.ndarray) -> None:
        """Recognise an older map from this keyframe and join the active map to it (module doc)."""
        self._kf_in_map += 1
        relocalize = self._kf_in_map % MAP_MERGE_RELOCALIZE_EVERY_KEYFRAMES == 0
        for old_id in sorted(self._old_maps):
            old = self._old_maps[old_id]
            if len(old.model) == 0:
                continue
            res = self.tracker.align(fp, old.model, T_world_cam, None)
            method = "tracking"
            if not (res.ok and res.inlier_fraction >= MAP_MERGE_MIN_INLIER_FRACTION) and relocalize:
                if old.relocalizer is None:
                    old.relocalizer = Relocalizer(self.tracker, old.model, np.array(self.priors + old.keyframe_poses))
                res = old.relocalizer.relocalize(fp, [T_world_cam])
                method = "relocalization"
            if res.ok and res.inlier_fraction >= MAP_MERGE_MIN_INLIER_FRACTION:
                self._merge_into(old_id, res.T_world_cam @ np.linalg.inv(T_world_cam), index, method)
                return

    def _merge_into(self, old_id: int, T_old_cur: np.ndarray, index: int, method: str) -> None:
        """Join the active map to map ``old_id``; ``T_old_cur [4, 4]`` moves active-map coordinates there."""
        old = self._old_maps.pop(old_id)
        cur = self.maps[self.map_id]
        cur.merged_into, cur.T_into_map, cur.merged_at_frame, cur.method = old_id, T_old_cur.copy(), index, method
        dt, dr = pose_change(np.eye(4), T_old_cur)
        logger.info("frame %d: map %d recognised in map %d (%s), merged; the maps were %.1f cm / %.1f deg apart",
                    index, self.map_id, old_id, method, 100 * dt, dr)
        old.builder.merge(self.builder, T_old_cur)
        pairs = sorted(zip(old.keyframe_indices + self.keyframe_indices,
                           old.keyframe_poses + [T_old_cur @ T for T in self.keyframe_poses]), key=lambda p: p[0])
        self.builder = old.builder
        self._surfels = SurfelCache(self.builder)
        self.model = self._surfels.model()
        self.keyframe_indices = [int(i) for i, _ in pairs]
        self.keyframe_poses = [T for _, T in pairs]
        self._relocalizer = None
        self._places = None
        self._coverage = None
        self.map_id = old_id
        self._kf_in_map = 0
        # Motion state follows the frame into the old map's coordinates.
        move = (lambda T: T_old_cur @ T)
        self._last = None if self._last is None else (self._last[0], move(self._last[1]))
        self._prev = None if self._prev is None else (self._prev[0], move(self._prev[1]))
        self._ref = None if self._ref is None else (self._ref[0], move(self._ref[1]))
        self._last_frame = None if self._last_frame is None else (self._last_frame[0], move(self._last_frame[1]))
        self._last_kf_pose = None if self._last_kf_pose is None else move(self._last_kf_pose)

    def to_root(self, map_id: int, T_map_cam: np.ndarray) -> tuple[int, np.ndarray]:
        """``(root map id, T [4, 4])``: a pose of map ``map_id`` in the frame of the map it was
        finally merged into (itself when never merged)."""
        T = np.asarray(T_map_cam, np.float64)
        m = map_id
        while self.maps[m].merged_into is not None:
            T = self.maps[m].T_into_map @ T
            m = self.maps[m].merged_into
        return m, T

    def map_record(self) -> dict:
        """What happened to the maps, for reports: one entry per map."""
        out = []
        for m in self.maps:
            dt, dr = pose_change(np.eye(4), m.T_into_map)
            out.append({"id": m.id, "first_frame": m.first_frame, "merged_into": m.merged_into,
                        "merged_at_frame": m.merged_at_frame, "method": m.method or None,
                        "correction_m": round(float(dt), 4), "correction_deg": round(float(dr), 3)})
        return {"n_maps": len(self.maps), "n_merged": sum(m.merged_into is not None for m in self.maps), "maps": out}

    def all_keyframes(self) -> list[tuple[int, list[int], list[np.ndarray]]]:
        """``[(map id, keyframe indices, T_map_cam poses)]`` of the active map and every map not merged."""
        out = [(self.map_id, self.keyframe_indices, self.keyframe_poses)]
        out += [(k, v.keyframe_indices, v.keyframe_poses) for k, v in sorted(self._old_maps.items())]
        return out

    def _reach(self, timestamp_s: float | None) -> Reach | None:
        """Where the camera can be at ``timestamp_s``: around the last placed frame, as far as
        :data:`RELOCALIZATION_MAX_SPEED_M_S` takes it (None: no placed frame or no times)."""
        if self._last is None or self._t_last is None or timestamp_s is None:
            return None
        dt_s = abs(timestamp_s - self._t_last)  # a session may run backwards in time
        if not np.isfinite(dt_s):
            return None
        return Reach(self._last[1][:3, 3].copy(), RELOCALIZATION_REACH_MARGIN_M + RELOCALIZATION_MAX_SPEED_M_S * dt_s)

    def _relocalize(self, index: int, fp, extra: list[np.ndarray],
                    fallback: tuple[np.ndarray, TrackResult] | None = None, reach: Reach | None = None) -> FrameEstimate:
        if len(self.model) == 0:
            return FrameEstimate(index, np.full((4, 4), np.nan), STATUS_LOST, 0.0, float("nan"), 0.0, note="empty map")
        fast = self.relocalizer.relocalize_fast(fp, extra, reach)  # milliseconds: tried on every lost frame
        if fast.ok:
            self._reloc_failures, self._reloc_wait = 0, FAST_ONLY_ATTEMPTS
            return FrameEstimate(index, fast.T_world_cam, STATUS_RELOCALIZED, fast.inlier_fraction, fast.residual_m, 0.0,
                                 note=f"relocalized from {fast.source} hypothesis, confidence {fast.confidence:.2f}")
        # Bounded cost: see FAST_ONLY_ATTEMPTS and RELOCALIZATION_BACKOFF_MAX_FRAMES. A map with
        # no viewpoints to index (an imported field) has only the full search.
        if self._reloc_wait > 0 and (len(self.places) or self._reloc_failures):
            self._reloc_wait -= 1
            if fallback is not None:
                guess, res = fallback
                return FrameEstimate(index, guess, STATUS_LOST, res.inlier_fraction, res.residual_m, 0.0,
                                     note=NOTE_BACKING_OFF)
            return FrameEstimate(index, np.full((4, 4), np.nan), STATUS_LOST, 0.0, float("nan"), 0.0,
                                 note=NOTE_BACKING_OFF)
        r = self.relocalizer.relocalize(fp, extra, reach)
        if r.ok:
            self._reloc_failures, self._reloc_wait = 0, FAST_ONLY_ATTEMPTS
            return FrameEstimate(index, r.T_world_cam, STATUS_RELOCALIZED, r.inlier_fraction, r.residual_m, 0.0,
                                 note=f"relocalized from {r.source} hypothesis, confidence {r.confidence:.2f}")
        self._reloc_failures += 1
        self._reloc_wait = min(2 ** (self._reloc_failures - 1), RELOCALIZATION_BACKOFF_MAX_FRAMES)
        if fallback is not None:
            guess, res = fallback
            return FrameEstimate(index, guess, STATUS_LOST, res.inlier_fraction, res.residual_m, 0.0, note="poor alignment")
        return FrameEstimate(index, np.full((4, 4), np.nan), STATUS_LOST, r.inlier_fraction, r.residual_m, 0.0,
                             note="relocalization failed")

    def _odometry(self, index: int, fp, guess: np.ndarray, prior: np.ndarray | None) -> np.ndarray | None:
        """Frame ``index`` aligned from ``guess`` to the frame before it (either direction) when
        that one was tracked (:meth:`RGBDTracker.odometry`), as the motion model's prediction;
        else None.

        Where the map leaves a direction free (a wall whose floor the first visit never saw), the
        pose there is the prediction's; a velocity taken from the last two such poses would carry
        any error on and grow it frame by frame. The last frame's own surfaces (that floor) hold
        the camera relative to it instead, so an error there grows no faster than odometry drifts;
        ``prior`` (the motion model's prediction) holds what neither frame pins (a bare wall).
        """
        if not self.cfg.odometry_prediction or self._last_frame is None or self._last is None:
            return None
        if abs(index - self._last[0]) != 1 or self._prev is None:  # _prev: the last frame was tracked
            return None
        prev, T_prev = self._last_frame
        reference = self._last_frame if self.cfg.photometric_weight > 0 else None
        return self.tracker.odometry(fp, frame_view(prev, T_prev, self.tracker.model_level), guess, reference, prior)

    def _align_to_saved_world(self, fp, guess: np.ndarray, prior: np.ndarray | None,
                              use_photo: bool) -> TrackResult | None:
        """An extension's frame aligned to the saved world alone, as along a fixed world; None where
        there is no saved world, the alignment fails, or under ``SAVED_WORLD_MIN_OVERLAP`` of the
        frame lands on it (mostly new surface: the session's own map places it)."""
        if self._saved_model is None or self.map_id != 0:
            return None
        res = self.tracker.align(fp, self._saved_model, guess, self._ref if use_photo else None, surface_behind=True,
                                 motion_prior=prior, map_reference=True, within_range=True)
        if not (res.ok and res.overlap >= SAVED_WORLD_MIN_OVERLAP):
            return None
        self.n_by_saved_world += 1
        return res

    def _align_to_last_frame(self, fp, guess: np.ndarray) -> TrackResult | None:
        """Mapping: align to the previous accepted frame's points when the map does not explain the
        frame (it looks where no keyframe has looked yet). None when that fails too."""
        if self._last_frame is None:
            return None
        prev, T_prev = self._last_frame
        pts, _ = backproject(prev.depth[0], None, self.camera, FRAME_TO_FRAME_STRIDE, *self.depth_range_m)
        if len(pts) < _MIN_VALID_DEPTH:
            return None
        pw = pts.astype(np.float64) @ T_prev[:3, :3].T + T_prev[:3, 3]
        model = SurfelModel.from_field(pw, self.builder.voxel_size_m)
        if len(model) == 0:
            return None
        res = self.tracker.align(fp, model, guess, (prev, T_prev) if self.cfg.photometric_weight > 0 else None)
        return res if res.ok else None

    def _accept(self, index: int, fp, est: FrameEstimate, timestamp_s: float | None) -> None:
        T = est.T_world_cam
        self._last_frame = (fp, T)
        if est.status in PLACED_STATUSES:
            self._reloc_failures, self._reloc_wait = 0, FAST_ONLY_ATTEMPTS
        consecutive = self._last is not None and abs(index - self._last[0]) == 1 and est.status == STATUS_TRACKED
        self._prev = self._last if consecutive else None
        self._t_prev = self._t_last if consecutive else None
        self._last = (index, T)
        self._t_last = timestamp_s
        if self._ref is None or est.status != STATUS_TRACKED or poses_differ(
                self._ref[1], T, self.cfg.reference_translation_m, self.cfg.reference_rotation_deg):
            self._ref = (fp, T)
        # A frame placed frame-to-frame beyond the map becomes a keyframe at once; one that moved
        # becomes a keyframe when enough of it is new surface (covisibility); a conflicting one never.
        beyond_map = est.note == NOTE_FRAME_TO_FRAME
        new_surface = not (est.new_surface < KEYFRAME_MIN_NEW_SURFACE)  # NaN (unknown): new
        if self.builder is not None and est.note != NOTE_CONFLICT and (
                self._last_kf_pose is None or beyond_map
                or (new_surface and poses_differ(self._last_kf_pose, T, self.kf_t, self.kf_r))):
            self._integrate(index, fp, T)
            est.keyframe = True
            self._ref = (fp, T)

    def _coverage_map(self) -> CoverageMap:
        """The active map's coverage, seeded from its voxels (a saved or merged map) on first use."""
        if self._coverage is None:
            self._coverage = CoverageMap()
            self._coverage.add_voxels(self.builder)
        return self._coverage

    def _frame_points_world(self, fp, T: np.ndarray) -> np.ndarray:
        """``[M, 3]`` the frame's coarsest-level points at pose ``T`` (a few thousand)."""
        pts = fp.points(len(fp.depth) - 1).points_cam
        return pts @ T[:3, :3].T + T[:3, 3]

    def _new_surface(self, fp, T: np.ndarray) -> float:
        return self._coverage_map().new_share(self._frame_points_world(fp, T))

    def _integrate(self, index: int, fp, T: np.ndarray) -> None:
        depth = fp.depth[0]
        rgb = fp.rgb
        pts, cols = backproject(depth, rgb, self.camera, self.fusion_stride, *self.depth_range_m)
        if rgb is None:
            cols = np.full((len(pts), 3), 128, np.uint8)
        merge = cover = np.ones(len(pts), bool)
        if self.one_surface or self._saved_model is not None:
            unmapped, conflicting = point_relation(self.model, pts, T, self.camera)
            cover = ~conflicting  # seen: a surface the map holds is covered, not new
            # An extension merges only what its world lacks: a second look at a surface the world
            # holds, from a pose never better than the world's, would thicken it and tilt its normals.
            merge = unmapped if self._saved_model is not None else cover
            self.n_refused_points += int(len(merge) - merge.sum())
        pw = pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        self._coverage_map().add(pw[cover])
        if merge.any():
            self.builder.integrate(pw[merge], cols[merge])
            self.model = self._surfels.model()
            self._relocalizer = None  # its map features are stale now
        self.keyframe_indices.append(int(index))
        self.keyframe_poses.append(T.copy())
        self._last_kf_pose = T.copy()


def _better(a: TrackResult, b: TrackResult) -> bool:
    if a.ok != b.ok:
        return a.ok
    return a.inlier_fraction > b.inlier_fraction

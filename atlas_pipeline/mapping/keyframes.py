"""Mapping poses and keyframe selection by pose change (paper section 5.3)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.config import LocalizationConfig, MappingConfig
from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.geometry import invert_se3, rotation_angle_rad
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.perception.rgbd import FusedFrames, read_ahead
from atlas_pipeline.progress import Progress
from atlas_pipeline.safe_arrays import load_json_object_checked, load_npz_checked, save_npz_deterministic
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["KeyframeSet", "SlamResult", "select_keyframes", "slam_poses", "uses_ground_truth", "build_keyframes",
           "slam_keyframes"]


# Where mapping poses come from (KeyframeSet.pose_source, GaussianWorld.pose_source).
POSE_SOURCES = ("ground_truth", "estimated")
# keyframes.npz members: (dtype kinds, ndim) -- T_world_cam [N, 4, 4], valid [N], indices [K].
_KEYFRAME_MEMBERS = {"T_world_cam": ("f", 3), "valid": ("b", 1), "indices": ("iu", 1)}
# Fewer valid depth pixels than this: the frame cannot anchor the world (as the tracker's floor).
_MIN_ANCHOR_DEPTH_PIXELS = 200


def select_keyframes(T_world_cam: np.ndarray, valid: np.ndarray, translation_m: float,
                     rotation_deg: float) -> np.ndarray:
    """Indices of keyframes: the first valid frame, then every frame that moved more than
    ``translation_m`` or turned more than ``rotation_deg`` from the previous keyframe.

    Args:
        T_world_cam: ``[N, 4, 4]`` poses (rows where ``valid`` is False are ignored).
        valid: ``[N]`` bool, frames that have a pose.
    """
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return idx
    keys = [int(idx[0])]
    for i in idx[1:]:
        rel = invert_se3(T_world_cam[keys[-1]]) @ T_world_cam[i]
        moved = np.linalg.norm(rel[:3, 3])
        turned = np.degrees(rotation_angle_rad(rel[:3, :3]))
        if moved > translation_m or turned > rotation_deg:
            keys.append(int(i))
    return np.asarray(keys, dtype=np.int64)


@dataclass
class SlamResult:
    """What :func:`slam_poses` found.

    Attributes:
        T_world_cam: ``[N, 4, 4]`` poses in the frame of the main map (NaN where never placed;
            frames of a map never merged keep that map's own frame, seeded at the last placed pose).
        status: ``[N]`` per-frame status (:mod:`atlas_pipeline.localization.sequence`).
        valid: ``[N]`` frames placed in the main map (not lost, not in a map of their own).
        keyframe_indices: ``[K]`` keyframes of the main map, increasing.
        loop_closure: :meth:`LoopClosureResult.record`, or None when loop closure is off.
        maps: :meth:`SequenceTracker.map_record` plus ``main``, the main map's id.
        n_attempted: frames processed (fewer than N when a time budget stopped the run).
        time_s: wall time of tracking, mapping and loop closure (frame decoding included).
        tracker: the :class:`SequenceTracker` at the end (its active map), for benchmarks.
    """

    T_world_cam: np.ndarray
    status: list[str]
    valid: np.ndarray
    keyframe_indices: np.ndarray
    loop_closure: dict | None
    maps: dict
    n_attempted: int
    time_s: float
    tracker: object = None


def slam_poses(manifest: FrameManifest, mapping: MappingConfig, localization: LocalizationConfig,
               depth_range_m: tuple[float, float], fusion_stride: int,
               log: Callable[[str], None] | None = None, frames=None, budget_s: float | None = None,
               on_frame: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> SlamResult:
    """Track and map the sequence with no ground truth: frame-to-model RGB-D tracking against the
    keyframes merged so far (:class:`SequenceTracker`). The first frame with depth defines the
    world. After ``mapping.new_map_after_lost_frames`` lost frames a new map starts and is merged
    back when the place is recognised; the map with the most keyframes is the main one. With
    ``mapping.loop_closure``, loops between the main map's keyframes are then closed and every
    pose corrected (:func:`atlas_pipeline.mapping.loop_closure.close_loops`).

    Args:
        frames: optional ``[(rgb, depth_m)]`` already in memory (benchmarks: decoding not timed),
            the first frames of the sequence; by default frames are read one at a time.
        budget_s: stop tracking after this many seconds (benchmarks); ``n_attempted`` says where.
        on_frame: called with ``(index, rgb [H, W, 3], depth_m [H, W])`` of every frame before it
            is tracked, for work that needs the decoded frames too (:class:`FrameFuser`); on the
            reader thread when frames are read from disk (:func:`read_ahead`), in frame order, and
            then also for the frame or two read ahead when ``budget_s`` stops the pass early.
    """
    import time

    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.localization.sequence import STATUS_LOST, SequenceTracker

    t0 = time.perf_counter()
    n = manifest.n_frames
    poses = np.full((n, 4, 4), np.nan)
    map_ids = np.zeros(n, np.int64)
    status: list[str] = []
    st = SequenceTracker(manifest.camera, localization, depth_range_m, builder=VoxelGaussianBuilder(mapping.voxel_size_m),
                         keyframe_translation_m=mapping.keyframe_translation_m,
                         keyframe_rotation_deg=mapping.keyframe_rotation_deg, fusion_stride=fusion_stride,
                         new_map_after_lost_frames=mapping.new_map_after_lost_frames)
    progress = Progress("tracking and mapping", n, log)
    started = False
    # Frames given in memory (fewer than the sequence: a warm-up, the rest not attempted), or
    # read ahead from disk.
    source = (((i, *f) for i, f in enumerate(frames[:n])) if frames is not None
              else read_ahead(manifest, range(n), on_frame))
    try:
        for i, rgb, depth in source:
            if frames is not None and on_frame is not None:  # in memory (read from disk, the reader ran it)
                on_frame(i, rgb, depth)
            # The first frame with depth anchors the world at the identity.
            anchor = None if started or np.count_nonzero(depth) < _MIN_ANCHOR_DEPTH_PIXELS else np.eye(4)
            est = st.process(i, rgb, depth, T_given=anchor, timestamp_s=float(manifest.timestamps_s[i]),
                             colour_delay_s=manifest.colour_delay_s(i))
            started = started or anchor is not None
            poses[i], map_ids[i] = est.T_world_cam, est.map_id
            status.append(est.status)
            progress.update(extra=f"{est.status}, {len(st.keyframe_indices)} keyframes, map {st.map_id}")
            if budget_s is not None and time.perf_counter() - t0 > budget_s and i + 1 < n:
                logger.warning("%s: time budget of %.0f s spent after %d of %d frames; stopping", manifest.dataset,
                               budget_s, i + 1, n)
                break
    finally:
        source.close()  # waits for the reader thread: its on_frame is done before the caller cleans up
    n_done = len(status)
    status += ["not_attempted"] * (n - n_done)
    if not any(len(kf) for _, kf, _ in st.all_keyframes()):
        raise DatasetError(manifest.root, "tracking found no frame with valid depth to start the map")
    # Every pose into the frame of the map it ended in; the main map is the one with most keyframes.
    roots = np.full(n, -1, np.int64)
    for i in range(n_done):
        if np.isfinite(poses[i]).all():
            roots[i], poses[i] = st.to_root(int(map_ids[i]), poses[i])
    maps = st.all_keyframes()
    main_id, kf_idx, _ = max(maps, key=lambda m: (len(m[1]), -m[0]))
    record = {**st.map_record(), "main": int(main_id)}
    if len(maps) > 1:
        logger.warning("%s: %d maps were never merged; frames outside the main map (%d) are left out of the world",
                       manifest.dataset, len(maps) - 1, main_id)
    n_lost = status.count(STATUS_LOST)
    if n_lost:
        logger.warning("%s: %d of %d frames lost while tracking", manifest.dataset, n_lost, n)
    idx = np.asarray(kf_idx, np.int64)
    valid = (np.array([s not in (STATUS_LOST, "not_attempted") for s in status]) & (roots == main_id)
             & np.isfinite(poses).all(axis=(1, 2)))
    loops = None
    if mapping.loop_closure:
        from atlas_pipeline.mapping.loop_closure import close_loops

        lc = close_loops(manifest, poses, valid, idx, localization, depth_range_m, fusion_stride, mapping.voxel_size_m,
                         mapping.loop_min_keyframe_gap, mapping.loop_search_radius_m, probes=mapping.loop_probes,
                         log=log)
        poses = np.where(valid[:, None, None], lc.T_world_cam, poses)
        loops = lc.record()
    return SlamResult(poses, status, valid, idx, loops, record, n_done, time.perf_counter() - t0, st)


def uses_ground_truth(manifest: FrameManifest, cfg: MappingConfig) -> bool:
    """``auto`` maps with ground truth when at least half the frames have it (as the paper does)."""
    n_gt = int(manifest.has_gt.sum())
    use_gt = cfg.pose_source == "ground_truth" or (cfg.pose_source == "auto" and n_gt >= manifest.n_frames / 2)
    if use_gt and n_gt == 0:
        raise DatasetError(manifest.root, "mapping.pose_source is ground_truth but the dataset has no ground truth")
    return use_gt


@dataclass
class KeyframeSet:
    """Mapping poses of all frames and the chosen keyframes.

    Attributes:
        T_world_cam: ``[N, 4, 4]`` mapping pose per frame (NaN where unknown).
        valid: ``[N]`` bool, frames with a mapping pose.
        indices: ``[K]`` int64 keyframe indices, increasing.
        pose_source: ``ground_truth`` or ``estimated``.
        loop_closure: what loop closure did (:meth:`LoopClosureResult.record`: the loops, how far
            the trajectory moved), or None (ground truth, loop closure off, an older artifact).
        maps: the maps of the session (:attr:`SlamResult.maps`), or None (ground truth, older artifact).
    """

    T_world_cam: np.ndarray
    valid: np.ndarray
    indices: np.ndarray
    pose_source: str
    loop_closure: dict | None = None
    maps: dict | None = None

    def save(self, directory: Path) -> list[Path]:
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / "keyframes.npz"
        with atomic_path(path) as tmp:
            save_npz_deterministic(tmp, T_world_cam=self.T_world_cam, valid=self.valid, indices=self.indices)
        meta = write_json_atomic(directory / "keyframes.json", {
            "pose_source": self.pose_source, "n_frames": int(len(self.valid)),
            "n_keyframes": int(len(self.indices)), "indices": [int(i) for i in self.indices],
            **({} if self.loop_closure is None else {"loop_closure": self.loop_closure}),
            **({} if self.maps is None else {"maps": self.maps}),
        })
        return [path, meta]

    @classmethod
    def load(cls, directory: Path) -> "KeyframeSet":
        """Read :meth:`save`'s folder; arrays are checked (dtype, shape, finite poses where valid,
        increasing in-range indices) and a malformed file raises ``ArtifactError`` naming it."""
        path, meta_path = directory / "keyframes.npz", directory / "keyframes.json"
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: keyframes missing keyframes.npz or keyframes.json")
        meta = load_json_object_checked(meta_path)
        pose_source = meta.get("pose_source")
        if pose_source not in POSE_SOURCES:
            raise ArtifactError(f"{meta_path}: pose_source must be one of {list(POSE_SOURCES)}, got {str(pose_source)[:40]!r}")
        z = load_npz_checked(path, _KEYFRAME_MEMBERS, error_type=ArtifactError)
        T, valid, idx = z["T_world_cam"], z["valid"], z["indices"]
        n = len(valid)
        if T.shape != (n, 4, 4):
            raise ArtifactError(f"{path}: T_world_cam has shape {list(T.shape)}, expected [{n}, 4, 4] (one per frame)")
        if not np.isfinite(T[valid]).all():
            raise ArtifactError(f"{path}: T_world_cam has NaN or infinite values in a frame marked valid")
        if len(idx) and (idx.min() < 0 or int(idx.max()) >= n or (np.diff(idx.astype(np.int64)) <= 0).any()):
            raise ArtifactError(f"{path}: indices must be increasing frame indices in [0, {n})")
        loops = meta.get("loop_closure")  # optional: artifacts written before loop closure lack it
        if loops is not None and not isinstance(loops, dict):
            raise ArtifactError(f"{meta_path}: loop_closure must be an object, got {type(loops).__name__}")
        maps = meta.get("maps")  # optional: artifacts written before multiple maps lack it
        if maps is not None and not isinstance(maps, dict):
            raise ArtifactError(f"{meta_path}: maps must be an object, got {type(maps).__name__}")
        return cls(T.astype(np.float64), valid, idx.astype(np.int64), pose_source, loops, maps)


def build_keyframes(manifest: FrameManifest, fused: FusedFrames, cfg: MappingConfig,
                    localization: LocalizationConfig, log: Callable[[str], None] | None = None) -> KeyframeSet:
    """Mapping poses and keyframes: ground truth (selected by motion), or the tracker's own
    estimates and keyframes (``mapping.pose_source: estimated``, or ``auto`` without ground truth)."""
    if uses_ground_truth(manifest, cfg):
        poses, valid = manifest.T_world_cam_gt.copy(), manifest.has_gt.copy()
        idx = select_keyframes(poses, valid, cfg.keyframe_translation_m, cfg.keyframe_rotation_deg)
        if len(idx) == 0:
            raise DatasetError(manifest.root, "no frame has a pose to map with")
        return KeyframeSet(poses, valid, idx, "ground_truth")
    return slam_keyframes(slam_poses(manifest, cfg, localization, (fused.min_depth_m, fused.max_depth_m),
                                      fused.stride, log))


def slam_keyframes(slam: SlamResult) -> KeyframeSet:
    """The keyframe set of a SLAM run. The corrected poses (loop closure) are the mapping poses:
    build_world re-fuses the map from them."""
    return KeyframeSet(slam.T_world_cam, slam.valid, slam.keyframe_indices, "estimated", slam.loop_closure, slam.maps)

"""Localize every frame of a sequence against a Gaussian world (paper section 5.4, without ground truth).

Tracking is frame-to-model (:mod:`atlas_pipeline.localization.sequence`): each frame is aligned to
the world's surfels (geometry) and to a recent frame (appearance), starting from a constant-velocity
guess; poor alignments are marked lost and recovered by relocalization. Ground truth is never read
while estimating; it is used afterwards to grade (ATE and RPE, TUM conventions).

Fail fast: a sequence from another place than the world's (the wrong ``--input`` for a bundle) is
all lost, and each lost frame pays a global relocalization (seconds). :func:`localize_sequence`
therefore stops once the world evidently does not contain the frames (see
:data:`MISMATCH_WINDOW_FRAMES` and :data:`MISMATCH_MAX_LOST_RUN_FRAMES`): frames not reached get
status ``not_attempted``, and the report's ``summary["outcome"]`` says ``stopped_world_mismatch``
with a ``stopped_reason``. The report is still returned (and saves as valid JSON: unknown poses and
figures are written as ``null``), so callers keep what was done.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from atlas_pipeline.config import LocalizationConfig
from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.geometry import pose_from_tq, tq_from_pose
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.localization.metrics import (
    align_rigid,
    ate,
    pose_errors,
    read_tum_trajectory,
    rpe,
    write_tum_trajectory,
)
from atlas_pipeline.localization.sequence import (
    NOTE_NO_DEPTH,
    PLACED_STATUSES,
    STATUS_ANCHOR,
    STATUS_LOST,
    STATUS_NOT_ATTEMPTED,
    STATUS_RELOCALIZED,
    STATUS_TRACKED,
    FrameEstimate,
    SequenceTracker,
)
from atlas_pipeline.localization.places import PlaceIndex, place_index
from atlas_pipeline.localization.tracker import SurfelModel, pyramid_levels
from atlas_pipeline.perception.rgbd import read_ahead
from atlas_pipeline.progress import Progress
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.safe_arrays import load_json_object_checked

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.gaussian_world.builder import GaussianWorld

logger = logging.getLogger(__name__)

__all__ = ["LocalizationReport", "localize_sequence", "localize", "localize_visit", "tracking_map", "grade", "OUTCOME_COMPLETE", "OUTCOME_STOPPED_WORLD_MISMATCH",
           "MISMATCH_WINDOW_FRAMES", "MISMATCH_MAX_LOST_RUN_FRAMES"]

# summary["outcome"] of a report.
OUTCOME_COMPLETE = "complete"  # every frame was processed
OUTCOME_STOPPED_WORLD_MISMATCH = "stopped_world_mismatch"  # stopped early: the world does not contain the frames

# Fail fast, rule 1: stop when none of the first MISMATCH_WINDOW_FRAMES frames *tried* against the
# map (enough valid depth to align; a given anchor does not count, its pose says nothing about the
# map) was placed (tracked or relocalized). In a world that contains the sequence a tried frame is
# placed almost always (tracked from the anchor, or relocalized with no initial pose), so five
# failures in a row from the start are very unlikely by chance. In a world from another place every
# tried frame is lost and pays a global relocalization (seconds each), so 5 bounds a mismatched run
# to tens of seconds whatever the sequence length, and still tolerates a start on a few blurred or
# featureless frames.
MISMATCH_WINDOW_FRAMES = 5
# Fail fast, rule 2: stop when more than this many frames in a row are lost (of any kind, including
# frames with no valid depth, which rule 1 does not count because nothing was tried) and no frame
# has been placed since the start. One second at TUM's 30 fps: a recording whose depth stays
# unusable that long from the start cannot be told apart from one the world does not contain.
MISMATCH_MAX_LOST_RUN_FRAMES = 30


def _json_safe(v):
    """``v`` with non-finite floats as None and NumPy scalars as Python ones (dicts and lists recursed),
    so ``json.dumps(..., allow_nan=False)`` accepts it."""
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json_safe(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    return v


# Summary figures that are timings: kept in memory (and in Dagster's metadata), never saved.
TIMING_SUMMARY_KEYS = ("mean_time_per_frame_s", "frames_per_s")


@dataclass
class LocalizationReport:
    """Per-frame pose estimates of a sequence against a world, graded against ground truth.

    Attributes:
        timestamps_s: ``[N]``.
        T_world_cam: ``[N, 4, 4]`` estimates.
        status: ``N`` strings: ``anchor`` (the start pose), ``tracked``, ``relocalized``, ``lost``,
            ``not_attempted`` (the run stopped before it: NaN pose and figures).
        fitness: ``[N]`` share of frame points with a model correspondence (inlier fraction).
        inlier_rmse_m: ``[N]`` RMS point-to-plane residual of those correspondences.
        time_s: ``[N]`` seconds spent per frame (reading excluded).
        T_world_cam_gt: ``[N, 4, 4]`` ground truth, NaN where unknown.
        error_t_m, error_rot_deg: ``[N]`` per-frame errors after the ATE alignment, NaN without ground truth.
        summary: aggregate figures (RMSE, ATE, counts, rate), and ``outcome`` (``complete`` or
            ``stopped_world_mismatch``) with ``stopped_reason`` (None when complete).
        camera: the intrinsics the frames were read with (``CameraIntrinsics.to_dict()``); None in
            reports written before they were recorded (the file then has no ``camera``).
        recording: the recording the frames are (name, root, content_hash, n_frames, camera:
            :func:`atlas_pipeline.scene_memory.recordings.recording_record`), so a reader of the
            report finds its frames by content; None in reports written before it was recorded.
    """

    dataset: str
    map_id: str
    timestamps_s: np.ndarray
    T_world_cam: np.ndarray
    status: list[str]
    fitness: np.ndarray
    inlier_rmse_m: np.ndarray
    time_s: np.ndarray
    T_world_cam_gt: np.ndarray
    error_t_m: np.ndarray
    error_rot_deg: np.ndarray
    summary: dict = field(default_factory=dict)
    camera: dict | None = None
    recording: dict | None = None

    @property
    def n_frames(self) -> int:
        return len(self.timestamps_s)

    def to_json(self) -> dict:
        """The report as JSON-ready data: unknown poses (NaN rows) have ``position_xyz`` and
        ``quat_xyzw`` null, and every non-finite figure (per frame or in the summary) is null."""
        t, q = tq_from_pose(self.T_world_cam)
        known = np.isfinite(self.T_world_cam).all(axis=(1, 2))
        has_gt = np.isfinite(self.T_world_cam_gt).all(axis=(1, 2))

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        frames = []
        for i in range(self.n_frames):
            frames.append({
                "frame_id": i, "timestamp_s": float(self.timestamps_s[i]), "status": self.status[i],
                "position_xyz": [float(v) for v in t[i]] if known[i] else None,
                "quat_xyzw": [float(v) for v in q[i]] if known[i] else None,
                "fitness": num(self.fitness[i]), "inlier_rmse_m": num(self.inlier_rmse_m[i]),
                "time_s": num(self.time_s[i]), "has_ground_truth": bool(has_gt[i]),
                "error_t_m": num(self.error_t_m[i]), "error_rot_deg": num(self.error_rot_deg[i]),
            })
        out = {"dataset": self.dataset, "map_id": self.map_id}
        if self.camera is not None:
            out["camera"] = _json_safe(self.camera)
        if self.recording is not None:
            out["recording"] = _json_safe(self.recording)
        return {**out, "summary": _json_safe(self.summary), "frames": frames}

    def save(self, directory: Path) -> list[Path]:
        """Write the report; timings (``time_s`` per frame, the summary's rates) are not written:
        the files are what the run found, equal bytes for an equal result (``time_s`` loads as NaN)."""
        directory.mkdir(parents=True, exist_ok=True)
        content = self.to_json()
        for f in content["frames"]:
            del f["time_s"]
        content["summary"] = {k: v for k, v in content["summary"].items() if k not in TIMING_SUMMARY_KEYS}
        js = write_json_atomic(directory / "localization.json", content)
        est = write_tum_trajectory(directory / "trajectory_estimated.tum", self.timestamps_s, self.T_world_cam)
        gt = write_tum_trajectory(directory / "trajectory_groundtruth.tum", self.timestamps_s, self.T_world_cam_gt)
        png = directory / "trajectory_top.png"
        with atomic_path(png) as tmp:
            tmp.write_bytes(self.trajectory_plot_png())
        return [js, est, gt, png]

    @classmethod
    def load(cls, directory: Path) -> "LocalizationReport":
        path = directory / "localization.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: localization.json missing")
        d = load_json_object_checked(path)  # bounded size, an object, errors naming the file
        fr = d["frames"]
        # A null position or quaternion is an unknown pose: a NaN row (as estimated). Files written
        # before timings left the content have time_s per frame: still read.
        T = np.full((len(fr), 4, 4), np.nan)
        known = [i for i, f in enumerate(fr) if f.get("position_xyz") is not None and f.get("quat_xyzw") is not None]
        if known:
            T[known] = pose_from_tq(np.array([fr[i]["position_xyz"] for i in known], np.float64),
                                    np.array([fr[i]["quat_xyzw"] for i in known], np.float64))
        gt_path = directory / "trajectory_groundtruth.tum"
        T_gt = np.full((len(fr), 4, 4), np.nan)
        if gt_path.is_file():
            # Header only when no frame had ground truth (unknown poses are never written).
            gt_ts, gt_poses = read_tum_trajectory(gt_path)
            if len(gt_ts):
                ts = np.array([f["timestamp_s"] for f in fr])
                for t_gt, P in zip(gt_ts, gt_poses):
                    T_gt[int(np.argmin(np.abs(ts - t_gt)))] = P

        def arr(key: str) -> np.ndarray:
            return np.array([np.nan if f.get(key) is None else f[key] for f in fr], dtype=np.float64)

        return cls(d["dataset"], d["map_id"], np.array([f["timestamp_s"] for f in fr]), T,
                   [f["status"] for f in fr], arr("fitness"), arr("inlier_rmse_m"), arr("time_s"), T_gt,
                   arr("error_t_m"), arr("error_rot_deg"), d.get("summary") or {},
                   d["camera"] if isinstance(d.get("camera"), dict) else None,
                   d["recording"] if isinstance(d.get("recording"), dict) else None)

    def aligned_poses(self) -> np.ndarray:
        """``[N, 4, 4]`` estimates moved onto the ground truth's frame by the ATE alignment (as
        plotted and graded); the estimates themselves where there are fewer than 3 graded frames."""
        ok = (np.isfinite(self.T_world_cam).all(axis=(1, 2)) & np.isfinite(self.T_world_cam_gt).all(axis=(1, 2))
              & np.array([s != STATUS_ANCHOR for s in self.status]))
        if ok.sum() < 3:
            return self.T_world_cam.copy()
        return align_rigid(self.T_world_cam[ok], self.T_world_cam_gt[ok]) @ self.T_world_cam

    def trajectory_plot_png(self, title: str = "") -> bytes:
        """Top view of the (aligned) estimated trajectory against ground truth, as PNG bytes."""
        from atlas_pipeline.viz.plots import trajectory_png

        has_gt = np.isfinite(self.T_world_cam_gt).all(axis=(1, 2)).any()
        return trajectory_png(self.aligned_poses()[:, :3, 3], self.T_world_cam_gt[:, :3, 3] if has_gt else None,
                              title or f"{self.dataset}: top view")

    def pose_source_poses(self, source: str) -> np.ndarray:
        """``estimated`` or ``ground_truth`` poses ``[N, 4, 4]``."""
        return self.T_world_cam if source == "estimated" else self.T_world_cam_gt


class _MismatchGuard:
    """Watches the frames of one run, in the order processed, for evidence that the world does not
    contain them (rules 1 and 2 above); :meth:`stop_reason` is None while the run should go on."""

    def __init__(self, window_frames: int, max_lost_run: int):
        self.window = window_frames
        self.max_lost_run = max_lost_run
        self.n_placed = 0  # tracked or relocalized, with a finite pose
        self.n_tried = 0  # frames aligned against the map (not anchors, not frames without depth)
        self.n_no_depth = 0
        self.lost_run = 0

    def add(self, est: FrameEstimate) -> None:
        placed = est.status in PLACED_STATUSES and bool(np.isfinite(est.T_world_cam).all())
        self.n_placed += placed
        if est.status == STATUS_ANCHOR:
            return
        no_depth = est.status == STATUS_LOST and est.note == NOTE_NO_DEPTH
        self.n_no_depth += no_depth
        self.n_tried += not no_depth
        self.lost_run = 0 if placed else self.lost_run + 1

    def stop_reason(self) -> str | None:
        if self.n_placed:
            return None
        if self.n_tried >= self.window:
            return f"none of the first {self.n_tried} frames tried could be placed"
        if self.lost_run > self.max_lost_run:
            return (f"{self.lost_run} frames in a row were lost ({self.n_no_depth} without valid depth) "
                    "and none was placed")
        return None


def localize_sequence(
    manifest: FrameManifest,
    model: SurfelModel,
    cfg: LocalizationConfig,
    T_world_cam_start: np.ndarray | None,
    anchor_index: int = 0,
    map_id: str = "",
    depth_range_m: tuple[float, float] = (0.1, 4.0),
    prior_poses: np.ndarray | None = None,
    log: Callable[[str], None] | None = None,
    stop_on_mismatch: bool = True,
    places: PlaceIndex | None = None,
) -> LocalizationReport:
    """Track every frame of ``manifest`` against a fixed map ``model``.

    Args:
        T_world_cam_start: ``[4, 4]`` pose of frame ``anchor_index`` in the world (where this
            session starts), or None: the first frame is then relocalized with no initial pose.
            Every other pose is estimated from the images and the map only; ground truth is
            read afterwards, to grade.
        anchor_index: the frame tracking starts from (forward to the end, then backward).
        depth_range_m: depth readings used, ``(min, max)``; the fusion settings of the world.
        prior_poses: ``[K, 4, 4]`` viewpoints for relocalization (the map's keyframe poses).
        places: the world's stored place index over ``prior_poses`` (used where it still fits).
        stop_on_mismatch: stop early when the world evidently does not contain the frames
            (module docstring; :data:`MISMATCH_WINDOW_FRAMES`, :data:`MISMATCH_MAX_LOST_RUN_FRAMES`).

    Returns:
        The report, also when stopped early (never raises for that): the frames not reached have
        status ``not_attempted`` and NaN pose and figures; ``summary["outcome"]`` is
        ``complete`` or ``stopped_world_mismatch``, ``summary["stopped_reason"]`` a sentence (None
        when complete), ``summary["n_attempted"]`` / ``["n_not_attempted"]`` the frames processed
        or not.
    """
    n = manifest.n_frames
    if not 0 <= anchor_index < n:
        raise ValueError(f"anchor_index {anchor_index} outside 0..{n - 1}")
    if len(model) == 0:
        raise ValueError("cannot localize against an empty map")
    st = SequenceTracker(manifest.camera, cfg, depth_range_m, model=model, prior_poses=prior_poses, places=places)
    T_est = np.full((n, 4, 4), np.nan)
    fitness = np.full(n, np.nan)
    rmse = np.full(n, np.nan)
    times = np.full(n, np.nan)
    status: list[str] = [STATUS_NOT_ATTEMPTED] * n
    progress = Progress("localizing", n, log)
    counts = {STATUS_TRACKED: 0, STATUS_LOST: 0, STATUS_RELOCALIZED: 0}
    guard = _MismatchGuard(MISMATCH_WINDOW_FRAMES, MISMATCH_MAX_LOST_RUN_FRAMES)
    stopped: str | None = None
    n_attempted = 0
    no_depth: list[int] = []  # frames lost for want of any depth pixel (their transitions say no_depth)
    # Forward from the anchor, then backward for frames before it (a sequence whose first frames
    # precede the map's first keyframe). Only the frames in flight are held in memory.
    for order in (range(anchor_index, n), range(anchor_index - 1, -1, -1)):
        if len(order) == 0 or stopped is not None:
            continue
        if order.start != anchor_index:
            st.reset(anchor_index, T_est[anchor_index] if np.isfinite(T_est[anchor_index]).all() else None)
        for i, rgb, depth in read_ahead(manifest, order):
            given = T_world_cam_start if (i == anchor_index and T_world_cam_start is not None) else None
            est = st.process(i, rgb, depth, T_given=given, timestamp_s=float(manifest.timestamps_s[i]),
                             colour_delay_s=manifest.colour_delay_s(i))
            T_est[i], status[i] = est.T_world_cam, est.status
            fitness[i], rmse[i], times[i] = est.inlier_fraction, est.residual_m, est.time_s
            counts[est.status] = counts.get(est.status, 0) + 1
            n_attempted += 1
            if est.status == STATUS_LOST and est.note == NOTE_NO_DEPTH:
                no_depth.append(i)
            progress.update(extra=f"{counts[STATUS_LOST]} lost, {counts[STATUS_RELOCALIZED]} relocalized")
            guard.add(est)
            if stop_on_mismatch and (why := guard.stop_reason()) is not None:
                if T_world_cam_start is None:
                    start = "no start pose: relocalized"
                else:
                    start = "tracked from the given start pose" + (", then relocalized" if cfg.relocalize else "")
                stopped = (f"stopped localizing '{manifest.dataset}' in world '{map_id}' after {n_attempted} of {n} "
                           f"frames: {why} ({start}), so the world evidently does not contain this sequence; "
                           f"{n - n_attempted} frames not attempted")
                break

    summary, err_t, err_r = grade(manifest.timestamps_s, T_est, status, manifest.T_world_cam_gt)
    est_times = np.array([t for t, s in zip(times, status) if s != STATUS_ANCHOR and np.isfinite(t)])
    summary.update({
        "n_frames": n, "anchor_index": int(anchor_index), "start": "given" if T_world_cam_start is not None else "relocalized",
        "mean_time_per_frame_s": float(est_times.mean()) if len(est_times) else float("nan"),
        "outcome": OUTCOME_COMPLETE if stopped is None else OUTCOME_STOPPED_WORLD_MISMATCH,
        "stopped_reason": stopped, "n_attempted": n_attempted, "no_depth_frames": sorted(no_depth),
    })
    summary["frames_per_s"] = 1.0 / summary["mean_time_per_frame_s"] if summary["mean_time_per_frame_s"] > 0 else float("nan")
    logger.info("localized %s: %s", manifest.dataset, {k: round(v, 4) if isinstance(v, float) else v for k, v in summary.items()})
    if stopped is not None:
        logger.warning(stopped)
        if log is not None:
            log(stopped)
    elif summary["n_lost"] >= n - 1 and n > 1:
        logger.warning("%s: every frame after the first was lost; check the world and the dataset match", manifest.dataset)
    from atlas_pipeline.scene_memory.recordings import recording_record

    return LocalizationReport(manifest.dataset, map_id, manifest.timestamps_s.copy(), T_est, status,
                              fitness, rmse, times, manifest.T_world_cam_gt.copy(), err_t, err_r, summary,
                              camera=manifest.camera.to_dict(), recording=recording_record(manifest))


def grade(timestamps_s: np.ndarray, T_est: np.ndarray, status: list[str], T_gt: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
    """Counts, and where ground truth exists ATE (rigidly aligned, TUM conventions) and RPE per
    second over the placed frames (tracked or relocalized: a lost frame's pose is the motion
    model's guess, not an estimate; anchors are excluded too, their pose is given). Returns
    ``(summary, error_t_m [N], error_rot_deg [N])``, per-frame errors after the alignment."""
    n = len(timestamps_s)
    summary: dict = {
        "n_tracked": status.count(STATUS_TRACKED), "n_lost": status.count(STATUS_LOST),
        "n_relocalized": status.count(STATUS_RELOCALIZED), "n_not_attempted": status.count(STATUS_NOT_ATTEMPTED),
    }
    err_t = np.full(n, np.nan)
    err_r = np.full(n, np.nan)
    has_gt = np.isfinite(T_gt).all(axis=(1, 2))
    graded = has_gt & np.isfinite(T_est).all(axis=(1, 2)) & np.array([s in PLACED_STATUSES for s in status])
    summary["n_graded"] = int(graded.sum())
    if graded.sum() >= 3:
        a = ate(T_est[graded], T_gt[graded])
        err_t[graded], err_r[graded] = a["errors_t_m"], a["errors_rot_deg"]
        raw_t, raw_r = pose_errors(T_est[graded], T_gt[graded])
        r = rpe(timestamps_s[graded], T_est[graded], T_gt[graded], 1.0, "s")
        summary.update({
            "ate_rmse_m": a["rmse_m"], "ate_mean_m": a["mean_m"], "ate_median_m": a["median_m"],
            "ate_max_m": a["max_m"], "ate_rot_rmse_deg": a["rot_rmse_deg"],
            **({"ate_rot_note": a["rot_note"]} if a["rot_note"] else {}),  # why the figure is NaN
            # Without alignment: meaningful when the world shares the ground truth's frame.
            "rmse_t_unaligned_m": float(np.sqrt(np.mean(raw_t**2))),
            "rmse_rot_unaligned_deg": float(np.sqrt(np.mean(raw_r**2))),
            "rpe_trans_rmse_m_per_s": r["trans_rmse_m"], "rpe_rot_rmse_deg_per_s": r["rot_rmse_deg"],
            "rpe_n_pairs": r["n_pairs"],
        })
    return summary, err_t, err_r


def tracking_map(world: GaussianWorld) -> SurfelModel:
    """The ``SurfelModel`` localization tracks against: surfels from the voxel statistics (the
    fitted Gaussians render the images better but no longer mark the surface exactly), with the
    Gaussians' colours as its appearance (as a bundle reloaded gives it)."""
    from atlas_pipeline.localization.tracker import VoxelAppearance

    model = SurfelModel.from_builder(world.tracking_voxels)
    model.builder = None
    model.fixed = True
    model.appearance_map = VoxelAppearance.from_field(world.field, world.tracking_voxels.voxel_size_m)
    return model


def bundle_tracking_files(world: GaussianWorld, camera, cfg: LocalizationConfig) -> tuple[SurfelModel, PlaceIndex]:
    """What a world's bundle stores for later sessions: its tracking map (:func:`tracking_map`,
    ``surfels.npz``) and that map's place index seen from its keyframes (``places.npz``) at the
    level ``cfg``'s pyramids give for ``camera``."""
    model = tracking_map(world)
    return model, place_index(model, camera, pyramid_levels(cfg), world.T_world_cam_keyframes)


def localize_visit(manifest: FrameManifest, world: GaussianWorld, cfg: PipelineConfig,
                   log: Callable[[str], None] | None = None,
                   tracking: tuple[SurfelModel, PlaceIndex] | None = None) -> LocalizationReport:
    """A recording localized in a world it was not the first to build (a second visit): no start
    pose, its first frame relocalized, the world's keyframe poses as relocalization priors.
    Never stopped as a mismatch: the world was extended with these frames.

    ``tracking``: the world's :func:`bundle_tracking_files` when the caller already made them (a
    bundle about to be written), so the place index is rendered once."""
    model, places = tracking if tracking is not None else (tracking_map(world), None)
    return localize_sequence(
        manifest, model, cfg.localization, T_world_cam_start=None, anchor_index=0,
        map_id=world.map_id, depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
        prior_poses=world.T_world_cam_keyframes, log=log, stop_on_mismatch=False, places=places,
    )


def localize(manifest: FrameManifest, world: GaussianWorld, cfg: PipelineConfig,
             log: Callable[[str], None] | None = None) -> LocalizationReport:
    """The localization stage: track the sequence against its own world, starting at the world's
    first keyframe (whose pose the world defines), with the world's keyframe poses as
    relocalization priors. Never stopped as a mismatch: the world was built from these frames."""
    anchor = int(world.keyframe_indices[0])
    return localize_sequence(
        manifest, tracking_map(world), cfg.localization,
        T_world_cam_start=world.T_world_cam_keyframes[0], anchor_index=anchor, map_id=world.map_id,
        depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
        prior_poses=world.T_world_cam_keyframes, log=log, stop_on_mismatch=False,
    )

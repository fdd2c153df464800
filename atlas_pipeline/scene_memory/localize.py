"""A recording placed in a saved world (``atlas-gs localize``) and its transitions (``atlas-gs
log-transitions``), each written into the world's bundle. Whether the part may go into the bundle
(:func:`atlas_pipeline.scene_memory.bundle.check_bundle_update`) is decided before any frame is read."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.errors import AtlasError, ConfigError
from atlas_pipeline.localization.localizer import OUTCOME_COMPLETE, OUTCOME_STOPPED_WORLD_MISMATCH
from atlas_pipeline.localization.sequence import STATUS_ANCHOR, STATUS_NOT_ATTEMPTED
from atlas_pipeline.sensors.camera import TUM_CAMERAS, CameraIntrinsics
from atlas_pipeline.sensors.registry import DatasetEntry

if TYPE_CHECKING:
    import pyarrow as pa

    from atlas_pipeline.localization.localizer import LocalizationReport

__all__ = ["tracking_voxel_m", "localize_into_bundle", "log_bundle_transitions", "camera_difference",
           "check_camera", "check_start_pose", "world_camera"]

logger = logging.getLogger(__name__)


# Intrinsics of two calibrations that agree within these are one camera (recalibrations of one
# sensor differ by a few tenths of a percent in focal length and a pixel or two in the principal
# point); beyond them the recording was taken, or is read, with another camera.
CAMERA_FOCAL_REL_TOL = 0.01  # fx, fy
CAMERA_CENTRE_REL_TOL = 0.01  # cx, cy, as a share of the image width / height
CAMERA_DISTORTION_TOL = 1e-3  # each radial-tangential coefficient


def tracking_voxel_m(bundle: Any, cfg: PipelineConfig) -> float:
    """The map resolution a world was built at (the profile's where the bundle does not say)."""
    voxel = (bundle.metadata.get("gaussians") or {}).get("voxel_size_m")  # either may be null
    return float(voxel) if voxel is not None else float(cfg.mapping.voxel_size_m)


def _camera_name(camera: CameraIntrinsics) -> str:
    """``camera`` in words: the TUM preset it matches, its intrinsics and image size."""
    preset = next((name for name, c in TUM_CAMERAS.items() if name != "default" and camera_difference(c, camera) is None),
                  None)
    words = (f"fx {camera.fx:g} fy {camera.fy:g} cx {camera.cx:g} cy {camera.cy:g}, {camera.width}x{camera.height}"
             + (", with lens distortion" if camera.distortion else "")
             + (f", depth scale {camera.depth_scale:g}" if camera.depth_scale != TUM_CAMERAS["default"].depth_scale
                else ""))
    return f"{preset} ({words})" if preset else words


def camera_difference(world: CameraIntrinsics, recording: CameraIntrinsics) -> str | None:
    """What differs between the camera a world was recorded with and a recording's, beyond the
    tolerances above (image size, focal lengths, principal point, distortion, depth scale); None
    when they are one camera."""
    diffs = []
    if (world.width, world.height) != (recording.width, recording.height):
        diffs.append(f"image size {recording.width}x{recording.height} vs {world.width}x{world.height}")
    for name in ("fx", "fy"):
        a, b = getattr(world, name), getattr(recording, name)
        if abs(b - a) > CAMERA_FOCAL_REL_TOL * a:
            diffs.append(f"{name} {b:g} vs {a:g}")
    for name, size in (("cx", world.width), ("cy", world.height)):
        a, b = getattr(world, name), getattr(recording, name)
        if abs(b - a) > CAMERA_CENTRE_REL_TOL * size:
            diffs.append(f"{name} {b:g} vs {a:g}")
    n_k = max(len(world.distortion), len(recording.distortion))
    kw = list(world.distortion) + [0.0] * (n_k - len(world.distortion))
    kr = list(recording.distortion) + [0.0] * (n_k - len(recording.distortion))
    if any(abs(a - b) > CAMERA_DISTORTION_TOL for a, b in zip(kw, kr)):
        diffs.append("lens distortion")
    if not np.isclose(world.depth_scale, recording.depth_scale, rtol=1e-6):
        diffs.append(f"depth scale {recording.depth_scale:g} vs {world.depth_scale:g}")
    return ", ".join(diffs) if diffs else None


def world_camera(metadata: dict[str, Any]) -> CameraIntrinsics | None:
    """The camera the world's recording was taken with (metadata ``dataset.camera``); None for a
    world with no recording (imported) or none recorded. A camera that is no usable camera (a
    bundle written before cameras were checked for what they mean, or edited) is a warning naming
    metadata.json's field, and None: it is only ever compared, never used to read frames."""
    ds = metadata.get("dataset")
    cam = ds.get("camera") if isinstance(ds, dict) else None
    if cam is None:
        return None
    try:
        if not isinstance(cam, dict):
            raise ConfigError(f"must be an object, found {type(cam).__name__}")
        return CameraIntrinsics.from_dict(cam)
    except AtlasError as exc:
        logger.warning("metadata.json: field dataset.camera is not a usable camera (%s): the recording's camera is "
                       "not compared with the world's", exc)
        return None


def check_camera(metadata: dict[str, Any], entry_name: str, camera: CameraIntrinsics) -> str | None:
    """Warn, naming both cameras, when the recording ``entry_name``'s ``camera`` is not the one the
    world was recorded with (another sensor in the same place is legitimate; a wrong ``--camera``
    is not, and places every frame wrongly). Returns the sentence logged, None when they agree."""
    world = world_camera(metadata)
    diff = camera_difference(world, camera) if world is not None else None
    if diff is None:
        return None
    note = (f"'{entry_name}' is read with camera {_camera_name(camera)}, but this world was recorded with "
            f"{_camera_name(world)} ({diff}); if that is not another sensor in the same place, give the "
            "recording's own camera (--camera / --intrinsics)")
    logger.warning("%s", note)
    return note


def check_start_pose(T_world_cam: np.ndarray, field: Any, max_depth_m: float) -> None:
    """Refuse a ``--start-pose`` ``[4, 4]`` whose camera centre lies farther than ``max_depth_m``
    (the farthest depth reading used) from the bounding box of the world's Gaussians ``field``:
    from there no reading can land on the world, so no frame could be placed (and the pose would
    be written as the anchor's). A ConfigError naming --start-pose, before any frame is read."""
    centre = np.asarray(T_world_cam, np.float64)[:3, 3]
    lo, hi = field.positions.min(axis=0).astype(np.float64), field.positions.max(axis=0).astype(np.float64)
    distance_m = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - centre, centre - hi))))
    if distance_m > max_depth_m:
        box = " .. ".join("(" + ", ".join(f"{v:.2f}" for v in b) + ")" for b in (lo, hi))
        raise ConfigError(f"--start-pose: the camera centre ({', '.join(f'{v:g}' for v in centre)}) is {distance_m:.3g} m "
                          f"from the world (its Gaussians lie within {box} m), farther than the {max_depth_m:g} m "
                          "the depth readings reach (fusion.max_depth_m): no frame could be placed from there; "
                          "give a pose in or near the world, or --relocalize")


def _none_placed(report: LocalizationReport, name: str) -> str | None:
    """Why a localization that ran to its end still did not place the recording ``name``: no frame
    tracked or relocalized although some were tried (an anchor is given, not placed). None when a
    frame was placed or nothing could be tried."""
    s = report.summary
    if s.get("outcome", OUTCOME_COMPLETE) != OUTCOME_COMPLETE or s.get("n_tracked", 0) + s.get("n_relocalized", 0):
        return None
    no_depth = set(s.get("no_depth_frames") or ())
    tried = sum(1 for i, st in enumerate(report.status)
                if st not in (STATUS_ANCHOR, STATUS_NOT_ATTEMPTED) and i not in no_depth)
    if not tried:
        return None
    start = {"given": "started from the given pose", "relocalized": "no start pose: relocalized"}.get(
        s.get("start"), "started from the given pose")
    return (f"localized '{name}' in world '{report.map_id}': none of the {tried} frames tried could be placed "
            f"({start}), so the world evidently does not contain this recording, or not where it started")


def _own_recording(metadata: dict[str, Any], entry: DatasetEntry, manifest: Any) -> dict[str, Any] | None:
    """The world's record (its ``dataset`` or one of its ``recordings``) of the recording whose
    frames ``manifest`` holds (read from ``entry``), by content: the same frames, or the same
    recording read to another frame count (``dataset.max_frames``); None for any other recording
    and for a world with no recording. Names are never compared."""
    from atlas_pipeline.scene_memory.recordings import record_of_frames, recording_label

    recordings = metadata.get("recordings")
    records = [metadata.get("dataset"), *(recordings if isinstance(recordings, list) else ())]
    record, frames = record_of_frames(records, manifest, entry)
    if record is not None and frames is not manifest:
        logger.info("'%s' is the world's recording %s, read to %d of its frames where the world holds %s",
                    entry.name, recording_label(record), manifest.n_frames, record.get("n_frames"))
    return record


def localize_into_bundle(world: str | Path, entry: DatasetEntry, cfg: PipelineConfig,
                         start_pose: np.ndarray | None = None, relocalize: bool = False,
                         drop_transitions: bool = False) -> LocalizationReport:
    """Track ``entry``'s frames through the world bundle at ``world`` and write the report into it
    (``drop_transitions``: the transitions of an earlier report leave with it). The start is
    :func:`atlas_pipeline.scene_memory.metadata.start_pose`'s (``start_pose``: a given
    ``T_world_cam``, refused before any frame is read when it is far from the world). The world's
    own recordings (by content, never by name) are never a mismatch; another that stops matching
    the map ends early, and one of which no frame was placed ends the same way: the report says
    so (``summary["outcome"]``). A camera other than the world's is warned about and recorded
    (``report.camera``, ``summary["world_camera_differs"]``)."""
    from atlas_pipeline.io_utils import check_writable
    from atlas_pipeline.localization.localizer import localize_sequence
    from atlas_pipeline.memory_estimate import check_localization_memory
    from atlas_pipeline.scene_memory.bundle import (
        bundle_keyframe_poses,
        check_bundle_update,
        load_world_bundle,
        update_world_bundle,
    )
    from atlas_pipeline.scene_memory.metadata import start_pose as anchor_pose
    from atlas_pipeline.sensors.registry import load_dataset

    bundle = load_world_bundle(world)  # verifies every file the bundle lists, and its map id and count
    check_bundle_update(world, entry.name, bundle.map_id, drop_transitions=drop_transitions, meta=bundle.metadata)
    check_writable(Path(world).parent)
    if start_pose is not None:
        check_start_pose(start_pose, bundle.field, cfg.fusion.max_depth_m)
    manifest = load_dataset(entry, cfg)
    check_localization_memory(cfg, manifest, len(bundle.field))
    camera_note = check_camera(bundle.metadata, entry.name, manifest.camera)
    own = _own_recording(bundle.metadata, entry, manifest)
    T0, anchor = anchor_pose(bundle.metadata, entry.name, start_pose, relocalize=relocalize,
                             content_hash=own["content_hash"] if own else manifest.content_hash,
                             n_frames=manifest.n_frames)
    if anchor >= manifest.n_frames:
        raise ConfigError(f"anchor frame {anchor} is beyond the {manifest.n_frames} frames loaded")
    report = localize_sequence(manifest, bundle.tracking_model(tracking_voxel_m(bundle, cfg)), cfg.localization,
                               T0, anchor, bundle.map_id, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                               prior_poses=bundle_keyframe_poses(bundle.metadata), stop_on_mismatch=own is None,
                               places=bundle.stored_places(manifest.camera))
    if camera_note is not None:
        report.summary["world_camera_differs"] = camera_note
    if (why := _none_placed(report, entry.name)) is not None:
        logger.warning("%s", why)
        report.summary.update(outcome=OUTCOME_STOPPED_WORLD_MISMATCH, stopped_reason=why)
    update_world_bundle(world, localization=report, drop_transitions=drop_transitions)
    return report


def _localized_frames(world: Path, entry: DatasetEntry, cfg: PipelineConfig, report: LocalizationReport) -> Any:
    """The frames of ``entry`` (read with ``cfg``) that ``report`` (``world``'s localization.json)
    placed: the recording it names by content hash (read again at the report's frame count when
    ``dataset.max_frames`` gave another: the first frames of one recording), or, for a report that
    records none, the frames at its times. A ConfigError naming --input (and dataset.max_frames
    where the counts differ) for any other recording, before its ground truth could be used."""
    from atlas_pipeline.interop.frames import REPORT_TIME_TOLERANCE_S
    from atlas_pipeline.scene_memory.recordings import read_frames_at, record_of_frames
    from atlas_pipeline.sensors.registry import load_dataset

    manifest = load_dataset(entry, cfg)
    n = len(report.timestamps_s)
    spec = f"--input '{entry.name}' ({entry.path})"
    loaded = f"{manifest.n_frames} frames" + (f" (dataset.max_frames={cfg.dataset.max_frames})"
                                              if cfg.dataset.max_frames is not None else "")
    recount = f", nor when read to the report's {n} frames (as dataset.max_frames={n} would)" \
        if manifest.n_frames != n else ""
    where = world / "localization.json"
    want = (report.recording or {}).get("content_hash")
    if want:
        _, frames = record_of_frames([{**report.recording, "n_frames": n}], manifest, entry)
        if frames is not None and frames.n_frames == n:
            return frames
        raise ConfigError(f"{spec} holds other frames than {where} placed: content hash "
                          f"{manifest.content_hash[:12] or 'unknown'} of {loaded}, the report's {want[:12]} of {n}"
                          f"{recount}; ground truth would be another recording's: give the recording that was "
                          "localized as --input")
    frames = manifest if manifest.n_frames == n else read_frames_at(entry, n)
    # rtol 0: a relative tolerance of Unix times (~1.3e9 s) would let frames hours apart pass
    if frames.n_frames != n or not np.allclose(frames.timestamps_s, report.timestamps_s, rtol=0.0,
                                               atol=REPORT_TIME_TOLERANCE_S):
        raise ConfigError(f"{spec}: its {loaded} are not at the times of the {n} frames {where} placed{recount}; "
                          "ground truth would be another recording's: give the recording that was localized as "
                          "--input")
    return frames


def log_bundle_transitions(world: str | Path, entry: DatasetEntry, cfg: PipelineConfig) -> pa.Table:
    """Write ``transitions.parquet`` into the world bundle at ``world`` from the localization of
    ``entry`` it holds (ground-truth poses read again from the dataset when
    ``transitions.pose_source`` is ``ground_truth``: only from the frames the localization placed,
    :func:`_localized_frames`); returns the table. The count of Gaussians is ``gaussians.bin``'s
    after every file is verified (the world is not loaded); the map id is the verified report's,
    which must be the one metadata.json states."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import (check_bundle_update, read_metadata, update_world_bundle,
                                                    verified_gaussian_count)
    from atlas_pipeline.transition_log.transitions import log_transitions

    world = Path(world)
    meta = read_metadata(world)
    n_gaussians = verified_gaussian_count(world, meta)  # every file's checksum, then gaussians.bin's header
    if not (world / "localization.json").is_file():
        spec = entry.name if entry.source_file else entry.path
        raise ConfigError(f"{world}: no localization.json; run `atlas-gs localize --world {world} --input {spec}` first")
    report = LocalizationReport.load(world)
    if report.dataset != entry.name:
        raise ConfigError(f"{world}/localization.json is for dataset '{report.dataset}', not '{entry.name}'")
    check_bundle_update(world, transitions_of={"dataset": entry.name, "map_id": report.map_id}, meta=meta)
    if cfg.transitions.pose_source == "ground_truth":  # refresh GT from the dataset, not the report
        report.T_world_cam_gt = _localized_frames(world, entry, cfg, report).T_world_cam_gt
    table = log_transitions(report, entry.name, n_gaussians, cfg)
    update_world_bundle(world, transitions=table)
    return table

"""What a world bundle's ``metadata.json`` says beyond the files it lists: the dataset, the
Gaussians, the anchor (where a later session on the same sequence starts), the keyframes, the
config and the lineage (who made it, when, from what, extended from which bundle).

One lineage builder (:func:`bundle_lineage`) for every bundle the project writes (``atlas-gs
build`` / ``build --extend`` / ``import-ply`` and the Dagster ``world_bundle`` asset), and the
reading side of the anchor (:func:`start_pose`, what ``atlas-gs localize`` starts from).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.scene_memory.bundle import load_world_bundle, write_bundle_files

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.sensors.tum import FrameManifest

__all__ = ["WorldBundleArtifact", "bundle_metadata", "bundle_lineage", "start_pose", "world_recording"]

# The lineage keys every builder shares, in the order metadata.json lists them; provenance a
# caller adds (upstream data versions, code versions ...) follows them, and ``parent`` comes last.
_LINEAGE_ORDER = ("created_by", "partition", "run_id", "created_utc", "profile", "config_overrides")
_UNSET: Any = object()


def bundle_lineage(created_by: str | None = None, *, partition: str | None = _UNSET, run_id: str | None = _UNSET,
                   profile: str | None = _UNSET, config_overrides: dict[str, Any] | None = _UNSET,
                   parent: dict[str, Any] | None = None, created_utc: str | None = None,
                   **provenance: Any) -> dict[str, Any]:
    """``lineage`` of a bundle's metadata.json (what :func:`atlas_pipeline.scene_memory.bundle.read_lineage`
    and ``atlas-gs lineage`` read back).

    ``created_by`` names the command (None: a Dagster run, told by its ``run_id``); ``partition``,
    ``run_id``, ``profile`` and ``config_overrides`` are recorded when given (even as None);
    ``created_utc`` defaults to now (UTC, seconds); ``provenance`` (e.g. ``upstream``,
    ``code_versions``) is recorded as given; ``parent`` (see
    :func:`atlas_pipeline.scene_memory.bundle.parent_reference`) names the bundle this world was
    extended from, None for a world built from scratch.
    """
    given = {"created_by": created_by, "partition": partition, "run_id": run_id, "profile": profile,
             "config_overrides": config_overrides,
             "created_utc": created_utc or datetime.now(timezone.utc).isoformat(timespec="seconds")}
    lineage = {k: given[k] for k in _LINEAGE_ORDER
               if given[k] is not _UNSET and not (k == "created_by" and given[k] is None)}
    lineage.update(provenance)
    lineage["parent"] = parent
    return lineage


def bundle_metadata(name: str, partition: str, world: GaussianWorld, manifest: FrameManifest,
                    cfg: PipelineConfig, lineage: dict[str, Any] | None = None,
                    parent: dict[str, Any] | None = None) -> dict[str, Any]:
    """metadata.json content (beyond what the writer adds: map id, counts, checksums).

    ``lineage`` is best made by :func:`bundle_lineage`; ``parent`` (see
    :func:`atlas_pipeline.scene_memory.bundle.parent_reference`), when given, overrides its
    ``parent``: the bundle this world was extended from, recorded as ``lineage.parent``.
    """
    from atlas_pipeline.scene_memory.recordings import recording_index, recording_record, world_keyframe_recordings

    lineage = dict(lineage or {})
    if parent is not None or "parent" not in lineage:
        lineage["parent"] = parent
    recordings, keyframe_recording = world_keyframe_recordings(world, manifest)
    own = recording_index(recordings, recording_record(manifest))
    own_keyframes = [k for k, j in enumerate(keyframe_recording) if j == own]
    return {
        "name": name,
        "partition": partition,
        "dataset": {"name": manifest.dataset, "root": str(manifest.root), "n_frames": manifest.n_frames,
                    "content_hash": manifest.content_hash, "camera": manifest.camera.to_dict()},
        "gaussians": {"voxel_size_m": world.tracking_voxels.voxel_size_m, "isotropic": world.field.is_isotropic,
                      "n_keyframes": int(len(world.keyframe_indices)), "pose_source": world.pose_source},
        # Where a session on the same sequence starts: the first keyframe of this recording (an
        # extended world's first keyframes are frames of its parent's), with the recording's hash.
        "anchor": ({"frame_index": int(world.keyframe_indices[own_keyframes[0]]),
                    "timestamp_s": float(manifest.timestamps_s[world.keyframe_indices[own_keyframes[0]]]),
                    "T_world_cam": world.T_world_cam_keyframes[own_keyframes[0]].tolist(),
                    "content_hash": manifest.content_hash} if own_keyframes else None),
        # The recordings the keyframes are frames of (by content hash; name and root are hints).
        "recordings": recordings,
        # Viewpoints the world was mapped from: relocalization priors for later sessions; each a
        # frame of recordings[recording[k]].
        "keyframes": {"indices": [int(i) for i in world.keyframe_indices],
                      "T_world_cam": [T.tolist() for T in world.T_world_cam_keyframes],
                      "recording": [int(j) for j in keyframe_recording]},
        "config": cfg.to_dict(),
        "lineage": lineage,
    }


def _section(metadata: dict[str, Any], key: str) -> dict[str, Any] | None:
    """``metadata[key]`` when it is an object; None when absent, null (an imported world's
    ``dataset``) or of another type."""
    value = metadata.get(key)
    return value if isinstance(value, dict) else None


def world_recording(metadata: dict[str, Any], content_hash: str) -> dict[str, Any] | None:
    """The recording of the world with ``metadata`` whose frames have ``content_hash``
    (``FrameManifest.content_hash``): its ``dataset``, or one of its ``recordings`` (every
    recording an extended world was mapped from, where the bundle lists them). None for any other
    recording, for an empty hash (nothing to prove identity with), and for a world with no recording
    (imported from a PLY). Names are never compared: a copy under the world's name is another
    recording unless its content is the same."""
    if not content_hash:
        return None
    recordings = metadata.get("recordings")
    candidates = [metadata.get("dataset"), *(recordings if isinstance(recordings, list) else ())]
    for rec in candidates:
        if isinstance(rec, dict) and rec.get("content_hash") == content_hash:
            return rec
    return None


def _anchor_refused(metadata: dict[str, Any], dataset: str, content_hash: str) -> tuple[str, int] | None:
    """Why the world's anchor is no start for the recording ``dataset`` with ``content_hash``, and
    the level to log it at; None when the anchor is that recording's (its main ``dataset``, by
    content, and the anchor is in it)."""
    ds = _section(metadata, "dataset")
    if ds is None:
        return ("this world has no recording (imported from a PLY?), so no anchor: relocalizing the first frame "
                f"of '{dataset}' with no prior pose (--start-pose gives one)"), logging.WARNING
    anchor = _section(metadata, "anchor")
    if anchor is None:
        return f"this world records no anchor: relocalizing the first frame of '{dataset}'", logging.INFO
    world_hash = ds.get("content_hash") if isinstance(ds.get("content_hash"), str) else ""
    if not content_hash or content_hash != world_hash:
        if ds.get("name") == dataset:  # the name says "the same recording", the content does not
            return (f"'{dataset}' has the name of the recording this world was built from, but not its frames "
                    f"(content hash {content_hash[:16] or 'unknown'}, the world's {world_hash[:16] or 'unknown'}): "
                    "another recording (not the world's frames, nor their first ones, nor more of them), so the "
                    "world's anchor is no start for it; relocalizing its first frame"), logging.WARNING
        return (f"no start pose for '{dataset}' in this world (built from '{ds.get('name')}'): relocalizing its "
                "first frame"), logging.INFO
    # The anchor belongs to the recording it names; one that does not name it is the first
    # keyframe's, which in a world extended from another bundle lies in the parent's recording.
    anchor_hash = anchor.get("content_hash")
    extended = bool((_section(metadata, "lineage") or {}).get("parent"))
    if (isinstance(anchor_hash, str) and anchor_hash != content_hash) or (anchor_hash is None and extended):
        return (f"this world was extended from another bundle and its anchor is not recorded as a frame of "
                f"'{dataset}': relocalizing its first frame"), logging.INFO
    return None


def start_pose(metadata: dict[str, Any], dataset: str, T_world_cam: np.ndarray | None = None,
               relocalize: bool = False, content_hash: str = "",
               n_frames: int | None = None) -> tuple[np.ndarray | None, int]:
    """Where localizing the recording ``dataset`` (frames of ``content_hash``; ``n_frames`` of them
    loaded, None: not known) in the bundle with ``metadata`` starts: ``(T_world_cam, frame)``.

    A given ``T_world_cam`` (of frame 0); else, unless ``relocalize``, the bundle's anchor when the
    recording is provably the one the anchor is in (:func:`world_recording` of its main
    ``dataset``, by content: a recording under the same name with other frames is not; the same
    recording read to another frame count is, given as the content hash of the world's record it
    matched, :func:`atlas_pipeline.scene_memory.recordings.record_of_frames`) and the anchor's
    frame is one of the ``n_frames`` loaded; else nowhere (``None, 0``): the first frame is then
    relocalized in the world with no initial pose, and one line says why (a warning where a user
    may have expected the anchor: an imported world, a recording named as the world's but with
    other frames, an anchor beyond the frames loaded).
    """
    if T_world_cam is not None:
        return T_world_cam, 0
    log = logging.getLogger("atlas_pipeline")
    if relocalize:
        log.info("relocalizing the first frame of '%s' (asked for), not starting at the world's anchor", dataset)
        return None, 0
    refused = _anchor_refused(metadata, dataset, content_hash)
    if refused is not None:
        log.log(refused[1], "%s", refused[0])
        return None, 0
    anchor = _section(metadata, "anchor") or {}
    try:
        T_anchor = np.asarray(anchor.get("T_world_cam"), np.float64)
    except (TypeError, ValueError):
        T_anchor = np.zeros(0)
    frame = anchor.get("frame_index")
    if T_anchor.shape != (4, 4) or not np.isfinite(T_anchor).all():
        raise BundleFormatError("metadata.json", "field anchor.T_world_cam must be a finite 4x4 matrix")
    if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
        raise BundleFormatError("metadata.json", f"field anchor.frame_index must be a frame number >= 0, got {frame!r}")
    if n_frames is not None and frame >= n_frames:
        log.warning("the world's anchor is frame %d of '%s', beyond the %d frames loaded (dataset.max_frames): "
                    "relocalizing its first frame", frame, dataset, n_frames)
        return None, 0
    return T_anchor, frame


@dataclass
class WorldBundleArtifact:
    """Everything a world bundle persists; saving writes the section 8.3 layout."""

    field: GaussianField
    metadata: dict[str, Any]
    localization: LocalizationReport | None = None
    transitions: pa.Table | None = None
    surfels: Any = None  # SurfelModel: the tracking map saved beside the Gaussians
    places: Any = None  # PlaceIndex of the tracking map seen from the keyframes

    def save(self, directory: Path) -> list[Path]:
        return write_bundle_files(directory, self.field, self.metadata, self.localization, self.transitions,
                                  surfels=self.surfels, places=self.places)

    @classmethod
    def load(cls, directory: Path) -> "WorldBundleArtifact":
        b = load_world_bundle(directory, source="bin")
        return cls(b.field, b.metadata)


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

from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.scene_memory.bundle import load_world_bundle, write_bundle_files

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.sensors.tum import FrameManifest

__all__ = ["WorldBundleArtifact", "bundle_metadata", "bundle_lineage", "start_pose"]

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
    lineage = dict(lineage or {})
    if parent is not None or "parent" not in lineage:
        lineage["parent"] = parent
    return {
        "name": name,
        "partition": partition,
        "dataset": {"name": manifest.dataset, "root": str(manifest.root), "n_frames": manifest.n_frames,
                    "content_hash": manifest.content_hash, "camera": manifest.camera.to_dict()},
        "gaussians": {"voxel_size_m": world.tracking_voxels.voxel_size_m, "isotropic": world.field.is_isotropic,
                      "n_keyframes": int(len(world.keyframe_indices)), "pose_source": world.pose_source},
        # Where a session on the same sequence starts: the first keyframe's frame and pose.
        "anchor": {"frame_index": int(world.keyframe_indices[0]),
                   "timestamp_s": float(manifest.timestamps_s[world.keyframe_indices[0]]),
                   "T_world_cam": world.T_world_cam_keyframes[0].tolist()},
        # Viewpoints the world was mapped from: relocalization priors for later sessions.
        "keyframes": {"indices": [int(i) for i in world.keyframe_indices],
                      "T_world_cam": [T.tolist() for T in world.T_world_cam_keyframes]},
        "config": cfg.to_dict(),
        "lineage": lineage,
    }


def start_pose(metadata: dict[str, Any], dataset: str, T_world_cam: np.ndarray | None = None,
               relocalize: bool = False) -> tuple[np.ndarray | None, int]:
    """Where localizing ``dataset`` in the bundle with ``metadata`` starts: ``(T_world_cam, frame)``.

    A given ``T_world_cam`` (of frame 0), else the bundle's own anchor when the bundle was built
    from the same dataset (and ``relocalize`` is off), else nowhere (``None, 0``): the first frame
    is then relocalized in the world with no initial pose.
    """
    if T_world_cam is not None:
        return T_world_cam, 0
    anchor = metadata.get("anchor")
    if relocalize or metadata.get("dataset", {}).get("name") != dataset or anchor is None:
        logging.getLogger("atlas_pipeline").info(
            "no start pose for '%s' in this world (built from '%s'): relocalizing its first frame",
            dataset, metadata.get("dataset", {}).get("name"))
        return None, 0
    return np.asarray(anchor["T_world_cam"], np.float64), int(anchor["frame_index"])


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


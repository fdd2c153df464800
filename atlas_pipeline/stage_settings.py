"""The config fields each pipeline stage reads: the one place that decides what a change makes stale.

A stage's artifact depends on its inputs and exactly these settings; the orchestrator versions them
(``settings/<stage>`` in ``assets/versioning.py``), so a change recomputes the stages that read it
and what depends on their output, nothing else. A field a stage reads but this table does not list
would let a changed setting reuse a stale artifact: add it here with the code that reads it.
"""

from __future__ import annotations

import json
from typing import Any, NamedTuple

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.mapping.keyframes import uses_ground_truth
from atlas_pipeline.sensors.tum import FrameManifest

__all__ = ["STAGES", "REVISIT_STAGE", "StageReads", "STAGE_READS", "stage_settings"]


class StageReads(NamedTuple):
    """Dotted config paths a stage reads (a section, a sub-section or one field) and, among them,
    those it does not (a check threshold is not an input of the artifact)."""

    paths: tuple[str, ...]
    without: tuple[str, ...] = ()


REVISIT_STAGE = "revisit_bundle"  # a second visit's world, extending its first visit's
STAGES = ("raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report", "transitions",
          "demo_videos", "render_evaluation", "world_bundle", REVISIT_STAGE)  # in dependency order

_DEPTH_RANGE = ("fusion.min_depth_m", "fusion.max_depth_m")
_CHECK_THRESHOLDS = ("localization.max_ate_m",)  # a blocking check's bound: it versions nothing
# The tracker (SLAM) reads the localization settings; the map's own range and the fit are not its.
_TRACKING = ("mapping.pose_source", "mapping.voxel_size_m", "mapping.keyframe_translation_m",
             "mapping.keyframe_rotation_deg", "mapping.loop_closure", "mapping.loop_min_keyframe_gap",
             "mapping.loop_search_radius_m", "mapping.loop_probes", "mapping.new_map_after_lost_frames",
             "localization")
# Keyframes chosen by motion along ground-truth poses: no tracker.
_GROUND_TRUTH_KEYFRAMES = ("mapping.pose_source", "mapping.keyframe_translation_m", "mapping.keyframe_rotation_deg")
_WHOLE_CONFIG = ("dataset", "fusion", "mapping", "localization", "transitions", "video", "evaluation")

STAGE_READS: dict[str, StageReads] = {
    "raw_dataset": StageReads(("dataset",)),
    "fused_frames": StageReads(("fusion",)),
    "keyframes": StageReads(_TRACKING, _CHECK_THRESHOLDS),
    "gaussian_world": StageReads(("mapping.voxel_size_m", "mapping.max_depth_m", "mapping.noise_adaptive_cells",
                                  "mapping.fill_depth_holes", "mapping.colour_delay_compensation",
                                  "mapping.colour_refinement", "mapping.fit", *_DEPTH_RANGE)),
    "localization_report": StageReads(("localization", *_DEPTH_RANGE), _CHECK_THRESHOLDS),
    "transitions": StageReads(("transitions",)),
    # the orbit is planned on the map's voxel grid (viz/camera_paths.py)
    "demo_videos": StageReads(("video", "mapping.voxel_size_m")),
    # colour taken late is compared with a render at its own time (localization.colour_delay_compensation)
    "render_evaluation": StageReads(("evaluation", "localization.colour_delay_compensation", *_DEPTH_RANGE)),
    "world_bundle": StageReads(_WHOLE_CONFIG),  # its metadata.json holds the whole config
    REVISIT_STAGE: StageReads(_WHOLE_CONFIG),
}


def _leaves(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{dotted path: value}`` of every field, sub-sections flattened (``mapping.fit.epochs``)."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        if isinstance(v, dict):
            out.update(_leaves(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _under(path: str, prefixes: tuple[str, ...]) -> bool:
    return any(path == p or path.startswith(p + ".") for p in prefixes)


def stage_settings(cfg: PipelineConfig, stage: str, manifest: FrameManifest | None = None) -> dict[str, Any]:
    """``{dotted field: value}`` (JSON values: tuples are lists) of exactly the settings ``stage``
    reads (:data:`STAGE_READS`). ``keyframes`` reads the tracker's only when it tracks:
    :func:`~atlas_pipeline.mapping.keyframes.uses_ground_truth` of the dataset's ``manifest``, the
    stage's own rule (tracking assumed without one)."""
    reads = STAGE_READS[stage]
    if stage == "keyframes" and manifest is not None and uses_ground_truth(manifest, cfg.mapping):
        reads = StageReads(_GROUND_TRUTH_KEYFRAMES)
    leaves = _leaves(json.loads(json.dumps(cfg.model_dump(exclude={"profile"}))))
    return {k: v for k, v in leaves.items() if _under(k, reads.paths) and not _under(k, reads.without)}

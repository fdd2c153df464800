"""Compatibility re-exports: the pipeline's stage functions, artifact classes, video rendering and
bundle metadata now live in the modules that own them; import from there.

- ``load_dataset``: :mod:`atlas_pipeline.sensors.registry`
- ``fuse``: :mod:`atlas_pipeline.perception.rgbd`
- ``select_keyframes_stage``, ``build_gaussian_world``: :mod:`atlas_pipeline.mapping.mapper`
- ``localize``, ``tracking_map``: :mod:`atlas_pipeline.localization.localizer`
- ``evaluate_rendering``: :mod:`atlas_pipeline.gaussian_world.evaluation`
- ``log_transitions``: :mod:`atlas_pipeline.transition_log.transitions`
- ``DemoVideos`` and the video renderers: :mod:`atlas_pipeline.viz.demo`
- ``WorldBundleArtifact``, ``bundle_metadata`` (and ``bundle_lineage``): :mod:`atlas_pipeline.scene_memory.metadata`

Kept only so code written against ``atlas_pipeline.pipeline`` keeps working; nothing in the
project's own library, assets or CLI imports it.
"""

from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering
from atlas_pipeline.localization.localizer import localize, tracking_map
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
from atlas_pipeline.perception.rgbd import fuse
from atlas_pipeline.scene_memory.metadata import WorldBundleArtifact, bundle_metadata
from atlas_pipeline.sensors.registry import load_dataset
from atlas_pipeline.transition_log.transitions import log_transitions
from atlas_pipeline.viz.demo import (
    DemoVideos,
    _render_size,
    orbit_trajectory,
    render_demo_videos,
    render_side_by_side_video,
    render_video,
)

__all__ = [
    "load_dataset",
    "fuse",
    "select_keyframes_stage",
    "build_gaussian_world",
    "tracking_map",
    "localize",
    "log_transitions",
    "evaluate_rendering",
    "DemoVideos",
    "WorldBundleArtifact",
    "render_demo_videos",
    "render_video",
    "render_side_by_side_video",
    "orbit_trajectory",
    "bundle_metadata",
    "_render_size",
]

"""The pipeline's stages as plain functions: what each Dagster asset and each CLI command calls.

Each function takes the artifacts of the stages before it and one config section, and returns a
typed artifact. No orchestration here: ordering, caching and persistence belong to the caller.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.io_utils import write_json_atomic
from atlas_pipeline.localization.localizer import LocalizationReport, localize_sequence
from atlas_pipeline.mapping.keyframes import KeyframeSet, build_keyframes
from atlas_pipeline.mapping.mapper import build_world
from atlas_pipeline.perception.rgbd import FusedFrames, fuse_frames
from atlas_pipeline.scene_memory.bundle import load_world_bundle, write_bundle_files
from atlas_pipeline.sensors.registry import DatasetEntry, ensure_dataset_files, read_dataset_manifest
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.transition_log.transitions import build_transitions

logger = logging.getLogger(__name__)

LogFn = Callable[[str], None]

__all__ = [
    "load_dataset",
    "fuse",
    "select_keyframes_stage",
    "build_gaussian_world",
    "localize",
    "log_transitions",
    "evaluate_rendering",
    "DemoVideos",
    "WorldBundleArtifact",
    "render_demo_videos",
    "render_video",
    "orbit_trajectory",
    "bundle_metadata",
]


def load_dataset(entry: DatasetEntry, cfg: PipelineConfig, log: LogFn | None = None) -> FrameManifest:
    """Make the dataset's files exist (generate / download) and read its frame manifest, whatever
    the layout (TUM, 7-Scenes, Replica, ScanNet, bag: ``entry.kind``)."""
    root = ensure_dataset_files(entry, log)
    return read_dataset_manifest(entry, cfg.dataset.max_frames, root)


def fuse(manifest: FrameManifest, cfg: PipelineConfig, log: LogFn | None = None) -> FusedFrames:
    return fuse_frames(manifest, cfg.fusion, log)


def select_keyframes_stage(manifest: FrameManifest, fused: FusedFrames, cfg: PipelineConfig,
                           log: LogFn | None = None) -> KeyframeSet:
    return build_keyframes(manifest, fused, cfg.mapping, cfg.localization, log)


def build_gaussian_world(fused: FusedFrames, keyframes: KeyframeSet, cfg: PipelineConfig,
                         log: LogFn | None = None, manifest: FrameManifest | None = None) -> GaussianWorld:
    """Merge the keyframes into a world; with the sequence's ``manifest``, then fit it to the
    keyframe images: colours first (``mapping.colour_refinement_iterations``, cheap), then every
    Gaussian parameter against colour and depth (``mapping.optimization_epochs``)."""
    world = build_world(fused, keyframes, cfg.mapping, log)
    mc = cfg.mapping
    fit_colours = mc.colour_refinement_iterations > 0
    optimize = mc.optimization_epochs > 0
    if manifest is None or not len(world.field) or not (fit_colours or optimize):
        return world
    idx = [int(i) for i in world.keyframe_indices]
    images = [manifest.read_rgb(i) for i in idx]
    if fit_colours:
        from atlas_pipeline.gaussian_world.refine import refine_colours

        world.field = refine_colours(world.field, images, world.T_world_cam_keyframes, manifest.camera.K,
                                     mc.colour_refinement_iterations, mc.colour_refinement_scale, log)
    if optimize:
        from atlas_pipeline.gaussian_world.optimize import OptimizationSettings, optimize_gaussians

        lo, hi = cfg.fusion.min_depth_m, cfg.fusion.max_depth_m
        depths = []
        for i in idx:  # the depth the map was built from: the fusion range only
            d = manifest.read_depth_m(i, allow_empty=True)
            depths.append(np.where((d >= lo) & (d <= hi), d, 0.0))
        settings = OptimizationSettings(epochs=mc.optimization_epochs, max_steps=mc.optimization_max_steps,
                                        scale=mc.optimization_scale,
                                        depth_weight=mc.optimization_depth_weight)
        res = optimize_gaussians(world.field, images, depths, list(world.T_world_cam_keyframes), manifest.camera.K,
                                 settings, log)
        world.field = res.field
        world.fit = {"epochs": settings.epochs, "steps": int(len(res.loss)), "scale": settings.scale,
                     "loss_first_epoch": float(res.loss[: len(idx)].mean()),
                     "loss_last_epoch": float(res.loss[-min(len(idx), len(res.loss)):].mean()),
                     "n_pruned": res.n_pruned, "seconds": round(res.seconds, 2)}
    return world


def tracking_map(world: GaussianWorld):
    """The ``SurfelModel`` localization tracks against: surfels from the voxel statistics (the
    fitted Gaussians render the images better but no longer mark the surface exactly)."""
    from atlas_pipeline.localization.tracker import SurfelModel

    return SurfelModel.from_builder(world.builder)


def localize(manifest: FrameManifest, world: GaussianWorld, cfg: PipelineConfig,
             log: LogFn | None = None) -> LocalizationReport:
    """Track the sequence against its own world, starting at the world's first keyframe (whose
    pose the world defines), with the world's keyframe poses as relocalization priors."""
    anchor = int(world.keyframe_indices[0])
    return localize_sequence(
        manifest, tracking_map(world), cfg.localization,
        T_world_cam_start=world.T_world_cam_keyframes[0], anchor_index=anchor, map_id=world.map_id,
        depth_range_m=(cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
        prior_poses=world.T_world_cam_keyframes, log=log,
    )


def evaluate_rendering(manifest: FrameManifest, world: GaussianWorld, report: LocalizationReport,
                       cfg: PipelineConfig, log: LogFn | None = None):
    """Render the world at the estimated pose of held-out frames (not keyframes: they never fed the
    map) and compare with the real images (:mod:`atlas_pipeline.gaussian_world.evaluation`)."""
    from atlas_pipeline.gaussian_world.evaluation import evaluate_views

    held = np.setdiff1d(np.arange(manifest.n_frames), world.keyframe_indices)
    held = held[np.isfinite(report.T_world_cam[held]).all(axis=(1, 2))][:: cfg.evaluation.view_stride]
    if cfg.evaluation.max_views is not None:
        held = held[: cfg.evaluation.max_views]
    return evaluate_views(world.field, manifest, report.T_world_cam, held, "estimated", world.map_id,
                          (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m), log=log)


def log_transitions(report: LocalizationReport, partition: str, n_gaussians: int,
                    cfg: PipelineConfig) -> pa.Table:
    """Transitions from the estimated (default) or ground-truth trajectory of ``report``.

    Estimated rows carry the tracking status of their frames (which decides ``valid``: lost frames
    and relocalization jumps are not motions); ground-truth rows have none (status ``unknown``,
    validity from pose finiteness and time only).
    """
    source = cfg.transitions.pose_source
    poses = report.pose_source_poses(source)  # [N, 4, 4] T_world_cam
    if source == "ground_truth" and not np.isfinite(poses).all(axis=(1, 2)).any():
        raise DatasetError(partition, "transitions.pose_source is ground_truth but the dataset has no ground truth")
    if source == "estimated":
        # Frames before the anchor were tracked backwards from it (see localize_sequence).
        return build_transitions(partition, report.map_id, n_gaussians, report.timestamps_s, poses, source,
                                 list(report.status), int(report.summary.get("anchor_index", 0)))
    return build_transitions(partition, report.map_id, n_gaussians, report.timestamps_s, poses, source)


@dataclass
class DemoVideos:
    """The rendered demo videos (orbit, trajectory, and real | render side by side) and how they were made."""

    orbit: Path
    trajectory: Path
    n_orbit_frames: int
    n_trajectory_frames: int
    size: tuple[int, int]
    side_by_side: Path | None = None

    def save(self, directory: Path) -> list[Path]:
        """Move the videos into ``directory`` (same file system: a rename) and describe them."""
        out = []
        sources = set()
        for attr in ("orbit", "trajectory", "side_by_side"):
            src = getattr(self, attr)
            if src is None:
                continue
            dst = directory / src.name
            if src.resolve() != dst.resolve():
                sources.add(src.parent)
                shutil.move(str(src), dst)
            setattr(self, attr, dst)
            out.append(dst)
        for folder in sources:  # the render's scratch folder, now empty: leave nothing behind
            with contextlib.suppress(OSError):
                folder.rmdir()
        out.append(write_json_atomic(directory / "videos.json", {
            "orbit": self.orbit.name, "trajectory": self.trajectory.name,
            "side_by_side": self.side_by_side.name if self.side_by_side else None,
            "n_orbit_frames": self.n_orbit_frames, "n_trajectory_frames": self.n_trajectory_frames,
            "size": list(self.size), "codec": "h264", "pixel_format": "yuv420p",
        }))
        return out

    @classmethod
    def load(cls, directory: Path) -> "DemoVideos":
        path = directory / "videos.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: videos.json missing")
        d = json.loads(path.read_text())
        sbs = d.get("side_by_side")
        return cls(directory / d["orbit"], directory / d["trajectory"], int(d["n_orbit_frames"]),
                   int(d["n_trajectory_frames"]), tuple(d["size"]), directory / sbs if sbs else None)


@dataclass
class WorldBundleArtifact:
    """Everything a world bundle persists; saving writes the section 8.3 layout."""

    field: GaussianField
    metadata: dict[str, Any]
    localization: LocalizationReport | None = None
    transitions: pa.Table | None = None
    surfels: Any = None  # SurfelModel: the tracking map saved beside the Gaussians

    def save(self, directory: Path) -> list[Path]:
        return write_bundle_files(directory, self.field, self.metadata, self.localization, self.transitions,
                                  surfels=self.surfels)

    @classmethod
    def load(cls, directory: Path) -> "WorldBundleArtifact":
        b = load_world_bundle(directory, source="bin")
        return cls(b.field, b.metadata)


def _render_size(width: int, height: int, K: np.ndarray, scale: float) -> tuple[int, int, np.ndarray]:
    """Video size (even, for yuv420p) and the intrinsics scaled to it (pixel centres kept)."""
    from atlas_pipeline.gaussian_world.raster import scale_camera

    return scale_camera(K, width, height, scale, multiple=2)


def orbit_trajectory(field: GaussianField, cfg: PipelineConfig, T_world_cam_keyframes: np.ndarray | None = None,
                     *, camera_K: np.ndarray | None = None, image_size: tuple[int, int] | None = None) -> np.ndarray:
    """``[n, 4, 4]`` ``T_world_cam`` poses of the orbit video (``video.orbit_frames`` of them).

    Given the poses the world was recorded from (``[K, 4, 4]``: the keyframes, or the estimated
    trajectory; non-finite poses are skipped), the camera circles what they looked at, at their
    distance and height, over the directions the map supports (a full orbit or a back-and-forth
    arc), never inside or behind geometry; else it flies through them (see
    :func:`atlas_pipeline.viz.camera_paths.plan_camera_path`). Without them: a circle around the
    world's centre, each pose pulled in until it is in free space. ``camera_K`` / ``image_size``
    (the video's camera) set the field of view the checks use.
    """
    from atlas_pipeline.viz.camera_paths import plan_camera_path

    vc = cfg.video
    path = plan_camera_path(field, T_world_cam_keyframes, vc.orbit_frames, cfg.mapping.voxel_size_m, K=camera_K,
                            image_size=image_size, fallback_height_m=vc.orbit_height_m,
                            fallback_radius_scale=vc.orbit_radius_scale)
    logger.info("orbit video path: %s", path.summary())
    return path.T_world_cam


def render_video(field: GaussianField, poses_se3: np.ndarray, camera_K: np.ndarray, width: int, height: int,
                 cfg: PipelineConfig, path: Path, label: str, log: LogFn | None = None) -> tuple[int, tuple[int, int]]:
    """Render ``field`` from every finite pose of ``poses_se3`` ``[n, 4, 4]`` into an MP4 at ``path``."""
    from atlas_pipeline.gaussian_world.render import render_gaussians
    from atlas_pipeline.progress import Progress
    from atlas_pipeline.viz.video import write_mp4

    if len(field) == 0:
        raise ValueError("cannot render an empty world")
    w, h, K = _render_size(width, height, camera_K, cfg.video.scale)
    poses = poses_se3[np.isfinite(poses_se3).all(axis=(1, 2))]

    def frames():
        progress = Progress(f"rendering {label} video", len(poses), log)
        for T in poses:
            r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors,
                                 field.opacities, T, K, w, h)
            progress.update()
            yield r.rgb

    path.parent.mkdir(parents=True, exist_ok=True)
    return write_mp4(frames(), path, fps=cfg.video.fps), (w, h)


def render_side_by_side_video(field: GaussianField, manifest: FrameManifest, poses_se3: np.ndarray,
                              cfg: PipelineConfig, path: Path, log: LogFn | None = None) -> int:
    """MP4 of real frame | render from its estimated pose, for every frame with a finite pose,
    at the dataset's frame size (frames read one at a time)."""
    from atlas_pipeline.gaussian_world.render import render_gaussians
    from atlas_pipeline.progress import Progress
    from atlas_pipeline.viz.video import side_by_side, write_mp4

    if len(field) == 0:
        raise ValueError("cannot render an empty world")
    cam = manifest.camera
    idx = np.flatnonzero(np.isfinite(poses_se3).all(axis=(1, 2)))

    def frames():
        progress = Progress("rendering side-by-side video", len(idx), log)
        for i in idx:
            r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                                 poses_se3[i], cam.K, cam.width, cam.height)
            progress.update()
            yield side_by_side(manifest.read_rgb(int(i)), r.rgb)

    path.parent.mkdir(parents=True, exist_ok=True)
    return write_mp4(frames(), path, fps=cfg.video.fps)


def render_demo_videos(field: GaussianField, trajectory_se3: np.ndarray, camera_K: np.ndarray,
                       width: int, height: int, cfg: PipelineConfig, out_dir: Path, name: str,
                       log: LogFn | None = None, manifest: FrameManifest | None = None) -> DemoVideos:
    """Orbit (around what the recorded camera looked at, framed from where it stood: see
    :func:`orbit_trajectory`), trajectory (replay of the estimated poses) and, given the sequence's
    ``manifest``, real | render side by side along the trajectory."""
    orbit_path = out_dir / f"{name}_orbit.mp4"
    traj_path = out_dir / f"{name}_trajectory.mp4"
    orbit = orbit_trajectory(field, cfg, trajectory_se3, camera_K=camera_K, image_size=(width, height))
    n_orbit, size = render_video(field, orbit, camera_K, width, height, cfg, orbit_path, "orbit", log)
    n_traj, _ = render_video(field, trajectory_se3, camera_K, width, height, cfg, traj_path, "trajectory", log)
    sbs_path = None
    if manifest is not None:
        sbs_path = out_dir / f"{name}_side_by_side.mp4"
        render_side_by_side_video(field, manifest, trajectory_se3, cfg, sbs_path, log)
    return DemoVideos(orbit_path, traj_path, n_orbit, n_traj, size, sbs_path)


def bundle_metadata(name: str, partition: str, world: GaussianWorld, manifest: FrameManifest,
                    cfg: PipelineConfig, lineage: dict[str, Any] | None = None,
                    parent: dict[str, Any] | None = None) -> dict[str, Any]:
    """metadata.json content (beyond what the writer adds: map id, counts, checksums).

    ``parent`` (see :func:`atlas_pipeline.scene_memory.bundle.parent_reference`) names the bundle
    this world was extended from; it is recorded as ``lineage.parent``.
    """
    lineage = dict(lineage or {})
    if parent is not None or "parent" not in lineage:
        lineage["parent"] = parent
    return {
        "name": name,
        "partition": partition,
        "dataset": {"name": manifest.dataset, "root": str(manifest.root), "n_frames": manifest.n_frames,
                    "content_hash": manifest.content_hash, "camera": manifest.camera.to_dict()},
        "gaussians": {"voxel_size_m": world.builder.voxel_size_m, "isotropic": world.field.is_isotropic,
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

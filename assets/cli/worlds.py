"""Commands on world bundles: ``build``, ``import-ply``, ``demo-video``, ``export``, ``lineage``."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from assets.artifacts import world_bundle_folder
from assets.cli import options
from assets.cli.output import out
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.io_utils import check_output_file, check_writable, prepare_output_dir
from atlas_pipeline.sensors.camera import TUM_CAMERAS
from atlas_pipeline.sensors.registry import load_dataset

logger = logging.getLogger("atlas_gs.cli")

# The export summary's fields the command prints (those the format has).
EXPORT_SUMMARY_KEYS = ("format", "pose_source", "n_images", "n_points3D", "n_vertices", "n_triangles", "n_free",
                       "n_occupied")


def cmd_build(args: argparse.Namespace) -> int:
    """Build a world bundle from a recording, or keep mapping into an earlier bundle (``--extend``)."""
    from atlas_pipeline.localization.localizer import tracking_map
    from atlas_pipeline.mapping.mapper import build_gaussian_world, extend_saved_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.scene_memory.bundle import BUNDLE_KIND, load_world_bundle, parent_reference, write_world_bundle
    from atlas_pipeline.scene_memory.metadata import bundle_lineage, bundle_metadata

    cfg = options.config(args)
    entry = options.dataset(args)
    inputs = [entry.path, args.extend]
    output = prepare_output_dir(args.output, BUNDLE_KIND, inputs, args.force)
    if args.extend:
        load_world_bundle(args.extend)  # every listed file verified (world.npz, surfels.npz ...) before any work
    manifest = load_dataset(entry, cfg)
    fused = fuse(manifest, cfg)

    parent = None
    if args.extend:
        parent = parent_reference(args.extend)  # checks it is a bundle
        world, n_new_keyframes = extend_saved_world(args.extend, manifest, fused, cfg)
    else:
        keyframes = select_keyframes_stage(manifest, fused, cfg)
        world = build_gaussian_world(fused, keyframes, cfg, manifest=manifest)
        n_new_keyframes = len(keyframes.indices)
    lineage = bundle_lineage("atlas-gs build", partition=entry.name, run_id=None, profile=cfg.profile,
                             config_overrides=options.overrides(args), parent=parent)
    meta = bundle_metadata(entry.name, entry.name, world, manifest, cfg, lineage)
    write_world_bundle(output, world.field, meta, extras=(world,), surfels=tracking_map(world), inputs=inputs)
    logger.info("wrote world with %d Gaussians to %s", len(world.field), output)
    out(json.dumps({"world": str(output.resolve()), "n_gaussians": len(world.field),
                    "n_keyframes": int(n_new_keyframes), "map_id": world.map_id,
                    "parent": parent}, indent=2, default=str))
    return 0


def cmd_import_ply(args: argparse.Namespace) -> int:
    """A Gaussian-splat PLY made elsewhere (3DGS layout) as a world bundle this pipeline can
    localize in, relocalize against, render and extend."""
    from atlas_pipeline.interop.ply_import import import_gaussian_ply

    imported = import_gaussian_ply(args.ply, args.output, args.voxel, args.force)
    out(json.dumps({"world": str(imported.bundle.resolve()), "n_gaussians": imported.n_gaussians,
                    "anisotropic": imported.anisotropic, "sh_degree": imported.sh_degree}, indent=2))
    return 0


def cmd_demo_video(args: argparse.Namespace) -> int:
    """An MP4 of a world bundle: an orbit framed from where the recording camera stood, or the
    localized trajectory."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle
    from atlas_pipeline.sensors.camera import CameraIntrinsics
    from atlas_pipeline.viz.demo import orbit_trajectory, render_video
    from atlas_pipeline.viz.video import is_atlas_video

    cfg = options.config(args)
    video = Path(args.output).expanduser()
    if video.suffix.lower() != ".mp4":
        raise ConfigError(f"--output {args.output}: demo videos are MP4 files; give a name ending in .mp4")
    check_output_file(video, [args.world], args.force, is_ours=is_atlas_video)
    check_writable(video.parent)
    bundle = load_world_bundle(args.world)
    dataset = bundle.metadata.get("dataset") or {}
    cam = CameraIntrinsics.from_dict(dataset["camera"]) if "camera" in dataset else TUM_CAMERAS["default"]
    if args.mode == "trajectory":
        if not (Path(args.world) / "localization.json").is_file():
            raise ConfigError(f"{args.world}: trajectory mode needs localization.json; run `atlas-gs localize` first")
        poses = LocalizationReport.load(Path(args.world)).T_world_cam
        poses = poses[np.isfinite(poses).all(axis=(1, 2))]  # frames never placed have no pose to render from
        if len(poses) == 0:
            raise ConfigError(f"{args.world}/localization.json: no frame was placed in this world; nothing to render")
    else:
        poses = orbit_trajectory(bundle.field, cfg, bundle_keyframe_poses(bundle.metadata), camera_K=cam.K,
                                 image_size=(cam.width, cam.height))
    render_video(bundle.field, poses, cam.K, cam.width, cam.height, cfg, video, args.mode)
    out(json.dumps({"video": str(video.resolve()), "mode": args.mode}, indent=2))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """A world for other tools: a COLMAP model or nerfstudio transforms.json with the frames (GPU
    trainers), a TSDF mesh, or a ROS occupancy grid; the library decides what and how."""
    from atlas_pipeline.interop.exports import DEFAULT_POSES, check_format, write_export
    from atlas_pipeline.interop.frames import check_frame_step, check_pose_source, source_from_bundle
    from atlas_pipeline.interop.mesh import check_voxel
    from atlas_pipeline.interop.occupancy import check_resolution

    fmt = check_format(args.format)
    poses = check_pose_source(args.poses or DEFAULT_POSES[fmt])
    step = check_frame_step(args.frame_step)
    check_voxel(args.voxel)
    check_resolution(args.resolution)
    world = world_bundle_folder(args.world)
    dataset = options.dataset(args) if args.input else None
    prepare_output_dir(args.output, "export", [world, dataset.path if dataset else None], args.force)
    src = source_from_bundle(world, poses, dataset, step)
    summary = write_export(args.output, src, fmt, args.force, inputs=(world,), voxel_m=args.voxel,
                           resolution_m=args.resolution)
    out(json.dumps({"output": str(Path(args.output).expanduser().resolve()), "world": str(world.resolve()),
                    **{k: summary[k] for k in EXPORT_SUMMARY_KEYS if k in summary}}, indent=2))
    return 0


def cmd_lineage(args: argparse.Namespace) -> int:
    """Print the lineage of a world bundle (a folder, or a partition's Dagster bundle)."""
    from atlas_pipeline.scene_memory.bundle import format_lineage, read_lineage

    lin = read_lineage(world_bundle_folder(args.bundle))
    if not args.show_config and not args.json:
        lin = {k: v for k, v in lin.items() if k != "config"}
    out(json.dumps(lin, indent=2) if args.json else format_lineage(lin))
    return 0

"""Commands on world bundles: ``build``, ``import-ply``, ``demo-video``, ``export``, ``lineage``."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from assets.artifacts import world_bundle_folder
from assets.cli import options
from assets.cli.output import out
from atlas_pipeline.io_utils import prepare_output_dir

logger = logging.getLogger("atlas_gs.cli")

# The export summary's fields the command prints (those the format has).
EXPORT_SUMMARY_KEYS = ("format", "pose_source", "n_images", "n_points3D", "n_vertices", "n_triangles", "n_free",
                       "n_occupied")


def cmd_build(args: argparse.Namespace) -> int:
    """Build a world bundle from a recording, or keep mapping into an earlier bundle (``--extend``)."""
    from atlas_pipeline.scene_memory.build import build_world_bundle

    cfg = options.config(args)
    built = build_world_bundle(options.dataset(args), cfg, args.output, args.extend, args.force, options.overrides(args))
    logger.info("wrote world with %d Gaussians to %s", built.n_gaussians, built.path)
    out(json.dumps({"world": str(built.path.resolve()), "n_gaussians": built.n_gaussians,
                    "n_keyframes": built.n_keyframes, "map_id": built.map_id, "parent": built.parent},
                   indent=2, default=str))
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
    from atlas_pipeline.viz.demo import write_bundle_video

    video = write_bundle_video(args.world, options.config(args), args.output, args.mode, args.force)
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
    """Print the lineage of a world bundle (a folder, or a partition's Dagster bundle). Every
    listed file is verified and the map id and count are gaussians.bin's (read, not loaded); a
    bundle that does not verify still has its lineage printed, with one warning line per file or
    field at fault, and exits with EXIT_ERROR."""
    from assets.cli.output import EXIT_ERROR
    from atlas_pipeline.scene_memory.bundle import format_lineage, read_lineage

    lin = read_lineage(world_bundle_folder(args.bundle), verify=True, strict=False)
    if not args.show_config and not args.json:
        lin = {k: v for k, v in lin.items() if k != "config"}
    out(json.dumps(lin, indent=2) if args.json else format_lineage(lin))
    for problem in lin["problems"]:
        logger.warning("%s; the lineage above is as metadata.json states it", problem)
    return 0 if lin["verified"] else EXIT_ERROR

"""The ``atlas-gs`` argument parser: every command and its options in one place.

Options several commands share (the config, the camera of a folder ``--input``, the world and
recording a localization reads, a partition of the Dagster pipeline) are parent parsers, so that
each is defined, and documented, once.
"""

from __future__ import annotations

import argparse

from assets.cli.datasets import cmd_dataset
from assets.cli.localization import cmd_evaluate_trajectory, cmd_localize, cmd_log_transitions, cmd_relocalize
from assets.cli.pipeline import cmd_run, cmd_status, cmd_ui
from assets.cli.view import DEFAULT_VIEW_PORT, cmd_view
from assets.cli.worlds import cmd_build, cmd_demo_video, cmd_export, cmd_import_ply, cmd_lineage
from assets.launch import MAX_DEFAULT_CONCURRENCY

DEFAULT_UI_PORT = 3000  # dagster dev's own default
LOOPBACK = "127.0.0.1"
DEFAULT_IMPORT_VOXEL_M = 0.02
DEFAULT_MESH_VOXEL_M = 0.02
DEFAULT_OCCUPANCY_CELL_M = 0.05
TUM_MAX_DT_S = 0.02  # TUM's timestamp association tolerance
DEFAULT_RPE_DELTA_S = 1.0
SET_HELP = "override one config value, e.g. --set localization.photometric_weight=0.5"
FORCE_FOLDER_HELP = "move a foreign --output folder aside instead of refusing"


def _parent() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(add_help=False)


def _config_options(profile_help: str) -> argparse.ArgumentParser:
    """``--profile`` and ``--set``: the config a command runs with."""
    p = _parent()
    p.add_argument("--profile", default=None, help=profile_help)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help=SET_HELP)
    return p


def _camera_option() -> argparse.ArgumentParser:
    p = _parent()
    p.add_argument("--camera", default=None, help="camera preset for a folder --input (freiburg1/2/3, default)")
    return p


def _world_and_recording() -> argparse.ArgumentParser:
    """``--world`` and ``--input``: the bundle a recording is placed in, and the recording."""
    p = _parent()
    p.add_argument("--world", required=True)
    p.add_argument("--input", required=True)
    return p


def _partition_options() -> argparse.ArgumentParser:
    """The partition(s) of a Dagster command and the config its runs use."""
    p = _parent()
    p.add_argument("dataset", nargs="?", default="synthetic", help="partition (registered dataset), default synthetic")
    p.add_argument("--all", action="store_true", help="every registered dataset")
    p.add_argument("--profile", default=None, help="config profile for the run (default: $ATLAS_PROFILE, else default)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help=SET_HELP)
    return p


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="atlas-gs", description="Atlas-GS: RGB-D to a persistent 3D Gaussian world.")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="more output: library and Dagster log lines, Dagster's run events, warnings, debug")
    sub = p.add_subparsers(dest="cmd", required=True)
    library = [_config_options("config profile name (configs/NAME.yaml) or YAML path "
                               "(default: $ATLAS_PROFILE, else default)"), _camera_option()]
    localized = [*library, _world_and_recording()]
    partition = [_partition_options()]

    b = sub.add_parser("build", help="build a world bundle from a dataset", parents=library)
    b.add_argument("--input", required=True, help="registered dataset name or TUM-layout folder")
    b.add_argument("--output", required=True, help="world bundle folder to write (new, empty, or an earlier bundle)")
    b.add_argument("--force", action="store_true",
                   help="if --output is a folder atlas-gs did not write, move it aside (never deleted) instead of refusing")
    b.add_argument("--extend", default=None, metavar="BUNDLE",
                   help="keep mapping into the world of this earlier bundle, recorded as the lineage parent: "
                        "the first frame is relocalized in it, then frames are tracked and keyframes merged "
                        "(with mapping.pose_source ground_truth: merged at their ground-truth poses)")
    b.set_defaults(func=cmd_build)

    ip = sub.add_parser("import-ply", help="make a world bundle from a Gaussian-splat PLY (3DGS layout)")
    ip.add_argument("ply")
    ip.add_argument("--output", required=True, help="bundle folder to write (new, empty, or an earlier bundle)")
    ip.add_argument("--force", action="store_true", help=FORCE_FOLDER_HELP)
    ip.add_argument("--voxel", type=float, default=DEFAULT_IMPORT_VOXEL_M,
                    help=f"map resolution assumed when tracking against it (m), default {DEFAULT_IMPORT_VOXEL_M}")
    ip.set_defaults(func=cmd_import_ply)

    rl = sub.add_parser("relocalize", help="place frames in a saved world with no initial pose", parents=localized)
    rl.add_argument("--frame", type=int, action="append", default=[], help="frame index (repeatable; default: all)")
    rl.set_defaults(func=cmd_relocalize)

    ev = sub.add_parser("evaluate-trajectory", help="ATE and RPE of a TUM trajectory file against ground truth")
    ev.add_argument("estimated", help="TUM file: timestamp tx ty tz qx qy qz qw")
    ev.add_argument("groundtruth", help="TUM file, e.g. a dataset's groundtruth.txt")
    ev.add_argument("--max-dt", type=float, default=TUM_MAX_DT_S,
                    help=f"timestamp association tolerance (s), TUM's {TUM_MAX_DT_S}")
    ev.add_argument("--delta", type=float, default=DEFAULT_RPE_DELTA_S, help="RPE interval in seconds")
    ev.set_defaults(func=cmd_evaluate_trajectory)

    lo = sub.add_parser("localize", help="localize a dataset's frames against a world bundle", parents=localized)
    lo.add_argument("--start-pose", default=None, help="'tx ty tz qx qy qz qw' of the first frame in the world")
    lo.add_argument("--relocalize", action="store_true",
                    help="ignore the world's anchor: find the first frame's pose by relocalization")
    lo.add_argument("--drop-transitions", action="store_true",
                    help="remove the bundle's transitions.parquet of another dataset (refused otherwise)")
    lo.set_defaults(func=cmd_localize)

    t = sub.add_parser("log-transitions", help="write transitions.parquet into a localized world bundle",
                       parents=localized)
    t.set_defaults(func=cmd_log_transitions)

    d = sub.add_parser("demo-video", help="render an orbit or trajectory MP4 of a world bundle", parents=library)
    d.add_argument("--world", required=True)
    d.add_argument("--output", required=True, help="MP4 file to write (new, or a video atlas-gs wrote)")
    d.add_argument("--force", action="store_true", help="move a foreign --output file aside instead of refusing")
    d.add_argument("--mode", choices=["orbit", "trajectory"], default="orbit")
    d.set_defaults(func=cmd_demo_video)

    r = sub.add_parser("run", help="materialize a dataset partition through Dagster (current artifacts are reused)",
                       parents=partition)
    r.add_argument("--stale-only", action="store_true",
                   help="materialize only the stale or missing assets (nothing when all are current)")
    r.add_argument("--json", action="store_true",
                   help="print the result as JSON (the default when stdout is not a terminal)")
    r.add_argument("--concurrency", type=int, default=None, metavar="N",
                   help=f"with --all: partitions run at a time, each in its own process (default: the cores, "
                        f"at most {MAX_DEFAULT_CONCURRENCY}; 1: one after another)")
    r.add_argument("--executor", default=None, choices=["in_process", "multiprocess", "dask"],
                   help="where a run's steps execute (default: $ATLAS_EXECUTOR, else in_process)")
    r.add_argument("--dask-scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="with --executor dask: the scheduler of a running cluster (default: "
                        "$ATLAS_DASK_SCHEDULER, else a local cluster started for the run)")
    r.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="which assets of a partition are stale or missing, and why", parents=partition)
    st.add_argument("--json", action="store_true", help="machine-readable: {partition: {asset: [reasons]}}")
    st.set_defaults(func=cmd_status)

    ex = sub.add_parser("export", help="a world for other tools: COLMAP / nerfstudio (GPU trainers), a mesh, an "
                                       "occupancy grid", parents=[_camera_option()])
    ex.add_argument("world", help="world bundle folder, or a partition name (its Dagster world bundle)")
    ex.add_argument("--format", required=True, choices=["colmap", "nerfstudio", "mesh", "occupancy"])
    ex.add_argument("--output", required=True, help="folder to write (new, empty, or an export atlas-gs wrote)")
    ex.add_argument("--force", action="store_true", help=FORCE_FOLDER_HELP)
    ex.add_argument("--poses", default=None, choices=["auto", "keyframes", "estimated", "ground_truth"],
                    help="which frames at which poses (default: auto for colmap/nerfstudio -- the localization's "
                         "placed frames if the bundle has one, else the keyframes; keyframes for mesh/occupancy)")
    ex.add_argument("--input", default=None, help="the frames' recording (registered name or folder), when the "
                                                  "bundle's own dataset is elsewhere")
    ex.add_argument("--frame-step", type=int, default=1, help="export every N-th of those frames (default 1)")
    ex.add_argument("--voxel", type=float, default=DEFAULT_MESH_VOXEL_M,
                    help=f"mesh: TSDF voxel size in metres (default {DEFAULT_MESH_VOXEL_M})")
    ex.add_argument("--resolution", type=float, default=DEFAULT_OCCUPANCY_CELL_M,
                    help=f"occupancy: cell size in metres (default {DEFAULT_OCCUPANCY_CELL_M})")
    ex.set_defaults(func=cmd_export)

    li = sub.add_parser("lineage", help="print the lineage of a world bundle")
    li.add_argument("bundle", help="bundle folder, or a partition name (its Dagster world bundle)")
    li.add_argument("--json", action="store_true", help="machine-readable JSON (includes the resolved config)")
    li.add_argument("--show-config", action="store_true", help="also print the resolved config")
    li.set_defaults(func=cmd_lineage)

    dataset_parsers = _add_dataset_commands(sub)

    ui = sub.add_parser("ui", help="start the Dagster web UI (dagster dev) with the project's DAGSTER_HOME")
    ui.add_argument("--host", default=LOOPBACK)
    ui.add_argument("--port", type=int, default=DEFAULT_UI_PORT)
    ui.set_defaults(func=cmd_ui)

    _add_view_command(sub)
    # -v after the command too (`atlas-gs run synthetic -v`); SUPPRESS keeps a -v given before it
    for sp in [*sub.choices.values(), *dataset_parsers]:
        sp.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="more output (as before the command)")
    return p


def _add_dataset_commands(sub) -> list[argparse.ArgumentParser]:
    """``dataset list | sync | show | fetch | add``; returns the subcommands' parsers."""
    ds = sub.add_parser("dataset", help="list, show or register datasets (partitions)")
    dsub = ds.add_subparsers(dest="dataset_cmd", required=True)
    dsub.add_parser("list", help="registered datasets")
    sy = dsub.add_parser("sync", help="which registered datasets (or NAMES) are partitions and why the others are "
                                      "not; nothing to do before Dagster's own commands (the definitions read the "
                                      "registry as they load)")
    sy.add_argument("names", nargs="*")
    sh = dsub.add_parser("show", help="one dataset's registry entry")
    sh.add_argument("name")
    fe = dsub.add_parser("fetch", help="download a preset's frames (or generate a synthetic dataset), making it a "
                                       "partition; a preset is not a partition before this (or its first run)")
    fe.add_argument("name")
    add = dsub.add_parser("add", help="register a recording (TUM, 7-Scenes, Replica, ScanNet folder or a "
                                      "ROS/RealSense bag) as a dataset (adds a partition)")
    add.add_argument("name")
    add.add_argument("path", help="the recording's folder, or a .bag file")
    add.add_argument("--kind", default=None, choices=["tum", "7scenes", "replica", "scannet", "bag"],
                     help="layout (default: detected from the folder)")
    add.add_argument("--camera", default=None,
                     help="camera preset: freiburg1/2/3, default, 7scenes, replica (default: the kind's preset; "
                          "ScanNet and bags read theirs)")
    add.add_argument("--intrinsics", default=None, help="'fx fy cx cy' instead of a preset")
    add.add_argument("--width", type=int, default=None, help="with --intrinsics (default: the kind's preset, 640)")
    add.add_argument("--height", type=int, default=None, help="with --intrinsics (default: the kind's preset, 480)")
    add.add_argument("--depth-scale", type=float, default=None,
                     help="raw depth units per metre, with --intrinsics (default: the kind's, TUM 5000)")
    add.add_argument("--fps", type=float, default=None, help="frame rate of 7-Scenes / Replica / ScanNet (default 30)")
    add.add_argument("--sequence", default=None, help="7-Scenes: the seq-XX folder when PATH is the scene folder")
    add.add_argument("--rgb-topic", default=None, help="bag: colour topic (default: detected)")
    add.add_argument("--depth-topic", default=None, help="bag: depth topic (default: detected)")
    add.add_argument("--replace", action="store_true",
                     help="re-point an already registered name (a preset or a local entry) at this folder")
    ds.set_defaults(func=cmd_dataset)
    return list(dsub.choices.values())


def _add_view_command(sub) -> argparse.ArgumentParser:
    """``view WORLD``: the browser viewer, or a Rerun recording (``--rrd``)."""
    v = sub.add_parser(
        "view", help="look around a world bundle in the browser: Gaussians, trajectories, keyframes (viser)")
    v.add_argument("world", metavar="WORLD", help="bundle folder, or a partition name (its Dagster world bundle)")
    v.add_argument("--port", type=int, default=DEFAULT_VIEW_PORT,
                   help=f"port to serve on (default {DEFAULT_VIEW_PORT}; 0: any free port; a taken port moves to "
                        "the next free one); the URL is printed")
    v.add_argument("--host", default=LOOPBACK,
                   help="loopback address to bind: 127.0.0.1 (default), ::1 or localhost. The viewer has no "
                        "login, so it is never bound to other interfaces; from another machine use "
                        "ssh -L PORT:127.0.0.1:PORT")
    v.add_argument("--report", default=None, metavar="PATH",
                   help="folder with a localization.json to show (default: the bundle's own, e.g. after "
                        "`atlas-gs localize`; for a partition, its localization report)")
    v.add_argument("--no-dataset", action="store_true",
                   help="do not read the dataset's frames: keyframe frusta without images, ground truth "
                        "only from the report")
    v.add_argument("--layers", nargs="+", default=[], metavar="DIR",
                   help="export folders with the mesh and occupancy layers to show (`atlas-gs export --format "
                        "mesh|occupancy --output DIR`; default for a partition: its world_mesh and occupancy_map)")
    v.add_argument("--no-layers", action="store_true",
                   help="do not compute the mesh and occupancy layers from the keyframes when no folder has them")
    v.add_argument("--rrd", default=None, metavar="FILE.rrd",
                   help="write a Rerun recording instead of serving: the Gaussians, trajectories, keyframes, "
                        "and per frame the pose, RGB, depth and tracking status (open with `rerun FILE.rrd`)")
    v.add_argument("--frame-step", type=int, default=1, metavar="N", help="--rrd: every N-th frame (default 1)")
    v.add_argument("--force", action="store_true", help="--rrd: replace an existing recording")
    v.set_defaults(func=cmd_view)
    return v

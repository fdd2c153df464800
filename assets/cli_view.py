"""``atlas-gs view WORLD``: the interactive browser viewer of a world bundle.

The command is wired into :func:`assets.cli.build_parser` with ``add_view_command(sub)``; the viewer
itself is :mod:`atlas_pipeline.viz.viewer` (library, no Dagster).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from atlas_pipeline.errors import ConfigError

logger = logging.getLogger("atlas_gs.cli")

# viser's own default port; a taken port is not an error (the next free one is used and named).
DEFAULT_VIEW_PORT = 8080


def _resolve_world(spec: str) -> tuple[Path, Path | None]:
    """``(bundle folder, default report folder or None)`` for WORLD: a bundle folder, or a partition
    name (its Dagster world bundle, as ``atlas-gs lineage`` resolves it)."""
    from atlas_pipeline.sensors.registry import validate_dataset_name

    target = Path(spec).expanduser()
    if target.is_dir():
        return target, None
    from assets.io_managers import artifacts_root

    name = validate_dataset_name(spec)
    root = artifacts_root()
    target = root / "world_bundle" / name
    if not target.is_dir():
        raise ConfigError(f"'{spec}' is neither a bundle folder nor a partition with a world bundle "
                          f"(looked in {target}; `atlas-gs run {name}` makes one)")
    # The partition's bundle carries its localization; the report artifact is the fallback.
    report = root / "localization_report" / name
    return target, (report if (report / "localization.json").is_file() else None)


def cmd_view(args: argparse.Namespace) -> int:
    """Serve the viewer of a world bundle until Ctrl-C; prints the URL to open."""
    from atlas_pipeline.viz.viewer import run_viewer

    if not getattr(args, "verbose", False):
        # websockets logs every browser connection at INFO; the URL line is what the user needs.
        logging.getLogger("websockets").setLevel(logging.WARNING)
    world, partition_report = _resolve_world(args.world)
    report: Path | None = Path(args.report).expanduser() if args.report else None
    if report is None and not (world / "localization.json").is_file():
        report = partition_report
    if args.rrd:
        return _write_rrd(args, world, report)
    return run_viewer(world, host=args.host, port=args.port, report=report, read_dataset=not args.no_dataset,
                      announce=lambda line: print(line, flush=True))


def _write_rrd(args: argparse.Namespace, world: Path, report: Path | None) -> int:
    """``--rrd FILE``: a Rerun recording instead of the browser viewer. An existing FILE is replaced
    only with ``--force`` and only when it is a Rerun recording (never a user's other file)."""
    try:
        from atlas_pipeline.viz.rerun_export import export_rerun
    except ImportError as exc:  # optional: the [rerun] extra
        raise ConfigError(f"--rrd needs the Rerun SDK ({exc}); install it with pip install 'atlas-gs[rerun]'") from None
    out = Path(args.rrd).expanduser()
    if out.suffix != ".rrd":
        raise ConfigError(f"--rrd {out}: the file name must end in .rrd")
    if not out.parent.is_dir():
        raise ConfigError(f"--rrd {out}: folder {out.parent} does not exist")
    if out.exists():
        if not args.force:
            raise ConfigError(f"--rrd {out} exists; give --force to replace it")
        if not out.is_file() or out.read_bytes()[:4] != RRD_MAGIC:
            raise ConfigError(f"--rrd {out} exists and is not a Rerun recording: not replaced")
    export_rerun(world, out, report=report, read_dataset=not args.no_dataset, frame_step=args.frame_step)
    print(out.resolve(), flush=True)
    return 0


RRD_MAGIC = b"RRF2"  # first bytes of a Rerun recording file (checked before --force replaces one)


def add_view_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``view`` to the ``atlas-gs`` subcommands (``subparsers`` of :func:`assets.cli.build_parser`)."""
    v = subparsers.add_parser(
        "view", help="look around a world bundle in the browser: Gaussians, trajectories, keyframes (viser)")
    v.add_argument("world", metavar="WORLD", help="bundle folder, or a partition name (its Dagster world bundle)")
    v.add_argument("--port", type=int, default=DEFAULT_VIEW_PORT,
                   help=f"port to serve on (default {DEFAULT_VIEW_PORT}; 0: any free port; a taken port moves to "
                        "the next free one); the URL is printed")
    v.add_argument("--host", default="127.0.0.1",
                   help="loopback address to bind: 127.0.0.1 (default), ::1 or localhost. The viewer has no "
                        "login, so it is never bound to other interfaces; from another machine use "
                        "ssh -L PORT:127.0.0.1:PORT")
    v.add_argument("--report", default=None, metavar="PATH",
                   help="folder with a localization.json to show (default: the bundle's own, e.g. after "
                        "`atlas-gs localize`; for a partition, its localization report)")
    v.add_argument("--no-dataset", action="store_true",
                   help="do not read the dataset's frames: keyframe frusta without images, ground truth "
                        "only from the report")
    v.add_argument("--rrd", default=None, metavar="FILE.rrd",
                   help="write a Rerun recording instead of serving: the Gaussians, trajectories, keyframes, "
                        "and per frame the pose, RGB, depth and tracking status (open with `rerun FILE.rrd`)")
    v.add_argument("--frame-step", type=int, default=1, metavar="N", help="--rrd: every N-th frame (default 1)")
    v.add_argument("--force", action="store_true", help="--rrd: replace an existing recording")
    v.set_defaults(func=cmd_view)
    return v

"""``atlas-gs view WORLD``: the interactive browser viewer of a world bundle.

The viewer itself is :mod:`atlas_pipeline.viz.viewer` (library, no Dagster); a Rerun recording
instead of it is :mod:`atlas_pipeline.viz.rerun_export`.
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
    name (its Dagster world bundle, whose localization report is the fallback report)."""
    from assets.artifacts import partition_report_folder, world_bundle_folder

    world = world_bundle_folder(spec)
    if Path(spec).expanduser().is_dir():
        return world, None
    return world, partition_report_folder(world.name)


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
    layers = [Path(d).expanduser() for d in args.layers]
    if not layers and not Path(args.world).expanduser().is_dir():
        # A partition: its own mesh and occupancy artifacts, where its exports job made them.
        from assets.io_managers import artifacts_root

        layers = [d for d in (artifacts_root() / a / world.name for a in ("world_mesh", "occupancy_map")) if d.is_dir()]
    return run_viewer(world, host=args.host, port=args.port, report=report, read_dataset=not args.no_dataset,
                      announce=lambda line: print(line, flush=True), layers=layers,
                      compute_layers=not args.no_layers)


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

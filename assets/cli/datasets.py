"""``dataset list | show | add | fetch | sync``: the registry of recordings (one partition each)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from assets.cli.output import EXIT_ERROR, out
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import (
    availability,
    dataset_on_disk,
    ensure_dataset_files,
    intrinsics_camera,
    load_registry,
    local_registry_path,
    not_on_disk_reason,
    recording_kind,
    register_local_dataset,
    registered_entries,
    registered_entry,
)


def _list(args: argparse.Namespace) -> int:
    for name, e in load_registry().items():
        out(f"{name:24s} {e.kind:10s} {availability(e):22s} {e.path}")
    return 0


def _show(args: argparse.Namespace) -> int:
    out(json.dumps(registered_entry(args.name).describe(), indent=2))
    return 0


def _fetch(args: argparse.Namespace) -> int:
    entry = registered_entry(args.name)
    was_there = dataset_on_disk(entry) and entry.path.exists()
    path = ensure_dataset_files(entry)  # generates a synthetic one, downloads a preset (progress bar)
    # On disk now: a partition of the definitions as they load from now on (assets.definitions).
    out(json.dumps({"dataset": entry.name, "path": str(path), "fetched": not was_there,
                    "partition_added": dataset_on_disk(entry)}, indent=2))
    return 0


def _add(args: argparse.Namespace) -> int:
    path = Path(args.path).expanduser()
    kind = recording_kind(path, args.kind)
    camera: Any = args.camera  # None: the kind's preset (TUM default, 7scenes, replica) or the data's own
    given = [o for o, v in (("--width", args.width), ("--height", args.height), ("--depth-scale", args.depth_scale))
             if v is not None]
    if given and not args.intrinsics:  # a preset's size and depth scale are its own: never ignored silently
        raise ConfigError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} used only with --intrinsics "
                          "(a camera preset has its own image size and depth scale); give --intrinsics "
                          "'fx fy cx cy' too, or leave them out")
    if args.intrinsics and args.camera:
        raise ConfigError("give --camera (a preset) or --intrinsics (your own), not both")
    if args.intrinsics:
        camera = intrinsics_camera(kind, args.intrinsics, args.width, args.height, args.depth_scale)
    params = {"fps": args.fps, "sequence": args.sequence, "rgb_topic": args.rgb_topic,
              "depth_topic": args.depth_topic}
    entry = register_local_dataset(args.name, path, camera, replace=args.replace, kind=kind,
                                   params={k: v for k, v in params.items() if v is not None})
    out(json.dumps({"registered": entry.describe(), "registry": str(local_registry_path()),
                    "partition_added": entry.name}, indent=2))
    return 0


def _sync(args: argparse.Namespace) -> int:
    """Which datasets are partitions and why the others are not; nothing to do before Dagster's own
    commands (the definitions read the registry as they load), kept for scripts."""
    reg = load_registry()
    entries = registered_entries(args.names or list(reg), reg)
    out(json.dumps({
        "partitions": [e.name for e in entries if dataset_on_disk(e)],
        "not_partitions": {e.name: not_on_disk_reason(e) for e in entries if not dataset_on_disk(e)},
    }, indent=2))
    return 0


DATASET_COMMANDS = {"list": _list, "show": _show, "fetch": _fetch, "add": _add, "sync": _sync}


def cmd_dataset(args: argparse.Namespace) -> int:
    command = DATASET_COMMANDS.get(args.dataset_cmd)
    return command(args) if command else EXIT_ERROR

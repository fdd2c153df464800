"""What the parsed options mean to the library: the config, the ``--set`` overrides, the dataset
an ``--input`` names, numbers given as one option value, the output format."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from atlas_pipeline.config import PipelineConfig, load_profile, parse_set_overrides
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.geometry import pose_from_tq
from atlas_pipeline.sensors.registry import DatasetEntry, dataset_from_spec

MIN_QUATERNION_NORM = 1e-9  # below this a --start-pose quaternion has no direction


def overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The ``--set KEY=VALUE`` items, parsed and checked (a bad item fails naming it)."""
    return parse_set_overrides(getattr(args, "set", None), "--set")


def config(args: argparse.Namespace) -> PipelineConfig:
    """The profile (``--profile``, else ``$ATLAS_PROFILE``, else default) with the ``--set`` overrides."""
    from assets.resources import resolve_profile

    cfg = load_profile(resolve_profile(args.profile))
    items = overrides(args)
    return cfg.with_overrides(items, "--set") if items else cfg


def dataset(args: argparse.Namespace) -> DatasetEntry:
    """The recording ``--input`` names (a registered dataset or a folder), with ``--camera``."""
    return dataset_from_spec(args.input, args.camera)


def numbers(text: str, n: int, option: str, names: str) -> list[float]:
    """``n`` finite numbers from a space-separated option value, or a ConfigError naming the option."""
    parts = str(text).replace(",", " ").split()
    if len(parts) != n:
        raise ConfigError(f"{option} needs {n} numbers ({names}), got {len(parts)}: {text!r}")
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        raise ConfigError(f"{option} needs {n} numbers ({names}), got {text!r}") from None
    if not all(np.isfinite(vals)):
        raise ConfigError(f"{option}: every number must be finite, got {text!r}")
    return vals


def start_pose(args: argparse.Namespace) -> np.ndarray | None:
    """``--start-pose`` as a 4x4 ``T_world_cam``, or None; where localization then starts is
    :func:`atlas_pipeline.scene_memory.metadata.start_pose`'s decision."""
    if not args.start_pose:
        return None
    vals = numbers(args.start_pose, 7, "--start-pose", "tx ty tz qx qy qz qw")
    if np.linalg.norm(vals[3:]) < MIN_QUATERNION_NORM:
        raise ConfigError("--start-pose: the quaternion qx qy qz qw has zero length")
    return pose_from_tq(np.array(vals[:3]), np.array(vals[3:]))


def json_output(args: argparse.Namespace) -> bool:
    """JSON for ``--json``, and for a stdout that is not a terminal (scripts, pipes); words for a
    person at a terminal."""
    return bool(getattr(args, "json", False)) or not sys.stdout.isatty()

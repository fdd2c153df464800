"""World bundles (paper section 8.3): a folder that persists one world across sessions.

::

    <bundle>/
      metadata.json        what, from where, how (lineage, config, file checksums)
      gaussians.ply        3DGS-layout PLY for other tools
      gaussians.bin        ATLASGS1 binary for fast reload
      localization.json    per-frame poses and errors (optional)
      transitions.parquet  state-action-state log (optional)

The folder is written under a temporary name and swapped into place whole, so a reader never sees
a bundle whose files disagree with each other.
"""

from __future__ import annotations

import datetime as _dt
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

import numpy as np

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.io_utils import atomic_dir, sha256_file, write_json_atomic
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.localization.metrics import write_tum_trajectory
from atlas_pipeline.scene_memory.binary import read_atlasgs1, write_atlasgs1
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply
from atlas_pipeline.transition_log.transitions import write_transitions

__all__ = [
    "BUNDLE_FORMAT", "WorldBundle", "write_world_bundle", "update_world_bundle", "load_world_bundle",
    "read_metadata", "copy_bundle", "write_bundle_files",
]

BUNDLE_FORMAT = "atlas-gs-world-bundle"
BUNDLE_VERSION = 1


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _write_parts(directory: Path, localization: LocalizationReport | None, transitions: pa.Table | None) -> None:
    if localization is not None:
        write_json_atomic(directory / "localization.json", localization.to_json())
        write_tum_trajectory(directory / "trajectory_estimated.tum", localization.timestamps_s, localization.T_world_cam)
    if transitions is not None:
        write_transitions(transitions, directory / "transitions.parquet")


def _file_table(directory: Path) -> dict[str, dict[str, Any]]:
    return {
        p.name: {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
        for p in sorted(directory.iterdir())
        if p.is_file() and p.name != "metadata.json" and not p.name.startswith(".")
    }


def write_bundle_files(
    directory: Path,
    field: GaussianField,
    metadata: dict[str, Any],
    localization: LocalizationReport | None = None,
    transitions: pa.Table | None = None,
) -> list[Path]:
    """Write a bundle's files into an existing (empty, temporary) folder; returns the paths."""
    write_gaussian_ply(field, directory / "gaussians.ply")
    write_atlasgs1(field, directory / "gaussians.bin")
    _write_parts(directory, localization, transitions)
    meta = {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "created_at": _utc_now(),
        "map_id": field.content_hash()[:16],
        "n_gaussians": len(field),
        **metadata,
        "files": _file_table(directory),
    }
    write_json_atomic(directory / "metadata.json", meta)
    return sorted(p for p in directory.iterdir() if p.is_file() and not p.name.startswith("."))


def write_world_bundle(
    directory: str | Path,
    field: GaussianField,
    metadata: dict[str, Any],
    localization: LocalizationReport | None = None,
    transitions: pa.Table | None = None,
) -> Path:
    """Write a complete bundle folder atomically; ``metadata`` (name, lineage, config ...) goes
    into metadata.json."""
    directory = Path(directory)
    with atomic_dir(directory) as tmp:
        write_bundle_files(tmp, field, metadata, localization, transitions)
    return directory


def update_world_bundle(directory: str | Path, localization: LocalizationReport | None = None,
                        transitions: pa.Table | None = None) -> Path:
    """Add or replace the localization or transitions of an existing bundle (CLI sessions)."""
    directory = Path(directory)
    meta = read_metadata(directory)
    _write_parts(directory, localization, transitions)
    meta["files"] = _file_table(directory)
    meta["updated_at"] = _utc_now()
    write_json_atomic(directory / "metadata.json", meta)
    return directory


def read_metadata(directory: Path) -> dict[str, Any]:
    path = directory / "metadata.json"
    if not path.is_file():
        raise BundleFormatError(directory, "not a world bundle (metadata.json missing)")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise BundleFormatError(path, f"invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if meta.get("format") != BUNDLE_FORMAT:
        raise BundleFormatError(path, f"format is {meta.get('format')!r}, expected {BUNDLE_FORMAT!r}")
    return meta


@dataclass
class WorldBundle:
    """A loaded bundle: the Gaussians and the metadata."""

    directory: Path
    field: GaussianField
    metadata: dict[str, Any]

    @property
    def map_id(self) -> str:
        return self.metadata.get("map_id", "")


def bundle_keyframe_poses(metadata: dict[str, Any]) -> np.ndarray:
    """``[K, 4, 4]`` poses the world was mapped from (metadata ``keyframes``), empty when absent;
    used as viewpoint priors for relocalization."""
    kf = metadata.get("keyframes") or {}
    poses = np.asarray(kf.get("T_world_cam", []), np.float64)
    if poses.size == 0:
        return np.zeros((0, 4, 4))
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.isfinite(poses).all():
        raise BundleFormatError("metadata.json", "keyframes.T_world_cam must be a list of finite 4x4 matrices")
    return poses


def load_world_bundle(directory: str | Path, source: str = "bin", verify: bool = True) -> WorldBundle:
    """Load a bundle's Gaussians from ``gaussians.bin`` (``source='bin'``) or ``gaussians.ply``.

    With ``verify`` the file's checksum must match metadata.json, so a truncated or edited file is
    reported instead of silently loaded.
    """
    directory = Path(directory)
    meta = read_metadata(directory)
    name = {"bin": "gaussians.bin", "ply": "gaussians.ply"}.get(source)
    if name is None:
        raise ValueError(f"source must be 'bin' or 'ply', got {source!r}")
    path = directory / name
    if verify:
        rec = meta.get("files", {}).get(name)
        if rec is None:
            raise BundleFormatError(directory / "metadata.json", f"no checksum recorded for {name}")
        if not path.is_file():
            raise BundleFormatError(path, "file listed in metadata.json is missing")
        if sha256_file(path) != rec["sha256"]:
            raise BundleFormatError(path, "checksum does not match metadata.json (file changed or truncated)")
    field = read_atlasgs1(path) if source == "bin" else read_gaussian_ply(path)
    return WorldBundle(directory, field, meta)


def copy_bundle(src: Path, dst: Path) -> Path:
    """Copy a bundle folder atomically (e.g. to export the Dagster artifact to a user path)."""
    read_metadata(src)
    with atomic_dir(dst) as tmp:
        for p in src.iterdir():
            if p.is_file() and not p.name.startswith("."):
                shutil.copy2(p, tmp / p.name)
    return dst


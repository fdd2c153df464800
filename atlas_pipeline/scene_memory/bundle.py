"""World bundles (paper section 8.3): a folder that persists one world across sessions.

::

    <bundle>/
      metadata.json        what, from where, how (lineage, config, file checksums)
      gaussians.ply        3DGS-layout PLY for other tools
      gaussians.bin        ATLASGS1 (isotropic) or ATLASGS2 binary for fast reload
      surfels.npz          the tracking map (surfel centres and normals from the voxel statistics;
                           the Gaussians are fitted to images and no longer mark the surface exactly)
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
from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_gaussian_binary
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply
from atlas_pipeline.transition_log.transitions import write_transitions

__all__ = [
    "BUNDLE_FORMAT", "WorldBundle", "write_world_bundle", "update_world_bundle", "load_world_bundle",
    "read_metadata", "copy_bundle", "write_bundle_files", "read_lineage", "format_lineage", "parent_reference",
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
    extras: tuple[Any, ...] = (),
    surfels: Any = None,
) -> list[Path]:
    """Write a bundle's files into an existing (empty, temporary) folder; returns the paths.

    ``surfels`` (a ``SurfelModel``) is the map localization tracks against; without it a reader
    derives one from the Gaussian centres.

    ``extras`` are objects with ``save(directory)`` stored beside the Gaussians (e.g. the
    ``GaussianWorld`` with its voxel statistics, so the world can be extended later).
    """
    write_gaussian_ply(field, directory / "gaussians.ply")
    write_gaussian_binary(field, directory / "gaussians.bin")
    _write_parts(directory, localization, transitions)
    if surfels is not None:
        surfels.save(directory / "surfels.npz")
    for extra in extras:
        extra.save(directory)
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
    extras: tuple[Any, ...] = (),
    surfels: Any = None,
) -> Path:
    """Write a complete bundle folder atomically; ``metadata`` (name, lineage, config ...) goes
    into metadata.json."""
    directory = Path(directory)
    with atomic_dir(directory) as tmp:
        write_bundle_files(tmp, field, metadata, localization, transitions, extras, surfels)
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

    def tracking_model(self, voxel_size_m: float | None = None):
        """The ``SurfelModel`` to localize against: ``surfels.npz`` (checksum verified) when the
        bundle has one, else surfels derived from the Gaussian centres (e.g. an imported PLY)."""
        from atlas_pipeline.localization.tracker import SurfelModel

        if "surfels.npz" in self.metadata.get("files", {}):
            return SurfelModel.load(_verified_file(self.directory, self.metadata, "surfels.npz"))
        voxel = voxel_size_m or float(self.metadata.get("gaussians", {}).get("voxel_size_m", 0.02))
        return SurfelModel.from_field(self.field.positions, voxel, self.field.opacities)


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


def _verified_file(directory: Path, meta: dict[str, Any], name: str) -> Path:
    """``directory / name`` after checking it is listed in metadata.json, present, and unchanged."""
    rec = meta.get("files", {}).get(name)
    if rec is None:
        raise BundleFormatError(directory / "metadata.json", f"no checksum recorded for {name}")
    path = directory / name
    if not path.is_file():
        raise BundleFormatError(path, "file listed in metadata.json is missing")
    if sha256_file(path) != rec["sha256"]:
        raise BundleFormatError(path, "checksum does not match metadata.json (file changed or truncated)")
    return path


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
    path = _verified_file(directory, meta, name) if verify else directory / name
    field = read_gaussian_binary(path) if source == "bin" else read_gaussian_ply(path)
    return WorldBundle(directory, field, meta)


def copy_bundle(src: Path, dst: Path) -> Path:
    """Copy a bundle folder atomically (e.g. to export the Dagster artifact to a user path)."""
    read_metadata(src)
    with atomic_dir(dst) as tmp:
        for p in src.iterdir():
            if p.is_file() and not p.name.startswith("."):
                shutil.copy2(p, tmp / p.name)
    return dst



def parent_reference(directory: str | Path) -> dict[str, Any]:
    """How a world extended from the bundle at ``directory`` names it in ``lineage.parent``."""
    directory = Path(directory).resolve()
    meta = read_metadata(directory)
    files = meta.get("files", {})
    return {
        "path": str(directory),
        "map_id": meta.get("map_id"),
        "partition": meta.get("partition"),
        "created_at": meta.get("created_at"),
        "gaussians_bin_sha256": files.get("gaussians.bin", {}).get("sha256"),
        "run_id": (meta.get("lineage") or {}).get("run_id"),
    }


def read_lineage(directory: str | Path) -> dict[str, Any]:
    """The lineage of a bundle: partition, upstream data versions, code versions, config, run id,
    creation time and parent, gathered from its metadata.json."""
    directory = Path(directory)
    meta = read_metadata(directory)
    lin = dict(meta.get("lineage") or {})
    return {
        "bundle": str(directory.resolve()),
        "map_id": meta.get("map_id"),
        "n_gaussians": meta.get("n_gaussians"),
        "partition": lin.get("partition", meta.get("partition")),
        "run_id": lin.get("run_id"),
        "created_utc": lin.get("created_utc", meta.get("created_at")),
        "created_by": lin.get("created_by", "dagster" if lin.get("run_id") else None),
        "profile": lin.get("profile", (meta.get("config") or {}).get("profile")),
        "config_overrides": lin.get("config_overrides", {}),
        "dataset": {k: (meta.get("dataset") or {}).get(k) for k in ("name", "root", "n_frames", "content_hash")},
        "upstream": lin.get("upstream", {}),
        "code_versions": lin.get("code_versions", {}),
        "parent": lin.get("parent"),
        "config": meta.get("config", {}),
    }


def format_lineage(lin: dict[str, Any]) -> str:
    """Human-readable lineage (what ``atlas-gs lineage`` prints)."""
    out = [
        f"bundle      {lin['bundle']}",
        f"map_id      {lin.get('map_id')}  ({lin.get('n_gaussians')} Gaussians)",
        f"partition   {lin.get('partition')}",
        f"run id      {lin.get('run_id') or '-'}",
        f"created     {lin.get('created_utc') or '-'}" + (f"  by {lin['created_by']}" if lin.get("created_by") else ""),
        f"profile     {lin.get('profile')}" + (f"  overrides {json.dumps(lin['config_overrides'])}"
                                              if lin.get("config_overrides") else ""),
        f"dataset     {lin['dataset'].get('name')} ({lin['dataset'].get('n_frames')} frames, "
        f"content {str(lin['dataset'].get('content_hash') or '-')[:16]}) at {lin['dataset'].get('root')}",
    ]
    parent = lin.get("parent")
    out.append(f"parent      {parent.get('path')} (map_id {parent.get('map_id')})" if parent else
               "parent      none (built from scratch)")
    if lin.get("upstream"):
        out.append("upstream    asset                 data version              code  config            run id")
        for a, u in lin["upstream"].items():
            out.append(f"            {a:21s} {str(u.get('data_version') or '-'):25s} {str(u.get('code_version') or '-'):5s} "
                       f"{str(u.get('config_hash') or '-'):17s} {u.get('run_id') or '-'}")
    if lin.get("code_versions"):
        out.append("code        " + ", ".join(f"{a}={v}" for a, v in lin["code_versions"].items()))
    for section, values in (lin.get("config") or {}).items():
        if isinstance(values, dict):
            out.append(f"config      {section}: " + ", ".join(f"{k}={v}" for k, v in values.items()))
        else:
            out.append(f"config      {section}: {values}")
    return "\n".join(out)

"""World bundles (paper section 8.3): a folder that persists one world across sessions.

::

    <bundle>/
      metadata.json        what, from where, how (lineage, config, file checksums)
      gaussians.ply        3DGS-layout PLY for other tools
      gaussians.bin        ATLASGS1 (isotropic) or ATLASGS2 binary for fast reload
      surfels.npz          the tracking map (surfel centres and normals from the voxel statistics;
                           the Gaussians are fitted to images and no longer mark the surface exactly)
      places.npz           the place index over the keyframes (relocalization with no start pose),
                           used by a later session whose map, keyframes and camera it was made for
      localization.json    per-frame poses and errors (optional)
      transitions.parquet  state-action-state log (optional)

Memory and disk of a world of N Gaussians (and V voxels of statistics; a mapped world has about
one voxel per Gaussian) are stated by :func:`bundle_disk_bytes`, :func:`world_memory_bytes`,
:func:`save_peak_bytes` and :func:`load_peak_bytes` (checked against measured RSS by
``benchmarks/bench_big_world.py`` and ``tests/test_big_world.py``): 55 bytes per Gaussian in
memory (``FIELD_BYTES_PER_GAUSSIAN``) and in ``gaussians.bin``, 79 in ``gaussians.ply`` (12 more in
each per SH coefficient of a field with view-dependent colour, which both files carry), 55 per
Gaussian plus 116 per voxel in ``world.npz``; writing needs a few bytes per Gaussian beyond the
world (every file is streamed or written in chunks), loading the arrays it returns plus about 10
bytes per Gaussian of checks.

The folder is written under a temporary name and swapped into place whole, so a reader never sees
a bundle whose files disagree with each other. Adding a localization or transitions to a bundle
verifies every file it lists first, then swaps in a new whole folder: a corrupt file is reported,
never re-hashed into a new metadata.json. ``metadata.json`` is validated against
:class:`BundleMetadataSchema` on every read.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import shutil
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField, field_bytes_per_gaussian
from atlas_pipeline.io_utils import (
    ARTIFACT_KIND,
    ARTIFACT_RECORD,
    MARKER_NAME,
    atomic_dir,
    check_output_dir,
    commit_dir,
    discard_dir,
    folder_kind,
    foreign_entries,
    read_marker,
    sha256_file,
    stage_dir,
    write_json_atomic,
)
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.localization.places import PLACES_FILE
from atlas_pipeline.localization.metrics import write_tum_trajectory
from atlas_pipeline.scene_memory.binary import (
    BYTES_PER_GAUSSIAN,
    HEADER_BYTES,
    MAGIC_V1,
    MAGIC_V2,
    atlasgs2_bytes_per_gaussian,
    read_gaussian_binary,
    write_gaussian_binary,
)
from atlas_pipeline.scene_memory.ply import (
    ply_bytes_per_gaussian,
    ply_header_max_bytes,
    read_gaussian_ply,
    write_gaussian_ply,
)
from atlas_pipeline.transition_log.transitions import write_transitions

__all__ = [
    "BUNDLE_FORMAT", "WorldBundle", "write_world_bundle", "update_world_bundle", "load_world_bundle",
    "read_metadata", "read_place_index", "verified_file", "write_bundle_files", "read_lineage", "format_lineage", "parent_reference",
    "map_id_of", "binary_identity", "verified_gaussian_count",
    "verify_bundle_files", "check_bundle_update", "check_identity", "BundleMetadataSchema", "BUNDLE_KIND",
    "VOXEL_BYTES_PER_VOXEL", "bundle_disk_bytes", "world_memory_bytes", "save_peak_bytes", "load_peak_bytes",
]

BUNDLE_FORMAT = "atlas-gs-world-bundle"
BUNDLE_VERSION = 1
BUNDLE_KIND = "world_bundle"  # output-policy kind (io_utils marker)
# metadata.json is a few hundred kB even with thousands of keyframe poses; refuse absurd ones
# before parsing (json.loads of a huge file would take the memory of several copies of it).
MAX_METADATA_BYTES = 256 * 1024 * 1024
_SHA256_HEX = r"^[0-9a-f]{64}$"
# Files a bundle may list: plain names in the bundle folder (never a path, never hidden).
_FILE_NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$"
# A world's map id: this many hex digits of its Gaussians' content hash (64 bits: two worlds
# sharing one by chance is out of the question, and it stays short enough to read).
MAP_ID_HEX_DIGITS = 16
# The map resolution assumed for a bundle that records none (the default profile's voxel size).
DEFAULT_TRACKING_VOXEL_M = 0.02

logger = logging.getLogger(__name__)

# ---- what a world costs (see the module docstring) ---------------------------------------------
# VoxelGaussianBuilder per voxel: id uint64, count int64, sum_xyz / sum_rgb [3] and sum_sq [6]
# float64, n_keyframes int32.
VOXEL_BYTES_PER_VOXEL = 8 + 8 + 24 + 24 + 48 + 4
_NPZ_OVERHEAD_BYTES = 64 * 1024  # world.npz: ~20 members' npy and zip headers, keyframe poses
# Writing: chunk buffers of the PLY encoder (~300 bytes per row of ply._CHUNK), numpy's savez
# buffers (16 MB), hashing reads (1 MB), with room for the allocator.
SAVE_FIXED_BYTES = 64 << 20
SAVE_BYTES_PER_GAUSSIAN = 4  # the isotropy mask deciding ATLASGS1 / ATLASGS2 (3 bytes)
# Loading: checks (a comparison mask over the ids, isfinite masks, one sorted copy of unsorted
# ids) beyond the arrays returned; per Gaussian and per voxel.
LOAD_CHECK_BYTES = 10
LOAD_FIXED_BYTES = 32 << 20  # chunked reads and checks, hashing reads, allocator slack


def world_memory_bytes(n_gaussians: int, n_voxels: int = 0, sh_degree: int = 0) -> int:
    """Bytes a loaded ``GaussianField`` of ``n_gaussians`` (plus ``n_voxels`` of voxel statistics,
    as ``GaussianWorld.load`` returns them) holds: ``55 N + 116 V`` (``12 K N`` more with ``K`` SH
    coefficients per channel beyond degree 0)."""
    return field_bytes_per_gaussian(sh_degree) * int(n_gaussians) + VOXEL_BYTES_PER_VOXEL * int(n_voxels)


def bundle_disk_bytes(n_gaussians: int, n_voxels: int | None = None, isotropic: bool = False,
                      sh_degree: int = 0) -> dict[str, int]:
    """Upper bounds of the bundle's Gaussian files in bytes: ``gaussians.bin`` (exact: 24 + 55 N, or
    16 + 31 N for an isotropic field; 12 K N more with ``K`` SH coefficients per channel),
    ``gaussians.ply`` (at most ~1 kB of header, ~2.5 kB at SH degree 3, + 79 N + 12 K N) and, with
    ``n_voxels``, ``world.npz`` (55 N + 12 K N + 116 V + at most 64 kB of headers and keyframes)."""
    n = int(n_gaussians)
    v = 1 if isotropic and not sh_degree else 2
    per_bin = BYTES_PER_GAUSSIAN[1] if v == 1 else atlasgs2_bytes_per_gaussian(sh_degree)
    out = {"gaussians.bin": HEADER_BYTES[v] + per_bin * n,
           "gaussians.ply": ply_header_max_bytes(sh_degree) + ply_bytes_per_gaussian(sh_degree) * n}
    if n_voxels is not None:
        out["world.npz"] = world_memory_bytes(n, n_voxels, sh_degree) + _NPZ_OVERHEAD_BYTES
    return out


def save_peak_bytes(n_gaussians: int) -> int:
    """Upper bound on what ``write_world_bundle`` (PLY, binary, the ``GaussianWorld``'s npz,
    checksums) allocates beyond the world it writes: ``4 N + 64 MB``."""
    return SAVE_BYTES_PER_GAUSSIAN * int(n_gaussians) + SAVE_FIXED_BYTES


def load_peak_bytes(n_gaussians: int, n_voxels: int | None = None) -> int:
    """Upper bound on the memory of ``load_world_bundle(source='bin')`` (the field it returns,
    ``55 N``, and its checks), plus, with ``n_voxels``, ``GaussianWorld.load`` of the same world
    (``55 N + 116 V`` more) -- results included: ``55 N + 10 N + 32 MB`` (+ ``65 N + 126 V``)."""
    n = int(n_gaussians)
    total = world_memory_bytes(n) + LOAD_CHECK_BYTES * n + LOAD_FIXED_BYTES
    if n_voxels is not None:
        total += world_memory_bytes(n, n_voxels) + LOAD_CHECK_BYTES * max(n, int(n_voxels))
    return total


class FileRecord(BaseModel):
    """One listed file: its size and sha256."""

    model_config = ConfigDict(extra="allow", strict=True)
    bytes: int = Field(ge=0)
    sha256: str = Field(pattern=_SHA256_HEX)


class GaussiansInfo(BaseModel):
    model_config = ConfigDict(extra="allow")
    voxel_size_m: float | None = Field(default=None, gt=0)

    @field_validator("voxel_size_m")
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError("must be a finite number > 0")
        return v


class BundleMetadataSchema(BaseModel):
    """What ``metadata.json`` must hold; other keys (lineage, config, dataset ...) are free-form."""

    model_config = ConfigDict(extra="allow")
    format: str
    version: int = Field(ge=1, le=BUNDLE_VERSION, strict=True)
    map_id: str = Field(default="", max_length=128)
    n_gaussians: int = Field(default=0, ge=0, strict=True)
    files: dict[str, FileRecord]
    gaussians: GaussiansInfo | None = None
    dataset: dict[str, Any] | None = None
    lineage: dict[str, Any] | None = None
    keyframes: dict[str, Any] | None = None

    @field_validator("format")
    @classmethod
    def _format(cls, v: str) -> str:
        if v != BUNDLE_FORMAT:
            raise ValueError(f"is {v!r}, expected {BUNDLE_FORMAT!r}")
        return v

    @field_validator("files")
    @classmethod
    def _names(cls, v: dict[str, FileRecord]) -> dict[str, FileRecord]:
        import re

        for name in v:
            if not re.match(_FILE_NAME, name) or name in ("metadata.json", MARKER_NAME):
                raise ValueError(f"lists {name!r}, which is not a plain file name of a bundle")
        return v


def map_id_of(field: GaussianField) -> str:
    """The map id of the world state ``field``: derived from its arrays (``content_hash``), so a
    bundle's id is a fact of its checksummed Gaussians, never a value copied from editable JSON."""
    return field.content_hash()[:MAP_ID_HEX_DIGITS]


# Bytes read at a time when a binary world's columns are hashed without loading it.
_STREAM_CHUNK_BYTES = 1 << 24
_F32 = 4  # bytes of a float32
_IDENTITY_XYZW = np.array([0.0, 0.0, 0.0, 1.0], "<f4")  # an ATLASGS1 Gaussian's rotation


def _binary_layout(path: Path) -> tuple[int, int, int, list[tuple[str, tuple[int, ...], int]]]:
    """``(version, count, sh_degree, columns)`` of the ATLASGS1/2 file at ``path`` from its header,
    its size checked against the count: ``columns`` are ``(name, shape, byte offset)`` in file
    order. A BundleFormatError naming the file when it is no such file or of the wrong size."""
    import struct

    from atlas_pipeline.gaussian_world.field import SH_MAX_DEGREE, sh_rest_count

    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(HEADER_BYTES[2])
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read ({exc.strerror or exc})") from None
    if head[:8] == MAGIC_V1 and len(head) >= HEADER_BYTES[1]:
        version, degree, header = 1, 0, HEADER_BYTES[1]
        n = struct.unpack("<Q", head[8:16])[0]
        per, shapes = BYTES_PER_GAUSSIAN[1], [("positions", (n, 3), _F32), ("scale", (n,), _F32),
                                              ("colors", (n, 3), 1), ("opacities", (n,), _F32), ("ids", (n,), 8)]
    elif head[:8] == MAGIC_V2 and len(head) >= HEADER_BYTES[2]:
        version, second, n = struct.unpack("<IIQ", head[8:24])
        header = HEADER_BYTES[2]
        degree = second if version == 3 else 0
        if version not in (2, 3) or (version == 3 and not 1 <= degree <= SH_MAX_DEGREE):
            raise BundleFormatError(path, f"ATLASGS2 version {version} (SH degree {second}) is not supported")
        per = atlasgs2_bytes_per_gaussian(degree)
        shapes = [("positions", (n, 3), _F32), ("scales", (n, 3), _F32), ("rotations_xyzw", (n, 4), _F32),
                  ("colors", (n, 3), 1), ("opacities", (n,), _F32), ("ids", (n,), 8),
                  ("sh_rest", (n, sh_rest_count(degree), 3), _F32)]
    else:
        raise BundleFormatError(path, f"not an ATLASGS binary (magic {head[:8]!r}, {size} bytes)")
    if size != header + n * per:
        raise BundleFormatError(path, f"count {n} needs {header + n * per} bytes, file has {size}")
    columns, offset = [], header
    for name, shape, itemsize in shapes:
        columns.append((name, shape, offset))
        offset += int(np.prod(shape)) * itemsize
    return version, n, degree, columns


def _column_chunks(f, offset: int, n_bytes: int, row_bytes: int):
    """The ``n_bytes`` at ``offset`` of the open file ``f``, in chunks of whole rows."""
    step = max(row_bytes, _STREAM_CHUNK_BYTES // row_bytes * row_bytes)
    f.seek(offset)
    for start in range(0, n_bytes, step):
        chunk = f.read(min(step, n_bytes - start))
        if len(chunk) != min(step, n_bytes - start):
            raise BundleFormatError(Path(f.name), "file changed while reading")
        yield chunk


def binary_identity(path: str | Path) -> tuple[int, str]:
    """``(count, map id)`` of the world in the ATLASGS1/2 file at ``path`` without loading it: the
    count from its header (the size checked against it), the map id (:func:`map_id_of` of the
    field :func:`read_gaussian_binary` would return) by hashing its columns as they lie in the
    file, the isotropic format's one scale and identity rotation expanded a chunk at a time. One
    read of the file and no arrays of its size, where loading checks and copies every value."""
    import hashlib
    import sys

    path = Path(path)
    version, n, degree, columns = _binary_layout(path)
    if sys.byteorder != "little":  # the field's arrays are native, the file's little endian
        field = read_gaussian_binary(path)
        return len(field), map_id_of(field)
    at = {name: (shape, offset) for name, shape, offset in columns}
    h = hashlib.sha256()
    with open(path, "rb") as f:
        order = ("ids", "positions", "scales", "rotations_xyzw", "colors", "opacities")
        for name in order + (("sh_rest",) if degree else ()):  # GaussianField.content_hash's order
            shape = (n, 3) if name == "scales" else (n, 4) if name == "rotations_xyzw" else at[name][0]
            h.update(name.encode())
            h.update(str(shape).encode())
            if not n:
                continue
            if version == 1 and name == "scales":
                for chunk in _column_chunks(f, at["scale"][1], n * _F32, _F32):
                    h.update(np.repeat(np.frombuffer(chunk, "<f4")[:, None], 3, axis=1).tobytes())
            elif version == 1 and name == "rotations_xyzw":
                rows = _STREAM_CHUNK_BYTES // (4 * _F32)
                for start in range(0, n, rows):
                    h.update(np.tile(_IDENTITY_XYZW, (min(rows, n - start), 1)).tobytes())
            else:
                shape_f, offset = at[name]
                row = int(np.prod(shape_f[1:], dtype=np.int64)) * (1 if name == "colors" else
                                                                   8 if name == "ids" else _F32)
                for chunk in _column_chunks(f, offset, n * row, row):
                    h.update(chunk)
    return n, h.hexdigest()[:MAP_ID_HEX_DIGITS]


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _write_parts(directory: Path, localization: LocalizationReport | None, transitions: pa.Table | None) -> None:
    if localization is not None:
        write_json_atomic(directory / "localization.json", localization.to_json())
        write_tum_trajectory(directory / "trajectory_estimated.tum", localization.timestamps_s, localization.T_world_cam)
    if transitions is not None:
        write_transitions(transitions, directory / "transitions.parquet")


def _part_names(localization: LocalizationReport | None, transitions: pa.Table | None) -> dict[str, dict[str, str]]:
    """The dataset and map each written part names, recorded beside its checksum: a reader (and the
    next update) sees which recording a part comes from without parsing it."""
    names: dict[str, dict[str, str]] = {}
    if localization is not None:
        for name in _PART_FILES["localization"]:
            names[name] = {"dataset": localization.dataset, "map_id": localization.map_id}
    if transitions is not None and transitions.num_rows:
        for name in _PART_FILES["transitions"]:
            names[name] = {"dataset": str(transitions.column("partition")[0]),
                           "map_id": str(transitions.column("map_id")[0])}
    return names


def _file_table(directory: Path, parts: dict[str, dict[str, str]] | None = None) -> dict[str, dict[str, Any]]:
    return {
        p.name: {"bytes": p.stat().st_size, "sha256": sha256_file(p), **(parts or {}).get(p.name, {})}
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
    places: Any = None,
) -> list[Path]:
    """Write a bundle's files into an existing (empty, temporary) folder; returns the paths.

    ``surfels`` (a ``SurfelModel``) is the map localization tracks against; without it a reader
    derives one from the Gaussian centres. ``places`` (a ``PlaceIndex`` of ``surfels`` seen from
    the keyframes) spares a later session indexing them again.

    ``extras`` are objects with ``save(directory)`` stored beside the Gaussians (e.g. the
    ``GaussianWorld`` with its voxel statistics, so the world can be extended later).
    """
    parts = _part_names(localization, transitions)
    loc, tr = parts.get("localization.json"), parts.get("transitions.parquet")
    if loc and tr and loc != tr:
        raise BundleFormatError(directory, f"the localization (dataset '{loc['dataset']}', map {loc['map_id']}) and the "
                                           f"transitions (dataset '{tr['dataset']}', map {tr['map_id']}) disagree")
    write_gaussian_ply(field, directory / "gaussians.ply")
    write_gaussian_binary(field, directory / "gaussians.bin")
    _write_parts(directory, localization, transitions)
    if surfels is not None:
        surfels.save(directory / "surfels.npz")
    if places is not None:
        places.save(directory / PLACES_FILE)
    for extra in extras:
        extra.save(directory)
    meta = {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "created_at": _utc_now(),
        "map_id": map_id_of(field),
        "n_gaussians": len(field),
        **metadata,
        "files": _file_table(directory, parts),
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
    places: Any = None,
    inputs: Iterable[str | Path] = (),
    force: bool = False,
) -> Path:
    """Write a complete bundle folder atomically; ``metadata`` (name, lineage, config ...) goes
    into metadata.json.

    ``directory`` may only be new, empty, or an earlier bundle holding nothing but its own files
    (:func:`atlas_pipeline.io_utils.check_output_dir`); ``inputs`` are folders the caller read,
    which are never replaced; ``force`` moves a foreign folder aside instead of refusing.
    """
    directory = Path(directory)
    check_output_dir(directory, BUNDLE_KIND, inputs, force)
    with atomic_dir(directory, kind=BUNDLE_KIND) as tmp:
        write_bundle_files(tmp, field, metadata, localization, transitions, extras, surfels, places)
    return directory


# Files update_world_bundle rewrites for each part (everything else is carried over, verified).
_PART_FILES = {"localization": ("localization.json", "trajectory_estimated.tum"),
               "transitions": ("transitions.parquet",)}


def verify_bundle_files(directory: str | Path, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """Check every file ``metadata.json`` lists: present, same size, same sha256. Returns the metadata.

    Raises BundleFormatError naming the first file that is missing, truncated or changed.
    """
    directory = Path(directory)
    meta = read_metadata(directory) if meta is None else meta
    for name in meta["files"]:
        verified_file(directory, meta, name)
    return meta


def _recorded_part(directory: Path, meta: dict[str, Any], name: str) -> dict[str, str] | None:
    """The dataset and map the listed part ``name`` names (None when the bundle has no such part):
    from its record in metadata.json, else (bundles written before records carried them) from the
    file itself."""
    rec = meta["files"].get(name)
    if rec is None:
        return None
    if isinstance(rec.get("dataset"), str) and isinstance(rec.get("map_id"), str):
        return {"dataset": rec["dataset"], "map_id": rec["map_id"]}
    path = directory / name
    try:
        if name == "transitions.parquet":
            import pyarrow.parquet as pq

            table = pq.read_table(path, columns=["partition", "map_id"])
            if not table.num_rows:
                return None
            return {"dataset": str(table.column("partition")[0]), "map_id": str(table.column("map_id")[0])}
        if name == "localization.json":
            data = json.loads(path.read_text(encoding="utf-8"))
            return {"dataset": str(data.get("dataset")), "map_id": str(data.get("map_id"))}
    except (OSError, ValueError, KeyError, AttributeError, pa.ArrowException) as exc:
        raise BundleFormatError(path, f"cannot read which dataset and map it is for ({exc})") from exc
    return None


def _live_artifact(directory: Path) -> bool:
    """Whether ``directory`` is the Dagster IO manager's own folder, not a copy of it (``cp -a``):
    its marker records where it was written. Without that place (older artifacts) it is a copy only
    when its record names an asset and partition the folder does not sit at (``<asset>/<partition>``)."""
    marker = read_marker(directory) or {}
    if isinstance(marker.get("path"), str):
        return Path(marker["path"]) == directory.resolve()
    try:
        record = json.loads((directory / ARTIFACT_RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return True
    resolved = directory.resolve()
    return not isinstance(record, dict) or \
        (resolved.parent.name, resolved.name) == (record.get("asset"), record.get("partition"))


def _check_updatable(directory: Path, meta: dict[str, Any]) -> None:
    kind = folder_kind(directory)
    if kind == ARTIFACT_KIND and _live_artifact(directory):
        raise BundleFormatError(directory, "is the world_bundle artifact of the Dagster IO manager (`atlas-gs run` "
                                           f"rewrites it); copy it first (`cp -a {directory} my-world`) and give "
                                           "the copy as --world; nothing was changed")
    if kind not in (None, BUNDLE_KIND, ARTIFACT_KIND):
        raise BundleFormatError(directory, f"is an Atlas-GS {kind} folder, not a world bundle; nothing was changed")
    # A copy of the artifact carries its record (_artifact.json): not a part of the bundle, dropped by the update.
    foreign = [n for n in foreign_entries(directory) if n not in meta["files"] and n not in ("metadata.json", ARTIFACT_RECORD)]
    if foreign:
        raise BundleFormatError(directory, f"holds files this bundle does not list ({', '.join(foreign[:5])}); "
                                           "move them out of the bundle folder first, nothing was changed")


def check_bundle_update(directory: str | Path, dataset: str | None = None, map_id: str | None = None,
                        transitions_of: dict[str, str] | None = None, drop_transitions: bool = False,
                        meta: dict[str, Any] | None = None) -> list[str]:
    """Decide, before any work, whether a localization of ``dataset`` on ``map_id`` (or transitions
    naming ``transitions_of``'s dataset and map) may be written into the bundle at ``directory``;
    raise BundleFormatError naming the file that would disagree. Returns the listed parts the update
    removes: transitions derived from the localization being replaced, which would no longer agree
    with it. Those of another recording are removed only with ``drop_transitions`` (they cannot be
    derived again from this bundle); refused otherwise.

    A bundle is one recording's truth: every part it lists names the same dataset and map.
    """
    directory = Path(directory)
    meta = read_metadata(directory) if meta is None else meta
    _check_updatable(directory, meta)
    world_map = str(meta.get("map_id", ""))
    for what, names in (("localization", {"map_id": map_id} if map_id is not None else None),
                        ("transitions", transitions_of)):
        if names is not None and world_map and names["map_id"] != world_map:
            raise BundleFormatError(directory, f"holds map {world_map}; the {what} to write is for map "
                                               f"{names['map_id']} (another world); nothing was changed")
    if transitions_of is not None:
        loc = {"dataset": dataset, "map_id": map_id or world_map} if dataset is not None else \
            _recorded_part(directory, meta, "localization.json")
        if loc is None:
            raise BundleFormatError(directory, "has no localization.json: transitions are derived from a "
                                               "localization, so localize first; nothing was changed")
        if loc["dataset"] != transitions_of["dataset"]:
            raise BundleFormatError(directory / "localization.json",
                                    f"is for dataset '{loc['dataset']}'; the transitions to write are for "
                                    f"'{transitions_of['dataset']}'; nothing was changed")
        return []
    if dataset is None:
        return []
    old = _recorded_part(directory, meta, "transitions.parquet")
    if old is None:
        return []
    if old["dataset"] != dataset and not drop_transitions:
        raise BundleFormatError(directory / "transitions.parquet",
                                f"holds the transitions of dataset '{old['dataset']}'; a localization of "
                                f"'{dataset}' would leave them beside a report they do not come from. Localize "
                                f"into a copy of the bundle (`cp -a {directory} {directory.name}-{dataset}`), or "
                                "drop them from this bundle (localize --drop-transitions); nothing was changed")
    return list(_PART_FILES["transitions"])


def update_world_bundle(directory: str | Path, localization: LocalizationReport | None = None,
                        transitions: pa.Table | None = None, drop_transitions: bool = False) -> Path:
    """Add or replace the localization or transitions of an existing bundle (CLI sessions).

    Every file the bundle lists is verified first (a corrupt file stops the update, so it is never
    re-hashed into a new metadata.json); a bundle holding files atlas-gs did not write is refused
    (the swap would drop them), and so is a part that would disagree with the others on dataset or
    map (:func:`check_bundle_update`, which also says which parts a new localization makes stale:
    they leave the bundle). The new bundle is assembled in a folder beside it (verified copies of
    the unchanged files, the new parts) and swapped in whole.
    """
    directory = Path(directory)
    meta = verify_bundle_files(directory)
    parts = _part_names(localization, transitions)
    loc, tr = parts.get("localization.json"), parts.get("transitions.parquet")
    stale = check_bundle_update(directory, loc["dataset"] if loc else None, loc["map_id"] if loc else None,
                                tr, drop_transitions, meta)
    for name in stale:
        logger.warning("%s: removed from the bundle: derived from the localization now replaced, it would not agree "
                       "with the new one (`atlas-gs log-transitions --world %s --input %s` derives it from the new one)",
                       directory / name, directory, loc["dataset"] if loc else "DATASET")
    replaced = set(stale)
    if localization is not None:
        replaced.update(_PART_FILES["localization"])
    if transitions is not None:
        replaced.update(_PART_FILES["transitions"])
    tmp = stage_dir(directory)
    try:
        files: dict[str, Any] = {}
        for name, rec in meta["files"].items():
            if name in replaced:
                continue
            shutil.copy2(directory / name, tmp / name)
            if sha256_file(tmp / name) != rec["sha256"]:  # the copy, not the source, goes into the bundle
                raise BundleFormatError(directory / name, "copy does not match its checksum (disk error?)")
            files[name] = dict(rec)
        _write_parts(tmp, localization, transitions)
        for name in sorted(replaced):
            if (tmp / name).is_file():
                files[name] = {"bytes": (tmp / name).stat().st_size, "sha256": sha256_file(tmp / name),
                               **parts.get(name, {})}
        meta = {**meta, "files": dict(sorted(files.items())), "updated_at": _utc_now()}
        write_json_atomic(tmp / "metadata.json", meta)
        commit_dir(tmp, directory, BUNDLE_KIND)
    finally:
        if tmp.exists():
            discard_dir(tmp)
    return directory


def _schema_error(path: Path, exc: ValidationError) -> BundleFormatError:
    first = exc.errors()[0]
    where = ".".join(str(x) for x in first.get("loc", ())) or "(top level)"
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return BundleFormatError(path, f"metadata field {where}: {first.get('msg')}{more}")


def read_metadata(directory: Path) -> dict[str, Any]:
    """``metadata.json`` of the bundle at ``directory``, validated against :class:`BundleMetadataSchema`."""
    directory = Path(directory)
    path = directory / "metadata.json"
    if not path.is_file():
        raise BundleFormatError(directory, "not a world bundle (metadata.json missing)")
    try:
        size = path.stat().st_size
        if size > MAX_METADATA_BYTES:
            raise BundleFormatError(path, f"is {size} bytes, more than any bundle's metadata ({MAX_METADATA_BYTES})")
        text = path.read_bytes().decode("utf-8")
        meta = json.loads(text)
    except UnicodeDecodeError as exc:
        raise BundleFormatError(path, f"not UTF-8 text (byte {exc.start})") from exc
    except json.JSONDecodeError as exc:
        raise BundleFormatError(path, f"invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    except RecursionError as exc:
        raise BundleFormatError(path, "JSON nested too deeply") from exc
    except ValueError as exc:  # not a JSONDecodeError: e.g. an integer of more than 4300 digits
        raise BundleFormatError(path, f"invalid JSON value ({exc})") from exc
    except OSError as exc:
        raise BundleFormatError(path, f"cannot read: {exc.strerror or exc}") from exc
    if not isinstance(meta, dict):
        raise BundleFormatError(path, f"must hold a JSON object, found {type(meta).__name__}")
    if meta.get("format") != BUNDLE_FORMAT:
        raise BundleFormatError(path, f"format is {meta.get('format')!r}, expected {BUNDLE_FORMAT!r}")
    try:
        BundleMetadataSchema.model_validate(meta)
    except ValidationError as exc:
        raise _schema_error(path, exc) from exc
    return meta


@dataclass
class WorldBundle:
    """A loaded bundle: the Gaussians and the metadata. ``verified``: every listed file's checksum
    was checked when it was loaded, so its parts are read without hashing them again, and
    metadata.json's ``map_id`` and ``n_gaussians`` were checked against the Gaussians."""

    directory: Path
    field: GaussianField
    metadata: dict[str, Any]
    verified: bool = False

    @cached_property
    def map_id(self) -> str:
        """The world's map id, derived from its Gaussians (:func:`map_id_of`; hashed once)."""
        return map_id_of(self.field)

    @property
    def n_gaussians(self) -> int:
        """How many Gaussians the world holds: those loaded, not metadata.json's figure."""
        return len(self.field)

    def part(self, name: str) -> Path:
        """``directory / name``, a file metadata.json lists: present and of its recorded size, and
        its checksum checked unless the whole bundle was at load (:func:`verified_file`)."""
        return bundle_part(self.directory, self.metadata, name, self.verified)

    def tracking_model(self, voxel_size_m: float | None = None):
        """The ``SurfelModel`` to localize against: ``surfels.npz`` (checksum verified) when the
        bundle has one, else surfels derived from the Gaussian centres (e.g. an imported PLY)."""
        from atlas_pipeline.localization.tracker import SurfelModel, VoxelAppearance

        voxel = voxel_size_m or float((self.metadata.get("gaussians") or {}).get("voxel_size_m") or
                                      DEFAULT_TRACKING_VOXEL_M)
        if "surfels.npz" in self.metadata.get("files", {}):
            model = SurfelModel.load(self.part("surfels.npz"))
        else:
            model = SurfelModel.from_field(self.field.positions, voxel, self.field.opacities)
        # the Gaussians' colours: what relocalization checks a pose's appearance against
        model.appearance_map = VoxelAppearance.from_field(self.field, voxel)
        model.fixed = True  # a saved world does not change while it is localized in
        return model

    def stored_places(self, camera):
        """The bundle's place index (:func:`read_place_index`)."""
        return read_place_index(self.directory, camera, self.metadata, self.verified)


def read_place_index(directory: str | Path, camera, meta: dict[str, Any] | None = None, verified: bool = False):
    """The place index the bundle at ``directory`` stores (``places.npz``, checksum verified unless
    ``verified`` says the bundle was, and checked), entries to be rendered later at ``camera``; None
    when the bundle has none. Whether it fits a session's map and camera is decided where it is used
    (its key)."""
    from atlas_pipeline.localization.places import PlaceIndex

    directory = Path(directory)
    meta = read_metadata(directory) if meta is None else meta
    if PLACES_FILE not in meta.get("files", {}):
        return None
    return PlaceIndex.load(bundle_part(directory, meta, PLACES_FILE, verified), camera)


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


def listed_file(directory: Path, meta: dict[str, Any], name: str) -> Path:
    """``directory / name`` after checking it is listed in metadata.json, present, and of the
    recorded size (:func:`verified_file` also checks its checksum)."""
    rec = meta.get("files", {}).get(name)
    if rec is None:
        raise BundleFormatError(directory / "metadata.json", f"no checksum recorded for {name}")
    path = directory / name
    if not path.is_file():
        raise BundleFormatError(path, "file listed in metadata.json is missing")
    size = path.stat().st_size
    if size != rec["bytes"]:
        raise BundleFormatError(path, f"is {size} bytes, metadata.json records {rec['bytes']} (file changed or truncated)")
    return path


def bundle_part(directory: Path, meta: dict[str, Any], name: str, verified: bool) -> Path:
    """:func:`listed_file` when the bundle's checksums were already ``verified``, else :func:`verified_file`."""
    return (listed_file if verified else verified_file)(directory, meta, name)


def verified_file(directory: Path, meta: dict[str, Any], name: str) -> Path:
    """``directory / name`` after checking it is listed in metadata.json, present, and unchanged."""
    path = listed_file(directory, meta, name)
    if sha256_file(path) != meta["files"][name]["sha256"]:
        raise BundleFormatError(path, "checksum does not match metadata.json (file changed or corrupted)")
    return path


def load_world_bundle(directory: str | Path, source: str = "bin", verify: bool = True) -> WorldBundle:
    """Load a bundle's Gaussians from ``gaussians.bin`` (``source='bin'``) or ``gaussians.ply``.

    With ``verify`` every file metadata.json lists (Gaussians, PLY, tracking map, world.npz,
    reports) must match its size and checksum, so a truncated or edited file is reported instead of
    silently loaded, and later written back as if it were good.
    """
    directory = Path(directory)
    meta = read_metadata(directory)
    name = {"bin": "gaussians.bin", "ply": "gaussians.ply"}.get(source)
    if name is None:
        raise ValueError(f"source must be 'bin' or 'ply', got {source!r}")
    if verify:
        verify_bundle_files(directory, meta)  # hashes every listed file once, the Gaussians included
        if name not in meta["files"]:
            raise BundleFormatError(directory / "metadata.json", f"no checksum recorded for {name}")
    path = directory / name
    field = read_gaussian_binary(path) if source == "bin" else read_gaussian_ply(path)
    bundle = WorldBundle(directory, field, meta, verified=verify)
    if verify:
        check_identity(bundle, name)
    return bundle


def _count_error(path: Path, stated: Any, n: int, source: str) -> BundleFormatError:
    return BundleFormatError(path, f"field n_gaussians is {stated!r}, but {source} (checksum verified) holds "
                                   f"{n} Gaussians: metadata.json was edited or belongs to another world; restore "
                                   "the bundle from a copy, or build it again")


def _map_id_error(path: Path, stated: Any, map_id: str, source: str) -> BundleFormatError:
    return BundleFormatError(path, f"field map_id is {stated!r}, but the Gaussians of {source} (checksum verified) "
                                   f"are map {map_id}: metadata.json was edited or belongs to another world; restore "
                                   "the bundle from a copy, or build it again")


def verified_gaussian_count(directory: str | Path, meta: dict[str, Any] | None = None) -> int:
    """How many Gaussians the bundle at ``directory`` holds, without loading them: every listed
    file verified (:func:`verify_bundle_files`), then the count in ``gaussians.bin``'s header,
    which metadata.json's ``n_gaussians`` must state (a BundleFormatError naming the field, as
    :func:`check_identity` raises)."""
    directory = Path(directory)
    meta = verify_bundle_files(directory, meta)
    if "gaussians.bin" not in meta["files"]:
        raise BundleFormatError(directory / "metadata.json", "no checksum recorded for gaussians.bin")
    _, n, _, _ = _binary_layout(directory / "gaussians.bin")
    if meta.get("n_gaussians") != n:
        raise _count_error(directory / "metadata.json", meta.get("n_gaussians"), n, "gaussians.bin")
    return n


def check_identity(bundle: WorldBundle, source: str = "gaussians.bin") -> None:
    """Refuse a bundle whose metadata.json states a ``n_gaussians`` or ``map_id`` other than its
    checksum-verified Gaussians (read from ``source``) have: a hand-edited or mixed-up
    metadata.json would otherwise be stamped into every report and transition made from it.
    Raises BundleFormatError naming metadata.json and the field."""
    path = bundle.directory / "metadata.json"
    stated_n = bundle.metadata.get("n_gaussians")
    if stated_n != bundle.n_gaussians:  # the cheap check first: no hashing for an edited count
        raise _count_error(path, stated_n, bundle.n_gaussians, source)
    stated_id = bundle.metadata.get("map_id")
    if stated_id != bundle.map_id:
        raise _map_id_error(path, stated_id, bundle.map_id, source)


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


def _lineage_problems(directory: Path, meta: dict[str, Any]) -> tuple[Any, Any, list[BundleFormatError]]:
    """``(map id, count, problems)`` of the bundle at ``directory`` with ``meta``: every listed
    file's size and checksum checked, and the map id and count of its ``gaussians.bin``
    (:func:`binary_identity`, the Gaussians never loaded) against those metadata.json states;
    where gaussians.bin does not verify, the stated ones. ``problems``: each file that does not
    verify and each field that disagrees, in that order (empty: the bundle verifies)."""
    problems: list[BundleFormatError] = []
    for name in meta["files"]:
        try:
            verified_file(directory, meta, name)
        except BundleFormatError as exc:
            problems.append(exc)
    map_id, n = meta.get("map_id"), meta.get("n_gaussians")
    path = directory / "metadata.json"
    if "gaussians.bin" not in meta["files"]:
        problems.append(BundleFormatError(path, "no checksum recorded for gaussians.bin"))
    elif not any(p.path == directory / "gaussians.bin" for p in problems):
        try:
            n_bin, id_bin = binary_identity(directory / "gaussians.bin")
        except BundleFormatError as exc:
            problems.append(exc)
        else:
            if n_bin != n:  # the count first, as check_identity does
                problems.append(_count_error(path, n, n_bin, "gaussians.bin"))
            elif id_bin != map_id:
                problems.append(_map_id_error(path, map_id, id_bin, "gaussians.bin"))
            map_id, n = id_bin, n_bin
    return map_id, n, problems


def read_lineage(directory: str | Path, verify: bool = False, strict: bool = True) -> dict[str, Any]:
    """The lineage of a bundle: partition, upstream data versions, code versions, config, run id,
    creation time and parent, gathered from its metadata.json.

    With ``verify`` every listed file's checksum is checked and the map id and count are those of
    ``gaussians.bin`` (:func:`binary_identity`: read, never loaded), which metadata.json must
    state; the result then holds ``verified`` and ``problems`` (one line per file that does not
    verify or field that disagrees, naming it). ``strict``: the first problem is raised as a
    BundleFormatError; else the lineage is still returned (as metadata.json states it where the
    Gaussians do not verify), with ``verified`` false: a damaged bundle's lineage is when it is
    wanted most. Without ``verify`` everything is as metadata.json states."""
    directory = Path(directory)
    meta = read_metadata(directory)
    problems: list[BundleFormatError] = []
    if verify:
        map_id, n_gaussians, problems = _lineage_problems(directory, meta)
        if problems and strict:
            raise problems[0]
    else:
        map_id, n_gaussians = meta.get("map_id"), meta.get("n_gaussians")
    lin = dict(meta.get("lineage") or {})
    out = {
        "bundle": str(directory.resolve()),
        "map_id": map_id,
        "n_gaussians": n_gaussians,
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
    if verify:
        out.update(verified=not problems, problems=[str(p) for p in problems])
    return out


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
    if "verified" in lin:
        out.append("verified    every listed file's checksum, and the map id and count of gaussians.bin"
                   if lin["verified"] else
                   f"verified    NO: {len(lin.get('problems') or ())} problem(s), the lineage is as metadata.json "
                   "states it")
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

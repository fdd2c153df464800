"""Typed IO managers: each artifact type is written in an open format under
``<root>/<asset>/<partition>/``, never pickled.

An artifact type is a library class with ``save(directory) -> list[Path]`` and a classmethod
``load(directory)``. The IO manager writes into a temporary folder and swaps it into place, so a
failed or interrupted run leaves the previous artifact whole. It also records ``_artifact.json``
(type, files, sha256 of each, one content hash over all of them) beside the files.

The root is a local or mounted (network) folder, or an object-store URL (``s3://bucket/prefix``,
``gs://...``): there every version is uploaded under a content-addressed prefix and published by one
atomic PUT of a small pointer object (:mod:`assets.storage` explains the layout and the guarantees);
files are staged and hashed locally either way, so data versions are the same on both.

Assets hand it a :class:`StagedArtifact` (written to the temporary folder by :meth:`ArtifactIOManager.stage`,
so its content hash, the data version, was known when the output was yielded; only the swap is
left) or :class:`Reused` (current on disk: nothing is written). Inputs are loaded by
:meth:`ArtifactIOManager.load_input` as the typed artifacts.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
from dagster import ConfigurableIOManager, InputContext, MetadataValue, OutputContext

from assets.storage import is_remote, local_scratch, object_store, root_key
from atlas_pipeline.config import project_root
from atlas_pipeline.errors import ArtifactError, AtlasError, WriteError
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.gaussian_world.evaluation import PhotometricReport
from atlas_pipeline.io_utils import (  # ARTIFACT_KIND: output-policy kind of every folder this IO manager writes
    ARTIFACT_KIND,
    MIN_FREE_BYTES,
    LockedError,
    ProcessLock,
    atomic_path,
    check_output_dir,
    check_writable,
    commit_dir,
    discard_dir,
    recover_dir,
    sha256_file,
    stage_dir,
    write_json_atomic,
)
from atlas_pipeline.interop.mesh import WorldMesh
from atlas_pipeline.interop.occupancy import OccupancyMap
from atlas_pipeline.interop.trainer_export import TrainerExport
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.mapping.keyframes import KeyframeSet
from atlas_pipeline.perception.rgbd import FusedFrames
from atlas_pipeline.scene_memory.metadata import WorldBundleArtifact
from atlas_pipeline.sensors.registry import validate_dataset_name
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.versioning import file_identity, verify_files
from atlas_pipeline.viz.demo import DemoVideos


class ParquetTable:
    """Adapter giving ``pyarrow.Table`` the save/load protocol (one ``table.parquet``)."""

    @staticmethod
    def save(table: pa.Table, directory: Path) -> list[Path]:
        path = directory / "table.parquet"
        with atomic_path(path) as tmp:
            pq.write_table(table, tmp)
        return [path]

    @staticmethod
    def load(directory: Path) -> pa.Table:
        path = directory / "table.parquet"
        if not path.is_file():
            raise ArtifactError(f"{path}: missing")
        return pq.read_table(path)


# The only types this IO manager reads or writes: loading never instantiates anything else.
ARTIFACT_TYPES: dict[str, Any] = {
    "FrameManifest": FrameManifest,
    "FusedFrames": FusedFrames,
    "KeyframeSet": KeyframeSet,
    "GaussianWorld": GaussianWorld,
    "LocalizationReport": LocalizationReport,
    "Table": ParquetTable,
    "DemoVideos": DemoVideos,
    "WorldBundleArtifact": WorldBundleArtifact,
    "PhotometricReport": PhotometricReport,
    "TrainerExport": TrainerExport,
    "WorldMesh": WorldMesh,
    "OccupancyMap": OccupancyMap,
}


def artifacts_root() -> Path:
    """``$ATLAS_ARTIFACTS_DIR`` or ``<project>/artifacts``; an object-store URL (``s3://...``) is
    returned as a universal-pathlib path of it."""
    env = os.environ.get("ATLAS_ARTIFACTS_DIR")
    if env and is_remote(env):
        return object_store(env).root
    from atlas_pipeline.io_utils import env_folder

    return env_folder("ATLAS_ARTIFACTS_DIR", env) if env else project_root() / "artifacts"


def artifact_dir(root: str | Path, asset: str, partition: str) -> Path:
    """``<root>/<asset>/<partition>``; the partition name is validated before it becomes a path
    (for an object-store root: the partition's prefix, holding its pointer and versions)."""
    validate_dataset_name(partition)
    if is_remote(root):
        return object_store(str(root)).prefix(asset, partition)
    return Path(root) / asset / partition


LOCKS_DIR = ".locks"  # under the root: one lock file per partition
# Free space asked before computing an asset, as a multiple of its previous version's size.
FREE_SPACE_FACTOR = 2


class PartitionBusyError(AtlasError):
    """Another live run is materializing the same partition."""


def read_artifact_record(directory: Path) -> dict[str, Any]:
    path = directory / "_artifact.json"
    if not path.is_file():
        raise ArtifactError(f"{directory}: no artifact record (_artifact.json); materialize the asset first")
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ArtifactError(f"{path}: invalid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(record, dict):
        raise ArtifactError(f"{path}: expected a JSON object")
    return record


def _load_typed(directory: Path, record: dict[str, Any]) -> Any:
    handler = ARTIFACT_TYPES.get(record.get("type", ""))
    if handler is None:
        raise ArtifactError(f"{directory}: unknown artifact type {record.get('type')!r}")
    return handler.load(directory)


@dataclass
class StagedArtifact:
    """An artifact written into a temporary folder beside its target, with its record (content
    hash) already known; the IO manager swaps it into place."""

    staging: Path
    target: Path
    record: dict[str, Any]
    value: Any = None  # the artifact object itself (for checks evaluated on it)

    @property
    def data_version(self) -> str:
        """The artifact's data version: its content hash (24 hex), from the bytes written only."""
        return self.record["content_hash"][:24]


@dataclass
class Reused:
    """The output of an asset whose artifact on disk is current (:func:`assets.versioning.reuse`):
    the IO manager leaves its files untouched."""

    asset: str
    partition: str


def _file_records(files: list[Path]) -> dict[str, dict[str, Any]]:
    out = {}
    for p in sorted(files, key=lambda q: q.name):
        out[p.name] = {**file_identity(p), "sha256": sha256_file(p)}
    return out


def _content_hash(record_files: dict[str, dict[str, Any]]) -> str:
    h = hashlib.sha256()
    for name, rec in record_files.items():
        h.update(f"{name}:{rec['sha256']};".encode())
    return h.hexdigest()


class ArtifactIOManager(ConfigurableIOManager):
    """Writes typed pipeline artifacts under ``root`` in open formats (Parquet, npz, JSON, PLY, MP4).

    ``root``: a folder, or an object-store URL (:mod:`assets.storage`). ``step_locks``: each step
    takes the partition's lock in its own process (the in-process executor: the run's process holds
    it for the whole run). With an executor that runs steps in other, long-lived processes (Dask
    workers), the process launching the run holds it instead (:meth:`hold_partition`) and steps
    take none: a worker would otherwise keep it after the run, or refuse its sibling steps.
    """

    root: str
    step_locks: bool = True

    @property
    def remote(self) -> bool:
        return is_remote(self.root)

    def _store(self):
        return object_store(self.root)

    def _dir(self, context: OutputContext | InputContext) -> Path:
        asset = context.asset_key.path[-1]
        partition = context.asset_partition_key if context.has_asset_partitions else "__all__"
        return artifact_dir(self.root, asset, partition)

    def directory(self, asset: str, partition: str) -> Path:
        return artifact_dir(self.root, asset, partition)

    def intact(self, asset: str, partition: str) -> bool:
        """Whether the artifact's files are all there with the bytes its record lists."""
        if self.remote:
            return self._store().intact(asset, validate_dataset_name(partition))
        directory = self.directory(asset, partition)
        recover_dir(directory)
        try:
            record = read_artifact_record(directory)
        except ArtifactError:
            return False
        ok, files = verify_files(directory, record.get("files", {}))
        if ok and files != record.get("files"):
            # Verified by content; keep the identities found (older records lack inode and change
            # time), so the next check is a stat again. A record that cannot be written costs reads.
            with contextlib.suppress(OSError, AtlasError):
                write_json_atomic(directory / "_artifact.json", {**record, "files": files})
        return ok

    def load_artifact(self, asset: str, partition: str) -> Any:
        """The typed artifact of ``asset``/``partition`` (what ``load_input`` gives an asset)."""
        if self.remote:  # a verified local copy of the current version
            local, record = self._store().fetch(asset, validate_dataset_name(partition))
            return _load_typed(local, record)
        directory = self.directory(asset, partition)
        recover_dir(directory)
        return _load_typed(directory, read_artifact_record(directory))

    def stage(self, asset: str, partition: str, obj: Any, run_id: str | None = None) -> StagedArtifact:
        """Write ``obj`` into a fresh temporary folder beside its target and describe it: the sha256
        (and size, mtime) of every file and their content hash. Nothing at the target changes until
        :meth:`commit`."""
        type_name = type(obj).__name__
        handler = ARTIFACT_TYPES.get(type_name)
        if handler is None:
            raise TypeError(f"ArtifactIOManager cannot store a {type_name}; known: {sorted(ARTIFACT_TYPES)}")
        target = self.directory(asset, partition)
        tmp = stage_dir(self._local_target(asset, partition))
        try:
            files = handler.save(obj, tmp) if handler is ParquetTable else obj.save(tmp)
            record_files = _file_records(list(files))
            content_hash = _content_hash(record_files)
            record = {
                "type": type_name,
                "asset": asset,
                "partition": partition,
                "run_id": run_id,
                "content_hash": content_hash,
                "files": record_files,
            }
            write_json_atomic(tmp / "_artifact.json", record)
        except OSError as exc:
            discard_dir(tmp)
            where = exc.filename or tmp
            raise WriteError(target, f"cannot write the {asset} artifact ({where}): {exc.strerror or exc}", exc.errno) from exc
        except BaseException:
            discard_dir(tmp)
            raise
        return StagedArtifact(tmp, target, record, obj)

    def _local_target(self, asset: str, partition: str) -> Path:
        """Where the artifact is staged: beside its folder, or (object-store root) in this machine's
        scratch folder, from where it is uploaded."""
        if self.remote:
            return local_scratch() / "staging" / root_key(self.root) / asset / validate_dataset_name(partition)
        return self.directory(asset, partition)

    def staging_folder(self, asset: str, partition: str) -> Path:
        """An empty scratch folder beside the artifact's target (same file system, so its files
        move into the artifact by rename); left-overs of dead runs are removed by the next run."""
        return stage_dir(self._local_target(asset, partition))

    def prepare(self, asset: str, partition: str) -> None:
        """Before computing: repair interrupted swaps, refuse a target that is not ours, and make
        sure the folder is writable with room for the new version (fails in milliseconds, not
        after the work)."""
        if self.remote:
            self._store().check_prefix(asset, validate_dataset_name(partition))
            check_writable(self._local_target(asset, partition).parent)  # the local staging
            return
        target = self.directory(asset, partition)
        check_output_dir(target, ARTIFACT_KIND, what=f"artifact folder of {asset}")  # repairs swaps first
        previous = sum(p.stat().st_size for p in target.iterdir() if p.is_file()) if target.is_dir() else 0
        check_writable(target.parent, max(MIN_FREE_BYTES, FREE_SPACE_FACTOR * previous))

    def _lock(self, partition: str) -> ProcessLock:
        # An object store has no file locks: a remote root's locks live on this machine (runs on
        # other machines are kept apart by the run queue's per-partition limit, README).
        base = local_scratch() / "locks" / root_key(self.root) if self.remote else Path(self.root) / LOCKS_DIR
        return ProcessLock(base / f"{validate_dataset_name(partition)}.lock")

    def lock_partition(self, partition: str, run_id: str) -> bool:
        """Hold this partition for the current process (and so its run); True when newly taken.

        Raises PartitionBusyError when another live process holds it: two runs of one partition
        would otherwise interleave and the loser would report success for output that is gone.
        Without ``step_locks`` (the launcher holds the lock) this takes nothing and returns False.
        """
        if not self.step_locks:
            return False
        return self.hold_partition(partition, f"Dagster run {run_id}", run_id=run_id)

    def hold_partition(self, partition: str, what: str, **info: Any) -> bool:
        """Take the partition's lock for this process, described as ``what``; see :meth:`lock_partition`."""
        try:
            return self._lock(partition).acquire({"what": what, "partition": partition, **info})
        except LockedError as exc:
            raise PartitionBusyError(
                f"partition '{partition}' is being materialized by another run ({exc}); this run stops before "
                "computing or writing anything: wait for that run to finish, then run again") from None

    def unlock_partition(self, partition: str) -> None:
        self._lock(partition).release()

    def commit(self, staged: StagedArtifact) -> Path:
        """Swap a staged folder into place (crash-consistent: see :func:`atlas_pipeline.io_utils.commit_dir`).
        A recompute that wrote the same bytes as the artifact in place leaves that one untouched
        (same files, same modification times). Object store: upload, then one pointer PUT."""
        if self.remote:
            try:
                self._store().publish(staged.staging, staged.record)
            finally:
                discard_dir(staged.staging)
            return staged.target
        check_output_dir(staged.target, ARTIFACT_KIND, what="artifact folder")
        try:
            same = read_artifact_record(staged.target).get("content_hash") == staged.record["content_hash"]
        except ArtifactError:
            same = False
        if same and self.intact(staged.record["asset"], staged.record["partition"]):
            discard_dir(staged.staging)
            return staged.target
        # The marker records where the artifact lives: a copy of it elsewhere (cp -a) is then a user's bundle.
        return commit_dir(staged.staging, staged.target, ARTIFACT_KIND, {"path": str(Path(staged.target).resolve())})

    # -- Dagster IO manager protocol ------------------------------------------------------------

    def handle_output(self, context: OutputContext, obj: Any) -> None:
        target = self._dir(context)
        if isinstance(obj, Reused):  # current on disk: nothing to write
            context.add_output_metadata({"path": MetadataValue.path(str(target))})
            return
        if not isinstance(obj, StagedArtifact):
            partition = context.asset_partition_key if context.has_asset_partitions else "__all__"
            obj = self.stage(context.asset_key.path[-1], partition, obj, run_id=context.run_id)
        if (str(obj.target) != str(target)) if self.remote else (obj.target.resolve() != target.resolve()):
            raise ArtifactError(f"staged artifact for {obj.target} handed to the output of {target}")
        self.commit(obj)
        context.add_output_metadata({"path": MetadataValue.path(str(target)),
                                     "content_hash": obj.record["content_hash"][:16]})

    def load_input(self, context: InputContext) -> Any:
        if not context.has_asset_partitions:
            return self.load_artifact(context.asset_key.path[-1], "__all__")
        keys = context.asset_partition_keys
        if not keys:  # an input from another partition that this partition does not have (a first visit)
            return None
        asset = context.asset_key.path[-1]
        try:
            return self.load_artifact(asset, keys[0])
        except ArtifactError as exc:
            if not context.has_partition_key or keys[0] == context.partition_key:
                raise
            raise ArtifactError(f"{asset} of partition {keys[0]}, an input of partition {context.partition_key}, "
                                f"is not available ({exc}): run `atlas-gs run {keys[0]}` first") from exc

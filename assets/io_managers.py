"""Typed IO managers: each artifact type is written in an open format under
``<root>/<asset>/<partition>/``, never pickled.

An artifact type is a library class with ``save(directory) -> list[Path]`` and a classmethod
``load(directory)``. The IO manager writes into a temporary folder and swaps it into place, so a
failed or interrupted run leaves the previous artifact whole. It also records ``_artifact.json``
(type, files, sha256 of each, one content hash over all of them) beside the files.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
from dagster import ConfigurableIOManager, InputContext, OutputContext

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.builder import GaussianWorld
from atlas_pipeline.io_utils import atomic_dir, atomic_path, sha256_file, write_json_atomic
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.mapping.keyframes import KeyframeSet
from atlas_pipeline.perception.rgbd import FusedFrames
from atlas_pipeline.pipeline import DemoVideos, WorldBundleArtifact
from atlas_pipeline.sensors.registry import validate_dataset_name
from atlas_pipeline.sensors.tum import FrameManifest


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
}


def artifact_dir(root: str | Path, asset: str, partition: str) -> Path:
    """``<root>/<asset>/<partition>``; the partition name is validated before it becomes a path."""
    validate_dataset_name(partition)
    return Path(root) / asset / partition


def read_artifact_record(directory: Path) -> dict[str, Any]:
    path = directory / "_artifact.json"
    if not path.is_file():
        raise ArtifactError(f"{directory}: no artifact record (_artifact.json); materialize the asset first")
    return json.loads(path.read_text())


class ArtifactIOManager(ConfigurableIOManager):
    """Writes typed pipeline artifacts under ``root`` in open formats (Parquet, npz, JSON, PLY, MP4)."""

    root: str

    def _dir(self, context: OutputContext | InputContext) -> Path:
        asset = context.asset_key.path[-1]
        partition = context.asset_partition_key if context.has_asset_partitions else "__all__"
        return artifact_dir(self.root, asset, partition)

    def handle_output(self, context: OutputContext, obj: Any) -> None:
        type_name = type(obj).__name__
        handler = ARTIFACT_TYPES.get(type_name)
        if handler is None:
            raise TypeError(f"ArtifactIOManager cannot store a {type_name}; known: {sorted(ARTIFACT_TYPES)}")
        target = self._dir(context)
        with atomic_dir(target) as tmp:
            files = handler.save(obj, tmp) if handler is ParquetTable else obj.save(tmp)
            record_files = {
                p.name: {"bytes": p.stat().st_size, "sha256": sha256_file(p)} for p in sorted(files)
            }
            h = hashlib.sha256()
            for name, rec in record_files.items():
                h.update(f"{name}:{rec['sha256']};".encode())
            record = {
                "type": type_name,
                "asset": context.asset_key.to_user_string(),
                "partition": context.asset_partition_key if context.has_asset_partitions else None,
                "run_id": context.run_id,
                "content_hash": h.hexdigest(),
                "files": record_files,
            }
            write_json_atomic(tmp / "_artifact.json", record)
        context.add_output_metadata({"path": str(target), "content_hash": record["content_hash"][:16]})

    def load_input(self, context: InputContext) -> Any:
        directory = self._dir(context)
        record = read_artifact_record(directory)
        handler = ARTIFACT_TYPES.get(record.get("type", ""))
        if handler is None:
            raise ArtifactError(f"{directory}: unknown artifact type {record.get('type')!r}")
        return handler.load(directory)

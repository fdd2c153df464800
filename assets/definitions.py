"""The one Dagster ``Definitions`` of Atlas-GS (``dagster dev`` loads ``defs`` from here)."""

from __future__ import annotations

import os
from pathlib import Path

from dagster import (
    AssetSelection,
    Definitions,
    StaticPartitionsDefinition,
    define_asset_job,
)

from assets.io_managers import ArtifactIOManager
from assets.pipeline_assets import build_pipeline_assets
from assets.resources import AtlasConfig
from atlas_pipeline.config import project_root
from atlas_pipeline.sensors.registry import load_registry


def artifacts_root() -> Path:
    """``$ATLAS_ARTIFACTS_DIR`` or ``<project>/artifacts``."""
    env = os.environ.get("ATLAS_ARTIFACTS_DIR")
    return Path(env).resolve() if env else project_root() / "artifacts"


def dataset_partitions(names: list[str] | None = None) -> StaticPartitionsDefinition:
    """One partition per registered dataset (registry order)."""
    return StaticPartitionsDefinition(names if names is not None else list(load_registry()))


def build_definitions(artifacts_dir: str | Path | None = None, profile: str = "default",
                      partition_names: list[str] | None = None) -> Definitions:
    root = str(artifacts_dir if artifacts_dir is not None else artifacts_root())
    partitions = dataset_partitions(partition_names)
    pipeline_assets = build_pipeline_assets(partitions)
    everything = define_asset_job(
        "atlas_gs_all", selection=AssetSelection.all(),
        description="Materialize every Atlas-GS asset of one dataset partition.",
    )
    return Definitions(
        assets=pipeline_assets,
        jobs=[everything],
        resources={
            "artifact_io": ArtifactIOManager(root=root),
            "atlas": AtlasConfig(profile=os.environ.get("ATLAS_PROFILE", profile)),
        },
    )


defs = build_definitions()

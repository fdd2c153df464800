"""Resources: the config profile and the dataset registry, as Dagster sees them."""

from __future__ import annotations

from typing import Any

from dagster import ConfigurableResource
from pydantic import Field

from atlas_pipeline.config import PipelineConfig, load_profile
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import DatasetEntry, load_registry


class AtlasConfig(ConfigurableResource):
    """Which config profile the run uses, with optional dotted overrides.

    ``profile`` is a name under ``configs/`` (``default``, ``demo``) or a path to a YAML file.
    ``overrides`` maps dotted keys to values, e.g. ``{"localization.photometric_weight": 0.5}``.
    """

    profile: str = "default"
    overrides: dict[str, Any] = Field(default_factory=dict)

    def load(self) -> PipelineConfig:
        cfg = load_profile(self.profile)
        return cfg.with_overrides(self.overrides) if self.overrides else cfg

    def dataset(self, name: str) -> DatasetEntry:
        registry = load_registry()
        if name not in registry:
            raise ConfigError(f"dataset '{name}' is not in the registry ({', '.join(registry)})")
        return registry[name]

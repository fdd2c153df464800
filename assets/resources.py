"""Resources: the config profile and the dataset registry, as Dagster sees them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dagster import ConfigurableResource
from pydantic import Field

from atlas_pipeline.config import PipelineConfig, configs_dir, load_profile
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import DatasetEntry, load_registry


# Parsed profiles by (profile, file size and mtime, overrides); PipelineConfig is immutable.
_LOADED: dict[tuple, PipelineConfig] = {}


def _file_stamp(profile: str) -> tuple:
    p = Path(profile)
    path = p if (p.suffix in (".yaml", ".yml") or p.exists()) else configs_dir() / f"{profile}.yaml"
    try:
        st = path.stat()
    except OSError:
        return (str(path), None)
    return (str(path.resolve()), st.st_size, st.st_mtime_ns)


class AtlasConfig(ConfigurableResource):
    """Which config profile the run uses, with optional dotted overrides.

    ``profile`` is a name under ``configs/`` (``default``, ``demo``) or a path to a YAML file.
    ``overrides`` maps dotted keys to values, e.g. ``{"localization.photometric_weight": 0.5}``.
    """

    profile: str = "default"
    overrides: dict[str, Any] = Field(default_factory=dict)

    def load(self) -> PipelineConfig:
        """The resolved config (parsed once per profile file version: every asset step asks)."""
        key = (self.profile, _file_stamp(self.profile), json.dumps(self.overrides, sort_keys=True, default=str))
        cfg = _LOADED.get(key)
        if cfg is None:
            cfg = load_profile(self.profile)
            cfg = cfg.with_overrides(self.overrides) if self.overrides else cfg
            if len(_LOADED) > 64:
                _LOADED.clear()
            _LOADED[key] = cfg
        return cfg

    def dataset(self, name: str) -> DatasetEntry:
        registry = load_registry()
        if name not in registry:
            raise ConfigError(f"dataset '{name}' is not in the registry ({', '.join(registry)})")
        return registry[name]

"""The pipeline's settings as typed Dagster config, generated from the library's config dataclasses.

:func:`atlas_config` builds the ``atlas`` resource for one profile: an :class:`AtlasConfig` with one
nested :class:`dagster.Config` per section of :class:`atlas_pipeline.config.PipelineConfig`
(``fusion``, ``mapping``, ...), each field typed as the dataclass declares it (``Literal`` choices
become enums, ``tuple[int, ...]`` a list) and defaulting to the profile's value, with a description
taken from the comment beside the field in ``atlas_pipeline/config.py`` and its allowed range. The
launchpad therefore lists every setting with its description and default, and a run config that
sets one field keeps the profile's value for every other. :meth:`AtlasConfig.load` validates the
whole config with the library's own rules (errors name the dotted field: ``mapping.voxel_size_m
must be a finite number > 0``), when a run starts.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import re
from functools import lru_cache
from typing import Any, Literal, get_args, get_origin, get_type_hints

from dagster import Config, ConfigurableResource
from pydantic import Field, create_model

from atlas_pipeline.config import RANGE_KEY, PipelineConfig, load_profile
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import DatasetEntry, load_registry

_SECTION_TYPES = {name: tp for name, tp in get_type_hints(PipelineConfig).items() if dataclasses.is_dataclass(tp)}
SECTIONS = tuple(_SECTION_TYPES)  # dataset, fusion, mapping, localization, transitions, video, evaluation
PROFILE_ENV = "ATLAS_PROFILE"  # the profile when none is named (the code location's default)


class AtlasConfig(ConfigurableResource):
    """The run's settings: the profile's values, each overridable per run (launchpad, ``--set``).

    The section fields are added per profile by :func:`atlas_config`; ``load()`` is what assets use.
    """

    profile: str = Field("default", description="the profile these defaults were read from (configs/NAME.yaml)")

    def load(self) -> PipelineConfig:
        """The run's :class:`PipelineConfig`, validated whole; a bad value raises ``ConfigError``
        naming the dotted field (``run config: localization.max_ate_m must be ...``)."""
        return _validated(json.dumps(self.model_dump(), sort_keys=True))


@lru_cache(maxsize=64)
def _validated(dumped: str) -> PipelineConfig:
    return PipelineConfig.from_dict(json.loads(dumped), "run config")


def dataset_entry(name: str) -> DatasetEntry:
    """The registered dataset behind partition ``name``."""
    registry = load_registry()
    if name not in registry:
        raise ConfigError(f"dataset '{name}' is not in the registry ({', '.join(registry)})")
    return registry[name]


def resolve_profile(profile: str | None) -> str:
    """An explicit profile wins; ``$ATLAS_PROFILE`` is only the default; then ``default``."""
    return profile or os.environ.get(PROFILE_ENV) or "default"


def atlas_config(profile: str | None = None, overrides: dict[str, Any] | None = None) -> AtlasConfig:
    """The ``atlas`` resource for ``profile`` (see :func:`resolve_profile`) with ``overrides``
    (dotted keys) as the defaults of a run; the profile and overrides are validated first."""
    name = resolve_profile(profile)
    cfg = load_profile(name)
    cfg = cfg.with_overrides(overrides, "--set") if overrides else cfg
    return _resource_class(json.dumps(cfg.to_dict(), sort_keys=True, default=list))()


@lru_cache(maxsize=16)
def _resource_class(dumped: str) -> type[AtlasConfig]:
    values = json.loads(dumped)
    sections = {}
    for name, cls in _SECTION_TYPES.items():
        model = _section_model(cls, tuple(sorted((k, json.dumps(v)) for k, v in values[name].items())))
        sections[name] = (model, Field(default_factory=model, description=f"the '{name}' section of the profile"))
    return create_model("AtlasConfig", __base__=AtlasConfig, __module__=__name__,
                        profile=(str, Field(values["profile"], description=AtlasConfig.model_fields["profile"].description)),
                        **sections)


@lru_cache(maxsize=128)
def _section_model(cls: type, values: tuple) -> type[Config]:
    """A ``Config`` class mirroring dataclass ``cls`` with ``values`` as defaults."""
    hints, notes, vals = get_type_hints(cls), _comments(cls), {k: json.loads(v) for k, v in values}
    fields = {}
    for f in dataclasses.fields(cls):
        rng = f.metadata.get(RANGE_KEY)
        bound = rng.describe() if rng is not None else ""
        choices = f"one of {', '.join(map(str, get_args(hints[f.name])))}" if get_origin(hints[f.name]) is Literal else ""
        desc = "; ".join(s for s in (notes.get(f.name, "").rstrip("."), choices, f"allowed: {bound}" if bound else "") if s)
        value = vals[f.name]  # JSON: a tuple is a list already
        fields[f.name] = (_config_type(hints[f.name]), Field(value, description=desc or f.name))
    return create_model(cls.__name__.replace("Config", "Settings"), __base__=Config, __module__=__name__, **fields)


def _config_type(tp: Any) -> Any:
    return list[get_args(tp)[0]] if get_origin(tp) is tuple else tp  # Dagster config has lists, not tuples


def _comments(cls: type) -> dict[str, str]:
    """``{field: comment}`` from the source of a config dataclass: the comment at the end of the
    field's line, or the comment lines right above it."""
    out, above = {}, []
    for line in inspect.getsource(cls).splitlines():
        s = line.strip()
        if s.startswith("#"):
            above.append(s.lstrip("# ").strip())
            continue
        m = re.match(r"(\w+)\s*:[^#]*?(?:#\s*(.*))?$", s)
        if m and not s.startswith(("class", "def", "@")):
            out[m.group(1)] = " ".join(above + ([m.group(2).strip()] if m.group(2) else []))
        above = []
    return out

"""The pipeline's settings as typed Dagster config, mirrored from the library's pydantic models.

:func:`atlas_config` builds the ``atlas`` resource for one profile: an :class:`AtlasConfig` with one
nested :class:`dagster.Config` per section of :class:`atlas_pipeline.config.PipelineConfig`
(``fusion``, ``mapping`` with ``mapping.fit``, ...), each field with the model's type (tuples as
lists: Dagster config has no tuples), description and allowed range, defaulting to the profile's
value. The launchpad therefore lists every setting with its description and default, and a run
config that sets one field keeps the profile's value for every other. :meth:`AtlasConfig.load`
validates the whole config with the library's model (errors name the dotted field:
``run config: mapping.voxel_size_m must be greater than 0, got -1``) when a run starts.
"""

from __future__ import annotations

import json
import os
from functools import lru_cache
from typing import Annotated, Any, Literal, get_args, get_origin

from dagster import Config, ConfigurableResource, Failure
from pydantic import BaseModel, Field, create_model

from atlas_pipeline.config import PipelineConfig, load_profile
from atlas_pipeline.config_reference import allowed_range
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import DatasetEntry, load_registry

# dataset, fusion, mapping, localization, transitions, video, evaluation
SECTIONS = tuple(k for k, f in PipelineConfig.model_fields.items() if isinstance(f.annotation, type)
                 and issubclass(f.annotation, BaseModel))
PROFILE_ENV = "ATLAS_PROFILE"  # the profile when none is named (the code location's default)


class RunConfigError(Failure, ConfigError):
    """A run config the library's model refuses. A Dagster ``Failure``, so the UI's first line is
    the message (naming the field), not a stack trace; a ``ConfigError`` for every other caller."""

    def __init__(self, message: str):
        Failure.__init__(self, description=message, allow_retries=False)


class AtlasConfig(ConfigurableResource):
    """The run's settings: the profile's values, each overridable per run (launchpad, ``--set``).

    The section fields are added per profile by :func:`atlas_config`; ``load()`` is what assets use.
    """

    profile: str = Field("default", description="the profile these defaults were read from (configs/NAME.yaml)")

    def load(self) -> PipelineConfig:
        """The run's :class:`PipelineConfig`, validated whole; a bad value raises ``ConfigError``
        naming the dotted field (``run config: localization.max_ate_m must be ...``)."""
        try:
            return _validated(json.dumps(self.model_dump(), sort_keys=True))
        except ConfigError as exc:
            raise RunConfigError(str(exc)) from None


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
    return _resource_class(json.dumps(cfg.to_dict(), sort_keys=True))()


@lru_cache(maxsize=16)
def _resource_class(dumped: str) -> type[AtlasConfig]:
    return _mirror(PipelineConfig, json.loads(dumped), "AtlasConfig", AtlasConfig)


def _mirror(model: type[BaseModel], values: dict[str, Any], name: str, base: type) -> type:
    """A Dagster ``Config`` (or ``base``) class with ``model``'s fields and ``values`` as defaults;
    sub-models become nested classes. No constraints: the library's model checks them in
    :meth:`AtlasConfig.load`, with messages naming the field."""
    fields: dict[str, Any] = {}
    for key, info in model.model_fields.items():
        tp = info.annotation
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            sub = _mirror(tp, values[key], tp.__name__.replace("Config", "Settings"), Config)
            fields[key] = (sub, Field(default_factory=sub, description=info.description or f"the '{key}' section"))
            continue
        if get_origin(tp) is tuple:  # Dagster config has lists, not tuples (nor element constraints)
            elem = get_args(tp)[0]
            tp = list[get_args(elem)[0] if get_origin(elem) is Annotated else elem]
        fields[key] = (tp, Field(values[key], description=_description(info)))
    return create_model(name, __base__=base, __module__=__name__, **fields)


def _description(info: Any) -> str:
    """The model field's description, its choices and its allowed range, for the launchpad."""
    bounds = allowed_range(info)
    choices = get_args(info.annotation) if get_origin(info.annotation) is Literal else ()
    return "; ".join([info.description or ""] + ([f"one of {', '.join(choices)}"] if choices else [])
                     + ([f"allowed: {bounds}"] if bounds else [])).strip("; ")

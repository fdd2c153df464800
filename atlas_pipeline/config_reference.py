"""The field reference of ``docs/configuration.md``, written from the config models.

``python -m atlas_pipeline.config_reference`` prints the tables (every field with its default,
allowed range and description); a test keeps the doc equal to them, so the doc cannot drift from
the models it describes.
"""

from __future__ import annotations

import json
from typing import Any

from annotated_types import Ge, Gt, Le, Lt
from pydantic import BaseModel

from atlas_pipeline.config import PipelineConfig

__all__ = ["BEGIN_MARK", "END_MARK", "markdown_tables", "allowed_range"]

BEGIN_MARK = "<!-- fields: python -m atlas_pipeline.config_reference -->"
END_MARK = "<!-- end of fields -->"
_BOUNDS = ((Gt, "gt", ">"), (Ge, "ge", ">="), (Lt, "lt", "<"), (Le, "le", "<="))


def _value(v: Any) -> str:
    if v is None or isinstance(v, (bool, str, tuple)):
        return f"`{json.dumps(list(v) if isinstance(v, tuple) else v)}`".replace('"', "")
    return repr(v)


def allowed_range(info: Any) -> str:
    """A model field's bounds in words (``> 0, <= 1``; empty when unbounded), for the docs and the launchpad."""
    return ", ".join(f"{word} {getattr(m, attr)}" for m in info.metadata for cls, attr, word in _BOUNDS
                     if isinstance(m, cls))


def _rows(model: type[BaseModel], values: BaseModel, prefix: str = "") -> list[str]:
    out = []
    for name, info in model.model_fields.items():
        tp = info.annotation
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            out += _rows(tp, getattr(values, name), f"{prefix}{name}.")
        else:
            out.append(f"| `{prefix}{name}` | {_value(getattr(values, name))} | {allowed_range(info)} | {info.description} |")
    return out


def markdown_tables() -> str:
    """One table per section of :class:`PipelineConfig` (defaults of the models), between the marks."""
    cfg, parts = PipelineConfig(), [BEGIN_MARK]
    for section, info in PipelineConfig.model_fields.items():
        if not (isinstance(info.annotation, type) and issubclass(info.annotation, BaseModel)):
            continue
        parts += [f"### `{section}`", "", "| field | default | allowed | meaning |", "|---|---|---|---|",
                  *_rows(info.annotation, getattr(cfg, section)), ""]
    return "\n".join(parts + [END_MARK])


if __name__ == "__main__":
    print(markdown_tables())

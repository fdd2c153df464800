"""Configuration profiles: YAML files in ``configs/`` parsed into frozen, validated dataclasses.

A profile has one section per pipeline stage. Each stage's artifacts depend only on its own
section (and upstream artifacts), which is what lets the orchestrator tell which stages are stale
after a config change.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal, get_args, get_type_hints

import yaml

from atlas_pipeline.errors import ConfigError

__all__ = [
    "DatasetConfig",
    "FusionConfig",
    "MappingConfig",
    "LocalizationConfig",
    "TransitionsConfig",
    "VideoConfig",
    "PipelineConfig",
    "project_root",
    "configs_dir",
    "load_profile",
    "load_yaml_file",
    "section_hash",
]

PoseSource = Literal["auto", "ground_truth", "estimated"]


@dataclass(frozen=True)
class DatasetConfig:
    max_frames: int | None = None  # keep the first N frames; None = all


@dataclass(frozen=True)
class FusionConfig:
    min_depth_m: float = 0.1
    max_depth_m: float = 4.0
    stride: int = 2  # back-project every ``stride``-th pixel in u and v


@dataclass(frozen=True)
class MappingConfig:
    pose_source: PoseSource = "auto"
    voxel_size_m: float = 0.02
    keyframe_translation_m: float = 0.08
    keyframe_rotation_deg: float = 8.0
    colour_refinement_iterations: int = 3  # fit Gaussian colours to the keyframe images; 0 = mean colours
    colour_refinement_scale: float = 0.5  # image scale of that fit
    optimization_epochs: int = 30  # 3DGS-style fit of every Gaussian parameter to the keyframes; 0 = off
    optimization_max_steps: int = 600  # cap on its steps (one keyframe each), whatever the keyframe count
    optimization_scale: float = 0.5  # image scale of that fit (1/n)
    optimization_depth_weight: float = 1.0  # depth L1 (m) against colour L1 ([0, 1]) in its loss


@dataclass(frozen=True)
class LocalizationConfig:
    iterations: tuple[int, ...] = (12, 8, 5)  # Gauss-Newton iterations per pyramid level, coarse to fine
    finest_level: int = 1  # finest pyramid level used: 0 = full resolution, 1 = half, ...
    max_correspondence_m: float = 0.1  # association gate at the coarsest level (halves per level)
    min_correspondence_m: float = 0.02  # ... and its floor, used at the finest level and for grading
    huber_depth_m: float = 0.01
    photometric_weight: float = 0.1  # 0 = geometry only
    motion_model: Literal["constant_velocity", "none"] = "constant_velocity"
    min_fitness: float = 0.15  # share of frame points with a model correspondence; below it: lost
    min_agreement: float = 0.6  # share of the points landing on the map that fit it; below it: lost
    max_residual_m: float = 0.02  # RMS point-to-plane residual; above it: lost
    reference_translation_m: float = 0.05  # photometric reference frame renewed after this motion
    reference_rotation_deg: float = 5.0
    relocalize: bool = True  # lost frames try global relocalization against the map
    max_ate_m: float = 0.05  # blocking check: ATE RMSE above this (where ground truth exists) fails


@dataclass(frozen=True)
class TransitionsConfig:
    pose_source: Literal["estimated", "ground_truth"] = "estimated"


@dataclass(frozen=True)
class VideoConfig:
    fps: float = 15.0
    orbit_frames: int = 90
    orbit_height_m: float = 1.0
    orbit_radius_scale: float = 1.2
    scale: float = 1.0


@dataclass(frozen=True)
class EvaluationConfig:
    view_stride: int = 2  # evaluate every n-th held-out (non-keyframe) frame
    max_views: int | None = None  # cap on the number of views; None = all selected


@dataclass(frozen=True)
class PipelineConfig:
    """A whole resolved profile."""

    profile: str = "default"
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    transitions: TransitionsConfig = field(default_factory=TransitionsConfig)
    video: VideoConfig = field(default_factory=VideoConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> "PipelineConfig":
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: a profile must be a mapping of sections")
        return _build(cls, data, source, "")

    def with_overrides(self, overrides: dict[str, Any], source: str = "<overrides>") -> "PipelineConfig":
        """Copy with dotted-key overrides applied, e.g. ``{"localization.photometric_weight": 0.5}``."""
        data = self.to_dict()
        for dotted, value in overrides.items():
            parts = dotted.split(".")
            node = data
            for p in parts[:-1]:
                if p not in node or not isinstance(node[p], dict):
                    raise ConfigError(f"{source}: unknown config section '{dotted}'")
                node = node[p]
            if parts[-1] not in node:
                raise ConfigError(f"{source}: unknown config key '{dotted}'")
            node[parts[-1]] = value
        return PipelineConfig.from_dict(data, source)


def _check_value(tp: Any, value: Any, where: str) -> Any:
    """Coerce and check one scalar against its annotated type."""
    args = get_args(tp)
    if getattr(tp, "__origin__", None) is Literal:
        if value not in args:
            raise ConfigError(f"{where}: must be one of {list(args)}, got {value!r}")
        return value
    if getattr(tp, "__origin__", None) is tuple:  # tuple[T, ...] from a YAML list
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: must be a list, got {value!r}")
        return tuple(_check_value(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
    if type(None) in args:  # Optional[...]
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)][0]
        return _check_value(inner, value, where)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: must be a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported config type {tp}")  # pragma: no cover


def _build(cls: type, data: dict[str, Any], source: str, prefix: str) -> Any:
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(prefix + u for u in unknown)}")
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        tp = hints[f.name]
        value = data[f.name]
        where = f"{source}: {prefix}{f.name}"
        if dataclasses.is_dataclass(tp):
            if value is None:
                value = {}
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: must be a mapping")
            kwargs[f.name] = _build(tp, value, source, prefix + f.name + ".")
        else:
            kwargs[f.name] = _check_value(tp, value, where)
    obj = cls(**kwargs)
    _validate(obj, source)
    return obj


def _validate(obj: Any, source: str) -> None:
    """Range checks that types alone cannot express."""
    def bad(msg: str) -> ConfigError:
        return ConfigError(f"{source}: {msg}")

    if isinstance(obj, DatasetConfig) and obj.max_frames is not None and obj.max_frames < 2:
        raise bad("dataset.max_frames must be at least 2 (or null)")
    if isinstance(obj, FusionConfig):
        if not 0 <= obj.min_depth_m < obj.max_depth_m:
            raise bad("fusion needs 0 <= min_depth_m < max_depth_m")
        if obj.stride < 1:
            raise bad("fusion.stride must be >= 1")
    if isinstance(obj, MappingConfig):
        if obj.voxel_size_m <= 0:
            raise bad("mapping.voxel_size_m must be positive")
        if obj.keyframe_translation_m < 0 or obj.keyframe_rotation_deg < 0:
            raise bad("mapping keyframe thresholds must be non-negative")
        if obj.colour_refinement_iterations < 0 or not 0 < obj.colour_refinement_scale <= 1:
            raise bad("mapping needs colour_refinement_iterations >= 0 and 0 < colour_refinement_scale <= 1")
        inv = 1.0 / obj.optimization_scale if obj.optimization_scale > 0 else 0.0
        if obj.optimization_epochs < 0 or not (0 < obj.optimization_scale <= 1 and abs(inv - round(inv)) < 1e-9):
            raise bad("mapping needs optimization_epochs >= 0 and optimization_scale = 1/n (1, 0.5, 0.25, ...)")
        if obj.optimization_max_steps < 1:
            raise bad("mapping.optimization_max_steps must be at least 1")
        if obj.optimization_depth_weight < 0:
            raise bad("mapping.optimization_depth_weight must be non-negative")
    if isinstance(obj, LocalizationConfig):
        if not obj.iterations or min(obj.iterations) < 0 or max(obj.iterations) < 1:
            raise bad("localization.iterations needs one non-negative count per pyramid level, at least one > 0")
        if not 0 <= obj.finest_level <= 3 or obj.finest_level + len(obj.iterations) > 6:
            raise bad("localization.finest_level must lie in 0..3 with at most 6 pyramid levels in all")
        if not 0 < obj.min_correspondence_m <= obj.max_correspondence_m:
            raise bad("localization needs 0 < min_correspondence_m <= max_correspondence_m")
        if obj.huber_depth_m <= 0 or obj.photometric_weight < 0 or obj.max_residual_m <= 0:
            raise bad("localization needs huber_depth_m > 0, photometric_weight >= 0, max_residual_m > 0")
        if not 0 <= obj.min_fitness <= 1 or not 0 <= obj.min_agreement <= 1:
            raise bad("localization.min_fitness and min_agreement must lie in [0, 1]")
        if not obj.max_ate_m > 0:
            raise bad("localization.max_ate_m must be positive")
    if isinstance(obj, EvaluationConfig):
        if obj.view_stride < 1 or (obj.max_views is not None and obj.max_views < 1):
            raise bad("evaluation needs view_stride >= 1 and max_views >= 1 (or null)")
    if isinstance(obj, VideoConfig):
        if obj.fps <= 0 or obj.orbit_frames < 1 or not 0 < obj.scale <= 4:
            raise bad("video needs fps > 0, orbit_frames >= 1 and 0 < scale <= 4")


def project_root() -> Path:
    """Root of the project (holds ``configs/``); ``ATLAS_PROJECT_ROOT`` overrides it."""
    env = os.environ.get("ATLAS_PROJECT_ROOT")
    if env:
        return Path(env).resolve()
    return Path(__file__).resolve().parents[1]


def configs_dir() -> Path:
    return project_root() / "configs"


def load_yaml_file(path: Path) -> Any:
    """Parse a YAML file with the safe loader; errors name the file and line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise ConfigError(f"{where}: invalid YAML ({getattr(exc, 'problem', exc)})") from exc


def load_profile(name_or_path: str | Path = "default") -> PipelineConfig:
    """Load a profile by name (``configs/<name>.yaml``) or by path to a YAML file."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        path = p
    else:
        name = str(name_or_path)
        if not name.replace("-", "").replace("_", "").isalnum():
            raise ConfigError(f"invalid profile name {name!r}")
        path = configs_dir() / f"{name}.yaml"
    data = load_yaml_file(path)
    if data is None:
        data = {}
    return PipelineConfig.from_dict(data, str(path))


def section_hash(section: Any) -> str:
    """Stable short hash of one config section (or any JSON-able value)."""
    if dataclasses.is_dataclass(section):
        section = dataclasses.asdict(section)
    blob = json.dumps(section, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]

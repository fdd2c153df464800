"""Configuration profiles: YAML files in ``configs/`` parsed into frozen, validated dataclasses.

A profile has one section per pipeline stage. Each stage's artifacts depend only on its own
section (and upstream artifacts), which is what lets the orchestrator tell which stages are stale
after a config change.

Validation happens whole and first, when a profile or an override is parsed
(:meth:`PipelineConfig.from_dict`, :meth:`PipelineConfig.with_overrides`, :func:`load_profile`),
so a bad value fails before any stage runs, never as a deep error three assets later. Each field
declares its allowed range beside its declaration (``metadata["range"]``, a :class:`Range`); the
type comes from its annotation (ints are ints, floats are finite numbers, tuples are checked
element-wise, Literals list their choices). Rules that tie fields together are named checks
(:data:`_SECTION_CHECKS`). Every error names the dotted field and the offending value, prefixed by
the source (YAML path or ``--set``): ``--set: mapping.voxel_size_m must be a finite number > 0, got nan``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, Literal, get_args, get_origin, get_type_hints

import yaml

from atlas_pipeline.errors import ConfigError

__all__ = [
    "DatasetConfig",
    "FusionConfig",
    "MappingConfig",
    "LocalizationConfig",
    "TransitionsConfig",
    "VideoConfig",
    "EvaluationConfig",
    "PipelineConfig",
    "Range",
    "project_root",
    "source_root",
    "configs_dir",
    "load_profile",
    "load_yaml_file",
    "parse_yaml",
    "UniqueKeyLoader",
    "section_hash",
]

# Profiles and registries are a few kB; refuse huge files before parsing them.
MAX_YAML_BYTES = 4 * 1024 * 1024

PoseSource = Literal["auto", "ground_truth", "estimated"]


@dataclass(frozen=True)
class Range:
    """Bounds a number (or each element of a tuple of numbers) must lie within; ``None``: unbounded.

    ``gt``/``lt`` are open bounds, ``ge``/``le`` closed ones (give at most one per side).
    """

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def __post_init__(self) -> None:
        if self.ge is not None and self.gt is not None or self.le is not None and self.lt is not None:
            raise ValueError("a Range takes at most one lower and one upper bound")

    def contains(self, v: float) -> bool:
        return ((self.ge is None or v >= self.ge) and (self.gt is None or v > self.gt)
                and (self.le is None or v <= self.le) and (self.lt is None or v < self.lt))

    def describe(self) -> str:
        """``> 0``, ``>= 2``, ``in (0, 1]``, ...; empty when unbounded."""
        lo, lo_open = (self.gt, True) if self.gt is not None else (self.ge, False)
        hi, hi_open = (self.lt, True) if self.lt is not None else (self.le, False)
        if lo is not None and hi is not None:
            return f"in {'(' if lo_open else '['}{_bound(lo)}, {_bound(hi)}{')' if hi_open else ']'}"
        if lo is not None:
            return f"{'>' if lo_open else '>='} {_bound(lo)}"
        if hi is not None:
            return f"{'<' if hi_open else '<='} {_bound(hi)}"
        return ""


def _bound(v: float) -> str:
    """A bound in words: whole numbers in full (``100000``, not ``1e+05``), others as ``%g``."""
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


POSITIVE = Range(gt=0)
NON_NEGATIVE = Range(ge=0)
UNIT_INTERVAL = Range(ge=0, le=1)  # shares and fractions
SCALE_AT_MOST_ONE = Range(gt=0, le=1)  # image scale factors that only shrink
MIN_FRAMES = 2  # a sequence needs two frames for one motion
MAX_FINEST_LEVEL = 3  # 1/8 resolution: coarser leaves too few pixels to track on
MAX_PYRAMID_LEVELS = 6  # finest_level + number of levels tracked
MAX_VIDEO_SCALE = 4.0  # renders beyond 4x the sensor size only cost time
# Upper bounds of every count: far above any useful value, low enough that a typo (1e9 for 90) is
# an error naming the field at load time, not hours of work or tens of GB later.
MAX_FRAMES = 1_000_000  # frames (views, keyframes) of one recording: 9 hours at 30 Hz
MAX_PIXEL_STRIDE = 64  # back-projecting every 64th pixel leaves 10x7 points of a 640x480 image
MAX_REFINEMENT_ITERATIONS = 1_000  # colour-only passes over the keyframes (default 0)
MAX_EPOCHS = 10_000  # passes of the keyframe fit over its keyframes (default 30)
MAX_FIT_STEPS = 100_000  # steps of the keyframe fit, one keyframe each: about a day of CPU (default 300)
MAX_STEPS_PER_KEYFRAME = 1_000  # (default 10)
MAX_COARSE_FACTOR = 16  # the coarse level at 1/16 of the fit's scale: 20 pixels across at 640 x 0.5
MAX_GN_ITERATIONS = 100  # Gauss-Newton iterations of one pyramid level (default 12, 8, 5)
MAX_VIDEO_FRAMES = 10_000  # frames of one orbit video: 11 minutes at 15 fps (default 90)
MAX_VIDEO_FPS = 240.0
RANGE_KEY = "range"  # the dataclass field metadata key holding a field's Range


def _setting(default: Any, range_: Range | None = None) -> Any:
    """A config field whose allowed range is declared with it (``metadata["range"]``)."""
    return field(default=default, metadata={RANGE_KEY: range_})


@dataclass(frozen=True)
class DatasetConfig:
    max_frames: int | None = _setting(None, Range(ge=MIN_FRAMES, le=MAX_FRAMES))  # keep the first N frames; None = all


@dataclass(frozen=True)
class FusionConfig:
    # Depth range of the fused frames and of tracking (localization); the map reaches further
    # (mapping.max_depth_m): tracking against 8 m of noisy depth broke.
    min_depth_m: float = _setting(0.1, NON_NEGATIVE)
    max_depth_m: float = _setting(4.0, POSITIVE)
    stride: int = _setting(2, Range(ge=1, le=MAX_PIXEL_STRIDE))  # back-project every ``stride``-th pixel in u and v


@dataclass(frozen=True)
class MappingConfig:
    pose_source: PoseSource = "auto"
    voxel_size_m: float = _setting(0.02, POSITIVE)
    # Depth range of the map (from fusion.min_depth_m; >= fusion.max_depth_m: named check): walls
    # past the tracking range still get Gaussians instead of rendering as background. 8 m: how far
    # Kinect-class structured-light sensors (TUM's) return depth, and where the project's synthetic
    # Kinect v1 cuts (sensors/synthetic.py SyntheticSpec.max_depth_m). Their noise grows with z^2
    # (sigma_z ~11 cm at 8 m, Nguyen et al. 2012), so points are merged with inverse-variance
    # weights and far depth counts less in the fit (mapping/mapper.py depth_sigma_m); the tracker
    # never sees these points.
    max_depth_m: float = _setting(8.0, POSITIVE)
    # Merge points into cells as wide as their depth noise (powers of two of voxel_size_m, up to 8):
    # far walls become a few wide Gaussians, not a cloud of small noisy ones (mapping/mapper.py).
    noise_adaptive_cells: bool = True
    # Give keyframe pixels without a depth reading, near one, that reading's depth (low weight), so
    # the fit can colour what the images show and the depth missed (mapping/mapper.py hole_fill_depth).
    fill_depth_holes: bool = True
    keyframe_translation_m: float = _setting(0.08, NON_NEGATIVE)
    keyframe_rotation_deg: float = _setting(8.0, NON_NEGATIVE)
    # Colour-only fit before the full one; 0 = none (the full fit fits colours too: 3 cost ~35
    # CPU-s on synthetic for 0.03 dB, benchmarks/bench_photometric.py).
    colour_refinement_iterations: int = _setting(0, Range(ge=0, le=MAX_REFINEMENT_ITERATIONS))
    colour_refinement_scale: float = _setting(0.5, SCALE_AT_MOST_ONE)  # image scale of that fit
    # 3DGS-style fit of every Gaussian parameter to the keyframes; 0 = off.
    optimization_epochs: int = _setting(30, Range(ge=0, le=MAX_EPOCHS))
    # Cap on its steps (one keyframe each), whatever the keyframe count.
    optimization_max_steps: int = _setting(300, Range(ge=1, le=MAX_FIT_STEPS))
    # ...but at least this many per keyframe: longer sequences get proportionally more steps (and
    # a proportionally longer schedule), so the fit's cost is linear in keyframes and its quality
    # does not fall with length; 0 = the fixed cap.
    optimization_min_steps_per_keyframe: int = _setting(10, Range(ge=0, le=MAX_STEPS_PER_KEYFRAME))
    optimization_scale: float = _setting(0.5, SCALE_AT_MOST_ONE)  # image scale of that fit (1/n: named check)
    optimization_depth_weight: float = _setting(1.0, NON_NEGATIVE)  # depth L1 (m) against colour L1 ([0, 1])
    # How far the fit may move a Gaussian off its surface (along its starting normal), in its
    # largest starting scales; 0 = free.
    optimization_normal_offset_max_scales: float = _setting(0.0, NON_NEGATIVE)
    # Colour taken after its depth image (its timestamp) moved to the depth time along the mapping
    # trajectory before the colour refinement and the fit (perception/colour_timing.py). Off: on
    # TUM fr1 (stamps 15 ms apart) it cost 2.3 dB held-out, where synthetic colour really taken
    # 15 ms late gained 2.5 dB (README, "Current figures" 0c).
    colour_delay_compensation: bool = False
    # Its schedule (gaussian_world/optimize.py; measured by benchmarks/bench_fit.py). First passes at
    # 1/factor of optimization_scale (2: a quarter of the image side at scale 0.5); 1 = none.
    optimization_coarse_factor: int = _setting(2, Range(ge=1, le=MAX_COARSE_FACTOR))
    optimization_coarse_max_steps: int = _setting(160, Range(ge=0, le=MAX_FIT_STEPS))  # cap on those steps (whole passes); 0 = none
    optimization_coarse_lr_scale: float = _setting(4.0, POSITIVE)  # every step size times this at the coarse level
    # Passes in a row whose mean loss does not beat the best by plateau_rel_tol (relative) end the
    # coarse level, then the fit; 0 = never stop early.
    optimization_plateau_patience: int = _setting(3, Range(ge=0, le=MAX_EPOCHS))
    optimization_plateau_rel_tol: float = _setting(0.005, UNIT_INTERVAL)
    # Densify and prune (3DGS) every this many steps, up to densify_until_step; 0 = never.
    optimization_densify_interval: int = _setting(50, Range(ge=0, le=MAX_FIT_STEPS))
    optimization_densify_until_step: int = _setting(160, Range(ge=0, le=MAX_FIT_STEPS))
    # Clone / split Gaussians whose mean view-space (NDC) position gradient exceeds this.
    optimization_densify_grad_threshold: float = _setting(2e-4, POSITIVE)
    optimization_prune_opacity: float = _setting(0.005, UNIT_INTERVAL)  # remove Gaussians below this opacity
    # Adam steps only the Gaussians each keyframe draws, each on its own step count (selective
    # Adam); false: every Gaussian every step (3DGS), which moves unseen ones on their momentum,
    # more the longer the path (optimize.OptimizationSettings.selective_adam).
    optimization_selective_adam: bool = True
    # Tracked poses (pose_source estimated): loops to earlier keyframes verified by the tracker,
    # then a pose graph of the keyframes (atlas_pipeline/mapping/loop_closure.py).
    loop_closure: bool = True
    loop_min_keyframe_gap: int = _setting(10, Range(ge=1, le=MAX_FRAMES))  # a loop's keyframes are at least this many keyframes apart
    loop_search_radius_m: float = _setting(0.3, POSITIVE)  # candidates: camera centres within this distance
    # Tracked poses: after this many lost frames in a row a new map is started and merged with the
    # old one when the place is recognised (ORB-SLAM3's Atlas); 0 = stay lost until relocalized.
    new_map_after_lost_frames: int = _setting(5, Range(ge=0, le=MAX_FRAMES))


@dataclass(frozen=True)
class LocalizationConfig:
    # Gauss-Newton iterations per pyramid level, coarse to fine (each >= 0; one > 0: named check).
    iterations: tuple[int, ...] = _setting((12, 8, 5), Range(ge=0, le=MAX_GN_ITERATIONS))
    # Finest pyramid level used: 0 = full resolution, 1 = half, ...
    finest_level: int = _setting(1, Range(ge=0, le=MAX_FINEST_LEVEL))
    # Association gate at the coarsest level (halves per level) ...
    max_correspondence_m: float = _setting(0.1, POSITIVE)
    # ... and its floor, used at the finest level and for grading (<= max: named check).
    min_correspondence_m: float = _setting(0.02, POSITIVE)
    huber_depth_m: float = _setting(0.01, POSITIVE)
    photometric_weight: float = _setting(0.1, NON_NEGATIVE)  # 0 = geometry only
    motion_model: Literal["constant_velocity", "none"] = "constant_velocity"
    min_fitness: float = _setting(0.15, UNIT_INTERVAL)  # share of frame points with a model correspondence; below: lost
    min_agreement: float = _setting(0.6, UNIT_INTERVAL)  # share of points landing on the map that fit it; below: lost
    max_residual_m: float = _setting(0.02, POSITIVE)  # RMS point-to-plane residual; above it: lost
    reference_translation_m: float = _setting(0.05, NON_NEGATIVE)  # photometric reference renewed after this motion
    reference_rotation_deg: float = _setting(5.0, NON_NEGATIVE)
    relocalize: bool = True  # lost frames try global relocalization against the map
    # colour taken after its depth image (unsynchronised streams, TUM fr1 ~15 ms) is moved to the
    # depth image's time with the motion model's velocity (perception/colour_timing.py)
    colour_delay_compensation: bool = True
    max_ate_m: float = _setting(0.05, POSITIVE)  # blocking check: ATE RMSE above this (where ground truth exists) fails


@dataclass(frozen=True)
class TransitionsConfig:
    pose_source: Literal["estimated", "ground_truth"] = "estimated"
    # Frames further apart than this (s) do not follow each other: the row between them is not
    # valid (reason ``gap``) and ends the run of transitions, instead of a velocity averaged over
    # the gap. 1 s: 30 frames of a 30 Hz sensor; TUM's dropped frames leave gaps of a few 0.1 s.
    max_gap_s: float = _setting(1.0, POSITIVE)


@dataclass(frozen=True)
class VideoConfig:
    fps: float = _setting(15.0, Range(gt=0, le=MAX_VIDEO_FPS))
    orbit_frames: int = _setting(90, Range(ge=1, le=MAX_VIDEO_FRAMES))
    orbit_height_m: float = _setting(1.0)  # above the world centre; any finite height (below it: negative)
    orbit_radius_scale: float = _setting(1.2, POSITIVE)
    scale: float = _setting(1.0, Range(gt=0, le=MAX_VIDEO_SCALE))


@dataclass(frozen=True)
class EvaluationConfig:
    view_stride: int = _setting(2, Range(ge=1, le=MAX_FRAMES))  # evaluate every n-th held-out (non-keyframe) frame
    max_views: int | None = _setting(None, Range(ge=1, le=MAX_FRAMES))  # cap on the number of views; None = all selected


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
        """Parse and validate a whole profile; a :class:`ConfigError` lists every bad field, one a line."""
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: a profile must be a mapping of sections, got {_show(data)}")
        errors: list[str] = []
        cfg = _parse(cls, data, "", errors)
        if errors or cfg is None:
            raise ConfigError("\n".join(f"{source}: {e}" for e in errors))
        return cfg

    def with_overrides(self, overrides: dict[str, Any], source: str = "<overrides>") -> "PipelineConfig":
        """Copy with dotted-key overrides applied, e.g. ``{"localization.photometric_weight": 0.5}``;
        the result is validated whole, as :meth:`from_dict` does."""
        data = self.to_dict()
        for dotted, value in overrides.items():
            parts = str(dotted).split(".")
            node = data
            for p in parts[:-1]:
                if p not in node or not isinstance(node[p], dict):
                    raise ConfigError(f"{source}: unknown config section '{dotted}'")
                node = node[p]
            if parts[-1] not in node:
                raise ConfigError(f"{source}: unknown config key '{dotted}'")
            node[parts[-1]] = value
        return PipelineConfig.from_dict(data, source)


# ---- validation ---------------------------------------------------------------------------------

_SHOW_MAX_CHARS = 80  # a value quoted in an error is cut to this length


class _Invalid(Exception):
    """One field's value does not fit its type or range (message without the source)."""

    def __init__(self, path: str, expected: str, value: Any):
        super().__init__(f"{path} must be {expected}, got {_show(value)}")


def _show(value: Any) -> str:
    text = repr(value)  # nan, inf, 'two', True, [1, 2]
    return text if len(text) <= _SHOW_MAX_CHARS else text[: _SHOW_MAX_CHARS - 3] + "..."


def _optional_inner(tp: Any) -> Any | None:
    """``T`` of ``T | None``; None for any other type."""
    args = get_args(tp)
    if type(None) in args and len(args) == 2:
        return next(a for a in args if a is not type(None))
    return None


_PLURAL = {int: "integers", float: "finite numbers"}


def _expectation(tp: Any, rng: Range | None) -> str:
    """What a value of annotated type ``tp`` within ``rng`` must be, in words."""
    bound = f" {rng.describe()}" if rng is not None and rng.describe() else ""
    if get_origin(tp) is tuple:
        return f"a list of {_PLURAL[get_args(tp)[0]]}{bound}"
    if get_origin(tp) is Literal:
        return f"one of {list(get_args(tp))}"
    inner = _optional_inner(tp)
    if inner is not None:
        return f"{_expectation(inner, rng)} or null"
    if tp is bool:
        return "true or false"
    if tp is int:
        return f"an integer{bound}"
    if tp is float:
        return f"a finite number{bound}"
    if tp is str:
        return "a string"
    raise TypeError(f"unsupported config type {tp}")  # a programming error: a new field type needs a rule


def _scalar_ok(tp: Any, value: Any, rng: Range | None) -> tuple[bool, Any]:
    """``(fits, coerced value)`` for one scalar of annotated type ``tp``."""
    if get_origin(tp) is Literal:
        return any(type(value) is type(a) and value == a for a in get_args(tp)), value
    inner = _optional_inner(tp)
    if inner is not None:
        return (True, None) if value is None else _scalar_ok(inner, value, rng)
    if tp is bool:
        return isinstance(value, bool), value
    if tp is str:
        return isinstance(value, str), value
    if isinstance(value, bool) or not isinstance(value, (int, float)):  # YAML true is not a number
        return False, value
    if tp is int:
        return isinstance(value, int) and (rng is None or rng.contains(value)), value
    if tp is float:
        try:
            v = float(value)
        except OverflowError:  # an int too large for a float
            return False, value
        return math.isfinite(v) and (rng is None or rng.contains(v)), v
    raise TypeError(f"unsupported config type {tp}")  # pragma: no cover


def _coerce(tp: Any, value: Any, path: str, rng: Range | None) -> Any:
    """``value`` checked against annotated type ``tp`` and ``rng`` (tuples element-wise); raises
    :class:`_Invalid` naming ``path`` (``path[i]`` for a tuple element)."""
    if get_origin(tp) is tuple:  # tuple[T, ...] from a YAML list
        if not isinstance(value, (list, tuple)):
            raise _Invalid(path, _expectation(tp, rng), value)
        elem = get_args(tp)[0]
        return tuple(_coerce(elem, v, f"{path}[{i}]", rng) for i, v in enumerate(value))
    ok, out = _scalar_ok(tp, value, rng)
    if not ok:
        raise _Invalid(path, _expectation(tp, rng), value)
    return out


def _parse(cls: type, data: dict[str, Any], prefix: str, errors: list[str]) -> Any | None:
    """Build ``cls`` from ``data``, appending every problem to ``errors``; None where there was one.

    Field checks run first; a section's named checks only once all its fields are valid (they
    compare fields, and an invalid one would make their message misleading).
    """
    n_errors = len(errors)
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = sorted((str(k) for k in data if k not in names))
    if unknown:
        errors.append(f"unknown key(s) {', '.join(prefix + u for u in unknown)}")
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        tp, value, path = hints[f.name], data[f.name], prefix + f.name
        if dataclasses.is_dataclass(tp):
            if value is None:  # an empty YAML section
                value = {}
            if not isinstance(value, dict):
                errors.append(f"{path} must be a mapping of keys, got {_show(value)}")
                continue
            section = _parse(tp, value, path + ".", errors)
            if section is not None:
                kwargs[f.name] = section
            continue
        try:
            kwargs[f.name] = _coerce(tp, value, path, f.metadata.get(RANGE_KEY))
        except _Invalid as exc:
            errors.append(str(exc))
    if len(errors) > n_errors:
        return None
    obj = cls(**kwargs)
    for check in _SECTION_CHECKS.get(cls, ()):
        problem = check(obj, prefix)
        if problem:
            errors.append(problem)
    return obj if len(errors) == n_errors else None


# Named checks of rules that tie fields together: (section, dotted prefix) -> message or None.

_RECIPROCAL_TOL = 1e-9  # the same tolerance gaussian_world.optimize applies


def _depth_interval_not_empty(c: FusionConfig, p: str) -> str | None:
    # Depths outside [min, max] are dropped: an empty interval back-projects nothing.
    if c.min_depth_m >= c.max_depth_m:
        return f"{p}min_depth_m must be < {p}max_depth_m ({c.max_depth_m!r}), got {c.min_depth_m!r}"
    return None


def _optimization_scale_is_reciprocal(c: MappingConfig, p: str) -> str | None:
    # The fit downsamples the keyframes by a whole factor n (block averages).
    n = round(1.0 / c.optimization_scale)
    if n < 1 or abs(1.0 / n - c.optimization_scale) > _RECIPROCAL_TOL:
        return f"{p}optimization_scale must be 1/n for a whole n (1, 0.5, 0.25, ...), got {c.optimization_scale!r}"
    return None


def _iterations_track_something(c: LocalizationConfig, p: str) -> str | None:
    # One count per pyramid level; all zero would never move the pose.
    if not c.iterations or max(c.iterations) < 1:
        return (f"{p}iterations must list one count per pyramid level, at least one of them > 0, "
                f"got {list(c.iterations)}")
    return None


def _pyramid_not_too_deep(c: LocalizationConfig, p: str) -> str | None:
    # Each level halves the image; deeper pyramids leave too few pixels at the coarsest level.
    if c.finest_level + len(c.iterations) > MAX_PYRAMID_LEVELS:
        return (f"{p}finest_level + len({p}iterations) must be <= {MAX_PYRAMID_LEVELS} pyramid levels, "
                f"got {c.finest_level} + {len(c.iterations)}")
    return None


def _correspondence_gates_ordered(c: LocalizationConfig, p: str) -> str | None:
    # The gate shrinks from max at the coarsest level down to min at the finest.
    if c.min_correspondence_m > c.max_correspondence_m:
        return (f"{p}min_correspondence_m must be <= {p}max_correspondence_m ({c.max_correspondence_m!r}), "
                f"got {c.min_correspondence_m!r}")
    return None


def _mapping_range_covers_tracking_range(c: PipelineConfig, p: str) -> str | None:
    # The map holds at least what the tracker sees: its range extends the fusion range.
    if c.mapping.max_depth_m < c.fusion.max_depth_m:
        return (f"{p}mapping.max_depth_m must be >= {p}fusion.max_depth_m ({c.fusion.max_depth_m!r}), "
                f"got {c.mapping.max_depth_m!r}")
    return None


_SECTION_CHECKS: dict[type, tuple[Callable[[Any, str], str | None], ...]] = {
    PipelineConfig: (_mapping_range_covers_tracking_range,),
    FusionConfig: (_depth_interval_not_empty,),
    MappingConfig: (_optimization_scale_is_reciprocal,),
    LocalizationConfig: (_iterations_track_something, _pyramid_not_too_deep, _correspondence_gates_ordered),
}


# ---- where things live -------------------------------------------------------------------------
# From a source checkout (this package beside pyproject.toml and configs/, as with ``pip install -e .``)
# everything stays in the checkout, as always. From an installed wheel the built-in profiles and
# dataset registry are read from the package (``atlas_pipeline/configs``, mapped from the top-level
# ``configs/`` at build time), and user state (``artifacts/``, ``data/``, ``.dagster_home/``,
# ``configs/datasets.local.yaml``) lives in ``$ATLAS_GS_HOME``, default the current working
# directory: never in site-packages.

STATE_HOME_ENV = "ATLAS_GS_HOME"  # user state, in a checkout or an install
PROJECT_ROOT_ENV = "ATLAS_PROJECT_ROOT"  # a whole project folder: its configs/ and its user state


def source_root() -> Path | None:
    """The source checkout this package is running from, or None when it is installed."""
    root = Path(__file__).resolve().parents[1]
    if (root / "pyproject.toml").is_file() and (root / "configs" / "datasets.yaml").is_file():
        return root
    return None


def project_root() -> Path:
    """The folder of the user state: ``artifacts/``, ``data/``, ``.dagster_home/`` and the local
    dataset registry ``configs/datasets.local.yaml`` (each has its own variable too).

    ``$ATLAS_PROJECT_ROOT``, else ``$ATLAS_GS_HOME``, else the source checkout, else (an installed
    package) the current working directory.
    """
    for var in (PROJECT_ROOT_ENV, STATE_HOME_ENV):
        env = os.environ.get(var)
        if env:
            return Path(env).expanduser().resolve()
    return source_root() or Path.cwd()


def configs_dir() -> Path:
    """The built-in profiles and dataset registry: ``$ATLAS_PROJECT_ROOT/configs``, else the
    checkout's ``configs/``, else the installed package's copy (read through importlib.resources)."""
    env = os.environ.get(PROJECT_ROOT_ENV)
    if env:
        return Path(env).expanduser().resolve() / "configs"
    src = source_root()
    return src / "configs" if src is not None else _packaged_configs()


_EXTRACTED_CONFIGS: Path | None = None


def _packaged_configs() -> Path:
    """The ``configs`` folder shipped in the package, as a real folder (extracted once per process
    when the package is imported from a zip)."""
    global _EXTRACTED_CONFIGS
    from importlib import resources

    res = resources.files("atlas_pipeline") / "configs"
    if isinstance(res, Path):
        return res
    if _EXTRACTED_CONFIGS is None:
        import atexit
        import shutil
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix="atlas-gs-configs-"))
        atexit.register(shutil.rmtree, tmp, True)
        for item in res.iterdir():
            if item.is_file() and item.name.endswith((".yaml", ".yml")):
                (tmp / item.name).write_bytes(item.read_bytes())
        _EXTRACTED_CONFIGS = tmp
    return _EXTRACTED_CONFIGS


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping of a YAML document names the same key twice (``problem_mark``: the second one)."""


class UniqueKeyLoader(yaml.SafeLoader):
    """The safe loader, refusing a key that a mapping repeats.

    PyYAML's own loaders keep the last of two equal keys without a word, so a profile or registry
    edited in two places silently loses the first value. Keys brought in by a merge (``<<: *base``)
    may still be overridden: only keys written in the mapping itself count.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            first_line: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    earlier = first_line.get(key)
                except TypeError:  # an unhashable key: the base class says so
                    continue
                if earlier is not None:
                    raise DuplicateKeyError(
                        "while constructing a mapping", node.start_mark,
                        f"duplicate key {_show(key)} (first on line {earlier}); YAML would keep only the last value",
                        key_node.start_mark)
                first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` of ``text`` that refuses duplicate keys (:class:`UniqueKeyLoader`)."""
    return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass


def load_yaml_file(path: Path) -> Any:
    """Parse a YAML file with the safe loader; errors name the file and line. A key repeated in
    one mapping is an error naming the file, the line of the repeat and the key (not the last
    value silently winning)."""
    try:
        size = path.stat().st_size
        if size > MAX_YAML_BYTES:
            raise ConfigError(f"{path}: {size} bytes is far more than any profile or registry ({MAX_YAML_BYTES})")
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except UnicodeDecodeError as exc:
        line = text_line_of(path, exc.start)
        raise ConfigError(f"{path}:{line}: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    try:
        return parse_yaml(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        if isinstance(exc, DuplicateKeyError):
            raise ConfigError(f"{where}: {exc.problem}") from None
        raise ConfigError(f"{where}: invalid YAML ({getattr(exc, 'problem', exc)})") from exc
    except RecursionError:
        raise ConfigError(f"{path}: YAML nested too deeply") from None
    except ValueError as exc:  # e.g. an integer of more than 4300 digits
        raise ConfigError(f"{path}: invalid value ({exc})") from None


def text_line_of(path: Path, offset: int) -> int:
    """1-based line of byte ``offset`` in ``path`` (for errors about undecodable bytes)."""
    try:
        with open(path, "rb") as f:
            return f.read(offset).count(b"\n") + 1
    except OSError:
        return 1


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


def parse_set_overrides(items: list[str] | tuple[str, ...] | None, option: str = "--set") -> dict[str, Any]:
    """``{dotted key: value}`` from ``KEY=VALUE`` strings (``--set`` of ``atlas-gs`` and the
    benchmarks), each value parsed as YAML (``0.5``, ``true``, ``[8,5,3]``, ``null``); keys are
    validated later by :meth:`PipelineConfig.with_overrides`. A ConfigError names the bad item."""
    overrides: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"{option} expects key=value, got {item!r}")
        k, v = item.split("=", 1)
        try:
            overrides[k.strip()] = parse_yaml(v)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{option} {item!r}: the value is not valid YAML ({getattr(exc, 'problem', exc)})") from None
    return overrides

"""Configuration profiles: YAML files in ``configs/`` parsed into frozen pydantic models.

A profile has one section per pipeline stage (``mapping.fit`` nested in ``mapping``). The models are
the single source of every setting: its type, default, allowed range (``Field(gt=...)``) and
description serve profiles, ``--set`` overrides, the Dagster resource and its launchpad
(``assets/resources.py`` mirrors them), and the docs. Which stage reads which fields is declared in
:mod:`atlas_pipeline.stage_settings`.

Validation happens whole and first, when a profile or an override is parsed
(:meth:`PipelineConfig.from_dict`, :meth:`PipelineConfig.with_overrides`, :func:`load_profile`),
so a bad value fails before any stage runs. Every error names the dotted field and the value,
prefixed by the source (YAML path or ``--set``), one a line:
``--set: mapping.voxel_size_m must be greater than or equal to 0.001, got -1``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, ValidationError, ValidationInfo,
                      field_validator, model_validator)

from atlas_pipeline.errors import ConfigError

__all__ = [
    "DatasetConfig",
    "FusionConfig",
    "FitConfig",
    "ColourRefinementConfig",
    "MappingConfig",
    "LocalizationConfig",
    "TransitionsConfig",
    "VideoConfig",
    "EvaluationConfig",
    "PipelineConfig",
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
MAX_SEED = 2**32 - 1  # NumPy's seed range
MIN_VOXEL_SIZE_M = 0.001  # 1 mm: finer than any RGB-D sensor's depth noise; each voxel then holds one point
MAX_VOXEL_SIZE_M = 1.0  # one Gaussian per metre cube leaves no room's surfaces to track against
MAX_DENSIFY_GROWTH = 16.0  # the densified field at most 16x its starting count (default 1.3)
_RECIPROCAL_TOL = 1e-9  # how close a scale must be to 1/n (the fit downsamples by whole factors)


class Section(BaseModel):
    """A config section: frozen, every key known, types strict (YAML ``true`` is not 1, ``"2"`` not
    2), numbers finite. A rule between two fields is a validator of the later one (it sees the
    earlier in ``info.data``), so pydantic's error names the field."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump()


class DatasetConfig(Section):
    max_frames: int | None = Field(None, ge=MIN_FRAMES, le=MAX_FRAMES,
                                   description="keep the first N frames; null = all")


class FusionConfig(Section):
    min_depth_m: float = Field(0.1, ge=0, description="nearest depth back-projected (m)")
    max_depth_m: float = Field(4.0, gt=0, description=(
        "farthest depth back-projected and tracked (m); the map reaches further (mapping.max_depth_m): "
        "tracking against 8 m of noisy depth broke"))
    stride: int = Field(2, ge=1, le=MAX_PIXEL_STRIDE, description="back-project every stride-th pixel in u and v")

    @field_validator("max_depth_m")
    @classmethod
    def _depth_interval_not_empty(cls, v: float, info: ValidationInfo) -> float:
        if v <= info.data.get("min_depth_m", -math.inf):  # depths outside [min, max] are dropped
            raise ValueError(f"must be > min_depth_m ({info.data['min_depth_m']!r})")
        return v


def _reciprocal(value: float) -> float:
    n = round(1.0 / value)
    if n < 1 or abs(1.0 / n - value) > _RECIPROCAL_TOL:
        raise ValueError("must be 1/n for a whole n (1, 0.5, 0.25, ...)")
    return value


class ColourRefinementConfig(Section):
    iterations: int = Field(0, ge=0, le=MAX_REFINEMENT_ITERATIONS, description=(
        "colour-only passes over the keyframes before the fit; 0 = none (the fit fits colours too)"))
    scale: float = Field(0.5, gt=0, le=1, description="image scale of those passes")


class FitConfig(Section):
    """The 3DGS-style fit of every Gaussian parameter to the keyframe images and depths
    (:func:`atlas_pipeline.gaussian_world.optimize.optimize_gaussians`; figures in docs/benchmarks.md,
    from ``benchmarks/bench_fit.py``). Its step sizes are larger than 3DGS's (30,000 steps): here a few
    hundred steps start from a field already close to the images."""

    epochs: int = Field(30, ge=0, le=MAX_EPOCHS, description="cap on the passes over the keyframes; 0 = no fit")
    max_steps: int | None = Field(300, ge=1, le=MAX_FIT_STEPS, description=(
        "cap on the steps (one keyframe each, forward and backward), whatever the keyframe count; null = none"))
    min_steps_per_keyframe: int = Field(10, ge=0, le=MAX_STEPS_PER_KEYFRAME, description=(
        "with max_steps, at least this many steps per keyframe: the cap, coarse_max_steps and the "
        "densification steps grow with the keyframes, so the cost is linear in them and each gets the "
        "same share; 0 = a fixed cap"))
    scale: Annotated[float, AfterValidator(_reciprocal)] = Field(
        0.5, gt=0, le=1, description="image scale of the fit (1/n: the keyframes are block-averaged)")
    lr_position_m: float = Field(5e-4, ge=0, description="Adam step size of the centres (m); 0 = frozen")
    lr_log_scale: float = Field(2e-2, ge=0, description="Adam step size of the log scales; 0 = frozen")
    lr_rotation_rad: float = Field(1e-2, ge=0, description="Adam step size of the rotations (rad); 0 = frozen")
    lr_opacity_logit: float = Field(5e-2, ge=0, description="Adam step size of the opacity logits; 0 = frozen")
    lr_color: float = Field(1e-2, ge=0, description="Adam step size of the colours ([0, 1]); 0 = frozen")
    sh_degree: int = Field(0, ge=0, le=3, description=(
        "spherical-harmonics degree of the colour the fit learns (view-dependent colour, 3DGS's order); "
        "0 = one colour per Gaussian (degree 3 gained 0.24 dB held-out on TUM teddy at 1.25x the fit's "
        "CPU, under the 0.5 dB a default needs: docs/benchmarks.md)"))
    sh_degree_interval: int = Field(25, ge=0, le=MAX_FIT_STEPS, description=(
        "the fit renders degree 0 first and one degree more every this many steps, up to sh_degree "
        "(3DGS: every 1000 of 30,000 steps; grows with the keyframes like the densification steps); "
        "0 = sh_degree from the first step"))
    lr_sh_rest: float = Field(1.8e-3, ge=0, description=(
        "Adam step size of the SH coefficients beyond degree 0; 3DGS's ratio: the degree-0 "
        "coefficient's (lr_color / 0.282) / 20; 0 = frozen"))
    lr_final_ratio: float = Field(1.0, gt=0, le=1, description=(
        "every step size decays exponentially to this fraction over the step cap; 1 = constant (with a "
        "few hundred steps the fit still improves at the end)"))
    depth_weight: float = Field(1.0, ge=0, description="weight of the depth L1 (m) against the colour L1 ([0, 1])")
    coverage_weight: float = Field(2.0, ge=0, description=(
        "weight of the transparency left where the sensor measured a surface (the render should be opaque there)"))
    max_scale_m: float = Field(0.1, gt=0, description="largest Gaussian scale after each step (m)")
    min_scale_m: float = Field(1e-4, gt=0, description="smallest Gaussian scale after each step (m)")
    normal_offset_max_scales: float = Field(0.0, ge=0, description=(
        "how far a centre may move along its starting normal, in its largest starting scale; 0 = free "
        "(bounded, an exported PLY keeps thin surfaces)"))
    seed: int = Field(0, ge=0, le=MAX_SEED, description="keyframe order of each pass and the samples of split Gaussians")
    coarse_factor: int = Field(2, ge=1, le=MAX_COARSE_FACTOR, description=(
        "the first passes run at scale / coarse_factor (2: a quarter of the image side at scale 0.5); 1 = none"))
    coarse_max_steps: int = Field(160, ge=0, le=MAX_FIT_STEPS, description=(
        "cap on the coarse level's steps (whole passes); 0 = no coarse level"))
    coarse_lr_scale: float = Field(4.0, gt=0, description="every step size times this at the coarse level")
    plateau_patience: int = Field(3, ge=0, le=MAX_EPOCHS, description=(
        "passes in a row whose mean loss does not beat the best by plateau_rel_tol end the coarse level, "
        "then the fit; 0 = never stop early"))
    plateau_rel_tol: float = Field(0.005, ge=0, le=1, description="relative gain a pass needs to count as progress")
    densify_interval: int = Field(50, ge=0, le=MAX_FIT_STEPS, description=(
        "steps between densify-and-prune rounds (3DGS); 0 = never"))
    densify_until_step: int = Field(160, ge=0, le=MAX_FIT_STEPS, description=(
        "no densification from this step on (rounds in the fine phase upset its loss)"))
    densify_grad_threshold: float = Field(2e-4, gt=0, description=(
        "mean view-space (NDC) position gradient above which a Gaussian is cloned or split"))
    densify_scale_m: float = Field(0.02, gt=0, description="a Gaussian with all scales at most this is cloned, a larger one split (m)")
    densify_max_growth: float = Field(1.3, ge=1, le=MAX_DENSIFY_GROWTH, description="the densified field holds at most this times the starting count")
    prune_opacity: float = Field(0.005, ge=0, le=1, description="Gaussians below this opacity are removed at each round")
    selective_adam: bool = Field(True, description=(
        "Adam steps only the Gaussians each keyframe draws, each on its own step count (Taming 3DGS); "
        "false: every Gaussian every step (3DGS), which moves unseen ones on their momentum, more the "
        "longer the path"))


class MappingConfig(Section):
    pose_source: PoseSource = Field("auto", description=(
        "poses of the map: ground_truth, estimated (the RGB-D tracker), or auto (ground truth where the dataset has it)"))
    voxel_size_m: float = Field(0.02, ge=MIN_VOXEL_SIZE_M, le=MAX_VOXEL_SIZE_M, description="voxel of the Gaussian map and the tracker's surfel map (m)")
    max_depth_m: float = Field(8.0, gt=0, description=(
        "depth range of the map (>= fusion.max_depth_m): walls past the tracking range still get "
        "Gaussians; 8 m is where Kinect-class sensors stop, far points weighted by their depth noise"))
    noise_adaptive_cells: bool = Field(True, description=(
        "merge points into cells as wide as their depth noise (powers of two of voxel_size_m, up to 8)"))
    fill_depth_holes: bool = Field(True, description=(
        "keyframe pixels without depth near a reading get that depth (low weight), so the fit colours them"))
    keyframe_translation_m: float = Field(0.08, ge=0, description="a new keyframe after this much motion (m)")
    keyframe_rotation_deg: float = Field(8.0, ge=0, description="... or this much rotation (deg)")
    colour_delay_compensation: bool = Field(False, description=(
        "the fit's colour moved to its depth image's time along the trajectory (off: it lost 2.3 dB "
        "held-out on TUM fr1, docs/benchmarks.md)"))
    loop_closure: bool = Field(True, description=(
        "estimated poses: loops to earlier keyframes verified by the tracker, then a pose graph"))
    loop_min_keyframe_gap: int = Field(10, ge=1, le=MAX_FRAMES, description="a loop joins keyframes at least this many apart")
    loop_search_radius_m: float = Field(0.3, gt=0, description="loop candidates: camera centres within this distance (m)")
    loop_probes: bool = Field(False, description=(
        "loop search also from tracked frames where the map took no keyframe (a return over mapped "
        "surfaces); off: on the synthetic presets it let wrong loops through (docs/tracking.md)"))
    new_map_after_lost_frames: int = Field(5, ge=0, le=MAX_FRAMES, description=(
        "estimated poses: after this many lost frames in a row a new map is started and merged when the "
        "place is recognised; 0 = stay lost until relocalized"))
    colour_refinement: ColourRefinementConfig = Field(default_factory=ColourRefinementConfig)
    fit: FitConfig = Field(default_factory=FitConfig)


class LocalizationConfig(Section):
    # not strict: a YAML list is the tuple (its counts are)
    iterations: tuple[Annotated[int, Field(ge=0, le=MAX_GN_ITERATIONS, strict=True)], ...] = Field(
        (12, 8, 5), strict=False, description="Gauss-Newton iterations per pyramid level, coarse to fine")
    finest_level: int = Field(1, ge=0, le=MAX_FINEST_LEVEL, description="finest pyramid level: 0 = full resolution, 1 = half")
    max_correspondence_m: float = Field(0.1, gt=0, description="association gate at the coarsest level (halves per level, m)")
    min_correspondence_m: float = Field(0.02, gt=0, description="its floor: the finest level, and grading (m)")
    huber_depth_m: float = Field(0.01, gt=0, description="Huber threshold of the point-to-plane residual (m)")
    photometric_weight: float = Field(0.1, ge=0, description=(
        "intensity term against the point-to-plane term, the last keyframe as reference (SLAM; a saved world "
        "without colours); 0 = geometry only"))
    map_photometric_weight: float = Field(1.0, ge=0, description=(
        "tracking in a saved world: intensity against the map's own colours instead of the last keyframe's; 0 = keyframe"))
    motion_model: Literal["constant_velocity", "none"] = Field("constant_velocity", description=(
        "initial guess: constant velocity, or the previous pose"))
    odometry_prediction: bool = Field(True, description=(
        "each tracked frame first aligned to the previous frame's own surface: the guess, and the pose "
        "where the map leaves the camera free"))
    min_fitness: float = Field(0.15, ge=0, le=1, description="share of frame points with a map correspondence; below: lost")
    min_agreement: float = Field(0.6, ge=0, le=1, description="share of the points landing on the map that fit it; below: lost")
    max_residual_m: float = Field(0.02, gt=0, description="RMS point-to-plane residual; above: lost (m)")
    reference_translation_m: float = Field(0.05, ge=0, description="the photometric reference is renewed after this motion (m)")
    reference_rotation_deg: float = Field(5.0, ge=0, description="... or this rotation (deg)")
    relocalize: bool = Field(True, description="lost frames try global relocalization against the map")
    colour_delay_compensation: bool = Field(True, description=(
        "colour taken after its depth image (TUM fr1: ~15 ms) moved to the depth time with the motion model's velocity"))
    max_ate_m: float = Field(0.05, gt=0, description="blocking check: ATE RMSE above this (where ground truth exists) fails (m)")

    @field_validator("iterations")
    @classmethod
    def _iterations_in_range(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if not v or max(v) < 1:  # all zero would never move the pose
            raise ValueError("must list one count per pyramid level, at least one of them > 0")
        return v

    @field_validator("finest_level")
    @classmethod
    def _pyramid_fits(cls, v: int, info: ValidationInfo) -> int:
        levels = len(info.data.get("iterations", ()))
        if v + levels > MAX_PYRAMID_LEVELS:  # each level halves the image
            raise ValueError(f"must be at most {MAX_PYRAMID_LEVELS - levels} with {levels} levels of iterations")
        return v

    @field_validator("min_correspondence_m")
    @classmethod
    def _gate_shrinks(cls, v: float, info: ValidationInfo) -> float:
        if v > info.data.get("max_correspondence_m", v):  # the gate shrinks from max to min
            raise ValueError(f"must be <= max_correspondence_m ({info.data['max_correspondence_m']!r})")
        return v


class TransitionsConfig(Section):
    pose_source: Literal["estimated", "ground_truth"] = Field("estimated", description=(
        "which poses define the states and actions"))
    max_gap_s: float = Field(1.0, gt=0, description=(
        "frames further apart do not follow each other: the row between them is not valid (reason gap) "
        "instead of a velocity averaged over the gap (s)"))


class VideoConfig(Section):
    fps: float = Field(15.0, gt=0, le=MAX_VIDEO_FPS, description="frames per second of the videos")
    orbit_frames: int = Field(90, ge=1, le=MAX_VIDEO_FRAMES, description="frames of the orbit video")
    orbit_height_m: float = Field(1.0, description="orbit camera height above the world centre (m; below it: negative)")
    orbit_radius_scale: float = Field(1.2, gt=0, description="orbit radius as a multiple of the world's horizontal extent")
    scale: float = Field(1.0, gt=0, le=MAX_VIDEO_SCALE, description="render size as a multiple of the dataset's image size")


class EvaluationConfig(Section):
    view_stride: int = Field(2, ge=1, le=MAX_FRAMES, description="evaluate every n-th held-out (non-keyframe) frame")
    max_views: int | None = Field(None, ge=1, le=MAX_FRAMES, description="cap on the number of views; null = all selected")


class PipelineConfig(Section):
    """A whole resolved profile."""

    profile: str = Field("default", description="the profile's name")
    dataset: DatasetConfig = Field(default_factory=DatasetConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig)
    transitions: TransitionsConfig = Field(default_factory=TransitionsConfig)
    video: VideoConfig = Field(default_factory=VideoConfig)
    evaluation: EvaluationConfig = Field(default_factory=EvaluationConfig)

    @model_validator(mode="after")
    def _map_covers_tracking_range(self) -> "PipelineConfig":
        if self.mapping.max_depth_m < self.fusion.max_depth_m:  # the map holds at least what the tracker sees
            raise ValueError(f"mapping.max_depth_m must be >= fusion.max_depth_m ({self.fusion.max_depth_m!r}), "
                             f"got {self.mapping.max_depth_m!r}")
        return self

    @classmethod
    def from_dict(cls, data: Any, source: str = "<dict>") -> "PipelineConfig":
        """Parse and validate a whole profile; a :class:`ConfigError` lists every bad field, one a line."""
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: a profile must be a mapping of sections, got {_show(data)}")
        # an empty YAML section (``mapping:``) is a section of defaults
        data = {k: {} if v is None and k in cls.model_fields and k != "profile" else v for k, v in data.items()}
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise ConfigError("\n".join(f"{source}: {_describe(e)}" for e in exc.errors())) from None

    def with_overrides(self, overrides: dict[str, Any], source: str = "<overrides>") -> "PipelineConfig":
        """Copy with dotted-key overrides applied, e.g. ``{"localization.photometric_weight": 0.5}``;
        the result is validated whole, as :meth:`from_dict` does.

        A section (``mapping``, ``mapping.fit``) given a mapping has those keys set, the others
        kept; given anything else (``null``, a number) it is a ConfigError naming the key, never a
        section of defaults. ``profile`` is the loaded profile's name, not a setting: an override
        of it is a ConfigError pointing to ``--profile`` (the name would be recorded in the lineage
        beside another profile's settings).
        """
        data = self.to_dict()
        for dotted, value in overrides.items():
            parts = str(dotted).split(".")
            if parts == ["profile"]:
                name = value if isinstance(value, str) else "NAME"
                raise ConfigError(f"{source}: profile must be chosen with --profile {name} (or $ATLAS_PROFILE), "
                                  f"not set: got {_show(value)}; it names the profile whose settings are loaded, "
                                  "and SECTION.KEY=VALUE overrides change those settings")
            node = data
            for p in parts[:-1]:
                if not isinstance(node.get(p), dict):
                    raise ConfigError(f"{source}: unknown config section '{dotted}'")
                node = node[p]
            if parts[-1] not in node:
                raise ConfigError(f"{source}: unknown config key '{dotted}'")
            if isinstance(node[parts[-1]], dict):
                _merge_section(node[parts[-1]], value, str(dotted), source)
            else:
                node[parts[-1]] = value
        return PipelineConfig.from_dict(data, source)


def _merge_section(section: dict[str, Any], value: Any, dotted: str, source: str) -> None:
    """Set the keys of the mapping ``value`` in ``section`` (the section ``dotted``), nested
    sections key by key; a ``value`` that is no mapping is a ConfigError naming ``dotted``."""
    if not isinstance(value, dict):
        keys = ", ".join(f"{dotted}.{k}" for k in list(section)[:3])
        shown = "null" if value is None else _show(value)  # as it was typed (YAML)
        raise ConfigError(f"{source}: {dotted} is a section of settings, not a value: got {shown}; set its "
                          f"keys ({keys} ...) or give a mapping of them ({dotted}={{key: value}})")
    for key, v in value.items():
        if key not in section:
            raise ConfigError(f"{source}: unknown config key '{dotted}.{key}'")
        if isinstance(section[key], dict):
            _merge_section(section[key], v, f"{dotted}.{key}", source)
        else:
            section[key] = v


_SHOW_MAX_CHARS = 80  # a value quoted in an error is cut to this length


def _show(value: Any) -> str:
    text = repr(value)  # nan, inf, 'two', True, [1, 2]
    return text if len(text) <= _SHOW_MAX_CHARS else text[: _SHOW_MAX_CHARS - 3] + "..."


_MESSAGES = {"extra_forbidden": "is not a known key", "model_type": "must be a mapping of keys"}


def _describe(error: dict[str, Any]) -> str:
    """One pydantic error as ``dotted.field must be ..., got VALUE`` (the whole profile's rule, at
    no field, words its own message)."""
    path = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in error["loc"]).lstrip(".")
    msg = _MESSAGES.get(error["type"]) or error["msg"].replace("Input should be", "must be", 1).removeprefix("Value error, ")
    return f"{path} {msg}, got {_show(error['input'])}" if path else msg


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


# YAML 1.2's exponent floats (1e-3, 2E5, 1.5e3): PyYAML follows YAML 1.1, whose floats need a dot
# and a signed exponent, and read them as text, which a number field then refused ("must be a valid
# number, got '1e-3'").
UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"))


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
    if isinstance(section, BaseModel):
        section = section.model_dump()
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

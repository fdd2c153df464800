import math
import re
from typing import Literal, get_args, get_origin

import pytest
from annotated_types import Ge, Gt, Le, Lt
from pydantic import BaseModel

from atlas_pipeline.config import PipelineConfig, load_profile, section_hash
from atlas_pipeline.errors import ConfigError

# Numbers any finite value of which is meaningful (a height below the centre is negative).
UNBOUNDED = {"video.orbit_height_m"}


def _leaf_fields(model: type[BaseModel] = PipelineConfig, prefix: str = "") -> list[tuple[str, object, object]]:
    """``(dotted name, annotation, FieldInfo)`` of every value of a profile, sections expanded."""
    out = []
    for name, info in model.model_fields.items():
        tp = info.annotation
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            out += _leaf_fields(tp, f"{prefix}{name}.")
        else:
            out.append((prefix + name, tp, info))
    return out


LEAVES = _leaf_fields()
FLOAT_FIELDS = [name for name, tp, _ in LEAVES if tp is float]
NON_FINITE = [math.nan, math.inf, -math.inf]


def _wrong_values(tp) -> list:
    """Values of the wrong type for annotated type ``tp`` (bools are not numbers, floats not ints)."""
    if tp is float:
        return ["0.5", True, None, [0.5]]
    if tp is int:
        return [2.5, 2.0, True, "3", None]
    if tp is bool:
        return [1, "yes", None]
    if tp is str:
        return [3, None, ["a"]]
    if get_origin(tp) is Literal:
        return [3, "not-a-choice", None, True]
    if get_origin(tp) is tuple:
        return [5, "12 8 5", [1.5], [True], [None]]
    if type(None) in get_args(tp):  # int | None
        return [2.5, True, "3"]
    raise AssertionError(f"no wrong values listed for {tp}: extend _wrong_values")


WRONG_TYPES = [(name, v) for name, tp, _ in LEAVES for v in _wrong_values(tp)]


def test_profiles_hold_the_papers_appendix_a_values():
    d = load_profile("default")
    assert d.mapping.voxel_size_m == 0.02 and d.fusion.max_depth_m == 4.0
    assert d.mapping.keyframe_translation_m == 0.08 and d.mapping.keyframe_rotation_deg == 8.0
    assert d.localization.iterations == (12, 8, 5) and d.localization.motion_model == "constant_velocity"
    demo = load_profile("demo")
    assert demo.mapping.voxel_size_m == 0.04 and demo.dataset.max_frames == 40


def test_defaults_pass_their_own_rules():
    assert PipelineConfig.from_dict(PipelineConfig().to_dict()) == PipelineConfig()
    assert PipelineConfig.from_dict({}) == PipelineConfig()


def test_every_field_is_covered_and_every_number_declares_its_range():
    assert len(FLOAT_FIELDS) >= 30 and "mapping.fit.lr_position_m" in FLOAT_FIELDS  # found by reflection, not listed
    for name, tp, info in LEAVES:
        assert info.description, f"{name} has no description (the launchpad and docs show it)"
        # (a tuple's element range is its section's rule: CROSS_FIELD below)
        if (tp in (int, float) or int in get_args(tp) and get_origin(tp) is not tuple) and name not in UNBOUNDED:
            assert any(isinstance(m, (Ge, Gt, Le, Lt)) for m in info.metadata), f"{name} declares no range"


def test_unknown_key_names_file_and_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("mapping:\n  voxel_sise_m: 0.02\n")
    with pytest.raises(ConfigError, match=r"bad.yaml.*mapping.voxel_sise_m"):
        load_profile(p)


def test_invalid_yaml_names_line(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("mapping:\n  voxel_size_m: [0.02\n")
    with pytest.raises(ConfigError, match=r"broken.yaml:\d+"):
        load_profile(p)


@pytest.mark.parametrize("value", NON_FINITE, ids=repr)
@pytest.mark.parametrize("name", FLOAT_FIELDS)
def test_non_finite_float_is_refused_naming_the_field(name, value):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides({name: value}, "--set")
    assert str(err.value) == f"--set: {name} must be a finite number, got {value!r}"


@pytest.mark.parametrize(("name", "value"), WRONG_TYPES, ids=[f"{n}={v!r}" for n, v in WRONG_TYPES])
def test_wrong_type_is_refused_naming_the_field(name, value):
    with pytest.raises(ConfigError, match=rf"^--set: {re.escape(name)}(\[\d+\])? must be "):
        load_profile("default").with_overrides({name: value}, "--set")


@pytest.mark.parametrize("name", [s for s in PipelineConfig.model_fields if s != "profile"] + ["mapping.fit"])
def test_a_section_must_be_a_mapping(name):
    data: dict = {}
    node = data
    *sections, last = name.split(".")
    for sec in sections:
        node = node.setdefault(sec, {})
    node[last] = 3
    with pytest.raises(ConfigError, match=rf"^<dict>: {re.escape(name)} must be a mapping of keys, got 3$"):
        PipelineConfig.from_dict(data)


def test_yaml_nan_names_file_and_field(tmp_path):
    p = tmp_path / "nan.yaml"
    p.write_text("mapping:\n  voxel_size_m: .nan\nvideo:\n  fps: -.inf\n")
    with pytest.raises(ConfigError) as err:
        load_profile(p)
    # Validated whole: every bad field is listed, one a line, each with the file.
    assert str(err.value).splitlines() == [f"{p}: mapping.voxel_size_m must be a finite number, got nan",
                                           f"{p}: video.fps must be a finite number, got -inf"]


OUT_OF_RANGE = [
    ("dataset.max_frames", 1, "greater than or equal to 2"),
    ("fusion.min_depth_m", -0.1, "greater than or equal to 0"),
    ("fusion.max_depth_m", 0.0, "greater than 0"),
    ("fusion.stride", 0, "greater than or equal to 1"),
    ("fusion.stride", 65, "less than or equal to 64"),
    ("mapping.voxel_size_m", 0.0, "greater than or equal to 0.001"),
    ("mapping.voxel_size_m", 0.0001, "greater than or equal to 0.001"),
    ("mapping.voxel_size_m", 2.0, "less than or equal to 1"),
    ("mapping.fit.densify_max_growth", 100.0, "less than or equal to 16"),
    ("mapping.keyframe_translation_m", -0.01, "greater than or equal to 0"),
    ("mapping.keyframe_rotation_deg", -1.0, "greater than or equal to 0"),
    ("mapping.colour_refinement.iterations", -1, "greater than or equal to 0"),
    ("mapping.colour_refinement.scale", 1.5, "less than or equal to 1"),
    ("mapping.colour_refinement.scale", 0.0, "greater than 0"),
    ("mapping.fit.epochs", -1, "greater than or equal to 0"),
    ("mapping.fit.max_steps", 0, "greater than or equal to 1"),
    ("mapping.fit.scale", 2.0, "less than or equal to 1"),
    ("mapping.fit.depth_weight", -1.0, "greater than or equal to 0"),
    ("mapping.fit.lr_position_m", -1e-4, "greater than or equal to 0"),
    ("mapping.fit.lr_final_ratio", 0.0, "greater than 0"),
    ("mapping.fit.seed", -1, "greater than or equal to 0"),
    ("localization.finest_level", 4, "less than or equal to 3"),
    ("localization.finest_level", -1, "greater than or equal to 0"),
    ("localization.max_correspondence_m", 0.0, "greater than 0"),
    ("localization.min_correspondence_m", -0.01, "greater than 0"),
    ("localization.huber_depth_m", 0.0, "greater than 0"),
    ("localization.photometric_weight", -0.1, "greater than or equal to 0"),
    ("localization.min_fitness", 1.1, "less than or equal to 1"),
    ("localization.min_agreement", -0.1, "greater than or equal to 0"),
    ("localization.max_residual_m", 0.0, "greater than 0"),
    ("localization.reference_translation_m", -1.0, "greater than or equal to 0"),
    ("localization.reference_rotation_deg", -1.0, "greater than or equal to 0"),
    ("localization.max_ate_m", 0.0, "greater than 0"),
    ("video.fps", 0, "greater than 0"),
    ("video.fps", 1e9, "less than or equal to 240"),
    ("video.orbit_frames", 0, "greater than or equal to 1"),
    ("video.orbit_frames", 10**9, "less than or equal to 10000"),
    ("video.orbit_radius_scale", 0.0, "greater than 0"),
    ("video.scale", 4.5, "less than or equal to 4"),
    ("evaluation.view_stride", 0, "greater than or equal to 1"),
    ("evaluation.max_views", 0, "greater than or equal to 1"),
]


@pytest.mark.parametrize(("name", "value", "expected"), OUT_OF_RANGE)
def test_out_of_range_is_refused_naming_the_field_and_range(name, value, expected):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides({name: value}, "--set")
    assert str(err.value) == f"--set: {name} must be {expected}, got {value!r}"


IN_RANGE_EDGES = {
    "fusion.min_depth_m": 0.0, "mapping.keyframe_translation_m": 0.0, "mapping.colour_refinement.iterations": 0,
    "mapping.colour_refinement.scale": 1.0, "mapping.fit.epochs": 0, "mapping.fit.scale": 0.25,
    "mapping.fit.depth_weight": 0, "localization.photometric_weight": 0.0, "localization.min_fitness": 1.0,
    "localization.min_agreement": 0.0, "localization.iterations": [0, 3], "dataset.max_frames": 2,
    "video.scale": 4, "video.orbit_height_m": -2.0, "evaluation.max_views": 1, "video.fps": 30,
}


def test_range_edges_are_accepted_and_ints_widen_to_floats():
    cfg = load_profile("default").with_overrides(IN_RANGE_EDGES, "--set")
    assert cfg.video.fps == 30.0 and isinstance(cfg.video.fps, float)
    assert cfg.localization.iterations == (0, 3) and cfg.dataset.max_frames == 2


CROSS_FIELD = [
    ({"fusion.min_depth_m": 5.0, "fusion.max_depth_m": 4.0},
     "fusion.max_depth_m must be > min_depth_m (5.0), got 4.0"),
    ({"fusion.min_depth_m": 4.0},
     "fusion.max_depth_m must be > min_depth_m (4.0), got 4.0"),
    ({"localization.min_correspondence_m": 0.2},
     "localization.min_correspondence_m must be <= max_correspondence_m (0.1), got 0.2"),
    ({"mapping.max_depth_m": 3.0},
     "mapping.max_depth_m must be >= fusion.max_depth_m (4.0), got 3.0"),
    ({"mapping.fit.scale": 0.3},
     "mapping.fit.scale must be 1/n for a whole n (1, 0.5, 0.25, ...), got 0.3"),
    ({"localization.iterations": []},
     "localization.iterations must list one count per pyramid level, at least one of them > 0, got []"),
    ({"localization.iterations": [0, 0]},
     "localization.iterations must list one count per pyramid level, at least one of them > 0, got [0, 0]"),
    ({"localization.iterations": [12, -1]},
     "localization.iterations[1] must be greater than or equal to 0, got -1"),
    ({"localization.finest_level": 3, "localization.iterations": [4, 3, 2, 1]},
     "localization.finest_level must be at most 2 with 4 levels of iterations, got 3"),
]


@pytest.mark.parametrize(("overrides", "message"), CROSS_FIELD)
def test_cross_field_rules_name_the_fields(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides(overrides, "--set")
    assert str(err.value) == f"--set: {message}"


def test_type_errors_in_a_file(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("fusion:\n  stride: two\n")
    with pytest.raises(ConfigError, match=r"t.yaml: fusion.stride must be a valid integer, got 'two'$"):
        load_profile(p)


def test_overrides_and_section_hash():
    cfg = load_profile("default")
    c2 = cfg.with_overrides({"localization.photometric_weight": 0.5, "localization.iterations": [4, 2]})
    assert c2.localization.photometric_weight == 0.5 and c2.localization.iterations == (4, 2)
    assert section_hash(c2.mapping) == section_hash(cfg.mapping)
    assert section_hash(c2.localization) != section_hash(cfg.localization)
    with pytest.raises(ConfigError, match="unknown config key"):
        cfg.with_overrides({"localization.nope": 1})


def test_profile_name_cannot_escape_configs():
    with pytest.raises(ConfigError):
        load_profile("../etc/passwd")


@pytest.mark.parametrize("command", [["run", "synthetic"], ["build", "--input", "synth-small", "--output", "w"]],
                         ids=["run", "build"])
def test_cli_refuses_a_nan_override_before_any_asset_runs(isolated, caplog, command):
    from assets.cli import main

    command = [str(isolated / c) if c == "w" else c for c in command]
    assert main([*command, "--set", "mapping.voxel_size_m=.nan"]) == 2
    assert "--set: mapping.voxel_size_m must be a finite number, got nan" in caplog.text
    assert not (isolated / "artifacts").exists() and not (isolated / "w").exists()
    assert not (isolated / "data").exists()  # not even the dataset was generated


def test_the_configuration_doc_is_the_models_reference():
    """docs/configuration.md lists every field with the models' default, range and description."""
    from pathlib import Path

    from atlas_pipeline.config_reference import BEGIN_MARK, END_MARK, markdown_tables

    doc = (Path(__file__).resolve().parents[1] / "docs" / "configuration.md").read_text(encoding="utf-8")
    start, end = doc.index(BEGIN_MARK), doc.index(END_MARK) + len(END_MARK)
    assert doc[start:end] == markdown_tables(), "regenerate: python -m atlas_pipeline.config_reference"
    assert all(f"| `{name.split('.', 1)[1]}` |" in doc for name, _, _ in LEAVES if "." in name)

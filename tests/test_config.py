import dataclasses
import math
import re
from typing import Literal, get_args, get_origin, get_type_hints

import pytest

from atlas_pipeline.config import RANGE_KEY, PipelineConfig, load_profile, section_hash
from atlas_pipeline.errors import ConfigError


def _leaf_fields() -> list[tuple[str, object, dataclasses.Field]]:
    """``(dotted name, annotated type, field)`` of every value of a profile, sections expanded."""
    out = []
    for sec in dataclasses.fields(PipelineConfig):
        tp = get_type_hints(PipelineConfig)[sec.name]
        if not dataclasses.is_dataclass(tp):
            out.append((sec.name, tp, sec))
            continue
        hints = get_type_hints(tp)
        out += [(f"{sec.name}.{f.name}", hints[f.name], f) for f in dataclasses.fields(tp)]
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
    assert len(FLOAT_FIELDS) >= 23 and "mapping.voxel_size_m" in FLOAT_FIELDS  # found by reflection, not listed
    for name, tp, f in LEAVES:
        numeric = tp in (int, float) or get_origin(tp) is tuple or int in get_args(tp)
        if numeric:  # declared beside the field, even where it is None (any finite value)
            assert RANGE_KEY in f.metadata, f"{name} declares no range"


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
    bound = r"( [^,]*| in [^,]*, [^,]*)?"  # "> 0", "in (0, 1]", or none
    assert re.fullmatch(rf"--set: {re.escape(name)} must be a finite number{bound}, got {value!r}", str(err.value))


@pytest.mark.parametrize(("name", "value"), WRONG_TYPES, ids=[f"{n}={v!r}" for n, v in WRONG_TYPES])
def test_wrong_type_is_refused_naming_the_field(name, value):
    with pytest.raises(ConfigError, match=rf"^--set: {re.escape(name)}(\[\d+\])? must be "):
        load_profile("default").with_overrides({name: value}, "--set")


@pytest.mark.parametrize("name", [s.name for s in dataclasses.fields(PipelineConfig) if s.name != "profile"])
def test_a_section_must_be_a_mapping(name):
    with pytest.raises(ConfigError, match=rf"^<dict>: {name} must be a mapping of keys, got 3$"):
        PipelineConfig.from_dict({name: 3})


def test_yaml_nan_names_file_and_field(tmp_path):
    p = tmp_path / "nan.yaml"
    p.write_text("mapping:\n  voxel_size_m: .nan\nvideo:\n  fps: -.inf\n")
    with pytest.raises(ConfigError) as err:
        load_profile(p)
    # Validated whole: every bad field is listed, one a line, each with the file.
    assert str(err.value).splitlines() == [f"{p}: mapping.voxel_size_m must be a finite number > 0, got nan",
                                           f"{p}: video.fps must be a finite number in (0, 240], got -inf"]


OUT_OF_RANGE = [
    ("dataset.max_frames", 1, "an integer in [2, 1000000] or null"),
    ("fusion.min_depth_m", -0.1, "a finite number >= 0"),
    ("fusion.max_depth_m", 0.0, "a finite number > 0"),
    ("fusion.stride", 0, "an integer in [1, 64]"),
    ("mapping.voxel_size_m", 0.0, "a finite number > 0"),
    ("mapping.keyframe_translation_m", -0.01, "a finite number >= 0"),
    ("mapping.keyframe_rotation_deg", -1.0, "a finite number >= 0"),
    ("mapping.colour_refinement_iterations", -1, "an integer in [0, 1000]"),
    ("mapping.colour_refinement_scale", 1.5, "a finite number in (0, 1]"),
    ("mapping.colour_refinement_scale", 0.0, "a finite number in (0, 1]"),
    ("mapping.optimization_epochs", -1, "an integer in [0, 10000]"),
    ("mapping.optimization_max_steps", 0, "an integer in [1, 100000]"),
    ("mapping.optimization_scale", 2.0, "a finite number in (0, 1]"),
    ("mapping.optimization_depth_weight", -1.0, "a finite number >= 0"),
    ("localization.iterations", [12, -1], "an integer in [0, 100]"),
    ("localization.finest_level", 4, "an integer in [0, 3]"),
    ("localization.finest_level", -1, "an integer in [0, 3]"),
    ("localization.max_correspondence_m", 0.0, "a finite number > 0"),
    ("localization.min_correspondence_m", -0.01, "a finite number > 0"),
    ("localization.huber_depth_m", 0.0, "a finite number > 0"),
    ("localization.photometric_weight", -0.1, "a finite number >= 0"),
    ("localization.min_fitness", 1.1, "a finite number in [0, 1]"),
    ("localization.min_agreement", -0.1, "a finite number in [0, 1]"),
    ("localization.max_residual_m", 0.0, "a finite number > 0"),
    ("localization.reference_translation_m", -1.0, "a finite number >= 0"),
    ("localization.reference_rotation_deg", -1.0, "a finite number >= 0"),
    ("localization.max_ate_m", 0.0, "a finite number > 0"),
    ("video.fps", 0, "a finite number in (0, 240]"),
    ("video.orbit_frames", 0, "an integer in [1, 10000]"),
    ("video.orbit_radius_scale", 0.0, "a finite number > 0"),
    ("video.scale", 4.5, "a finite number in (0, 4]"),
    ("evaluation.view_stride", 0, "an integer in [1, 1000000]"),
    ("evaluation.max_views", 0, "an integer in [1, 1000000] or null"),
]


@pytest.mark.parametrize(("name", "value", "expected"), OUT_OF_RANGE)
def test_out_of_range_is_refused_naming_the_field_and_range(name, value, expected):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides({name: value}, "--set")
    shown = value[-1] if isinstance(value, list) else value
    index = r"\[\d+\]" if isinstance(value, list) else ""
    assert re.fullmatch(rf"--set: {re.escape(name)}{index} must be {re.escape(expected)}, got {shown!r}",
                        str(err.value))


IN_RANGE_EDGES = {
    "fusion.min_depth_m": 0.0, "mapping.keyframe_translation_m": 0.0, "mapping.colour_refinement_iterations": 0,
    "mapping.colour_refinement_scale": 1.0, "mapping.optimization_epochs": 0, "mapping.optimization_scale": 0.25,
    "mapping.optimization_depth_weight": 0, "localization.photometric_weight": 0.0, "localization.min_fitness": 1.0,
    "localization.min_agreement": 0.0, "localization.iterations": [0, 3], "dataset.max_frames": 2,
    "video.scale": 4, "video.orbit_height_m": -2.0, "evaluation.max_views": 1, "video.fps": 30,
}


def test_range_edges_are_accepted_and_ints_widen_to_floats():
    cfg = load_profile("default").with_overrides(IN_RANGE_EDGES, "--set")
    assert cfg.video.fps == 30.0 and isinstance(cfg.video.fps, float)
    assert cfg.localization.iterations == (0, 3) and cfg.dataset.max_frames == 2


CROSS_FIELD = [
    ({"fusion.min_depth_m": 5.0, "fusion.max_depth_m": 4.0},
     "fusion.min_depth_m must be < fusion.max_depth_m (4.0), got 5.0"),
    ({"fusion.min_depth_m": 4.0},
     "fusion.min_depth_m must be < fusion.max_depth_m (4.0), got 4.0"),
    ({"localization.min_correspondence_m": 0.2},
     "localization.min_correspondence_m must be <= localization.max_correspondence_m (0.1), got 0.2"),
    ({"mapping.optimization_scale": 0.3},
     "mapping.optimization_scale must be 1/n for a whole n (1, 0.5, 0.25, ...), got 0.3"),
    ({"localization.iterations": []},
     "localization.iterations must list one count per pyramid level, at least one of them > 0, got []"),
    ({"localization.iterations": [0, 0]},
     "localization.iterations must list one count per pyramid level, at least one of them > 0, got [0, 0]"),
    ({"localization.finest_level": 3, "localization.iterations": [4, 3, 2, 1]},
     "localization.finest_level + len(localization.iterations) must be <= 6 pyramid levels, got 3 + 4"),
]


@pytest.mark.parametrize(("overrides", "message"), CROSS_FIELD)
def test_cross_field_rules_name_both_fields(overrides, message):
    with pytest.raises(ConfigError) as err:
        load_profile("default").with_overrides(overrides, "--set")
    assert str(err.value) == f"--set: {message}"


def test_type_errors_in_a_file(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("fusion:\n  stride: two\n")
    with pytest.raises(ConfigError, match=r"t.yaml: fusion.stride must be an integer in \[1, 64\], got 'two'$"):
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
    assert "--set: mapping.voxel_size_m must be a finite number > 0, got nan" in caplog.text
    assert not (isolated / "artifacts").exists() and not (isolated / "w").exists()
    assert not (isolated / "data").exists()  # not even the dataset was generated

"""Issue 28: trust under hostile input. Each bad input is an error (or a warning) that names the
file, line, field or option it is about, never a traceback, a misleading message or a silent
wrong result."""

from __future__ import annotations

import textwrap

import pytest

from atlas_pipeline.errors import ConfigError


# ---- a key repeated in a profile or the dataset registry ---------------------------------------

@pytest.mark.parametrize("kind, text, line, key", [
    ("profile", """\
        mapping:
          voxel_size_m: 0.02
          voxel_size_m: 0.05
        """, 3, "voxel_size_m"),
    ("profile", """\
        mapping:
          voxel_size_m: 0.02
        localization:
          finest_level: 1
        mapping:
          optimization_epochs: 0
        """, 5, "mapping"),
    ("profile", """\
        video: {fps: 15, fps: 30}
        """, 1, "fps"),
    ("registry", """\
        datasets:
          mine:
            kind: synthetic
            n_frames: 12
          mine:
            kind: synthetic
            n_frames: 40
        """, 5, "mine"),
    ("registry", """\
        datasets:
          mine:
            kind: synthetic
            seed: 0
            seed: 1
        """, 5, "seed"),
])
def test_a_repeated_yaml_key_names_file_line_and_key(tmp_path, kind, text, line, key):
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.sensors.registry import load_registry

    path = tmp_path / f"{kind}.yaml"
    path.write_text(textwrap.dedent(text))
    with pytest.raises(ConfigError) as err:
        load_profile(path) if kind == "profile" else load_registry([path])
    msg = str(err.value)
    assert msg.startswith(f"{path}:{line}: duplicate key '{key}' (first on line "), msg


def test_merge_keys_may_still_be_overridden(tmp_path):
    from atlas_pipeline.config import parse_yaml

    data = parse_yaml("base: &b {fps: 15, scale: 1.0}\nvideo:\n  <<: *b\n  fps: 30\n")
    assert data["video"] == {"fps": 30, "scale": 1.0}


def test_a_repeated_key_in_a_set_value_is_refused():
    from atlas_pipeline.config import parse_set_overrides

    with pytest.raises(ConfigError, match=r"--set 'x=\{a: 1, a: 2\}'.*duplicate key 'a'"):
        parse_set_overrides(["x={a: 1, a: 2}"])


# ---- counts and sizes bounded at load time ---------------------------------------------------------

def _counts() -> list[tuple[str, object, object]]:
    """``(dotted name, annotated type, Range)`` of every count of a profile (int, int | None,
    tuple of ints), found by reflection so a new count cannot be left unbounded."""
    import dataclasses
    from typing import get_args, get_origin, get_type_hints

    from atlas_pipeline.config import RANGE_KEY, PipelineConfig

    out = []
    for sec in dataclasses.fields(PipelineConfig):
        tp = get_type_hints(PipelineConfig)[sec.name]
        if not dataclasses.is_dataclass(tp):
            continue
        hints = get_type_hints(tp)
        for f in dataclasses.fields(tp):
            ftp = hints[f.name]
            if ftp is int or int in get_args(ftp) and get_origin(ftp) is not tuple or get_args(ftp)[:1] == (int,):
                out.append((f"{sec.name}.{f.name}", ftp, f.metadata.get(RANGE_KEY)))
    return out


COUNTS = _counts()


def test_the_counts_are_found():
    names = {n for n, _, _ in COUNTS}
    assert {"video.orbit_frames", "mapping.optimization_epochs", "localization.iterations",
            "dataset.max_frames", "fusion.stride", "evaluation.max_views"} <= names


@pytest.mark.parametrize("name, tp, rng", COUNTS + [("video.fps", float, None), ("video.scale", float, None)],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_every_count_and_size_has_a_maximum_checked_when_the_profile_is_loaded(tmp_path, name, tp, rng):
    import dataclasses
    from typing import get_origin

    from atlas_pipeline.config import RANGE_KEY, PipelineConfig, load_profile

    section, key = name.split(".")
    if rng is None:
        rng = next(f for f in dataclasses.fields(type(getattr(PipelineConfig(), section)))
                   if f.name == key).metadata[RANGE_KEY]
    top = rng.le if rng.le is not None else rng.lt
    assert top is not None, f"{name} has no upper bound"
    too_many = int(top) + 1 if tp is not float else top * 2
    shown = [too_many] if get_origin(tp) is tuple else too_many
    path = tmp_path / "huge.yaml"
    path.write_text(f"{section}:\n  {key}: {shown}\n")
    with pytest.raises(ConfigError) as err:
        load_profile(path)
    index = "[0]" if get_origin(tp) is tuple else ""
    assert str(err.value).startswith(f"{path}: {name}{index} must be "), str(err.value)
    assert f"{top:g}" in str(err.value) or str(int(top)) in str(err.value)
    assert str(err.value).endswith(f"got {too_many!r}")


@pytest.mark.parametrize("item, message", [
    ("video.orbit_frames=1000000000", "--set: video.orbit_frames must be an integer in [1, 10000], got 1000000000"),
    ("mapping.optimization_epochs=1000000", "--set: mapping.optimization_epochs must be an integer in [0, 10000], "
                                            "got 1000000"),
    ("localization.iterations=[12,8,100000]", "--set: localization.iterations[2] must be an integer in [0, 100], "
                                              "got 100000"),
])
def test_a_huge_count_fails_before_any_work(isolated, caplog, item, message):
    from assets.cli import main

    out = isolated / "w"
    assert main(["build", "--input", "synth-small", "--output", str(out), "--set", item]) == 2
    assert message in caplog.text
    assert not out.exists() and not (isolated / "data").exists()  # nothing generated, nothing written

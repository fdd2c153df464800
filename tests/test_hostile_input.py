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

import pytest

from atlas_pipeline.config import PipelineConfig, load_profile, section_hash
from atlas_pipeline.errors import ConfigError


def test_profiles_hold_the_papers_appendix_a_values():
    d = load_profile("default")
    assert d.mapping.voxel_size_m == 0.02 and d.fusion.max_depth_m == 4.0
    assert d.mapping.keyframe_translation_m == 0.08 and d.mapping.keyframe_rotation_deg == 8.0
    assert d.localization.iterations == (12, 8, 5) and d.localization.motion_model == "constant_velocity"
    demo = load_profile("demo")
    assert demo.mapping.voxel_size_m == 0.04 and demo.dataset.max_frames == 40


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


def test_type_and_range_errors(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("fusion:\n  stride: two\n")
    with pytest.raises(ConfigError, match="fusion.stride: must be an integer"):
        load_profile(p)
    with pytest.raises(ConfigError, match="min_depth_m < max_depth_m"):
        PipelineConfig.from_dict({"fusion": {"min_depth_m": 5.0, "max_depth_m": 4.0}})


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

"""One lineage builder for every bundle, the start-pose policy read from a bundle's anchor, and the
``--set`` parser the CLI and the benchmarks share."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.config import parse_set_overrides
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.scene_memory.bundle import read_lineage
from atlas_pipeline.scene_memory.metadata import bundle_lineage, start_pose


def test_lineage_of_a_cli_build_lists_its_keys_in_order_with_the_parent_last():
    parent = {"path": "/w/parent", "map_id": "abc"}
    lin = bundle_lineage("atlas-gs build", partition="synth", run_id=None, profile="default",
                         config_overrides={"mapping.voxel_size_m": 0.05}, parent=parent, created_utc="2024-01-01T00:00:00+00:00")
    assert list(lin) == ["created_by", "partition", "run_id", "created_utc", "profile", "config_overrides", "parent"]
    assert lin["created_by"] == "atlas-gs build" and lin["run_id"] is None and lin["parent"] == parent


def test_lineage_of_a_dagster_run_has_no_created_by_and_keeps_its_provenance_in_order():
    lin = bundle_lineage(partition="synth", run_id="r1", profile="default", config_overrides={},
                         raw_content_hash="h", upstream={"a": {}}, settings={}, dataset_files="v",
                         code_versions={"world_bundle": "7"})
    assert list(lin) == ["partition", "run_id", "created_utc", "profile", "config_overrides", "raw_content_hash",
                         "upstream", "settings", "dataset_files", "code_versions", "parent"]
    assert lin["parent"] is None and lin["created_utc"].endswith("+00:00")


def test_lineage_records_only_the_fields_given():
    lin = bundle_lineage("atlas-gs import-ply")
    assert list(lin) == ["created_by", "created_utc", "parent"] and lin["parent"] is None


def test_read_lineage_reads_what_the_builder_wrote(tmp_path):
    import json

    from atlas_pipeline.scene_memory.bundle import BUNDLE_FORMAT

    lin = bundle_lineage("atlas-gs build", partition="p", run_id=None, profile="fast", config_overrides={"a.b": 1},
                         parent={"path": "/x", "map_id": "m"})
    (tmp_path / "metadata.json").write_text(json.dumps({"format": BUNDLE_FORMAT, "version": 1, "map_id": "m2",
                                                        "n_gaussians": 3, "files": {}, "lineage": lin}))
    back = read_lineage(tmp_path)
    assert back["created_by"] == "atlas-gs build" and back["profile"] == "fast" and back["partition"] == "p"
    assert back["config_overrides"] == {"a.b": 1} and back["parent"]["map_id"] == "m"
    assert back["created_utc"] == lin["created_utc"]


META = {"dataset": {"name": "synth", "content_hash": "h0"},
        "anchor": {"frame_index": 3, "T_world_cam": np.eye(4).tolist()}}


def test_start_pose_is_the_anchor_for_the_same_dataset():
    T, i = start_pose(META, "synth", content_hash="h0")
    assert i == 3 and np.allclose(T, np.eye(4))


@pytest.mark.parametrize("dataset, relocalize, meta", [("other", False, META), ("synth", True, META),
                                                       ("synth", False, {"dataset": {"name": "synth",
                                                                                     "content_hash": "h0"}})])
def test_start_pose_relocalizes_for_another_dataset_on_request_or_without_an_anchor(dataset, relocalize, meta):
    assert start_pose(meta, dataset, relocalize=relocalize, content_hash="h1" if dataset == "other" else "h0") == (None, 0)


def test_a_given_start_pose_wins_at_frame_zero():
    T0 = np.diag([1.0, -1.0, -1.0, 1.0])
    T, i = start_pose(META, "synth", T0, relocalize=True)
    assert i == 0 and T is T0


def test_set_parser_reads_yaml_values():
    assert parse_set_overrides([" localization.iterations =[8, 5, 3]", "mapping.pose_source=estimated",
                                "video.scale=0.5", "evaluation.max_views=null", "a.b=x=y"]) == {
        "localization.iterations": [8, 5, 3], "mapping.pose_source": "estimated", "video.scale": 0.5,
        "evaluation.max_views": None, "a.b": "x=y"}
    assert parse_set_overrides(None) == {} and parse_set_overrides([]) == {}


@pytest.mark.parametrize("item, message", [("mapping.voxel_size_m", "--set expects key=value"),
                                           ("a.b=[1, 2", "the value is not valid YAML")])
def test_set_parser_names_the_bad_item(item, message):
    with pytest.raises(ConfigError, match=message):
        parse_set_overrides([item])


def test_cli_and_benchmarks_share_the_parser():
    """The CLI's ``--set`` is ``config.parse_set_overrides`` (what the benchmarks call): the same
    values for the same items, the same error naming the item."""
    import argparse

    from assets.cli import options

    assert options.parse_set_overrides is parse_set_overrides
    items = ["fusion.max_depth_m=3.5", "mapping.fit.selective_adam=false", "video.fps=24"]
    assert options.overrides(argparse.Namespace(set=items)) == parse_set_overrides(items, "--set")
    with pytest.raises(ConfigError, match="fusion.max_depth_m=\\[1"):
        options.overrides(argparse.Namespace(set=["fusion.max_depth_m=[1"]))

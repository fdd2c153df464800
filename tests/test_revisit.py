"""A second visit through the Dagster graph: registry ``extends``, the revisit_bundle asset, its
lineage and staleness across the two partitions, and the registry's errors naming the field."""

from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml
from dagster import DagsterInstance

from assets.launch import run_request
from assets.definitions import build_definitions
from assets.resources import atlas_config
from assets.staleness import stale_assets
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import load_registry, revisits
from tests.conftest import SMALL_SYNTH

FIRST, SECOND = "synth-a", "synth-b"
# The same room (same seed) walked again with a shaking hand: another trajectory through one place.
SECOND_SPEC = {**SMALL_SYNTH, "shake_m": 0.003, "shake_deg": 0.15}


@pytest.fixture
def two_visits(isolated):
    reg = isolated / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {
        FIRST: {"kind": "synthetic", **SMALL_SYNTH},
        SECOND: {"kind": "synthetic", "extends": FIRST, **SECOND_SPEC}}}))
    return isolated


def _run(root, instance, partition, overrides=None):
    defs = build_definitions(root / "artifacts")
    run_config, tags = run_request("default", overrides or {})
    return defs.resolve_job_def("atlas_gs_all").execute_in_process(
        partition_key=partition, instance=instance, run_config=run_config, tags=tags)


def _materialized(result) -> dict[str, dict]:
    return {e.asset_key.path[-1]: e.event_specific_data.materialization.metadata for e in result.all_events
            if e.event_type_value == "ASSET_MATERIALIZATION" and len(e.asset_key.path) == 1}


def _data_version(instance, asset: str, partition: str) -> str:
    from assets.versioning import data_version, record
    from dagster import AssetKey

    return data_version(record(instance, AssetKey(asset), partition))


@pytest.mark.slow
def test_a_second_visit_extends_the_first_visits_world_with_its_lineage(two_visits):
    root, instance = two_visits, DagsterInstance.ephemeral()
    art = root / "artifacts"
    first = _run(root, instance, FIRST)
    assert first.success and "revisit_bundle" not in _materialized(first)  # a first visit: skipped
    assert not (art / "revisit_bundle" / FIRST).exists()
    second = _run(root, instance, SECOND)
    md = _materialized(second)["revisit_bundle"]
    assert md["extends"].value == FIRST and md["reused"].value is False
    bundle = art / "revisit_bundle" / SECOND
    meta = json.loads((bundle / "metadata.json").read_text())
    parent = meta["lineage"]["parent"]
    # The lineage names the first visit's world, the very materialization it extended.
    assert parent["partition"] == FIRST
    assert parent["world"]["data_version"] == _data_version(instance, "gaussian_world", FIRST)
    assert parent["world"]["run_id"] == first.run_id
    assert meta["partition"] == SECOND and meta["dataset"]["name"] == SECOND
    first_meta = json.loads((art / "world_bundle" / FIRST / "metadata.json").read_text())
    assert parent["map_id"] == first_meta["map_id"]
    # The second visit localized in the extended world with no start pose: every frame placed.
    loc = json.loads((bundle / "localization.json").read_text())
    assert loc["summary"]["n_lost"] == 0 and loc["summary"]["n_tracked"] + loc["summary"].get("n_relocalized", 0) == 12
    df = pd.read_parquet(bundle / "transitions.parquet")
    assert (df["partition"] == SECOND).all() and (df["map_id"] == meta["map_id"]).all() and len(df) == 11
    # Rerun: nothing changed, nothing recomputed.
    again = _materialized(_run(root, instance, SECOND))
    assert again["revisit_bundle"]["reused"].value is True
    defs = build_definitions(art)
    assert stale_assets(defs, instance, SECOND, atlas_config()) == {}
    # The first visit's world changes: the second visit's revisit bundle is stale for that reason.
    _run(root, instance, FIRST, {"mapping.fit.epochs": 1})
    stale = stale_assets(defs, instance, SECOND, atlas_config())
    assert stale == {"revisit_bundle": [f"gaussian_world [{FIRST}] has a new data version"]}


def test_extends_must_name_a_registered_first_visit(tmp_path):
    def registry(datasets):
        path = tmp_path / "reg.yaml"
        path.write_text(yaml.safe_dump({"datasets": datasets}))
        return [path]

    synth = {"kind": "synthetic", "n_frames": 4}
    assert revisits(load_registry(registry({"a": synth, "b": {**synth, "extends": "a"},
                                            "c": {**synth, "extends": "a"}}))) == {"b": "a", "c": "a"}
    cases = [
        ({"b": {**synth, "extends": "nowhere"}}, "datasets.b.extends: no dataset named 'nowhere' is registered"),
        ({"b": {**synth, "extends": "b"}}, "datasets.b.extends: a dataset cannot extend its own world"),
        ({"b": {**synth, "extends": 3}}, "datasets.b.extends: must be the name of another dataset, got 3"),
        ({"b": {**synth, "extends": "../x"}}, "datasets.b.extends: invalid dataset name '../x'"),
        ({"a": synth, "b": {**synth, "extends": "a"}, "c": {**synth, "extends": "b"}},
         "datasets.c.extends: 'b' is itself a second visit (it extends 'a'); name the first visit, 'a'"),
    ]
    for datasets, message in cases:
        with pytest.raises(ConfigError) as err:
            load_registry(registry(datasets))
        assert message in str(err.value) and "reg.yaml" in str(err.value)


def test_run_all_runs_a_second_visit_after_its_first_visit(tmp_path):
    from assets.launch import first_visits_first

    path = tmp_path / "reg.yaml"
    synth = {"kind": "synthetic", "n_frames": 4}
    path.write_text(yaml.safe_dump({"datasets": {"visit2": {**synth, "extends": "visit1"}, "other": synth,
                                                 "visit1": synth}}))
    reg = load_registry([path])
    assert first_visits_first(["visit2", "other", "visit1"], reg) == ["other", "visit1", "visit2"]
    # Without its first visit in the run, a second visit keeps its place (its input is read as stored).
    assert first_visits_first(["visit2", "other"], reg) == ["visit2", "other"]


@pytest.mark.slow
def test_a_second_visit_run_before_its_first_visit_names_the_run_to_do_first(two_visits):
    defs = build_definitions(two_visits / "artifacts")
    run_config, tags = run_request("default", {})
    result = defs.resolve_job_def("atlas_gs_all").execute_in_process(
        partition_key=SECOND, instance=DagsterInstance.ephemeral(), run_config=run_config, tags=tags,
        raise_on_error=False)
    assert not result.success
    failures = [str(e.event_specific_data.error) for e in result.all_events if e.event_type_value == "STEP_FAILURE"]
    assert any(f"gaussian_world of partition {FIRST}, an input of partition {SECOND}" in f
               and f"run `atlas-gs run {FIRST}` first" in f for f in failures), failures
    assert not (two_visits / "artifacts" / "revisit_bundle" / SECOND).exists()


def test_a_visit_localized_with_its_bundles_tracking_files_renders_no_place_index_again(small_manifest, monkeypatch):
    """The revisit asset makes the bundle's tracking map and place index first and localizes with
    them: the same report as a session that indexes the world itself, no view rendered twice."""
    import numpy as np

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.localization.localizer import bundle_tracking_files, localize_visit
    from atlas_pipeline.localization.places import PlaceIndex
    from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse

    cfg = load_profile("default").with_overrides({"mapping.fit.epochs": 0})
    fused = fuse(small_manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(small_manifest, fused, cfg), cfg)
    expected = localize_visit(small_manifest, world, cfg)
    tracking = bundle_tracking_files(world, small_manifest.camera, cfg.localization)

    def rendered_again(*_args, **_kwargs):
        raise AssertionError("a view of the place index was rendered again")

    monkeypatch.setattr(PlaceIndex, "add_keyframe", rendered_again)
    got = localize_visit(small_manifest, world, cfg, tracking=tracking)
    assert got.summary["n_lost"] == expected.summary["n_lost"] == 0
    np.testing.assert_array_equal(got.T_world_cam, expected.T_world_cam)

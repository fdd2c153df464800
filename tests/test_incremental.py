"""Reruns recompute only what is stale; lineage, dataset partitions and blocking checks."""

import json
import os
from pathlib import Path

import pytest
from dagster import AssetKey, DagsterInstance, build_sensor_context

from assets.cli import main
from assets.launch import run_request
from assets.definitions import build_definitions, loaded_partitions
from assets.resources import atlas_config
from assets.staleness import stale_assets
from atlas_pipeline.sensors.registry import load_registry

# The small synthetic frames are 160x120: registering them needs their own camera (checked whole).
SMALL_INTRINSICS = ["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120"]

PART = "synth-small"
UPSTREAM = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world"]
DOWNSTREAM_OF_LOCALIZATION = ["localization_report", "transitions", "demo_videos", "render_evaluation", "world_bundle"]


def _run(root: Path, instance, overrides=None, raise_on_error=True):
    """The job as `atlas-gs run --set` launches it: the overrides as run config and tags."""
    defs = build_definitions(root / "artifacts")
    run_config, tags = run_request("default", overrides or {})
    return defs.resolve_job_def("atlas_gs_all").execute_in_process(
        partition_key=PART, instance=instance, run_config=run_config, tags=tags, raise_on_error=raise_on_error)


def _dagster_ui_status(defs, instance, partition) -> dict[str, str]:
    """What Dagster's UI shows (its stale-status resolver; private API, used by this test only)."""
    from dagster._core.asset_graph_view.asset_graph_view import AssetGraphView, TemporalContext
    from dagster._core.definitions.data_version import CachingStaleStatusResolver
    from dagster._time import get_current_datetime

    graph = defs.resolve_asset_graph()
    view = AssetGraphView(temporal_context=TemporalContext(effective_dt=get_current_datetime(), last_event_id=None),
                          instance=instance, asset_graph=graph)
    resolver = CachingStaleStatusResolver(instance=instance, asset_graph=graph, loading_context=view)
    # What the partition's runs materialize: not the exports (a job of their own), nor the revisit
    # bundle of a first visit (skipped: nothing to extend).
    job = {k for k in graph.materializable_asset_keys
           if defs.resolve_assets_def(k).group_names_by_key[k] != "exports" and k.to_user_string() != "revisit_bundle"}
    return {k.to_user_string(): resolver.get_status(k, partition).value for k in job}


def _files(root: Path, assets=None) -> dict[str, tuple[int, bytes]]:
    art = root / "artifacts"
    return {str(p.relative_to(art)): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(art.rglob("*")) if p.is_file() and (assets is None or p.relative_to(art).parts[0] in assets)}


def _materializations(result) -> dict[str, dict]:
    """Metadata of the pipeline assets materialized (settings/* left out)."""
    return {ev.asset_key.path[-1]: ev.event_specific_data.materialization.metadata for ev in result.all_events
            if ev.event_type_value == "ASSET_MATERIALIZATION" and len(ev.asset_key.path) == 1}


def _data_versions(instance, names):
    out = {}
    for a in names:
        ev = instance.get_latest_materialization_event(AssetKey(a))
        out[a] = ev.dagster_event.event_specific_data.materialization.tags.get("dagster/data_version")
    return out


@pytest.fixture
def persistent(isolated):
    with DagsterInstance.get() as instance:  # DAGSTER_HOME of the isolated fixture
        yield isolated, instance


@pytest.mark.slow
def test_second_run_reuses_everything_and_touches_nothing(persistent):
    root, instance = persistent
    first = _run(root, instance)
    before = _files(root)
    dv_before = _data_versions(instance, UPSTREAM + DOWNSTREAM_OF_LOCALIZATION)
    second = _run(root, instance)
    assert _files(root) == before  # bytes and modification times
    md = _materializations(second)
    assert set(md) == set(UPSTREAM + DOWNSTREAM_OF_LOCALIZATION)
    assert all(m["reused"].value for m in md.values())
    assert all(not m["reused"].value for m in _materializations(first).values())
    logs = [e.user_message for e in instance.all_logs(second.run_id) if e.user_message]
    assert sorted(m.split()[2] for m in logs if m.startswith("reused cached")) == sorted(md)
    # Same data versions, so nothing downstream becomes stale; checks are reported again.
    assert _data_versions(instance, list(md)) == dv_before
    checks = {e.asset_check_evaluation_data.check_name: e.asset_check_evaluation_data.passed
              for e in second.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"}
    assert checks == {"gaussians_finite_and_nonempty": True, "ate_within_bound": True,
                      "transitions_schema": True, "bundle_reload_identical": True}
    # Metadata worth looking at survives reuse: the plot and the preview travel with the record.
    assert "trajectory_plot" in md["localization_report"] and "render_preview" in md["gaussian_world"]
    assert md["localization_report"]["trajectory_plot"].value.startswith("![")
    assert "preview" in md["transitions"] and "compute_s" in md["fused_frames"]


@pytest.mark.slow
def test_localization_change_recomputes_only_localization_and_downstream(persistent):
    root, instance = persistent
    _run(root, instance)
    up_before = _files(root, UPSTREAM)
    change = {"localization.map_photometric_weight": 0.3}
    defs = build_definitions(root / "artifacts")
    assert set(_dagster_ui_status(defs, instance, PART).values()) == {"FRESH"}
    # What a run with the change would recompute: the settings of localization_report (and of the
    # bundle, which records the whole config) changed; everything after it may change.
    stale = stale_assets(defs, instance, PART, atlas_config(None, change))
    assert sorted(stale) == sorted(DOWNSTREAM_OF_LOCALIZATION)
    assert stale["localization_report"] == ["settings changed: localization.map_photometric_weight 1.0 -> 0.3"]
    # The UI of a code location whose profile has the change (edited, reloaded): the settings it changes
    # show as stale (keyframes' in case the dataset is tracked; this one is not, see test_keyframes_read...).
    ui = _dagster_ui_status(build_definitions(root / "artifacts", overrides=change), instance, PART)
    assert sorted(k for k, v in ui.items() if v != "FRESH") == [
        "settings/keyframes", "settings/localization_report", "settings/revisit_bundle", "settings/world_bundle"]
    result = _run(root, instance, change)
    md = _materializations(result)
    assert sorted(a for a, m in md.items() if not m["reused"].value) == sorted(DOWNSTREAM_OF_LOCALIZATION)
    assert _files(root, UPSTREAM) == up_before
    rec = json.loads((root / "artifacts" / "localization_report" / PART / "_artifact.json").read_text())
    assert rec["run_id"] == result.run_id
    # The run recorded its overrides; everything is current again, in the UI's view and for the change.
    assert instance.get_run_by_id(result.run_id).tags["atlas/set/localization.map_photometric_weight"] == "0.3"
    assert instance.get_run_by_id(result.run_id).run_config["resources"]["atlas"]["config"] == {
        "localization": {"map_photometric_weight": 0.3}}
    assert set(_dagster_ui_status(defs, instance, PART).values()) == {"FRESH"}
    assert stale_assets(defs, instance, PART, atlas_config(None, change)) == {}
    # Back to the profile's value: localization and after recomputed; a check threshold versions nothing.
    assert sorted(stale_assets(defs, instance, PART, atlas_config())) == sorted(DOWNSTREAM_OF_LOCALIZATION)
    assert sorted(stale_assets(defs, instance, PART, atlas_config(None, {**change, "localization.max_ate_m": 1.0}))) == [
        "world_bundle"]  # its metadata.json holds the whole config


@pytest.mark.slow
def test_edited_raw_files_are_noticed(persistent):
    root, instance = persistent
    _run(root, instance)
    depth = sorted((root / "data" / PART / "depth").iterdir())[3]
    depth.write_bytes(depth.read_bytes())  # same bytes, new mtime: the content hashes say nothing changed
    assert stale_assets(build_definitions(root / "artifacts"), instance, PART, atlas_config()) == {}
    # One digit of a pose changed, size and modification time restored (what cp -p, rsync -t leave)
    gt = root / "data" / PART / "groundtruth.txt"
    st, text = gt.stat(), gt.read_text()
    i = len(text.rstrip("\n")) - 1  # the last digit of the last quaternion: 1e-7 off, still a pose
    gt.write_text(text[:i] + ("1" if text[i] != "1" else "2") + text[i + 1:])
    os.utime(gt, ns=(st.st_atime_ns, st.st_mtime_ns))
    # The registry sensor observes the dataset's files (the daemon records what it returns): the UI
    # shows the raw dataset stale.
    sensor = build_definitions(root / "artifacts").resolve_sensor_def("dataset_registry_sensor")
    for event in sensor(build_sensor_context(instance=instance)).asset_events:
        instance.report_runless_asset_event(event)
    assert _dagster_ui_status(build_definitions(root / "artifacts"), instance, PART)["raw_dataset"] == "STALE"
    status = stale_assets(build_definitions(root / "artifacts"), instance, PART, atlas_config())
    assert status.pop("raw_dataset") == ["dataset files changed"]
    assert all(r.endswith("(may change)") for reasons in status.values() for r in reasons)
    result = _run(root, instance)
    assert not _materializations(result)["raw_dataset"]["reused"].value


@pytest.mark.slow
def test_cli_stale_only_runs_nothing_when_current_then_only_the_changed(isolated, capsys):
    assert main(["run", PART]) == 0
    capsys.readouterr()
    assert main(["run", PART, "--stale-only"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stale"] == [] and out["ran"] is False
    assert main(["status", PART, "--json", "--set", "localization.map_photometric_weight=0.5"]) == 0
    status = json.loads(capsys.readouterr().out)[PART]
    assert sorted(status) == sorted(DOWNSTREAM_OF_LOCALIZATION)
    assert main(["run", PART, "--stale-only", "--set", "localization.map_photometric_weight=0.5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert sorted(out["stale"]) == sorted(out["recomputed"]) == sorted(DOWNSTREAM_OF_LOCALIZATION)
    assert out["reused"] == []


@pytest.mark.slow
def test_bundle_lineage_and_lineage_command(persistent, capsys):
    root, instance = persistent
    result = _run(root, instance)
    bundle = root / "artifacts" / "world_bundle" / PART
    lin = json.loads((bundle / "metadata.json").read_text())["lineage"]
    assert lin["partition"] == PART and lin["run_id"] == result.run_id and lin["created_utc"]
    assert set(lin["upstream"]) == set(UPSTREAM) | {"localization_report", "transitions"}
    dvs = _data_versions(instance, list(lin["upstream"]))
    assert {a: u["data_version"] for a, u in lin["upstream"].items()} == dvs
    fused_def = build_definitions(root / "artifacts").resolve_assets_def(AssetKey("fused_frames"))
    assert lin["code_versions"]["world_bundle"]
    assert lin["code_versions"]["fused_frames"] == fused_def.get_asset_spec(AssetKey("fused_frames")).code_version == "2"
    assert lin["parent"] is None
    assert main(["lineage", PART]) == 0
    text = capsys.readouterr().out
    assert f"run id      {result.run_id}" in text and dvs["gaussian_world"] in text and "parent      none" in text
    assert main(["lineage", str(bundle), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["run_id"] == result.run_id and js["config"]["localization"]["photometric_weight"] == 0.1
    assert main(["lineage", "no-such-bundle"]) == 2


@pytest.mark.slow
def test_extended_world_names_its_parent(isolated, capsys):
    from atlas_pipeline.scene_memory.bundle import read_lineage

    parent = isolated / "worlds" / "first"
    assert main(["build", "--input", PART, "--output", str(parent)]) == 0
    child = isolated / "worlds" / "second"
    assert main(["build", "--input", PART, "--output", str(child), "--extend", str(parent)]) == 0
    capsys.readouterr()
    lin = read_lineage(child)
    pmeta = json.loads((parent / "metadata.json").read_text())
    assert lin["parent"]["path"] == str(parent.resolve()) and lin["parent"]["map_id"] == pmeta["map_id"]
    assert read_lineage(parent)["parent"] is None
    assert main(["lineage", str(child)]) == 0
    assert f"parent      {parent.resolve()} (map_id {pmeta['map_id']})" in capsys.readouterr().out


@pytest.mark.slow
def test_failing_blocking_check_stops_downstream(persistent):
    root, instance = persistent
    result = _run(root, instance, {"localization.max_ate_m": 1e-9}, raise_on_error=False)
    checks = {e.asset_check_evaluation_data.check_name: e.asset_check_evaluation_data
              for e in result.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"}
    assert checks["ate_within_bound"].passed is False
    done = set(_materializations(result))
    assert "localization_report" in done
    assert not done & {"transitions", "world_bundle", "demo_videos"}
    assert not (root / "artifacts" / "world_bundle" / PART).exists()
    # A rerun with the same bound reuses the report and replays the failed check: still gated.
    again = _run(root, instance, {"localization.max_ate_m": 1e-9}, raise_on_error=False)
    assert _materializations(again)["localization_report"]["reused"].value
    assert "world_bundle" not in _materializations(again)


def test_dataset_add_adds_a_partition_and_the_sensor_names_datasets_to_reload_for(isolated, small_synthetic, capsys):
    import yaml

    from atlas_pipeline.errors import ConfigError
    from atlas_pipeline.sensors.registry import validate_dataset_name

    for bad in ("Bad Name!", "../escape", "", "-lead"):
        with pytest.raises(ConfigError):
            validate_dataset_name(bad)
    assert main(["dataset", "add", "../x", str(small_synthetic)]) == 2
    assert main(["dataset", "add", "my-room", str(small_synthetic), *SMALL_INTRINSICS]) == 0
    defs = build_definitions(isolated / "artifacts")
    assert "my-room" in loaded_partitions(defs)  # the definitions read the registry as they load
    sensor = defs.resolve_sensor_def("dataset_registry_sensor")
    with DagsterInstance.get() as instance:
        for event in sensor(build_sensor_context(instance=instance)).asset_events:  # first look: its files
            instance.report_runless_asset_event(event)
        assert sensor(build_sensor_context(instance=instance)).skip_message.endswith("unchanged on disk")
        # A dataset written into the registry by hand after they loaded: the sensor says to reload.
        reg = isolated / "datasets.local.yaml"
        data = yaml.safe_load(reg.read_text())
        data["datasets"]["by-hand"] = {"kind": "tum", "path": str(small_synthetic), "camera": "freiburg1"}
        reg.write_text(yaml.safe_dump(data))
        skip = sensor(build_sensor_context(instance=instance)).skip_message
        assert "until the code location reloads: by-hand (" in skip and "my-room" not in skip, skip
        assert "by-hand" in loaded_partitions(build_definitions(isolated / "artifacts"))  # reloaded
        # A broken registry is reported, not raised.
        reg.write_text("datasets:\n  Bad Name: {kind: tum, path: x}\n")
        skip = sensor(build_sensor_context(instance=instance))
        assert "Bad Name" in skip.skip_message and "invalid dataset name" in skip.skip_message


def test_register_dataset_job_from_the_ui(isolated, small_synthetic):
    defs = build_definitions(isolated / "artifacts")
    with DagsterInstance.get() as instance:
        job = defs.resolve_job_def("register_dataset")
        ok = job.execute_in_process(instance=instance, run_config={"ops": {"register_dataset_op": {"config": {
            "name": "ui-room", "path": str(small_synthetic), "intrinsics": "131.25 131.25 79.5 59.5",
            "width": 160, "height": 120}}}})
        assert ok.success and "ui-room" in loaded_partitions(build_definitions(isolated / "artifacts"))
        bad = job.execute_in_process(instance=instance, raise_on_error=False, run_config={"ops": {
            "register_dataset_op": {"config": {"name": "UI Room", "path": str(small_synthetic)}}}})
        assert not bad.success and "UI Room" not in load_registry()


def test_keyframes_read_the_tracker_settings_exactly_when_they_track(small_manifest):
    """One ground-truth rule: the keyframes stage's own (mapping.keyframes.uses_ground_truth). A
    dataset with ground truth for a third of its frames is mapped from tracked poses, so its keyframes
    depend on the tracker's settings (a groundtruth.txt being there is not enough)."""
    import dataclasses

    import numpy as np

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping.keyframes import uses_ground_truth
    from assets.versioning import STAGES, stage_settings

    cfg = load_profile("default")
    n = small_manifest.n_frames
    partial = dataclasses.replace(small_manifest, has_gt=np.arange(n) < n // 3)
    assert uses_ground_truth(small_manifest, cfg.mapping) and not uses_ground_truth(partial, cfg.mapping)
    assert "localization.photometric_weight" not in stage_settings(cfg, "keyframes", small_manifest)
    assert "localization.photometric_weight" in stage_settings(cfg, "keyframes", partial)
    # Per field, not per section: the keyframe fit's settings shape the world, not the keyframes;
    # the ATE bound is read by its check only (and recorded in the bundles' config).
    assert "mapping.fit.epochs" not in stage_settings(cfg, "keyframes", partial)
    assert "mapping.fit.epochs" in stage_settings(cfg, "gaussian_world")
    assert [s for s in STAGES if "localization.max_ate_m" in stage_settings(cfg, s, partial)] == [
        "world_bundle", "revisit_bundle"]

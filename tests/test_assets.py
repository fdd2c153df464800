"""The whole asset graph, materialized in-process into a temporary folder (as Dagster's examples test)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from dagster import DagsterInstance

from assets.launch import run_request
from assets.definitions import build_definitions, loaded_partitions
from assets.resources import dataset_entry
from atlas_pipeline.scene_memory.bundle import load_world_bundle

ASSETS = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
          "transitions", "demo_videos", "render_evaluation", "world_bundle"]


def _materialize(root: Path, partition: str, profile: str = "default", overrides=None, raise_on_error=True,
                 instance=None):
    """Run the job on ``partition`` in-process (``instance``: ephemeral unless given)."""
    defs = build_definitions(root / "artifacts", profile=profile)
    instance = instance or DagsterInstance.ephemeral()
    run_config, tags = run_request(profile, overrides or {})
    return defs.resolve_job_def("atlas_gs_all").execute_in_process(
        partition_key=partition, instance=instance, run_config=run_config, tags=tags, raise_on_error=raise_on_error)


def test_library_does_not_import_dagster():
    code = ("import sys, atlas_pipeline.scene_memory.bundle, atlas_pipeline.versioning, "
            "atlas_pipeline.scene_memory.metadata, atlas_pipeline.viz.demo, atlas_pipeline.mapping.mapper, "
            "atlas_pipeline.viz.plots; print('dagster' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_partitions_come_from_the_registry(isolated):
    keys = loaded_partitions(build_definitions(isolated / "artifacts"))  # no instance holds them
    assert keys[0] == "synthetic" and "synth-small" in keys and "tum-fr3-teddy" not in keys  # a download preset: a partition once fetched


@pytest.mark.slow
def test_full_graph_materializes_on_synthetic(isolated):
    result = _materialize(isolated, "synth-small")
    assert result.success
    art = isolated / "artifacts"
    for a in ASSETS:
        rec = json.loads((art / a / "synth-small" / "_artifact.json").read_text())
        assert rec["partition"] == "synth-small" and rec["files"]
    bundle = art / "world_bundle" / "synth-small"
    assert {"metadata.json", "gaussians.ply", "gaussians.bin", "localization.json", "transitions.parquet"} <= {
        p.name for p in bundle.iterdir()}
    meta = json.loads((bundle / "metadata.json").read_text())
    assert meta["partition"] == "synth-small" and meta["lineage"]["run_id"] == result.run_id
    df = pd.read_parquet(bundle / "transitions.parquet")
    assert len(df) == 11 and df["action_vx_mps"].dtype == np.float64 and df["valid"].all()
    assert (df["pose_source"] == "estimated").all()
    loc = json.loads((bundle / "localization.json").read_text())["summary"]
    assert loc["rmse_t_unaligned_m"] < 0.005 and loc["ate_rmse_m"] < 0.003
    for source in ("bin", "ply"):
        f = load_world_bundle(bundle, source).field
        assert len(f) == meta["n_gaussians"]
    videos = sorted((art / "demo_videos" / "synth-small").glob("*.mp4"))
    assert [v.name for v in videos] == ["synth-small_orbit.mp4", "synth-small_side_by_side.mp4",
                                        "synth-small_trajectory.mp4"]
    ev = json.loads((art / "render_evaluation" / "synth-small" / "photometric.json").read_text())
    held = set(range(12)) - set(meta["keyframes"]["indices"])
    assert ev["summary"]["n_views"] >= 1 and {v["frame"] for v in ev["views"]} <= held
    # Sanity bounds for a 4-keyframe 160x120 world. Depth L1 (pixels within the 4 m tracking range)
    # was 4-5 cm before the map reached 8 m and is ~6 cm since: Gaussians past 4 m, seen through
    # the edges of nearer ones, pull the alpha-blended depth back (README, "Mapping range").
    assert ev["summary"]["mean_psnr_masked_db"] > 15 and ev["summary"]["mean_depth_l1_m"] < 0.08
    assert (art / "render_evaluation" / "synth-small" / "preview.png").stat().st_size > 0
    checks = {e.asset_check_evaluation_data.check_name: e.asset_check_evaluation_data.passed
              for e in result.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"}
    assert checks == {"gaussians_finite_and_nonempty": True, "bundle_reload_identical": True,
                      "ate_within_bound": True, "transitions_schema": True}
    # Timings are materialization metadata, not artifact content (equal results, equal bytes).
    loc = json.loads((art / "localization_report" / "synth-small" / "localization.json").read_text())
    assert "frames_per_s" not in loc["summary"] and "time_s" not in loc["frames"][0]
    assert "seconds" not in json.loads((art / "gaussian_world" / "synth-small" / "world.json").read_text())["fit"]
    md = {e.asset_key.path[-1]: e.event_specific_data.materialization.metadata for e in result.all_events
          if e.event_type_value == "ASSET_MATERIALIZATION" and len(e.asset_key.path) == 1}
    assert md["localization_report"]["frames_per_s"].value > 0 and md["gaussian_world"]["compute_s"].value > 0
    assert all(m["compute_s"].value >= 0 for m in md.values())


@pytest.mark.slow
def test_bad_input_fails_and_keeps_earlier_artifacts(isolated):
    assert _materialize(isolated, "synth-small").success
    art = isolated / "artifacts"
    before = {p: p.read_bytes() for p in (art / "raw_dataset" / "synth-small").iterdir()}
    # Break the dataset: a malformed line in rgb.txt.
    rgb = isolated / "data" / "synth-small" / "rgb.txt"
    lines = rgb.read_text().splitlines()
    lines[4] = "not-a-time rgb/x.png"
    rgb.write_text("\n".join(lines) + "\n")
    # The synthetic generator would regenerate a tampered folder only if its marker changed; keep it.
    result = _materialize(isolated, "synth-small", raise_on_error=False)
    assert not result.success
    msgs = " ".join(str(e.event_specific_data.error.cause.message) for e in result.all_events
                    if e.is_step_failure and e.event_specific_data.error.cause)
    assert "rgb.txt:5" in msgs and "timestamp is not a number" in msgs
    assert {p: p.read_bytes() for p in (art / "raw_dataset" / "synth-small").iterdir()} == before


def test_unknown_partition_name_is_refused(isolated):
    from atlas_pipeline.errors import ConfigError

    with pytest.raises(ConfigError):
        dataset_entry("no-such-dataset")


def _config_fields(defs):
    """The ``atlas`` resource's config fields as the launchpad shows them (Dagster's config schema)."""
    schema = defs.resolve_job_def("atlas_gs_all").run_config_schema.config_type
    return schema.fields["resources"].config_type.fields["atlas"].config_type.fields["config"].config_type.fields


def test_launchpad_shows_every_setting_with_its_description_and_the_profiles_default(isolated):
    from atlas_pipeline.config import load_profile

    demo = json.loads(json.dumps(load_profile("demo").to_dict()))
    fields = _config_fields(build_definitions(isolated / "artifacts", profile="demo"))
    assert fields["profile"].default_value == "demo"
    n = 0

    def check(fields_here, values, path):
        nonlocal n
        assert set(fields_here) == set(values), path
        for name, value in values.items():
            f = fields_here[name]
            assert f.description, (path, name)
            if isinstance(value, dict):  # a sub-section (mapping.fit)
                check(f.config_type.fields, value, f"{path}.{name}")
                continue
            assert f.default_provided and f.default_value == value, (path, name)
            n += 1

    for section, values in demo.items():
        if isinstance(values, dict):
            check(fields[section].config_type.fields, values, section)
    assert n >= 60  # every field of every section
    loc = fields["localization"].config_type.fields
    assert "allowed: > 0" in loc["max_ate_m"].description and "ATE" in loc["max_ate_m"].description
    assert "constant_velocity" in loc["motion_model"].description  # a Literal: an enum listing its choices


def test_run_config_sets_one_field_and_an_invalid_value_names_it(isolated):
    from atlas_pipeline.errors import ConfigError

    atlas = build_definitions(isolated / "artifacts", profile="demo").resources["atlas"]
    run = type(atlas)(localization={"photometric_weight": 0.5})  # what a run config of one field gives
    cfg = run.load()
    assert cfg.localization.photometric_weight == 0.5 and cfg.mapping.voxel_size_m == 0.04 and cfg.profile == "demo"
    assert cfg.localization.iterations == (12, 8, 5)
    with pytest.raises(ConfigError, match=r"run config: mapping.voxel_size_m must be greater than or equal to 0.001, got -1.0"):
        type(atlas)(mapping={"voxel_size_m": -1.0}).load()


def test_an_explicit_profile_beats_atlas_profile_and_loading_writes_nothing(isolated, monkeypatch):
    monkeypatch.setenv("ATLAS_PROFILE", "demo")
    assert build_definitions(isolated / "artifacts").resources["atlas"].profile == "demo"
    assert build_definitions(isolated / "artifacts", profile="default").resources["atlas"].profile == "default"
    home = isolated / "dagster_home"
    subprocess.run([sys.executable, "-c", "import assets.definitions"], check=True, cwd=Path(__file__).resolve().parents[1])
    assert list(home.iterdir()) == []  # no instance was even opened


@pytest.mark.slow
def test_dagster_asset_materialize_works_from_a_fresh_dagster_home(isolated):
    """Dagster's own command, nothing before it: the partitions are the registry's, read as the
    definitions load (no `atlas-gs dataset sync`)."""
    import os

    home = isolated / "dagster_home"
    assert list(home.iterdir()) == []
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, "-m", "dagster", "asset", "materialize", "--select", "*",
                          "--partition", "synth-small", "-m", "assets.definitions"],
                         cwd=root, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    for a in ASSETS:
        assert json.loads((isolated / "artifacts" / a / "synth-small" / "_artifact.json").read_text())["files"]
    with DagsterInstance.get() as instance:
        (run,) = instance.get_runs()
        assert run.is_success and run.tags["dagster/partition"] == "synth-small"


def test_the_data_version_tag_is_dagsters():
    """assets.versioning reads and writes data versions through this tag: fails when Dagster moves it."""
    from dagster._core.definitions.data_version import DATA_VERSION_TAG

    from assets.versioning import DATA_VERSION_TAG as ours

    assert ours == DATA_VERSION_TAG


def test_a_bad_run_config_fails_the_run_with_the_field_as_its_first_line(isolated):
    """In the UI a refused run config reads as our message (an intentional failure), not a stack trace."""
    from dagster import DagsterInstance

    job = build_definitions(isolated / "artifacts").resolve_job_def("atlas_gs_all")
    res = job.execute_in_process(partition_key="synth-small", instance=DagsterInstance.ephemeral(), raise_on_error=False,
                                 run_config={"resources": {"atlas": {"config": {"mapping": {"voxel_size_m": -1.0}}}}})
    failure = next(ev for ev in res.all_events if ev.event_type_value == "STEP_FAILURE")
    assert failure.event_specific_data.user_failure_data.description == (
        "run config: mapping.voxel_size_m must be greater than or equal to 0.001, got -1.0")
    assert not (isolated / "artifacts").exists() or not any((isolated / "artifacts").rglob("*.npz"))

"""The whole asset graph, materialized in-process into a temporary folder (as Dagster's examples test)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from dagster import DagsterInstance, materialize

from assets.definitions import build_definitions, sync_dataset_partitions
from assets.io_managers import ArtifactIOManager
from assets.resources import AtlasConfig
from atlas_pipeline.scene_memory.bundle import load_world_bundle

ASSETS = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
          "transitions", "demo_videos", "render_evaluation", "world_bundle"]


def _materialize(root: Path, partition: str, profile: str = "default", overrides=None, raise_on_error=True,
                 instance=None):
    """Materialize every asset of ``partition`` in-process (``instance``: ephemeral unless given)."""
    defs = build_definitions(root / "artifacts", profile=profile, overrides=overrides)
    instance = instance or DagsterInstance.ephemeral()
    sync_dataset_partitions(instance)
    return materialize(
        list(defs.assets), partition_key=partition, instance=instance,
        resources={"artifact_io": ArtifactIOManager(root=str(root / "artifacts")),
                   "atlas": AtlasConfig(profile=profile, overrides=overrides or {})},
        raise_on_error=raise_on_error,
    )


def test_library_does_not_import_dagster():
    code = ("import sys, atlas_pipeline.pipeline, atlas_pipeline.scene_memory.bundle, atlas_pipeline.versioning, "
            "atlas_pipeline.viz.plots; print('dagster' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_partitions_come_from_the_registry(isolated):
    from dagster._core.definitions.partitions.context import partition_loading_context

    defs = build_definitions(isolated / "artifacts")
    instance = DagsterInstance.ephemeral()
    assert sync_dataset_partitions(instance)[:1] == ["synthetic"]
    assert sync_dataset_partitions(instance) == []  # idempotent
    with partition_loading_context(dynamic_partitions_store=instance):
        keys = defs.resolve_job_def("atlas_gs_all").partitions_def.get_partition_keys()
    assert keys[0] == "synthetic" and "synth-small" in keys and "tum-fr3-teddy" in keys


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
    assert ev["summary"]["mean_psnr_masked_db"] > 15 and ev["summary"]["mean_depth_l1_m"] < 0.05
    assert (art / "render_evaluation" / "synth-small" / "preview.png").stat().st_size > 0
    checks = {e.asset_check_evaluation_data.check_name: e.asset_check_evaluation_data.passed
              for e in result.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"}
    assert checks == {"gaussians_finite_and_nonempty": True, "bundle_reload_identical": True,
                      "ate_within_bound": True, "transitions_schema": True}


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
        AtlasConfig().dataset("no-such-dataset")

"""The whole pipeline on real TUM RGB-D frames registered as datasets (skipped without them)."""

import json

import pandas as pd
import pytest
from dagster import DagsterInstance

from assets.definitions import build_definitions
from atlas_pipeline.sensors.registry import load_registry, register_local_dataset
from tests.conftest import tum_folder

pytestmark = [pytest.mark.tum, pytest.mark.slow]  # the whole graph on real frames


@pytest.mark.parametrize("folder,name,camera,max_rmse_m", [
    ("tum_fr1_xyz_10", "tum-fr1-xyz-10", "freiburg1", 0.03),
    ("tum_fr3_teddy_100", "tum-fr3-teddy-100", "freiburg3", 0.10),
])
def test_real_sequence_through_every_asset(isolated, folder, name, camera, max_rmse_m):
    root = tum_folder(folder)
    register_local_dataset(name, root, camera)
    assert name in load_registry()
    # Registered before the definitions load: one of their partitions.
    defs = build_definitions(isolated / "artifacts", profile="demo" if "teddy" in name else "default")
    instance = DagsterInstance.ephemeral()
    # What `atlas-gs run` materializes (the exports are a job of their own: a desk recording that
    # shows no floor has no occupancy grid to export).
    result = defs.resolve_job_def("atlas_gs_all").execute_in_process(partition_key=name, instance=instance)
    assert result.success
    bundle = isolated / "artifacts" / "world_bundle" / name
    summary = json.loads((bundle / "localization.json").read_text())["summary"]
    assert summary["n_graded"] > 0 and summary["ate_rmse_m"] is not None
    # An honest bound, not a target: poses come from tracking alone (ground truth only grades).
    assert summary["ate_rmse_m"] < max_rmse_m
    df = pd.read_parquet(bundle / "transitions.parquet")
    meta = json.loads((bundle / "metadata.json").read_text())
    assert len(df) == meta["dataset"]["n_frames"] - 1
    assert meta["dataset"]["camera"]["fx"] == {"freiburg1": 517.306408, "freiburg3": 535.4}[camera]

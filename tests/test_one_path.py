"""One tracking path. The CLI (`build` then `localize`, the map reloaded from the bundle)
and the Dagster graph (the map handed from asset to asset) give the same poses, bit for bit."""

import numpy as np
import pytest

from assets.cli import main
from atlas_pipeline.localization.localizer import LocalizationReport
from atlas_pipeline.scene_memory.bundle import read_metadata

# Mapping from tracked poses (the route that differed); the keyframe fit does not move the map the
# tracker uses, so it is off to keep the test short.
SETTINGS = ["--set", "mapping.pose_source=estimated", "--set", "mapping.fit.epochs=0"]


@pytest.mark.slow
def test_cli_and_dagster_give_the_same_poses(isolated, capsys):
    world = isolated / "world"
    assert main(["build", "--input", "synth-small", "--output", str(world), *SETTINGS]) == 0
    assert main(["localize", "--world", str(world), "--input", "synth-small", *SETTINGS]) == 0
    assert main(["run", "synth-small", *SETTINGS]) == 0
    capsys.readouterr()
    cli = LocalizationReport.load(world)
    dag = LocalizationReport.load(isolated / "artifacts" / "localization_report" / "synth-small")
    assert cli.status == dag.status and cli.status.count("tracked") == len(cli.status) - 1
    np.testing.assert_array_equal(cli.T_world_cam, dag.T_world_cam)
    # the maps were made from the same keyframes at the same tracked poses
    kf_cli = np.asarray(read_metadata(world)["keyframes"]["T_world_cam"])
    kf_dag = np.asarray(read_metadata(isolated / "artifacts" / "world_bundle" / "synth-small")["keyframes"]["T_world_cam"])
    np.testing.assert_array_equal(kf_cli, kf_dag)

"""The graph on a real local Dask cluster (a scheduler and two worker processes on 127.0.0.1,
started and stopped here) gives the same artifacts, byte for byte, as an in-process run."""

import json
import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

pytest.importorskip("dagster_dask")
pytest.importorskip("distributed")

from assets.cli import main  # noqa: E402
from assets.definitions import build_definitions, executor_name  # noqa: E402
from atlas_pipeline.errors import ConfigError  # noqa: E402

ASSETS = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
          "transitions", "demo_videos", "render_evaluation", "world_bundle"]
RUN_SPECIFIC = ("run_id", "created_at", "created_utc")  # provenance of a run, not content


@contextmanager
def _local_cluster():
    """A LocalCluster's scheduler address (the workers inherit this process's environment and
    signal handlers when it starts)."""
    from distributed import LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           scheduler_port=0, dashboard_address=None)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def _tails_of(folder: Path) -> list[int]:
    """Pids of running ``tail`` processes reading a file under ``folder`` (Dagster's compute-log
    mirrors; Linux ``/proc``; empty elsewhere)."""
    out = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argv and Path(argv[0].decode(errors="replace")).name == "tail" and \
                any(str(folder).encode() in a for a in argv[1:]):
            out.append(int(proc.name))
    return out


def _without_run_ids(value):
    if isinstance(value, dict):
        return {k: _without_run_ids(v) for k, v in value.items() if k not in RUN_SPECIFIC}
    if isinstance(value, list):
        return [_without_run_ids(v) for v in value]
    return value


def _artifact_digest(root: Path, partition: str) -> dict:
    """{asset: {file: sha256}} from each _artifact.json; the bundle's metadata.json compared
    without its run ids and times (its lineage names the run)."""
    out = {}
    for a in ASSETS:
        rec = json.loads((root / a / partition / "_artifact.json").read_text())
        out[a] = {n: f["sha256"] for n, f in rec["files"].items()}
        if a == "world_bundle":
            meta = json.loads((root / a / partition / "metadata.json").read_text())
            out[a]["metadata.json"] = _without_run_ids(meta)
    return out


def test_executor_is_chosen_by_config_and_checked(isolated, monkeypatch):
    assert executor_name() == "in_process"
    monkeypatch.setenv("ATLAS_EXECUTOR", "dask")
    defs = build_definitions(isolated / "artifacts", dask_scheduler="tcp://127.0.0.1:1")
    assert defs.resolve_job_def("atlas_gs_all").executor_def.name == "dask"
    assert defs.resources["artifact_io"].step_locks is False  # the launcher holds the partition lock
    monkeypatch.setenv("ATLAS_EXECUTOR", "spark")
    with pytest.raises(ConfigError, match="ATLAS_EXECUTOR"):
        build_definitions(isolated / "artifacts")


@pytest.mark.slow
def test_dask_cluster_gives_byte_identical_artifacts(isolated, monkeypatch, capsys):
    """Run as from a non-interactive shell's background job (SIGINT ignored), the cluster started
    after an in-process run, as in a long-lived process: Dagster's run left SIGTERM ignored, the
    workers inherited it, and each Dask step waited 60 s for its compute-log tails (which stayed
    running). The Dask run now ends within 45 s of the serial run and leaves no tail behind."""
    from dagster import DagsterEventType, DagsterInstance
    from distributed import Client

    from assets.dask_executor import _ignores_sigterm

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # both put back by conftest's _signal_handlers_restored
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    t0 = time.perf_counter()
    assert main(["run", "synth-small", "--json"]) == 0
    serial_s = time.perf_counter() - t0
    local = json.loads(capsys.readouterr().out)
    assert local["success"]
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # as before the run (atlas-gs puts it back)

    # Another artifacts folder and instance; the same dataset folder and registry.
    monkeypatch.setenv("ATLAS_ARTIFACTS_DIR", str(isolated / "artifacts-dask"))
    monkeypatch.setenv("DAGSTER_HOME", str(isolated / "dagster_home_dask"))
    (isolated / "dagster_home_dask").mkdir()
    with _local_cluster() as address:
        with Client(address) as client:
            assert not any(client.run(_ignores_sigterm).values())
        argv = ["run", "synth-small", "--json", "--executor", "dask", "--dask-scheduler", address]
        t0 = time.perf_counter()
        assert main(argv) == 0
        dask_s = time.perf_counter() - t0
        on_dask = json.loads(capsys.readouterr().out)
        assert on_dask["success"] and sorted(on_dask["recomputed"]) == sorted(ASSETS), on_dask
        # A minute per step made it 10 minutes; the workers' imports and first calls cost seconds.
        assert dask_s < serial_s + 45, f"Dask run {dask_s:.1f} s, serial {serial_s:.1f} s"

        # The steps ran in the workers, not here.
        logs = DagsterInstance.get().all_logs(on_dask["run_id"], of_type=DagsterEventType.STEP_START)
        pids = {e.dagster_event.pid for e in logs}
        assert pids and os.getpid() not in pids

        assert _artifact_digest(isolated / "artifacts-dask", "synth-small") == \
            _artifact_digest(isolated / "artifacts", "synth-small")

        # A second run on the cluster reuses every asset.
        assert main(argv) == 0
        again = json.loads(capsys.readouterr().out)
        assert again["success"] and again["recomputed"] == [] and sorted(again["reused"]) == sorted(ASSETS)
    assert _tails_of(isolated) == []  # every step's compute-log tail has exited


def test_dask_sizes_step_results_without_walking_dagster_records():
    """A step's result (a list of events) holds ``@record`` values that forbid iteration; dask's
    own tuple walk fails on them (a warning per step on every worker), the registered size does not."""
    from dagster import AssetMaterialization, DagsterEvent, MetadataValue
    from dagster._core.events import StepMaterializationData
    from dask.sizeof import sizeof

    import assets.dask_executor  # noqa: F401 - registers the size of an event

    event = DagsterEvent(event_type_value="ASSET_MATERIALIZATION", job_name="atlas_gs_all", step_key="keyframes",
                         event_specific_data=StepMaterializationData(AssetMaterialization(
                             asset_key="keyframes", metadata={"n": 3, "path": MetadataValue.path("/tmp/x")})))
    with pytest.raises(Exception, match="Iteration is not allowed"):
        sizeof.dispatch(tuple)(event)  # dask's default for a tuple subclass
    assert 100 < sizeof(event) < 10_000
    assert sizeof([event] * 4) >= 4 * sizeof(event)

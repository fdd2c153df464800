"""``atlas-gs run --all`` runs partitions in parallel (a bounded pool of worker processes, each an
ordinary Dagster run in the shared sqlite instance)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from assets.cli import main
from tests.conftest import SMALL_SYNTH

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def project_with_datasets(root: Path, names: list[str]) -> Path:
    """A project folder whose registry holds only ``names`` (small synthetic sequences, one seed
    each), so that ``--all`` means exactly them; the profiles are the checkout's."""
    (root / "configs").mkdir(parents=True)
    for p in CONFIGS.glob("*.yaml"):
        if not p.name.startswith("datasets"):
            shutil.copy(p, root / "configs" / p.name)
    entries = {n: {"kind": "synthetic", **SMALL_SYNTH, "seed": i} for i, n in enumerate(names)}
    (root / "configs" / "datasets.yaml").write_text(yaml.safe_dump({"datasets": entries}))
    return root


def test_concurrency_below_one_is_refused(isolated):
    assert main(["run", "--all", "--concurrency", "0"]) == 2


@pytest.mark.slow
def test_run_all_runs_partitions_in_parallel_processes(isolated, monkeypatch, capsys):
    from dagster import DagsterInstance

    names = ["par-a", "par-b"]
    monkeypatch.setenv("ATLAS_PROJECT_ROOT", str(project_with_datasets(isolated / "project", names)))
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(isolated / "none.yaml"))
    from atlas_pipeline.sensors.registry import ensure_dataset_files, load_registry

    for entry in load_registry().values():
        ensure_dataset_files(entry)
    # The command as a user runs it: a fresh process, datasets on disk, so its workers are forked.
    cli = subprocess.run([sys.executable, "-m", "assets.cli", "run", "--all", "--concurrency", "2", "--json"],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    assert cli.returncode == 0, cli.stderr[-3000:]
    docs = json.loads(cli.stdout)  # one document: a list of the partitions' summaries
    assert [d["partition"] for d in docs] == names  # in partition order
    assert all(d["success"] and len(d["recomputed"]) == 9 for d in docs), docs
    # One line per stage and partition, named (they interleave; a forked worker once also wrote
    # through its copy of the parent's handler, unnamed).
    lines = [ln for ln in cli.stderr.splitlines() if "world_bundle " in ln]
    assert sorted(ln.split()[0] for ln in lines) == [f"{n}:" for n in names], cli.stderr

    instance = DagsterInstance.get()
    runs = [instance.get_run_by_id(d["run_id"]) for d in docs]
    pids = {r.tags["atlas/pid"] for r in runs}
    assert len(pids) == 2  # each partition in its own worker process
    stats = [instance.get_run_stats(r.run_id) for r in runs]
    a, b = stats
    assert a.start_time < b.end_time and b.start_time < a.end_time  # they overlapped in time

    # Both partitions are current now: a second --all reuses everything.
    assert main(["run", "--all", "--concurrency", "2", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert all(d["success"] and d["recomputed"] == [] for d in again), again


def test_the_instance_config_example_queues_runs_two_at_a_time_one_per_partition(tmp_path, monkeypatch):
    from dagster import DagsterInstance

    shutil.copy(CONFIGS / "instance" / "dagster.yaml", tmp_path / "dagster.yaml")
    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path))
    with DagsterInstance.get() as instance:
        queue = instance.run_coordinator.get_run_queue_config()
    assert type(instance.run_coordinator).__name__ == "QueuedRunCoordinator"
    assert queue.max_concurrent_runs == 2
    assert queue.tag_concurrency_limits == [
        {"key": "dagster/partition", "value": {"applyLimitPerUniqueValue": True}, "limit": 1}]


@pytest.mark.slow
def test_workers_are_forked_only_before_numbas_parallel_runtime_started():
    """GNU OpenMP aborts a child forked after the parent used it, so ``--all`` forks its workers
    (to share the parent's imports) only while no parallel kernel has run here; then it spawns."""
    import textwrap

    code = textwrap.dedent("""
        import numpy as np
        from numba import njit, prange
        from assets.launch import worker_start_method

        @njit(parallel=True)
        def total(a):
            s = 0.0
            for i in prange(a.size):
                s += a[i]
            return s

        before = worker_start_method()
        total(np.ones(64))
        print(before, worker_start_method())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    expected = "fork spawn" if sys.platform.startswith("linux") else "spawn spawn"
    assert out.stdout.split() == expected.split()


def test_the_largest_recordings_start_first(tmp_path):
    """``run --all`` submits partitions largest first (ties in registry order), sized by the bytes
    of their files: links are not followed, an absent folder is 0."""
    from assets.launch import longest_first
    from atlas_pipeline.sensors.registry import DatasetEntry, recording_bytes

    assert longest_first([10, 30, 20, 30]) == [1, 3, 2, 0]
    small, big = tmp_path / "small", tmp_path / "big"
    (small / "rgb").mkdir(parents=True)
    (big / "depth").mkdir(parents=True)
    (small / "rgb" / "1.png").write_bytes(b"x" * 100)
    (big / "depth" / "1.png").write_bytes(b"x" * 300)
    (big / "rgb.txt").write_bytes(b"x" * 7)
    (small / "elsewhere").symlink_to(big, target_is_directory=True)  # not counted twice
    sizes = [recording_bytes(DatasetEntry(n, "tum", p)) for n, p in
             [("small", small), ("big", big), ("gone", tmp_path / "gone")]]
    assert sizes == [100, 307, 0]
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"x" * 42)
    assert recording_bytes(DatasetEntry("bag", "bag", bag)) == 42

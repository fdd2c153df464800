"""Run bookkeeping the Dagster instance cannot do alone: which process runs a run, and failing runs
whose process died.

A run killed with SIGKILL (or by a machine reboot) never reports its end, so the instance shows it
``STARTED`` forever. Every Atlas-GS asset step tags its run with the process that executes it
(:func:`tag_run_process`); :func:`reap_dead_runs` marks runs whose tagged process is gone as failed.
It runs when ``atlas-gs`` opens the instance and on every tick of the registry sensor under
``dagster dev``.

With an executor whose steps run in long-lived worker processes (Dask), a worker is not the run's
process: the process launching the run tags it (:func:`launcher_tags`) and workers tag nothing.

A run in a process's main thread changes that process's signal handlers for good (see
:func:`signal_dispositions_kept`); ``atlas-gs`` puts them back after every command.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from dagster import DagsterInstance, DagsterRunStatus, RunsFilter

from atlas_pipeline.io_utils import process_alive

logger = logging.getLogger("atlas_gs.runs")

PID_TAG = "atlas/pid"
HOST_TAG = "atlas/host"
PID_START_TAG = "atlas/pid_start_ticks"  # guards against a recycled pid
_IN_FLIGHT = [DagsterRunStatus.STARTED, DagsterRunStatus.STARTING, DagsterRunStatus.CANCELING]
_tagged: set[str] = set()


def _start_ticks(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux ``/proc``), None elsewhere."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().split(b")")[-1].split()[19].decode()
    except (OSError, IndexError):
        return None


def in_dask_worker() -> bool:
    """Whether this code runs as a task of a dask.distributed worker (imports nothing new)."""
    distributed = sys.modules.get("distributed")
    if distributed is None:
        return False
    try:
        distributed.get_worker()
    except ValueError:
        return False
    return True


def launcher_tags(pid: int | None = None) -> dict[str, str]:
    """Tags naming this process (or ``pid``) as the one a run depends on (set at launch by
    ``atlas-gs run`` when the steps run elsewhere): the run is marked failed if it dies first."""
    pid = os.getpid() if pid is None else pid
    tags = {PID_TAG: str(pid), HOST_TAG: socket.gethostname()}
    ticks = _start_ticks(pid)
    if ticks:
        tags[PID_START_TAG] = ticks
    return tags


def tag_run_process(instance: DagsterInstance, run_id: str) -> None:
    """Record on the run which process executes it (once per run and process). A Dask worker
    tags nothing: it outlives the run and is not the run's process (see :func:`launcher_tags`)."""
    if run_id in _tagged:
        return
    if in_dask_worker():
        _tagged.add(run_id)
        return
    try:
        run = instance.get_run_by_id(run_id)
    except Exception as exc:  # bookkeeping only
        logger.debug("cannot read run %s: %s", run_id, exc)
        run = None
    if run is not None and PID_TAG in run.tags:  # tagged at launch, or by an earlier step's process
        _tagged.add(run_id)
        return
    # A step in a child process (the multiprocess executor) depends on its parent, which outlives it.
    parent = multiprocessing.parent_process()
    tags = launcher_tags(parent.pid if parent is not None else None)
    try:
        instance.add_run_tags(run_id, tags)
        _tagged.add(run_id)
    except Exception as exc:  # an ephemeral or read-only instance: bookkeeping only, never fatal
        logger.debug("could not tag run %s with its process: %s", run_id, exc)


def _dead(tags: dict[str, str]) -> str | None:
    """Why the process that ran a run is gone (None: alive, or not ours to judge)."""
    if tags.get(HOST_TAG) != socket.gethostname() or not tags.get(PID_TAG, "").isdigit():
        return None
    pid = int(tags[PID_TAG])
    if not process_alive(pid):
        return f"its process (pid {pid}) is gone"
    recorded = tags.get(PID_START_TAG)
    if recorded and _start_ticks(pid) not in (None, recorded):
        return f"its process (pid {pid}) is gone (the pid now belongs to another process)"
    return None


def reap_dead_runs(instance: DagsterInstance) -> list[str]:
    """Mark in-flight runs whose process died as failed; returns their run ids."""
    reaped = []
    try:
        runs = instance.get_runs(filters=RunsFilter(statuses=_IN_FLIGHT))
    except Exception as exc:
        logger.debug("cannot list runs: %s", exc)
        return reaped
    for run in runs:
        why = _dead(dict(run.tags))
        if why is None:
            continue
        instance.report_run_failed(run, message=f"Marked failed by atlas-gs: {why} while the run was in progress.")
        logger.warning("run %s (%s) was left in progress by a process that died; marked it failed",
                       run.run_id, run.job_name)
        reaped.append(run.run_id)
    return reaped


_KEPT_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def signal_dispositions_kept() -> Iterator[None]:
    """Put SIGINT's and SIGTERM's handlers back as they were once the block ends.

    Every Dagster run executed in a process's main thread (``execute_in_process``, ``execute_job``)
    sets SIGTERM to SIGINT's handler when it ends (``dagster._utils.interrupts``: SIGTERM is handled
    like Ctrl-C, for Kubernetes). In a process whose SIGINT is ignored (started in the background
    by a non-interactive shell, by CI or by a supervisor) that leaves SIGTERM *ignored*, and every
    process started afterwards inherits that (an ignored signal stays ignored across ``exec``):
    the workers of a Dask cluster started later, and in them Dagster's ``tail -F`` mirrors of each
    step's compute log, which the step's teardown stops with SIGTERM and then waits 30 s for, once
    for stdout and once for stderr: a minute after every step, and the tails left running for good.
    Outside the main thread (where Dagster changes nothing) this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.getsignal(s) for s in _KEPT_SIGNALS}
    try:
        yield
    finally:
        for s, handler in saved.items():
            if handler is not None and signal.getsignal(s) is not handler:  # None: set outside Python
                signal.signal(s, handler)

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

import contextlib
import logging
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from dagster import DagsterInstance, DagsterRunStatus, RunsFilter

from atlas_pipeline.errors import ConfigError, WriteError
from atlas_pipeline.io_utils import check_writable, discard_own_staging, process_alive

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


# ---- Ctrl-C and SIGTERM: one line and status 130 or 143 ------------------------------------------

INTERRUPTED_EXIT = 130  # 128 + SIGINT: what a shell reports for a command Ctrl-C ended
INTERRUPTED_MESSAGE = "interrupted; nothing half-written is left"
TERMINATED_EXIT = 143  # 128 + SIGTERM: what a shell reports for a command `kill` (or a supervisor) ended
TERMINATED_MESSAGE = "terminated (SIGTERM); nothing half-written is left"
# How a signal ends a command: (exit status, its one line).
_ENDINGS = {signal.SIGINT: (INTERRUPTED_EXIT, INTERRUPTED_MESSAGE),
            signal.SIGTERM: (TERMINATED_EXIT, TERMINATED_MESSAGE)}
# How long the children a SIGTERM is passed on to (pool workers) get to end themselves, removing
# their own staging, before they are killed.
CHILD_GRACE_S = 10.0
_CHILD_POLL_S = 0.05


def end_interrupted(say: bool = True, signum: int = signal.SIGINT) -> None:
    """The end of a command that Ctrl-C (``signum`` SIGINT) or SIGTERM stopped: this process's
    staging removed, one line (unless ``say`` is False: a pool worker, whose parent says it), status
    130 or 143, at once.

    Raising KeyboardInterrupt instead (Python's default, and Dagster's interrupt inside a step)
    lands in whatever runs: inside numba's kernels and compiler callbacks it is dropped (the command
    goes on), turns into a SystemError, or crashes the process. Every output is written under a
    temporary name and renamed whole, and a folder swap under way is repaired by the next open, so
    ending here leaves no half-written file and starts no later step; a Dagster run left in
    progress is marked failed when atlas-gs next opens the instance (:func:`reap_dead_runs`).
    Children in process groups of their own, which a Ctrl-C does not reach, are stopped first
    (:func:`stop_detached_children`); a SIGTERM, sent to this process alone, is passed on to the
    children of its own group (pool workers, :func:`stop_group_children`)."""
    if signum != signal.SIGINT:
        stop_group_children(signum)
    stop_detached_children()
    discard_own_staging()
    code, message = _ENDINGS.get(signum, _ENDINGS[signal.SIGINT])
    if say:
        with contextlib.suppress(OSError):
            os.write(2, (message + "\n").encode())
    os._exit(code)


def _children(pid: int) -> dict[int, int]:
    """The children of process ``pid``, each with its process group, from ``/proc`` (empty where
    there is none)."""
    try:
        entries = os.listdir("/proc")
    except OSError:
        return {}
    found = {}
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            stat = Path("/proc", entry, "stat").read_text()
        except OSError:  # gone meanwhile, or not ours to read
            continue
        fields = stat.rsplit(")", 1)[-1].split()  # after "pid (comm)": state ppid pgrp ...
        if len(fields) >= 3 and int(fields[1]) == pid:
            found[int(entry)] = int(fields[2])
    return found


def detached_children(pid: int | None = None) -> list[int]:
    """Process ids of the children of ``pid`` (this process) that run in a process group other than
    its own, from ``/proc`` (empty where there is none)."""
    pid = os.getpid() if pid is None else pid
    group = os.getpgid(pid)
    return [child for child, pgrp in _children(pid).items() if pgrp != group]


def stop_detached_children() -> None:
    """SIGKILL this process's children in process groups of their own (ffmpeg: imageio-ffmpeg starts
    it so) but Dagster's log mirrors (:data:`_LOG_MIRRORS`, which end with the process). A terminal's
    Ctrl-C does not reach them, and they would outlive the command: ffmpeg finishing a video into
    staging just removed, printing its errors (or leaving the file) after the command's last line."""
    for child in detached_children():
        if child in _LOG_MIRRORS:
            continue
        with contextlib.suppress(OSError):
            os.kill(child, signal.SIGKILL)
            os.waitpid(child, 0)


def _signals_ignored(pid: int) -> int:
    """The mask of signals process ``pid`` ignores (bit ``n - 1`` for signal ``n``; 0 when unknown)."""
    try:
        for line in Path("/proc", str(pid), "status").read_text().splitlines():
            if line.startswith("SigIgn:"):
                return int(line.split()[1], 16)
    except (OSError, ValueError, IndexError):
        pass
    return 0


def stop_group_children(signum: int) -> None:
    """Pass ``signum`` on to this process's children in its own process group (pool workers, which
    end themselves as this process does) but those that ignore it (multiprocessing's resource
    tracker, which ends with this process); kill those still running after :data:`CHILD_GRACE_S`."""
    import time

    group = os.getpgid(0)
    mask = 1 << (signum - 1)
    children = []
    for child, pgrp in _children(os.getpid()).items():
        if pgrp != group or _signals_ignored(child) & mask:
            continue
        try:
            os.kill(child, signum)
        except OSError:  # gone meanwhile
            continue
        children.append(child)
    deadline = time.monotonic() + CHILD_GRACE_S
    while (children := [c for c in children if process_alive(c)]) and time.monotonic() < deadline:
        time.sleep(_CHILD_POLL_S)
    for child in children:
        with contextlib.suppress(OSError):
            os.kill(child, signal.SIGKILL)


@contextmanager
def interrupts_end_the_command(say: bool = True) -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM end the command (:func:`end_interrupted`), also during a
    Dagster run executed in this process (whose own interrupt handling is kept off meanwhile). A
    signal ignored when the block starts stays ignored (SIGINT of a background job). Outside the
    main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handled = [s for s in _ENDINGS if signal.getsignal(s) is not signal.SIG_IGN]
    try:
        from dagster._utils import interrupts as dagster_interrupts
    except ImportError:  # another Dagster layout: its runs handle Ctrl-C themselves
        dagster_interrupts = None
    replace = getattr(dagster_interrupts, "_replace_interrupt_signal", None)
    owner = os.getpid()

    def ended(signum: int, _frame) -> None:
        # A forked pool worker inherits this handler until it sets its own: its parent says the line.
        end_interrupted(say and os.getpid() == owner, signum)

    previous = {s: signal.signal(s, ended) for s in handled}
    if replace is not None:
        dagster_interrupts._replace_interrupt_signal = lambda _handler: None
    try:
        yield
    finally:
        if replace is not None:
            dagster_interrupts._replace_interrupt_signal = replace
        for s, handler in previous.items():
            if handler is not None:  # None: set outside Python, cannot be put back from here
                signal.signal(s, handler)


class _DetachedSubprocess:
    """``subprocess`` as Dagster's compute-log module sees it: children start in their own process
    group, so a terminal's Ctrl-C (SIGINT to the foreground group) reaches the run, which stops them,
    and not Dagster's ``tail -F`` and orphan watcher, whose KeyboardInterrupt tracebacks it printed."""

    def __getattr__(self, name: str):
        return getattr(subprocess, name)

    @staticmethod
    def Popen(*args, **kwargs):  # noqa: N802 - subprocess's name
        kwargs.setdefault("process_group", 0)
        process = subprocess.Popen(*args, **kwargs)
        _LOG_MIRRORS.add(process.pid)
        return process


# Dagster's compute-log mirrors started by this process: during a step the process's stdout and
# stderr are files these mirror to the terminal, so they carry the command's last line and are not
# stopped with the other detached children.
_LOG_MIRRORS: set[int] = set()


@contextmanager
def compute_log_mirrors_detached() -> Iterator[None]:
    """Dagster's compute-log mirrors (``tail -F`` and ``watch_orphans.py``) of the runs in the block
    start in their own process groups (:class:`_DetachedSubprocess`)."""
    try:
        from dagster._core.execution import compute_logs
    except ImportError:  # another Dagster layout: its children get Ctrl-C as before
        yield
        return
    if getattr(compute_logs, "subprocess", None) is not subprocess:
        yield
        return
    compute_logs.subprocess = _DetachedSubprocess()
    try:
        yield
    finally:
        compute_logs.subprocess = subprocess


# ---- DAGSTER_HOME ---------------------------------------------------------------------------------

DAGSTER_HOME_ENV = "DAGSTER_HOME"


def prepare_dagster_home(default: Path) -> Path:
    """``$DAGSTER_HOME`` (else ``default``), checked before Dagster opens it, and set in the
    environment: an absolute path (Dagster's rule), a folder (made when missing), writable with
    room for the instance's database. Each fault is one :class:`ConfigError` or :class:`WriteError`
    naming the path, and folders made here are removed again when a check fails."""
    raw = os.environ.get(DAGSTER_HOME_ENV)
    home = Path(raw).expanduser() if raw else Path(default)
    name = f"{DAGSTER_HOME_ENV}={raw}" if raw else f"{DAGSTER_HOME_ENV} (default {home})"
    if not home.is_absolute():
        raise ConfigError(f"{name}: must be an absolute path (Dagster's rule), e.g. "
                          f"{DAGSTER_HOME_ENV}={Path.cwd() / home}; nothing was created")
    if os.path.lexists(home) and not home.is_dir():
        raise ConfigError(f"{name}: {home} is a file, not a folder; point {DAGSTER_HOME_ENV} at a folder "
                          "(it is made when missing)")
    made = [p for p in (home, *home.parents) if not os.path.lexists(p)]
    try:
        check_writable(home)  # makes the folder, writes a probe, asks for free space
    except WriteError as exc:
        for p in made:  # deepest first: only what this made, only while empty
            with contextlib.suppress(OSError):
                p.rmdir()
        raise ConfigError(f"{name}: {exc}") from None
    os.environ[DAGSTER_HOME_ENV] = str(home)
    return home


def instance_storage_error(exc: BaseException) -> str | None:
    """One line for an error of the instance's database (SQLite under ``$DAGSTER_HOME``: a disk
    that filled during the command, a read-only or damaged file), None for any other error."""
    try:
        from sqlalchemy.exc import DatabaseError, OperationalError
    except ImportError:
        return None
    if not isinstance(exc, (OperationalError, DatabaseError)):
        return None
    reason = str(getattr(exc, "orig", None) or exc).splitlines()[0]
    fix = "free space there" if "full" in reason.lower() else \
        f"move the folder aside (a new {DAGSTER_HOME_ENV} starts an empty instance)"
    return (f"{DAGSTER_HOME_ENV}={os.environ.get(DAGSTER_HOME_ENV, '?')}: the Dagster instance's database "
            f"failed: {reason} ({fix}, or point {DAGSTER_HOME_ENV} elsewhere)")

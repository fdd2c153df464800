"""Dagster runs of dataset partitions as the command line starts them.

A launch opens the instance and the definitions for a profile and ``--set`` overrides, picks the
partitions (registered datasets on disk, a download preset fetched first), then runs them: one after
another in this process, or several at a time in a bounded pool of worker processes whose kernels
share the cores. Each run is an ordinary Dagster run recorded in ``$DAGSTER_HOME``, so the web UI
shows it; its summary (what was computed or reused, the outputs on disk, errors) is a plain dict
for the caller to print.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from atlas_pipeline.config import parse_set_overrides, project_root
from atlas_pipeline.errors import DatasetError
from atlas_pipeline.sensors.registry import (
    DatasetEntry,
    ensure_dataset_files,
    files_missing,
    load_registry,
    needs_download,
    recording_bytes,
    registered_entry,
    validate_dataset_name,
)

logger = logging.getLogger("atlas_gs.launch")

ASSET_ORDER = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
               "transitions", "demo_videos", "render_evaluation", "world_bundle"]
JOB_NAME = "atlas_gs_all"
# The Python logger a launched run's Dagster records go to (instead of Dagster's coloured console
# logger); the command line formats and filters it. The run's event log is written either way.
RUN_LOGGER = "atlas_gs.run"
MAX_DEFAULT_CONCURRENCY = 4  # default partitions at a time: the cores, at most this (each run holds a sequence)
NUMBA_THREADS_ENV = "NUMBA_NUM_THREADS"
DAGSTER_HOME_FOLDER = ".dagster_home"  # under the project root, unless $DAGSTER_HOME names another


def use_project_dagster_home() -> Path:
    """``$DAGSTER_HOME``, default ``<project>/.dagster_home``, checked and made ready for the instance."""
    from assets.runs import prepare_dagster_home

    return prepare_dagster_home(project_root() / DAGSTER_HOME_FOLDER)


def dagster_dev_command(host: str, port: int) -> list[str]:
    """``dagster dev`` for this project, to run from the project root (where this changes to): a
    checkout's workspace.yaml, else the definitions module of an installed copy."""
    os.chdir(project_root())
    where = ["-w", "workspace.yaml"] if Path("workspace.yaml").is_file() else ["-m", "assets.definitions"]
    return ["dagster", "dev", *where, "-h", host, "-p", str(port)]


@dataclass
class Launch:
    """What the runs of one command share: the definitions for its profile, the instance, the
    validated ``atlas`` config and ``--set`` overrides, and the partitions to run."""

    defs: Any
    instance: Any
    atlas: Any
    overrides: dict[str, Any]
    partitions: list[str]
    profile: str | None  # as given (None: $ATLAS_PROFILE, else default); step processes resolve it again

    @functools.cached_property
    def job(self) -> Any:
        """The job with its records sent to :data:`RUN_LOGGER`."""
        return self.defs.resolve_job_def(JOB_NAME).with_logger_defs(run_logger_defs())


def prepare_launch(profile: str | None, set_items: list[str] | None, dataset: str | None, every: bool,
                   fetch: bool) -> Launch:
    """DAGSTER_HOME, the definitions for ``profile``, the ``--set`` items validated (a bad key fails
    here, naming the key), the instance, and the partitions: ``dataset``, or with ``every`` all the
    registered ones, that are on disk. ``fetch``: download a preset first (with ``every``, one that
    fails or whose files are gone is left out with a warning instead of ending the command)."""
    use_project_dagster_home()
    from dagster import DagsterInstance

    from assets.definitions import build_definitions, loaded_partitions
    from assets.resources import atlas_config
    from assets.runs import reap_dead_runs

    overrides = parse_set_overrides(set_items, "--set")
    atlas = atlas_config(profile, overrides)
    registry = load_registry()
    partitions = list(registry) if every else [validate_dataset_name(dataset)]
    for p in partitions:
        registered_entry(p, registry)
    if fetch:
        partitions = [p for p in partitions if fetch_partition(registry[p], skip_on_error=every)]
    defs = build_definitions(profile=profile)
    loaded = set(loaded_partitions(defs))
    for p in [p for p in partitions if p not in loaded]:  # not on disk: a preset not fetched, files gone
        missing = files_missing(registry[p])
        if not every:
            raise missing
        logger.warning("%s left out: %s", p, missing)
    partitions = [p for p in partitions if p in loaded]
    instance = DagsterInstance.get()
    reap_dead_runs(instance)  # runs left STARTED by a killed process are marked failed
    return Launch(defs, instance, atlas, overrides, partitions, profile)


def fetch_partition(entry: DatasetEntry, skip_on_error: bool = False) -> bool:
    """Download a preset whose frames are not on disk (with a progress bar), so that it can become a
    partition before its run; True when the entry's data is there now. ``skip_on_error``: a failed
    download is a warning and the dataset is left out, not the end of the command."""
    if not needs_download(entry):
        return True
    try:
        ensure_dataset_files(entry)
    except DatasetError as exc:
        if not skip_on_error:
            raise
        logger.warning("%s left out: %s", entry.name, exc)
        return False
    logger.info("%s: downloaded into %s", entry.name, entry.path)
    return True


def run_logger_defs() -> dict[str, Any]:
    """The job's loggers for a launched run: Dagster's records go to :data:`RUN_LOGGER`."""
    from dagster import logger as dagster_logger

    @dagster_logger(description="atlas-gs command line: Dagster's records in the CLI's format")
    def atlas_cli(_init_context):
        return logging.getLogger(RUN_LOGGER)

    return {"console": atlas_cli}


def run_request(profile: str, overrides: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """Run config and tags of a run with ``--set`` ``overrides``: the overrides as the ``atlas``
    resource's config (the other fields keep the profile's values) and as tags ``atlas/set/KEY``."""
    config: dict[str, Any] = {}
    for dotted, value in overrides.items():
        *sections, key = dotted.split(".")
        node = config
        for section in sections:  # mapping.fit.epochs: nested like the resource's config
            node = node.setdefault(section, {})
        node[key] = list(value) if isinstance(value, tuple) else value
    tags = {"atlas/profile": profile, **{f"atlas/set/{k}": json.dumps(v) for k, v in overrides.items()}}
    return ({"resources": {"atlas": {"config": config}}} if config else {}), tags


def first_visits_first(partitions: list[str], registry) -> list[str]:
    """``partitions`` in their order, except that a second visit (registry ``extends``) runs after
    the first visit it extends when both are in the list."""
    chosen = set(partitions)
    return sorted(partitions, key=lambda p: registry[p].extends in chosen)


def stale_partitions(launch: Launch) -> dict[str, dict[str, list[str]]]:
    """Per partition, its stale or missing assets and why; runs nothing."""
    from assets.staleness import stale_assets

    return {p: stale_assets(launch.defs, launch.instance, p, launch.atlas) for p in launch.partitions}


# How Dagster starts the message of an error it caught: its class's qualified name. For the
# library's own errors, whose message says everything, the name is left out.
LIBRARY_ERROR_PREFIX = re.compile(r"^atlas_pipeline\.errors\.\w+: ")


def step_error(ev: Any) -> str:
    """The message of a failed step's error (the cause's, where the step wrapped one)."""
    err = getattr(ev.event_specific_data, "error", None)
    if err is None:
        return "failed"
    return LIBRARY_ERROR_PREFIX.sub("", (err.cause.message if err.cause else err.message).strip())


def ran(result) -> dict[str, list[str]]:
    """``recomputed`` and ``reused`` pipeline assets of a run (settings/* and observations left out)."""
    out: dict[str, list[str]] = {"recomputed": [], "reused": []}
    for ev in result.all_events:
        if ev.event_type_value == "ASSET_MATERIALIZATION" and len(ev.asset_key.path) == 1:
            md = ev.event_specific_data.materialization.metadata
            out["reused" if md.get("reused") is not None and md["reused"].value else "recomputed"].append(
                ev.asset_key.path[-1])
    return {k: sorted(v) for k, v in out.items()}


def _failures(result) -> dict[str, list[str]]:
    """A failed run's ``errors`` (one per failed step) and ``failed_checks``, where it has them."""
    found: dict[str, list[str]] = {}
    for ev in result.all_events:
        if ev.is_failure and ev.step_key:
            found.setdefault("errors", []).append(f"{ev.step_key}: {step_error(ev)}")
    for ev in result.all_events:
        if ev.event_type_value == "ASSET_CHECK_EVALUATION" and not ev.event_specific_data.passed:
            d = ev.event_specific_data
            found.setdefault("failed_checks", []).append(
                f"{d.asset_key.to_user_string()}:{d.check_name}: {d.description or ''}".strip())
    return found


def run_partition(launch: Launch, partition: str, stale_only: bool = False, executor: str | None = None,
                  dask_scheduler: str | None = None) -> dict[str, Any]:
    """Materialize the partition's assets (``stale_only``: only the stale or missing ones; none when
    all are current) and return its summary: success, run id, computed and reused assets, the
    outputs on disk, the localization's figures, errors and failed checks. A summary with ``ran``
    False says that nothing was stale."""
    from assets.artifacts import localization_summary, partition_outputs
    from assets.runs import compute_log_mirrors_detached
    from assets.staleness import stale_assets, stale_selection

    selection = None
    if stale_only:
        stale = stale_assets(launch.defs, launch.instance, partition, launch.atlas)
        for a, reasons in stale.items():
            logger.info("%s [%s] stale: %s", a, partition, "; ".join(reasons))
        if not stale:
            current = {"partition": partition, "stale": [], "ran": False}
            if "world_bundle" in (outputs := partition_outputs(partition)):
                current["world_bundle"] = outputs["world_bundle"]
            return current
        selection = stale_selection(stale)
    from atlas_pipeline.memory_estimate import check_entry_memory

    check_entry_memory(launch.atlas.load(), load_registry()[partition])  # before any asset of the run
    try:
        with compute_log_mirrors_detached():  # Ctrl-C reaches the run, which stops them, not them
            result = execute_partition(launch, partition, selection, executor, dask_scheduler)
    finally:
        launch.defs.resources["artifact_io"].unlock_partition(partition)
    summary = {"partition": partition, "success": result.success, "run_id": result.run_id, **ran(result),
               **partition_outputs(partition)}
    if stale_only:
        summary["stale"] = sorted(stale)
    if result.success and (loc := localization_summary(partition)) is not None:
        summary["localization"] = loc
    if not result.success:
        summary.update(_failures(result))
    return summary


def execute_partition(launch: Launch, partition: str, selection, executor: str | None, dask_scheduler: str | None):
    """One partition's run on the chosen executor (``executor``, else ``$ATLAS_EXECUTOR``): in this
    process (the default), or with steps in other processes (multiprocess, Dask) through Dagster's
    ``execute_job`` on a job each step process rebuilds; then this process holds the partition lock
    for the whole run and is the process the run is tagged with."""
    from assets.definitions import executor_name
    from assets.resources import resolve_profile
    from assets.runs import launcher_tags

    run_config, tags = run_request(launch.atlas.profile, launch.overrides)
    run_config = {**run_config, "loggers": {"console": {}}}  # a logger runs only when the run config names it
    chosen = executor_name(executor)
    tags = {**tags, **launcher_tags()}
    if chosen == "in_process":
        return launch.job.execute_in_process(partition_key=partition, instance=launch.instance, raise_on_error=False,
                                             asset_selection=selection, run_config=run_config, tags=tags)
    from dagster import build_reconstructable_job, execute_job

    store = launch.defs.resources["artifact_io"]
    store.hold_partition(partition, f"atlas-gs run (pid {os.getpid()}, executor {chosen})")
    recon = build_reconstructable_job("assets.definitions", "atlas_gs_all_job", reconstructable_kwargs={
        "artifacts_dir": store.root, "profile": resolve_profile(launch.profile), "executor": chosen,
        "dask_scheduler": dask_scheduler})
    return execute_job(recon, launch.instance, run_config=run_config, tags={**tags, "dagster/partition": partition},
                       asset_selection=selection)


# ---- several partitions at a time: a bounded pool of worker processes sharing the cores -----------


def default_concurrency() -> int:
    return max(1, min(os.cpu_count() or 1, MAX_DEFAULT_CONCURRENCY))


def worker_start_method() -> str:
    """How the pool starts its workers: ``fork`` on Linux while this process has not started
    Numba's parallel runtime, so each worker starts with the parent's imports (Dagster and the
    command line: about 3 s of CPU a worker otherwise); else ``spawn``. GNU OpenMP, Numba's threading
    layer here, cannot be used in a child forked after the parent used it, and ``atlas-gs run
    --all`` only reaches the pool before any kernel has run unless it generated a dataset first.
    The threads the parent does hold (OpenBLAS's, Arrow's pool and jemalloc's) re-initialise after
    a fork through their own at-fork handlers."""
    import multiprocessing

    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return "spawn"
    numba_parallel = sys.modules.get("numba.np.ufunc.parallel")
    started = numba_parallel is not None and getattr(numba_parallel, "_is_initialized", True)
    return "spawn" if started else "fork"


class CoreShare:
    """A pool worker's share of the cores now: all of them divided among the runs still going
    (``unfinished``, a counter in shared memory that each worker lowers when a run ends), so the
    last runs get the cores the finished ones left instead of leaving them idle."""

    def __init__(self, unfinished, concurrency: int, cores: int):
        self.unfinished, self.concurrency, self.cores = unfinished, concurrency, cores

    def __call__(self) -> int:
        running = max(1, min(self.concurrency, self.unfinished.value))
        return max(1, self.cores // running)


_POOL_SHARE: CoreShare | None = None  # set in a pool worker whose kernels follow the share


def init_worker(share: CoreShare | None) -> None:
    """A pool worker's start: its kernels follow ``share`` (None: ``$NUMBA_NUM_THREADS`` as set)."""
    global _POOL_SHARE
    _POOL_SHARE = share
    if share is not None:
        from atlas_pipeline.cores import kernel_threads, use_core_share

        use_core_share(share)
        kernel_threads()  # before any kernel: the stages before the first rasterizer call too


def _pool_task(task: Callable[[str], Any], partition: str) -> Any:
    """``task(partition)`` in a pool worker, with this run's core share from its start; the run's
    end hands its cores to the runs still going."""
    try:
        if _POOL_SHARE is not None:
            from atlas_pipeline.cores import kernel_threads

            kernel_threads()
        return task(partition)
    finally:
        if _POOL_SHARE is not None:
            with _POOL_SHARE.unfinished.get_lock():
                _POOL_SHARE.unfinished.value -= 1


def longest_first(sizes: list[int]) -> list[int]:
    """Indices of ``sizes`` largest first, ties in their order: with more partitions than workers,
    a long recording started last would run on alone at the end (longest processing time first,
    the classic list-scheduling rule)."""
    return sorted(range(len(sizes)), key=lambda k: -sizes[k])


def run_in_pool(partitions: list[str], concurrency: int, task: Callable[[str], Any],
                executor: str | None = None) -> Iterator[Any]:
    """``task(partition)`` for every partition, up to ``concurrency`` at a time in worker processes
    of a bounded pool; yields the results in partition order, each as soon as it and the ones
    before it are done. ``task`` must be picklable (a module-level function or a partial of one).

    The largest recordings start first (:func:`longest_first`); a second visit starts once the
    run of the first visit it extends has ended. Each worker's kernels get its share of the cores,
    re-read as runs end (:class:`CoreShare`; unless ``$NUMBA_NUM_THREADS`` is set), so parallel
    runs do not oversubscribe them and the last ones use the cores the others left."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    registry = load_registry()
    order = longest_first([recording_bytes(registry[p]) for p in partitions])
    # The library's modules are not imported here first: the workers import what their stages
    # need at the same time, on all cores, where importing them here would run alone.
    from assets.definitions import executor_name

    context = multiprocessing.get_context(worker_start_method())
    cores = os.cpu_count() or 1
    user_set = bool(os.environ.get(NUMBA_THREADS_ENV))
    in_process = executor_name(executor) == "in_process"
    share = CoreShare(context.Value("i", len(partitions)), concurrency, cores) if in_process and not user_set else None
    # Steps run in other processes (--executor multiprocess) read a fixed share from the environment.
    fixed = not in_process and not user_set
    if fixed:
        os.environ[NUMBA_THREADS_ENV] = str(max(1, cores // concurrency))
    try:
        with ProcessPoolExecutor(max_workers=concurrency, mp_context=context, initializer=init_worker,
                                 initargs=(share,)) as pool:
            first_of = {k: partitions.index(registry[p].extends) for k, p in enumerate(partitions)
                        if registry[p].extends in partitions}
            futures = {k: pool.submit(_pool_task, task, partitions[k]) for k in order if k not in first_of}
            for k in (k for k in order if k in first_of):
                futures[first_of[k]].result()
                futures[k] = pool.submit(_pool_task, task, partitions[k])
            for k in range(len(partitions)):
                yield futures[k].result()
    finally:
        if fixed:
            os.environ.pop(NUMBA_THREADS_ENV, None)

"""The one Dagster ``Definitions`` of Atlas-GS (``dagster dev`` loads ``defs`` from here).

Partitions are the registered datasets, kept as Dagster *dynamic* partitions named ``datasets``:
registering a folder adds a partition without touching code. Three ways keep the instance's
partitions in step with the registry (``configs/datasets.yaml`` + the local registry file):

* ``atlas-gs dataset add`` / ``dataset fetch`` / ``run`` add them directly;
* the ``dataset_registry_sensor`` (running by default under ``dagster dev``) adds every registered
  dataset that is not a partition yet, so an entry written by hand or by the CLI shows in the UI;
* the ``register_dataset`` job lets the UI's launchpad register a TUM-layout folder;
* ``atlas-gs dataset sync`` adds them to a fresh ``$DAGSTER_HOME`` before ``dagster asset materialize``.

Only datasets a run can build offline are partitions: synthetic ones and those on disk. A download
preset (``url`` in the registry) becomes one once fetched, so the UI never offers runs that must fail.

Loading this module reads the profile and the registry and writes nothing. The profile is
``$ATLAS_PROFILE`` (default ``default``) unless :func:`build_definitions` names one.
"""


import logging
import os
from pathlib import Path
from typing import Any, Optional

from dagster import (
    AssetKey,
    AssetObservation,
    AssetRecordsFilter,
    AssetSelection,
    Config,
    DagsterInstance,
    DefaultSensorStatus,
    Definitions,
    DynamicPartitionsDefinition,
    OpExecutionContext,
    SensorEvaluationContext,
    SensorResult,
    SkipReason,
    ExecutorDefinition,
    JobDefinition,
    define_asset_job,
    in_process_executor,
    multiprocess_executor,
    job,
    op,
    sensor,
)

from pydantic import Field as PField

from assets.io_managers import ArtifactIOManager, artifacts_root
from assets.pipeline_assets import build_pipeline_assets, dataset_version
from assets.resources import atlas_config, dataset_entry
from assets.runs import reap_dead_runs
from assets.versioning import DATA_VERSION_TAG, DATASET_FILES, data_version, record
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import (
    camera_from_intrinsics,
    dataset_on_disk,
    load_registry,
    needs_download,
    register_local_dataset,
    validate_dataset_name,
)

logger = logging.getLogger("atlas_gs.definitions")

DATASETS = DynamicPartitionsDefinition(name="datasets")


def dataset_partitions(names: list[str] | None = None) -> DynamicPartitionsDefinition:
    """The dataset partitions (dynamic: their keys live in the Dagster instance). ``names`` is
    accepted for compatibility and ignored; use :func:`sync_dataset_partitions`."""
    return DATASETS


def registered_partition_names() -> list[str]:
    """Registered dataset names (registry order), each checked by the registry's name rule."""
    return [validate_dataset_name(n) for n in load_registry()]


def available_partition_names() -> list[str]:
    """Registered datasets a run can build offline (registry order): synthetic ones and those on
    disk. A download preset is left out until fetched (``atlas-gs dataset fetch NAME``), so the UI
    does not offer partitions whose runs must fail without the network."""
    return [validate_dataset_name(n) for n, e in load_registry().items() if dataset_on_disk(e)]


def unfetched_partitions(instance: DagsterInstance) -> list[str]:
    """Partitions of download presets whose frames are not on disk and that were never
    materialized (added by an older atlas-gs): nothing is lost by removing them."""
    have = set(instance.get_dynamic_partitions(DATASETS.name))
    out = []
    for name, entry in load_registry().items():
        if name in have and needs_download(entry) and not instance.fetch_materializations(
                AssetRecordsFilter(asset_key=AssetKey("raw_dataset"), asset_partitions=[name]), limit=1).records:
            out.append(name)
    return out


def sync_dataset_partitions(instance: DagsterInstance, names: list[str] | None = None) -> list[str]:
    """Add every registered dataset (or each of ``names``) that a run can build offline and that is
    not a partition yet; returns the added ones. Without ``names``, partitions of presets never
    fetched nor materialized are removed. A name whose frames are not on disk is not added."""
    registry = load_registry()
    if names is None:
        for name in unfetched_partitions(instance):
            instance.delete_dynamic_partition(DATASETS.name, name)
            logger.info("removed partition %s: not downloaded yet (`atlas-gs dataset fetch %s` adds it)", name, name)
    wanted = [validate_dataset_name(n) for n in (names if names is not None else available_partition_names())]
    have = set(instance.get_dynamic_partitions(DATASETS.name))
    new = []
    for n in wanted:
        if n in have:
            continue
        if n in registry and not dataset_on_disk(registry[n]):
            logger.info("%s is not on disk yet: not a partition until `atlas-gs dataset fetch %s`", n, n)
            continue
        new.append(n)
    if new:
        instance.add_dynamic_partitions(DATASETS.name, new)
        logger.info("added dataset partitions: %s", ", ".join(new))
    return new


def changed_datasets(instance: DagsterInstance, names: list[str]) -> list[AssetObservation]:
    """Observations of ``dataset_files`` for every dataset on disk whose data version differs from
    its last observation (what makes ``raw_dataset`` show stale in the UI after frames are edited)."""
    out = []
    for n in names:
        try:
            version = dataset_version(n) if dataset_entry(n).path.exists() else None
        except Exception:  # an entry that cannot be read is reported when it is materialized
            continue
        if version is not None and version != data_version(record(instance, DATASET_FILES, n)):
            out.append(AssetObservation(asset_key=DATASET_FILES, partition=n, tags={DATA_VERSION_TAG: version}))
    return out


@sensor(minimum_interval_seconds=30, default_status=DefaultSensorStatus.RUNNING,
        description="Adds a dynamic partition for every dataset in the registry (configs/datasets.yaml and "
                    "the local registry) that a run can build offline and that is not one yet (a download "
                    "preset once `atlas-gs dataset fetch` put its frames on disk), removes partitions of presets "
                    "never fetched nor materialized, and observes dataset_files of every dataset whose files changed.")
def dataset_registry_sensor(context: SensorEvaluationContext):
    reap_dead_runs(context.instance)  # runs whose process died are marked failed (assets.runs)
    try:
        names = available_partition_names()
        gone = unfetched_partitions(context.instance)
    except Exception as exc:  # a broken registry file: say which and what, do not crash the daemon
        return SkipReason(f"dataset registry unreadable: {exc}")
    have = set(context.instance.get_dynamic_partitions(DATASETS.name))
    new = [n for n in names if n not in have]
    observed = changed_datasets(context.instance, [n for n in names if n in have])
    if not new and not gone and not observed:
        return SkipReason(f"all {len(names)} datasets on disk are partitions, none changed on disk")
    requests = ([DATASETS.build_add_request(new)] if new else []) + ([DATASETS.build_delete_request(gone)] if gone else [])
    return SensorResult(dynamic_partitions_requests=requests, asset_events=observed)


class RegisterDatasetConfig(Config):
    """A folder in TUM RGB-D layout to register as a dataset partition."""

    name: str = PField(description="partition name: lower-case letters, digits, '-', '_'")
    path: str = PField(description="the folder (rgb.txt, depth.txt, optional groundtruth.txt)")
    kind: Optional[str] = PField(None, description="tum, 7scenes, replica, scannet or bag (default: detected)")
    camera: Optional[str] = PField(None, description="camera preset (default: the kind's own; TUM: default)")
    intrinsics: Optional[str] = PField(None, description="'fx fy cx cy' instead of a preset")
    width: int = PField(640, description="image width (with intrinsics)")
    height: int = PField(480, description="image height (with intrinsics)")
    depth_scale: float = PField(5000.0, description="depth units per metre (with intrinsics)")
    replace: bool = PField(False, description="re-point a name that is already registered")


@op(description="Validate the name and the TUM layout, write the local registry, add the partition.")
def register_dataset_op(context: OpExecutionContext, config: RegisterDatasetConfig) -> None:
    camera = (camera_from_intrinsics(config.intrinsics, config.width, config.height, config.depth_scale, "intrinsics")
              if config.intrinsics else config.camera)
    entry = register_local_dataset(config.name, config.path, camera, replace=config.replace, kind=config.kind)
    sync_dataset_partitions(context.instance, [entry.name])
    context.log.info(f"registered dataset {entry.name} -> {entry.path}; partition added")


@job(description="Register a TUM-layout folder as a dataset partition (launch from the UI's launchpad "
                 "with name, path and camera).")
def register_dataset():
    register_dataset_op()


# ---- executors: where a run's steps execute -----------------------------------------------------

EXECUTOR_ENV = "ATLAS_EXECUTOR"  # in_process (default), multiprocess or dask
DASK_SCHEDULER_ENV = "ATLAS_DASK_SCHEDULER"  # tcp://HOST:PORT of a running dask.distributed scheduler
EXECUTORS = ("in_process", "multiprocess", "dask")
# Without a scheduler address the Dask executor starts a local cluster for the run: one worker
# process per core, one thread each (Dagster steps are not thread-safe; numba uses the cores).
DASK_LOCAL_THREADS_PER_WORKER = 1


def executor_name(name: str | None = None) -> str:
    """``name``, else ``$ATLAS_EXECUTOR``, else ``in_process``; checked."""
    chosen = (name or os.environ.get(EXECUTOR_ENV) or "in_process").strip().lower().replace("-", "_")
    if chosen not in EXECUTORS:
        raise ConfigError(f"executor '{chosen}' (--executor or ${EXECUTOR_ENV}) is not one of {', '.join(EXECUTORS)}")
    return chosen


def select_executor(name: str | None = None, dask_scheduler: str | None = None) -> ExecutorDefinition:
    """The Dagster executor of the ``atlas_gs_all`` job (see :func:`executor_name`).

    ``in_process``: every step in the run's process (the default: one process per run, the partition
    lock held by it). ``multiprocess``: one process per step. ``dask``: each step a task on a
    dask.distributed cluster (``dagster-dask``), the scheduler at ``dask_scheduler`` or
    ``$ATLAS_DASK_SCHEDULER``, else a local cluster started for the run. Both of the last need a
    persistent instance (``$DAGSTER_HOME``) and artifacts on storage every worker sees.
    """
    chosen = executor_name(name)
    if chosen == "in_process":
        return in_process_executor
    if chosen == "multiprocess":
        return multiprocess_executor
    try:  # dagster-dask's executor, submitting around two upstream faults (assets/dask_executor.py)
        from assets.dask_executor import atlas_dask_executor
    except ImportError as exc:
        raise ConfigError("executor 'dask' needs dagster-dask: pip install 'atlas-gs[distributed]'") from exc
    address = dask_scheduler or os.environ.get(DASK_SCHEDULER_ENV)
    cluster = ({"existing": {"address": address}} if address else
               {"local": {"threads_per_worker": DASK_LOCAL_THREADS_PER_WORKER}})
    return atlas_dask_executor.configured({"cluster": cluster}, name="dask")


def atlas_gs_all_job(artifacts_dir: str | None = None, profile: str | None = None, executor: str | None = None,
                     dask_scheduler: str | None = None) -> JobDefinition:
    """The ``atlas_gs_all`` job, rebuilt by name in every process that runs a step (Dagster's
    ``build_reconstructable_job``: the multiprocess and Dask executors need a job they can rebuild)."""
    return build_definitions(artifacts_dir, profile=profile, executor=executor,
                             dask_scheduler=dask_scheduler).resolve_job_def("atlas_gs_all")


def build_definitions(artifacts_dir: str | Path | None = None, profile: str | None = None,
                      partition_names: list[str] | None = None,
                      overrides: dict[str, Any] | None = None, executor: str | None = None,
                      dask_scheduler: str | None = None) -> Definitions:
    """The definitions for one profile: ``profile`` if given, else ``$ATLAS_PROFILE``, else ``default``;
    ``overrides`` (dotted keys) change the run defaults the launchpad shows; ``executor`` /
    ``dask_scheduler``: see :func:`select_executor`. Writes nothing."""
    root = str(artifacts_dir if artifacts_dir is not None else artifacts_root())
    chosen = executor_name(executor)
    run_executor = select_executor(chosen, dask_scheduler)
    everything = define_asset_job(
        "atlas_gs_all", selection=AssetSelection.all(include_sources=True),
        description="Observe the dataset's files, then materialize every Atlas-GS asset of one dataset partition "
                    "and run its checks (assets whose inputs, settings and code are unchanged are reused).",
        executor_def=run_executor,
    )
    atlas = atlas_config(profile, overrides)
    return Definitions(
        assets=build_pipeline_assets(dataset_partitions(partition_names), atlas.load()),
        jobs=[everything, register_dataset],
        sensors=[dataset_registry_sensor],
        # By default one process per run: the partition lock (ArtifactIOManager.lock_partition) is
        # held by the run's process, and the numba kernels use the cores themselves.
        executor=run_executor,
        resources={
            # Steps in other processes: the process launching the run holds the partition lock.
            "artifact_io": ArtifactIOManager(root=root, step_locks=chosen == "in_process"),
            "atlas": atlas,
        },
    )


defs = build_definitions()

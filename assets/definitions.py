"""The one Dagster ``Definitions`` of Atlas-GS (``dagster dev`` loads ``defs`` from here).

Partitions are the registered datasets a run can build offline (synthetic ones and those on disk),
read from the registry (``configs/datasets.yaml`` + the local registry file) whenever the
definitions load: a ``StaticPartitionsDefinition``, so Dagster's own commands work from a fresh
``$DAGSTER_HOME`` with no step before them (``dagster asset materialize --select '*' --partition
synthetic -m assets.definitions``), and the instance holds no partition list to keep in step.
Registering a folder adds a partition without touching code: ``atlas-gs`` loads the definitions
for every command, a running ``dagster dev`` once its code location reloads (the UI's *Reload*;
the ``dataset_registry_sensor`` says when the registry has datasets the loaded code does not).
A download preset (``url`` in the registry) becomes a partition once fetched, so the UI never
offers runs that must fail.

Loading this module reads the profile and the registry and writes nothing (it opens no instance).
The profile is ``$ATLAS_PROFILE`` (default ``default``) unless :func:`build_definitions` names one.
"""


import logging
import os
from pathlib import Path
from typing import Any, Optional

from dagster import (
    AssetObservation,
    AssetSelection,
    Config,
    DagsterInstance,
    DefaultSensorStatus,
    Definitions,
    OpExecutionContext,
    SensorDefinition,
    SensorEvaluationContext,
    SensorResult,
    SkipReason,
    StaticPartitionsDefinition,
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
from assets.export_assets import EXPORT_GROUP, build_export_assets
from assets.pipeline_assets import build_pipeline_assets, dataset_version
from assets.resources import atlas_config, dataset_entry
from assets.runs import reap_dead_runs
from assets.versioning import DATA_VERSION_TAG, DATASET_FILES, data_version, record
from atlas_pipeline.errors import ConfigError
from atlas_pipeline.sensors.registry import (
    camera_from_intrinsics,
    dataset_on_disk,
    load_registry,
    register_local_dataset,
    validate_dataset_name,
)

logger = logging.getLogger("atlas_gs.definitions")

RELOAD_HINT = "reload the code location (the UI's Reload) to see them; atlas-gs sees them now"


def available_partition_names() -> list[str]:
    """Registered datasets a run can build offline (registry order): synthetic ones and those on
    disk. A download preset is left out until fetched (``atlas-gs dataset fetch NAME``), so the UI
    does not offer partitions whose runs must fail without the network."""
    return [validate_dataset_name(n) for n, e in load_registry().items() if dataset_on_disk(e)]


def dataset_partitions(names: list[str] | None = None) -> StaticPartitionsDefinition:
    """The dataset partitions: ``names``, else the registry's datasets a run can build offline now
    (:func:`available_partition_names`)."""
    return StaticPartitionsDefinition(list(names) if names is not None else available_partition_names())


def loaded_partitions(defs: Definitions) -> list[str]:
    """The partitions ``defs`` was built with (registry order)."""
    return list(defs.resolve_job_def("atlas_gs_all").partitions_def.get_partition_keys())


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


def registry_sensor(loaded: list[str]) -> SensorDefinition:
    """The ``dataset_registry_sensor`` of definitions whose partitions are ``loaded``."""
    loaded = list(loaded)

    @sensor(name="dataset_registry_sensor", minimum_interval_seconds=30, default_status=DefaultSensorStatus.RUNNING,
            description="Observes dataset_files of every dataset partition whose files changed on disk (the UI then "
                        "shows raw_dataset stale), marks runs whose process died as failed, and says which datasets "
                        "the registry (configs/datasets.yaml and the local registry) has or lost since the code "
                        "location loaded: partitions are read from it when the definitions load (Reload to see them).")
    def dataset_registry_sensor(context: SensorEvaluationContext):
        reap_dead_runs(context.instance)  # runs whose process died are marked failed (assets.runs)
        try:
            names = available_partition_names()
        except Exception as exc:  # a broken registry file: say which and what, do not crash the daemon
            return SkipReason(f"dataset registry unreadable: {exc}")
        new = [n for n in names if n not in loaded]
        gone = [n for n in loaded if n not in names]
        drift = "; ".join(part for part in (
            f"not partitions until the code location reloads: {', '.join(new)}" if new else "",
            f"no longer registered or on disk: {', '.join(gone)}" if gone else "") if part)
        if drift:
            drift = f"{drift} ({RELOAD_HINT})"
        observed = changed_datasets(context.instance, [n for n in loaded if n in names])
        if not observed:
            return SkipReason(drift or f"all {len(loaded)} dataset partitions unchanged on disk")
        if drift:
            context.log.info(drift)
        return SensorResult(asset_events=observed)

    return dataset_registry_sensor


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


@op(description="Validate the name and the TUM layout, write the local registry.")
def register_dataset_op(context: OpExecutionContext, config: RegisterDatasetConfig) -> None:
    camera = (camera_from_intrinsics(config.intrinsics, config.width, config.height, config.depth_scale, "intrinsics")
              if config.intrinsics else config.camera)
    entry = register_local_dataset(config.name, config.path, camera, replace=config.replace, kind=config.kind)
    context.log.info(f"registered dataset {entry.name} -> {entry.path}: a partition once the code location "
                     f"reloads (the UI's Reload; `atlas-gs run {entry.name}` runs it now)")


@job(description="Register a TUM-layout folder as a dataset (launch from the UI's launchpad with name, path and "
                 "camera); it is a partition once the code location reloads.")
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
    ``partition_names``: the partitions (default: the registry's datasets a run can build offline,
    read now); ``overrides`` (dotted keys) change the run defaults the launchpad shows; ``executor`` /
    ``dask_scheduler``: see :func:`select_executor`. Writes nothing."""
    root = str(artifacts_dir if artifacts_dir is not None else artifacts_root())
    chosen = executor_name(executor)
    run_executor = select_executor(chosen, dask_scheduler)
    everything = define_asset_job(
        "atlas_gs_all", selection=AssetSelection.all(include_sources=True) - AssetSelection.groups(EXPORT_GROUP),
        description="Observe the dataset's files, then materialize every Atlas-GS asset of one dataset partition "
                    "and run its checks (assets whose inputs, settings and code are unchanged are reused).",
        executor_def=run_executor,
    )
    atlas = atlas_config(profile, overrides)
    partitions = dataset_partitions(partition_names)
    exports = define_asset_job(
        "atlas_gs_exports", selection=AssetSelection.groups(EXPORT_GROUP),
        description="Materialize the exports of one partition (COLMAP, nerfstudio, mesh, occupancy grid) from its "
                    "materialized dataset, world and localization.", executor_def=run_executor)
    return Definitions(
        assets=build_pipeline_assets(partitions, atlas.load()) + build_export_assets(partitions),
        jobs=[everything, exports, register_dataset],
        sensors=[registry_sensor(partitions.get_partition_keys())],
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

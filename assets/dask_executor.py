"""Dagster's Dask executor (``dagster-dask``) for the ``atlas_gs_all`` job, with two upstream faults
worked around. Every step still runs as dagster-dask's own task function
(:func:`dagster_dask.executor.query_on_dask_worker`) on a ``dask.distributed`` cluster; only the
submission differs from :class:`dagster_dask.DaskExecutor`:

* dask looks inside every tuple argument of a task (``distributed.utils_comm.unpack_remotedata``;
  ``dask._task_spec.parse_input`` from 2024.12) and rebuilds named tuples field by field. A run of
  a partitioned job carries ``DagsterRun.partitions_subset``, a Dagster ``@record`` that forbids
  iteration, so dagster-dask 0.29.27 fails every partitioned run at submission ("Iteration is not
  allowed on `@record` KeyRangesPartitionsSubset"). The task's arguments travel here in one opaque
  object (:class:`_Sealed`), pickled as a whole by dask's own plumbing.
* dagster-dask names a task ``<job>.<step>``, so two runs of one job on one cluster (two
  partitions) share task keys and the second is given the first one's results (dagster-io/dagster
  issue 21418). The key here also holds the run id.

A step's result is a list of :class:`~dagster.DagsterEvent`; dask sizes every result it keeps by
walking tuples, and an event holds Dagster ``@record`` values that forbid iteration, so each worker
logged "Sizeof calculation for object of type 'list' failed" for every step. An event's size here
is the length of its serialized form (what Dagster stores of it), registered with dask's ``sizeof``
when a worker imports this module to run a step.

A worker that ignores SIGTERM (inherited from the process that started the cluster, see
:func:`assets.runs.signal_dispositions_kept`) makes every step wait a minute for Dagster's compute-log
``tail`` processes, which then never exit: each run warns, naming the workers.

Remove this module once dagster-dask handles both (then use ``dagster_dask.dask_executor``).
"""

from __future__ import annotations

from typing import Any

from dagster import (
    DagsterEvent,
    DagsterInvariantViolationError,
    Field,
    Permissive,
    Selector,
    StringSource,
    executor,
    multiple_process_executor_requirements,
    serialize_value,
)
from dagster_dask.executor import DaskExecutor, get_dask_resource_requirements, query_on_dask_worker
from dask.sizeof import sizeof


@sizeof.register(DagsterEvent)
def _event_bytes(event: DagsterEvent) -> int:
    """About the memory an event holds (see the module docstring)."""
    return len(serialize_value(event))


class _Sealed:
    """A task's arguments as one object dask does not look into."""

    __slots__ = ("args",)

    def __init__(self, *args: Any):
        self.args = args

    def __getstate__(self):
        return self.args

    def __setstate__(self, state):
        self.args = state


def _ignores_sigterm() -> bool:
    """On a worker: whether SIGTERM is ignored in its process (and so in every child it starts)."""
    import signal

    return signal.getsignal(signal.SIGTERM) == signal.SIG_IGN


def _execute_step(dependencies: list[Any], sealed: _Sealed):
    """On a worker: dagster-dask's step function (``dependencies`` only orders the tasks)."""
    return query_on_dask_worker(dependencies, *sealed.args)


class AtlasDaskExecutor(DaskExecutor):
    """:class:`dagster_dask.DaskExecutor` for an existing scheduler or a local cluster (the two
    cluster kinds this project configures), submitting as the module docstring says."""

    def execute(self, plan_context, execution_plan):
        import dask.distributed

        if not plan_context.instance.is_persistent:
            raise DagsterInvariantViolationError("Dask execution requires a persistent DagsterInstance ($DAGSTER_HOME)")
        run = plan_context.dagster_run
        job_name = plan_context.job_name
        if self.cluster_type == "existing":
            cluster, own = self.cluster_configuration["address"], None
        elif self.cluster_type == "local":
            own = cluster = dask.distributed.LocalCluster(**self.build_dict(job_name))
        else:
            raise DagsterInvariantViolationError(f"cluster type {self.cluster_type!r}: only 'existing' and 'local' here")
        instance_ref = plan_context.instance.get_ref()
        try:
            with dask.distributed.Client(cluster) as client:
                deaf = sorted(w for w, ignored in client.run(_ignores_sigterm).items() if ignored)
                if deaf:
                    plan_context.log.warning(
                        f"dask workers {', '.join(deaf)} ignore SIGTERM (inherited from the process that started "
                        "them): each step waits 60 s for Dagster's compute-log tail processes, which are left "
                        "running; start the cluster from a process that does not ignore SIGTERM")
                futures: dict[str, Any] = {}
                for level in execution_plan.get_steps_to_execute_by_level():
                    for step in level:
                        deps = [futures[k] for inp in step.step_inputs for k in inp.dependency_keys]
                        sealed = _Sealed(plan_context.reconstructable_job, run, plan_context.run_config, [step.key],
                                         instance_ref, execution_plan.known_state)
                        futures[step.key] = client.submit(
                            _execute_step, deps, sealed, key=f"{job_name}.{step.key}.{run.run_id}", pure=False,
                            resources=get_dask_resource_requirements(step.tags))
                for _future, events in dask.distributed.as_completed(list(futures.values()), with_results=True):
                    yield from events
        finally:
            if own is not None:
                own.close()


@executor(
    name="dask",
    requirements=multiple_process_executor_requirements(),
    config_schema={"cluster": Field(Selector({
        "existing": Field({"address": StringSource}, description="Connect to an existing scheduler."),
        "local": Field(Permissive(), is_required=False, description="distributed.LocalCluster parameters."),
    }))},
)
def atlas_dask_executor(init_context):
    """Each step a task on a dask.distributed cluster (see :mod:`assets.dask_executor`)."""
    ((cluster_type, cluster_configuration),) = init_context.executor_config["cluster"].items()
    return AtlasDaskExecutor(cluster_type, cluster_configuration)

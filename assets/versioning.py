"""Versioning on Dagster's terms: the config fields each asset reads, reuse of current artifacts, lineage.

Whether an artifact is current is decided from what Dagster records with every materialization:
the asset's code version and the data versions of its inputs. Besides its upstream assets, each
pipeline asset reads ``settings/<asset>`` (exactly the config fields it uses, declared in
:mod:`atlas_pipeline.stage_settings`;
data version: their hash) and ``raw_dataset`` reads ``dataset_files`` (the dataset folder, an
observable source asset; data version: its registry entry and file signature). Data versions come
from content only (the hash of the files written; timings are metadata), so an identical recompute
leaves everything downstream current. :func:`changes` applies Dagster's staleness rule (the one its
UI shows) to the partition's latest materialization: :func:`reuse` before computing, and
``atlas-gs status`` (:mod:`assets.staleness`) for a config not run yet.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import time
from typing import Any

from dagster import (AssetExecutionContext, AssetKey, AssetRecordsFilter, DagsterInstance, DataProvenance, DataVersion,
                     EventLogRecord, Failure, MaterializeResult, MetadataValue, Output)

from assets.io_managers import Reused
from assets.runs import tag_run_process
from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.sensors.tum import FrameManifest
from atlas_pipeline.stage_settings import REVISIT_STAGE, STAGES, stage_settings

__all__ = ["STAGES", "REVISIT_STAGE", "stage_settings", "DATASET_FILES", "FIRST_VISIT_WORLD", "settings_version",
           "settings_key", "settings_result", "record", "data_version", "changes", "reuse", "versioned",
           "artifact", "lineage"]

DATA_VERSION_TAG = "dagster/data_version"  # where Dagster keeps an event's data version (a test pins it)
DATASET_FILES = AssetKey("dataset_files")
# Materialized only for a second visit (a registry entry with ``extends``): its world extends the
# first visit's, an input from that visit's partition.
FIRST_VISIT_WORLD = AssetKey("gaussian_world")
_STARTED: dict[tuple[str, AssetKey], float] = {}  # (run, asset) -> when reuse() decided to compute


def settings_version(values: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(values, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]


def settings_key(stage: str) -> AssetKey:
    return AssetKey(["settings", stage])


def settings_result(key: AssetKey, values: dict[str, Any]) -> MaterializeResult:
    """A ``settings/<stage>`` materialization: the values as metadata, their hash as data version."""
    return MaterializeResult(asset_key=key, data_version=DataVersion(settings_version(values)),
                             metadata={"settings": MetadataValue.json(values)})


def record(instance: DagsterInstance, key: AssetKey, partition: str, before: int | None = None,
           after: int | None = None) -> EventLogRecord | None:
    """Latest materialization (observation, for ``dataset_files``) of ``key``/``partition``,
    optionally among event ids ``< before`` / ``> after``."""
    fetch = instance.fetch_observations if key == DATASET_FILES else instance.fetch_materializations
    recs = fetch(AssetRecordsFilter(asset_key=key, asset_partitions=[partition], before_storage_id=before,
                                    after_storage_id=after), limit=1).records
    return recs[0] if recs else None


def data_version(rec: EventLogRecord | None) -> str | None:
    return rec.asset_event.tags.get(DATA_VERSION_TAG) if rec is not None else None


def changes(instance: DagsterInstance, key: AssetKey, partition: str, code_version: str | None, deps,
            settings: dict[str, Any] | None = None, dataset: str | None = None, stale=(),
            dep_partitions: dict[AssetKey, str] | None = None) -> list[str]:
    """Why the latest materialization of ``key``/``partition`` is not current (empty: it is).

    Dagster's rule: never materialized, another code version, or an input (``deps``) whose partition
    has a newer event with another data version than the one consumed (Dagster records the newest
    event id of each input at that time). ``settings``: compare the ``settings/<asset>`` consumed
    with these values instead; ``dataset``: the ``dataset_version`` metadata with this; ``stale``:
    inputs that will be recomputed; ``dep_partitions``: inputs read from another partition (a
    second visit's first-visit world)."""
    dep_partitions = dep_partitions or {}
    last = record(instance, key, partition)
    prov = DataProvenance.from_tags(last.asset_materialization.tags) if last is not None else None
    if prov is None:
        return ["never materialized"]
    out = [] if prov.code_version == code_version else [f"code version {prov.code_version} -> {code_version}"]
    for dep in sorted(deps):
        cursor = prov.input_storage_ids.get(dep)
        dep_p = dep_partitions.get(dep, partition)
        used = record(instance, dep, dep_p, before=cursor + 1) if cursor is not None else None
        if dep.path[-1] in stale and len(dep.path) == 1 and dep not in dep_partitions:
            out.append(f"{dep.path[-1]} will be recomputed (may change)")
        elif dep == settings_key(key.path[-1]) and settings is not None:
            if settings_version(settings) != data_version(used):
                old = used.asset_materialization.metadata["settings"].value if used is not None else {}
                out.append("settings changed: " + ", ".join(f"{k} {old.get(k)!r} -> {settings.get(k)!r}" for k in
                                                            sorted(set(old) | set(settings)) if old.get(k) != settings.get(k)))
        elif dep == DATASET_FILES and dataset is not None:
            if getattr(last.asset_materialization.metadata.get("dataset_version"), "value", None) != dataset:
                out.append("dataset files changed")
        elif dep not in prov.input_data_versions:
            out.append(f"new input {dep.to_user_string()}")
        elif (newer := record(instance, dep, dep_p, after=cursor)) is not None and data_version(newer) != data_version(used):
            out.append(f"{dep.to_user_string()}{f' [{dep_p}]' if dep_p != partition else ''} has a new data version")
    return out


def reuse(context: AssetExecutionContext, cfg: PipelineConfig, manifest: FrameManifest | None = None,
          dataset: str | None = None, dep_partitions: dict[AssetKey, str] | None = None) -> Output | None:
    """Call first in an asset: takes the partition's lock, checks that ``settings/<asset>`` holds the
    run's settings, and returns an ``Output`` repeating the latest materialization when
    :func:`changes` finds nothing and the files are intact; None: compute (target checked writable)."""
    store, key, p, inst = context.resources.artifact_io, context.asset_key, context.partition_key, context.instance
    name, run_id = key.path[-1], context.run.run_id
    store.lock_partition(p, run_id)  # one run per partition at a time
    tag_run_process(inst, run_id)  # so a killed run can be marked failed (assets.runs)
    settings = stage_settings(cfg, name, manifest)
    if (have := data_version(record(inst, settings_key(name), p))) != settings_version(settings):
        raise Failure(f"settings/{name} [{p}] (version {have}) does not hold this run's settings "
                      f"({settings_version(settings)}): materialize it in the same run, as the atlas_gs_all job does")
    code = context.assets_def.get_asset_spec(key).code_version
    why = changes(inst, key, p, code, context.assets_def.asset_deps[key], settings, dataset,
                  dep_partitions=dep_partitions) or (
        [] if store.intact(name, p) else ["artifact files changed or missing"])
    if why:
        context.log.info(f"computing {name} [{p}]: {'; '.join(why)}")
        store.prepare(name, p)  # a read-only, full or foreign target fails now, not after the work
        _STARTED[(run_id, key)] = time.perf_counter()
        return None
    last = record(inst, key, p)
    context.log.info(f"reused cached {name} [{p}]: code version {code}, settings and every input's data version "
                     f"unchanged since run {last.run_id}; data version {data_version(last)}, no recomputation")
    return Output(Reused(name, p), data_version=DataVersion(data_version(last)),
                  metadata={**last.asset_materialization.metadata, "reused": True, "reused_from_run": last.run_id})


def versioned(context: AssetExecutionContext, value: Any, metadata: dict[str, Any]) -> Output:
    """The computed artifact, staged by the IO manager so that its content hash (the data version) is
    known; the IO manager moves it into place."""
    name, p, run_id = context.asset_key.path[-1], context.partition_key, context.run.run_id
    t0 = _STARTED.pop((run_id, context.asset_key), time.perf_counter())
    md = {**metadata, "reused": False, "compute_s": round(time.perf_counter() - t0, 3)}
    staged = context.resources.artifact_io.stage(name, p, value, run_id=run_id)
    return Output(staged, data_version=DataVersion(staged.data_version), metadata=md)


def artifact(context: AssetExecutionContext, out: Output) -> Any:
    """The artifact behind an asset's ``out``: the value computed, or the reused one reloaded."""
    if isinstance(out.value, Reused):
        return context.resources.artifact_io.load_artifact(out.value.asset, out.value.partition)
    return out.value.value


def _upstream_entry(rec: EventLogRecord) -> dict[str, Any]:
    """Data version, code version, run and time of one materialization, as lineage records them."""
    prov = DataProvenance.from_tags(rec.asset_materialization.tags)
    return {"data_version": data_version(rec), "code_version": prov.code_version, "run_id": rec.run_id,
            "created_utc": _dt.datetime.fromtimestamp(rec.timestamp, _dt.timezone.utc).isoformat(timespec="seconds")}


def lineage(context: AssetExecutionContext, dep_partitions: dict[AssetKey, str] | None = None) -> dict[str, Any]:
    """The running asset's ancestors (same partition), walked through the input provenance Dagster
    recorded: ``upstream`` (data version, code version, run, time of each), the ``settings`` each
    read (data versions) and the ``dataset_files`` version. An input read from another partition
    (``dep_partitions``) is recorded as ``name[partition]`` without its own ancestors (the parent
    bundle's lineage holds those)."""
    inst, p = context.instance, context.partition_key
    dep_partitions = dep_partitions or {}
    out: dict[str, Any] = {"upstream": {}, "settings": {}, "dataset_files": None}
    todo, seen = sorted(context.assets_def.asset_deps[context.asset_key]), set()
    while todo:
        dep = todo.pop(0)
        dep_p = dep_partitions.get(dep, p)  # the direct inputs come first, so an ancestor is never mapped
        if dep in seen or (rec := record(inst, dep, dep_p)) is None:
            continue
        seen.add(dep)
        if dep_p != p:
            out["upstream"][f"{dep.path[-1]}[{dep_p}]"] = _upstream_entry(rec)
        elif dep == DATASET_FILES:
            out["dataset_files"] = data_version(rec)
        elif len(dep.path) > 1:
            out["settings"][dep.path[-1]] = data_version(rec)
        else:
            out["upstream"][dep.path[-1]] = _upstream_entry(rec)
            todo.extend(sorted(DataProvenance.from_tags(rec.asset_materialization.tags).input_data_versions))
    return {k: dict(sorted(v.items())) if isinstance(v, dict) else v for k, v in out.items()}

"""Versioned, self-skipping assets: :func:`atlas_asset` wraps an asset body with the versioning rules
of :mod:`atlas_pipeline.versioning`.

What the wrapper does for every asset, so asset bodies stay plain "inputs in, artifact out":

* Declares ``code_version`` to Dagster with the hash of the config sections that shape the asset
  folded in (``"1+cfg.3fa2c1d0"``): after a config change, reloading the definitions makes Dagster
  mark exactly the shaped assets (and everything downstream) stale.
* Declares the body's inputs (parameters named after upstream assets) as Dagster ``deps`` and
  reads them itself, lazily (:class:`assets.io_managers.LazyArtifact`: the upstream record, not the
  arrays): Dagster then neither loads nor logs them, which keeps a reusing step to a few events.
  It computes the input fingerprint (code version, config section hashes, upstream data
  versions, partition, raw-data signature) and, when the artifact on disk was made from the same
  fingerprint and its files are intact, *reuses* it: no input is loaded, no file is written, the run
  log says ``reused cached <asset>``, and the materialization carries the recorded data version,
  metadata and check results.
* Otherwise loads the inputs, runs the body, evaluates the asset's checks, writes the artifact into
  a staging folder (content hash known before Dagster sees the output) and returns it with
  ``data_version = hash(content hash, config hash)``; the IO manager swaps it into place.
"""

from __future__ import annotations

import contextvars
import datetime as _dt
import inspect
import time
import typing
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from dagster import (
    AssetCheckResult,
    BetaWarning,
    AssetCheckSeverity,
    AssetCheckSpec,
    AssetExecutionContext,
    AssetKey,
    ConfigurableResource,
    DataVersion,
    Output,
    asset,
    deserialize_value,
    serialize_value,
)

from assets.io_managers import ArtifactIOManager, CachedArtifact, LazyArtifact
from assets.resources import AtlasConfig
from assets.runs import tag_run_process
from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.versioning import (
    combined_config_hash,
    config_section_hashes,
    maps_with_tracking,
    files_intact,
    input_fingerprint,
    stage_sections,
)

__all__ = ["AtlasCheck", "atlas_asset", "dagster_code_version", "current_asset_info", "upstream_lineage",
           "expected_fingerprint", "CODE_VERSION_KEY"]

IO_KEY = "artifact_io"


def _output(value: Any, dv: str, metadata: dict[str, Any]) -> Output:
    """``Output`` with the asset's own data version (the parameter Dagster still marks beta)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BetaWarning)
        return Output(value, data_version=DataVersion(dv), metadata=metadata)
# Asset definition metadata: the stage's own code version (Dagster's code_version adds the config hash).
CODE_VERSION_KEY = "atlas/code_version"
SECTIONS_KEY = "atlas/config_sections"

Identity = Callable[[str, AtlasConfig], Mapping[str, Any]]
# Per stage: extra fingerprint content (the raw dataset's files); filled by atlas_asset(identity=...).
_IDENTITIES: dict[str, Identity] = {}


def expected_fingerprint(stage: str, code_version: str, partition: str, atlas: AtlasConfig,
                         upstream_data_versions: Mapping[str, str], cfg: PipelineConfig | None = None) -> str:
    """The fingerprint ``stage`` would be computed from now (the wrapper and ``--stale-only`` both use it)."""
    cfg = cfg if cfg is not None else atlas.load()
    identity = _IDENTITIES.get(stage)
    extra = dict(identity(partition, atlas)) if identity else {}
    return input_fingerprint(stage, code_version, partition, stage_config_hashes(cfg, stage, partition, atlas),
                             upstream_data_versions, extra)


def _dataset_has_ground_truth(partition: str, atlas: AtlasConfig) -> bool | None:
    """Cheap answer (no frames read): synthetic data has ground truth; a TUM folder has it when
    ``groundtruth.txt`` is there. None when unknown (not registered, not downloaded yet)."""
    try:
        entry = atlas.dataset(partition)
    except Exception:  # an unregistered partition fails later, with its own clear error
        return None
    if entry.kind == "synthetic":
        return True
    return (Path(entry.path) / "groundtruth.txt").is_file() if Path(entry.path).is_dir() else None


def stage_config_hashes(cfg: PipelineConfig, stage: str, partition: str | None, atlas: AtlasConfig | None) -> dict[str, str]:
    """Config section hashes of ``stage`` for one partition (keyframes follow the tracker's
    settings only when that partition is mapped from tracked poses)."""
    tracking = False
    if stage == "keyframes":
        gt = _dataset_has_ground_truth(partition, atlas) if (partition is not None and atlas is not None) else True
        tracking = maps_with_tracking(cfg, gt)
    return config_section_hashes(cfg, stage, tracking)


@dataclass(frozen=True)
class AtlasCheck:
    """An asset check evaluated on the artifact the asset computed: ``evaluate(value, cfg)``."""

    spec: AssetCheckSpec
    evaluate: Callable[[Any, PipelineConfig], AssetCheckResult]


@dataclass(frozen=True)
class AssetRunInfo:
    """What the wrapper knows about the asset it is running (for lineage)."""

    asset: str
    code_version: str
    fingerprint: str
    config_sections: dict[str, str]
    inputs: dict[str, str]


_CURRENT: contextvars.ContextVar[AssetRunInfo | None] = contextvars.ContextVar("atlas_asset", default=None)


def current_asset_info() -> AssetRunInfo | None:
    """The versioning info of the asset body now running (None outside :func:`atlas_asset`)."""
    return _CURRENT.get()


def dagster_code_version(code_version: str, stage: str, cfg: PipelineConfig | None) -> str:
    """Code version as Dagster sees it: the stage's code version plus the hash of its config sections."""
    if cfg is None:
        return code_version
    # Partition-independent (the UI's code version): keyframes count the tracker's settings only
    # when the profile always maps from tracked poses.
    return f"{code_version}+cfg.{combined_config_hash(stage_config_hashes(cfg, stage, None, None))[:8]}"


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _is_resource(annotation: Any) -> bool:
    return inspect.isclass(annotation) and issubclass(annotation, ConfigurableResource)


def _check_record(r: AssetCheckResult) -> dict[str, Any]:
    return {"check_name": r.check_name, "passed": bool(r.passed),
            "severity": (r.severity or AssetCheckSeverity.ERROR).value, "description": r.description,
            "metadata": serialize_value(dict(r.metadata or {}))}


def _check_from_record(d: Mapping[str, Any]) -> AssetCheckResult:
    md = deserialize_value(d["metadata"]) if d.get("metadata") else {}
    return AssetCheckResult(check_name=d["check_name"], passed=bool(d["passed"]),
                            severity=AssetCheckSeverity(d.get("severity", "ERROR")),
                            description=d.get("description"),
                            metadata={**md, "replayed_from_cache": True})


class _BodyContext:
    """The asset context as the body sees it: ``add_output_metadata`` collects into the artifact's
    metadata (recorded for reuse, and valid with check outputs present); the rest is Dagster's."""

    def __init__(self, context: AssetExecutionContext):
        self._context = context
        self.collected: dict[str, Any] = {}

    def add_output_metadata(self, metadata: Mapping[str, Any], output_name: str | None = None,
                            mapping_key: str | None = None) -> None:
        self.collected.update(metadata)

    def __getattr__(self, item: str) -> Any:
        return getattr(self._context, item)


def _selected(context: AssetExecutionContext, name: str) -> bool:
    return any(k.name == name for k in context.selected_asset_check_keys)


def atlas_asset(*, code_version: str, checks: Sequence[AtlasCheck] = (),
                identity: Identity | None = None,
                definition_config: PipelineConfig | None = None, **asset_kwargs: Any):
    """``@asset`` with code/data versions, input fingerprints and reuse of current artifacts.

    Args:
        code_version: the stage's code version; bump it when the stage's code changes its output.
        checks: checks evaluated on the computed artifact (declared as the asset's check specs).
        identity: extra fingerprint content for assets without upstream artifacts (raw data).
        definition_config: the config the definitions were built with, folded into the code
            version Dagster compares for staleness (the run itself uses the ``atlas`` resource).
        asset_kwargs: passed to ``dagster.asset`` (io_manager_key must be ``artifact_io``).
    """

    def decorate(fn: Callable[..., Any]) -> Any:
        name = asset_kwargs.get("name") or fn.__name__
        if identity is not None:
            _IDENTITIES[name] = identity
        sig = inspect.signature(fn)
        hints = typing.get_type_hints(fn)
        params = list(sig.parameters.values())
        if not params or params[0].name != "context":
            raise TypeError(f"{name}: an atlas_asset body takes `context` first")
        resources = [p.name for p in params[1:] if _is_resource(hints.get(p.name))]
        inputs = [p.name for p in params[1:] if p.name not in resources]
        wants_atlas = "atlas" in resources
        # What Dagster sees: the context and the resources (the atlas resource always); inputs are
        # deps read by the wrapper; no return annotation (the output is a staged artifact).
        wrapper_params = [params[0].replace(annotation=AssetExecutionContext)]
        wrapper_params += [p.replace(annotation=hints[p.name]) for p in params[1:] if p.name in resources]
        if not wants_atlas:
            wrapper_params.append(inspect.Parameter("atlas", inspect.Parameter.KEYWORD_ONLY, annotation=AtlasConfig))

        def run(context: AssetExecutionContext, **kwargs: Any):
            atlas: AtlasConfig = kwargs["atlas"]
            store: ArtifactIOManager = getattr(context.resources, IO_KEY)
            partition = context.partition_key
            # One run per partition at a time; the run's process is recorded so a killed run can
            # be marked failed later (assets.runs).
            store.lock_partition(partition, context.run.run_id)
            tag_run_process(context.instance, context.run.run_id)
            cfg = atlas.load()
            sections = stage_config_hashes(cfg, name, partition, atlas)
            config_hash = combined_config_hash(sections)
            lazies: dict[str, LazyArtifact] = {n: store.lazy(n, partition, name) for n in inputs}
            upstream = {n: lz.data_version for n, lz in lazies.items()}
            fp = expected_fingerprint(name, code_version, partition, atlas, upstream, cfg)
            check_names = {c.spec.name for c in checks}
            token = _CURRENT.set(AssetRunInfo(name, code_version, fp, sections, upstream))
            try:
                # ---- reuse ----
                record = store.record(name, partition)
                directory = store.directory(name, partition)
                if (record is not None and record.get("fingerprint") == fp and record.get("data_version")
                        and check_names <= {c["check_name"] for c in record.get("checks", [])}
                        and files_intact(directory, record.get("files", {}))):
                    dv = record["data_version"]
                    context.log.info(
                        f"reused cached {name} [{partition}]: inputs, config ({', '.join(sections)}) and code "
                        f"v{code_version} unchanged (fingerprint {fp[:12]}), data version {dv}; no recomputation")
                    md = deserialize_value(record["metadata"]) if record.get("metadata") else {}
                    yield _output(CachedArtifact(directory, record), dv, {
                        **md, "reused": True, "reused_from_run": str(record.get("run_id")),
                        "fingerprint": fp[:16], "data_version": dv,
                    })
                    for c in record.get("checks", []):
                        if c["check_name"] in check_names and _selected(context, c["check_name"]):
                            yield _check_from_record(c)
                    return
                # ---- recompute ----
                why = ("no cached artifact" if record is None else
                       "cached artifact's files changed" if record.get("fingerprint") == fp else
                       "inputs, config or code changed")
                context.log.info(f"computing {name} [{partition}]: {why} (fingerprint {fp[:12]})")
                store.prepare(name, partition)  # a read-only, full or foreign target fails now, not after the work
                t0 = time.perf_counter()
                call = {n: lz.get() for n, lz in lazies.items()}
                t_load = time.perf_counter() - t0
                call.update({r: kwargs[r] for r in resources})
                body_context = _BodyContext(context)
                result = fn(body_context, **call)
                events = list(result) if inspect.isgenerator(result) else [result]
                value, out_md, body_checks = None, {}, []
                n_out = 0
                for ev in events:
                    if isinstance(ev, AssetCheckResult):
                        body_checks.append(ev)
                    elif isinstance(ev, Output):
                        value, out_md, n_out = ev.value, dict(ev.metadata or {}), n_out + 1
                    else:
                        value, n_out = ev, n_out + 1
                if n_out != 1:
                    raise TypeError(f"{name}: the asset body must produce exactly one output, got {n_out}")
                compute_s = time.perf_counter() - t0
                if name in _IDENTITIES:
                    # The body may have made the raw files exist (generated, downloaded): record the
                    # fingerprint of the files it actually read.
                    fp = expected_fingerprint(name, code_version, partition, atlas, upstream, cfg)
                results = body_checks + [c.evaluate(value, cfg) for c in checks]
                out_md = {**body_context.collected, **out_md}
                all_md = {**out_md,
                          "compute_s": round(compute_s, 3), "load_inputs_s": round(t_load, 3)}
                staged = store.stage(name, partition, value, {
                    "code_version": code_version,
                    "config_sections": sections,
                    "config_hash": config_hash,
                    "inputs": upstream,
                    "fingerprint": fp,
                    "created_utc": _utc_now(),
                    "metadata": serialize_value(all_md),
                    "checks": [_check_record(r) for r in results],
                }, config_hash=config_hash, run_id=context.run.run_id)
                dv = staged.record["data_version"]
                yield _output(staged, dv, {
                    **out_md, "reused": False, "compute_s": round(compute_s, 3),
                    "load_inputs_s": round(t_load, 3), "fingerprint": fp[:16], "data_version": dv,
                })
                for r in results:
                    if _selected(context, r.check_name):
                        yield r
            finally:
                _CURRENT.reset(token)

        run.__name__ = fn.__name__
        run.__qualname__ = fn.__qualname__
        run.__doc__ = fn.__doc__
        run.__module__ = fn.__module__
        run.__signature__ = inspect.Signature(wrapper_params)  # type: ignore[attr-defined]
        existing_specs = list(asset_kwargs.pop("check_specs", []) or [])
        deps = list(asset_kwargs.pop("deps", []) or []) + [AssetKey(n) for n in inputs]
        metadata = {**asset_kwargs.pop("metadata", {}), CODE_VERSION_KEY: code_version,
                    SECTIONS_KEY: ", ".join(stage_sections(name))}
        return asset(
            name=name, deps=deps, metadata=metadata,
            code_version=dagster_code_version(code_version, name, definition_config),
            check_specs=existing_specs + [c.spec for c in checks],
            **{k: v for k, v in asset_kwargs.items() if k != "name"},
        )(run)

    return decorate


def upstream_lineage(context: AssetExecutionContext) -> dict[str, Any]:
    """Every ancestor artifact of the running asset (same partition), from the artifact records:
    ``{asset: {data_version, code_version, config_hash, run_id, created_utc}}``."""
    store: ArtifactIOManager = getattr(context.resources, IO_KEY)
    partition = context.partition_key
    info = current_asset_info()
    todo = list(info.inputs) if info else [k.path[-1] for k in context.assets_def.dependency_keys]
    out: dict[str, Any] = {}
    while todo:
        a = todo.pop(0)
        if a in out:
            continue
        rec = store.record(a, partition) or {}
        out[a] = {"data_version": rec.get("data_version") or rec.get("content_hash"),
                  "code_version": rec.get("code_version"), "config_hash": rec.get("config_hash"),
                  "config_sections": sorted(rec.get("config_sections", {})),
                  "run_id": rec.get("run_id"), "created_utc": rec.get("created_utc")}
        todo.extend(rec.get("inputs", {}))
    return dict(sorted(out.items()))


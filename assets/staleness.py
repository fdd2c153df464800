"""Which assets of a partition are stale or missing, from Dagster's view and from the artifacts.

Two views are combined, and an asset is stale when either says so:

* Dagster's (``CachingStaleStatusResolver``, the same the UI shows): never materialized, code
  version changed (the config hash is part of it), or an upstream data version changed;
* the artifacts' (``_artifact.json``): missing, files changed, or made from another fingerprint
  than the current code, config, upstream data versions and raw files give (this catches what
  Dagster cannot see: edited dataset files, artifacts deleted or made under another DAGSTER_HOME).

Everything downstream of a stale asset is stale too.
"""

from __future__ import annotations

from typing import Any

from dagster import AssetKey, DagsterInstance, Definitions

from assets.io_managers import ArtifactIOManager
from assets.resources import AtlasConfig
from assets.versioning import CODE_VERSION_KEY, expected_fingerprint
from atlas_pipeline.versioning import files_intact

__all__ = ["dagster_status", "stale_assets"]


def dagster_status(defs: Definitions, instance: DagsterInstance, partition: str) -> dict[str, tuple[str, list[str]]]:
    """``{asset: (FRESH|STALE|MISSING, [causes])}`` as Dagster computes it."""
    from dagster._core.asset_graph_view.asset_graph_view import AssetGraphView, TemporalContext
    from dagster._core.definitions.data_version import CachingStaleStatusResolver
    from dagster._time import get_current_datetime

    graph = defs.resolve_asset_graph()
    view = AssetGraphView(temporal_context=TemporalContext(effective_dt=get_current_datetime(), last_event_id=None),
                          instance=instance, asset_graph=graph)
    resolver = CachingStaleStatusResolver(instance=instance, asset_graph=graph, loading_context=view)
    out = {}
    for key in graph.materializable_asset_keys:
        status = resolver.get_status(key, partition)
        causes = [f"{c.key.asset_key.to_user_string()}: {c.reason}"
                  for c in resolver.get_stale_root_causes(key, partition)] if status.value == "STALE" else []
        out[key.path[-1]] = (status.value, causes)
    return out


def _topological(defs: Definitions) -> list[tuple[str, list[str], Any]]:
    graph = defs.resolve_asset_graph()
    order, seen = [], set()

    def visit(key: AssetKey) -> None:
        if key in seen:
            return
        seen.add(key)
        for parent in sorted(graph.get(key).parent_keys):
            visit(parent)
        order.append(key)

    for k in sorted(graph.materializable_asset_keys):
        visit(k)
    out = []
    for k in order:
        node = graph.get(k)
        assets_def = node.assets_def
        inputs = {key.path[-1]: name for name, key in assets_def.keys_by_input_name.items()}
        out.append((k.path[-1], sorted(inputs), assets_def))
    return out


def stale_assets(defs: Definitions, instance: DagsterInstance, partition: str, store: ArtifactIOManager,
                 atlas: AtlasConfig) -> dict[str, list[str]]:
    """``{asset: [reasons]}`` for every stale or missing asset of ``partition`` (empty: all current)."""
    cfg = atlas.load()
    dagster = dagster_status(defs, instance, partition)
    stale: dict[str, list[str]] = {}
    records: dict[str, dict[str, Any] | None] = {}
    for name, inputs, assets_def in _topological(defs):
        reasons = []
        status, causes = dagster.get(name, ("FRESH", []))
        if status == "MISSING":
            reasons.append("dagster: never materialized in this instance")
        elif status == "STALE":
            reasons += [f"dagster: {c}" for c in causes] or ["dagster: stale"]
        up_stale = [i for i in inputs if i in stale]
        if up_stale:
            reasons.append(f"upstream will change: {', '.join(up_stale)}")
        rec = records[name] = store.record(name, partition)
        if rec is None:
            reasons.append("no artifact on disk")
        else:
            if not files_intact(store.directory(name, partition), rec.get("files", {})):
                reasons.append("artifact files changed on disk")
            if not up_stale and all(records.get(i) for i in inputs):
                code_version = str(assets_def.metadata_by_key[assets_def.key].get(CODE_VERSION_KEY, ""))
                upstream = {i: str(records[i].get("data_version") or records[i].get("content_hash"))
                            for i in inputs}
                if rec.get("fingerprint") != expected_fingerprint(name, code_version, partition, atlas, upstream, cfg):
                    reasons.append("inputs, config, code or raw files differ from the artifact's")
        if reasons:
            stale[name] = reasons
    return stale

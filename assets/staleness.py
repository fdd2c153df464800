"""Which assets of a partition a run would recompute, and why (``atlas-gs status``, ``run --stale-only``).

Dagster's own rule (:func:`assets.versioning.changes`, what its UI shows and what each asset applies
before computing), with two inputs taken as a run would find them rather than as last recorded: the
settings the given config makes, and the dataset's files on disk. Assets downstream of a stale one
are listed as "may change" (an identical recompute leaves them current).
"""

from __future__ import annotations

from dagster import AssetKey, DagsterInstance, Definitions

from assets.pipeline_assets import dataset_version
from assets.resources import AtlasConfig, dataset_entry
from assets.versioning import (DATASET_FILES, FIRST_VISIT_WORLD, REVISIT_STAGE, STAGES, changes, settings_key,
                               stage_settings)

__all__ = ["stale_assets", "stale_selection"]


def stale_assets(defs: Definitions, instance: DagsterInstance, partition: str, atlas: AtlasConfig) -> dict[str, list[str]]:
    """``{asset: [reasons]}`` for every stale or missing asset of ``partition`` (empty: all current)."""
    cfg, store = atlas.load(), defs.resources["artifact_io"]
    specs = {s.key: s for s in defs.resolve_all_asset_specs()}
    stale: dict[str, list[str]] = {}
    first_visit = dataset_entry(partition).extends
    for name in STAGES:
        if name == REVISIT_STAGE and first_visit is None:
            continue  # a first visit has no revisit bundle
        spec = specs[AssetKey(name)]
        manifest = store.load_artifact("raw_dataset", partition) if name == "keyframes" and store.intact(
            "raw_dataset", partition) else None  # keyframes: the settings this dataset makes it read
        why = changes(instance, spec.key, partition, spec.code_version, [d.asset_key for d in spec.deps],
                      stage_settings(cfg, name, manifest), dataset_version(partition), stale,
                      dep_partitions={FIRST_VISIT_WORLD: first_visit} if name == REVISIT_STAGE else None)
        if why or not store.intact(name, partition):
            stale[name] = why or ["artifact files changed or missing"]
    return stale


def stale_selection(stale: dict[str, list[str]]) -> list[AssetKey]:
    """A run of the ``stale`` assets: them, their settings (from the run's config), and the dataset's
    files when the raw dataset is read again."""
    keys = [AssetKey(a) for a in stale] + [settings_key(a) for a in stale]
    return keys + ([DATASET_FILES] if "raw_dataset" in stale else [])

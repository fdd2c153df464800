"""A partition's outputs under the artifacts root, as the commands find them.

The Dagster assets write each partition's results into ``<artifacts>/<asset>/<partition>/``; the
commands that name a partition instead of a folder (``export``, ``lineage``, ``view``) and the run
summaries read them from there. Only paths that exist are returned: a failed run must not point
at output it did not write.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from atlas_pipeline.errors import AtlasError, ConfigError
from atlas_pipeline.sensors.registry import validate_dataset_name

REPORT_FILE = "localization.json"
# The localization summary's fields a run summary repeats (the rest stay in the report).
LOCALIZATION_SUMMARY_KEYS = ("n_tracked", "n_lost", "n_relocalized", "ate_rmse_m", "rpe_trans_rmse_m_per_s")


def _root() -> Path:
    from assets.io_managers import artifacts_root

    return artifacts_root()


def world_bundle_folder(spec: str) -> Path:
    """A bundle folder, or the name of a partition whose Dagster world bundle is on disk."""
    target = Path(spec).expanduser()
    if target.is_dir():
        return target
    try:
        name = validate_dataset_name(spec)
    except AtlasError:
        raise ConfigError(f"'{spec}' is neither a bundle folder nor a partition with a world bundle "
                          "(no such folder)") from None
    target = _root() / "world_bundle" / name
    if not target.is_dir():
        raise ConfigError(f"'{spec}' is neither a bundle folder nor a partition with a world bundle "
                          f"(looked in {target}; `atlas-gs run {name}` makes one)")
    return target


def partition_report_folder(partition: str) -> Path | None:
    """The folder of the partition's localization report, None when it has none."""
    folder = _root() / "localization_report" / partition
    return folder if (folder / REPORT_FILE).is_file() else None


def partition_outputs(partition: str) -> dict[str, Any]:
    """The partition's outputs on disk: ``world_bundle`` and ``transitions`` where they exist, and
    ``videos`` (every demo MP4, sorted)."""
    root = _root()
    bundle = root / "world_bundle" / partition
    outputs: dict[str, Any] = {}
    if (bundle / "metadata.json").is_file():
        outputs["world_bundle"] = str(bundle)
    if (bundle / "transitions.parquet").is_file():
        outputs["transitions"] = str(bundle / "transitions.parquet")
    outputs["videos"] = [str(x) for x in sorted((root / "demo_videos" / partition).glob("*.mp4"))]
    return outputs


def localization_summary(partition: str) -> dict[str, Any] | None:
    """The headline figures of the partition's localization report, None when it has none."""
    folder = partition_report_folder(partition)
    if folder is None:
        return None
    summary = json.loads((folder / REPORT_FILE).read_text())["summary"]
    return {k: summary.get(k) for k in LOCALIZATION_SUMMARY_KEYS}

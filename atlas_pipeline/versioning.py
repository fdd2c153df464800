"""Versions of pipeline artifacts: which config shapes which stage, input fingerprints, data versions.

An artifact is *current* when the fingerprint of what would produce it now (stage code version,
the config sections that shape it, the data versions of its inputs, the partition, and for the raw
dataset a cheap signature of the files on disk) equals the fingerprint recorded when it was written,
and its files are still the ones recorded. A current artifact is reused, not recomputed.

The data version of an artifact is a hash of what it wrote (the content hash over its files) and
of the config sections that shaped it, so two artifacts with the same bytes made under different
settings still differ.

No orchestration here (the library never imports Dagster); ``assets/versioning.py`` applies it.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping

from atlas_pipeline.config import PipelineConfig, section_hash
from atlas_pipeline.io_utils import sha256_file

__all__ = [
    "ALL_SECTIONS",
    "STAGE_CONFIG_SECTIONS",
    "stage_sections",
    "maps_with_tracking",
    "config_section_hashes",
    "combined_config_hash",
    "input_fingerprint",
    "data_version",
    "dataset_signature",
    "files_intact",
]

ALL_SECTIONS: tuple[str, ...] = ("dataset", "fusion", "mapping", "localization", "transitions", "video", "evaluation")

# The one place that says which config sections shape which stage's artifact. A stage also depends
# on its upstream artifacts, so e.g. keyframes follow a fusion change through fused_frames' data
# version; the list names only the sections the stage's own code reads.
STAGE_CONFIG_SECTIONS: dict[str, tuple[str, ...]] = {
    "raw_dataset": ("dataset",),
    "fused_frames": ("fusion",),
    "keyframes": ("mapping",),
    "gaussian_world": ("mapping",),
    "localization_report": ("localization", "fusion"),  # the depth range of the frames tracked
    "transitions": ("transitions",),
    "demo_videos": ("video", "fusion"),  # the side-by-side video shows the real frames
    "render_evaluation": ("evaluation", "fusion"),  # the sensor depth range compared
    "world_bundle": ALL_SECTIONS,  # metadata.json carries the whole resolved config
}


def stage_sections(stage: str, maps_with_tracking: bool = False) -> tuple[str, ...]:
    """Config sections that shape ``stage``; a stage not listed depends on the whole config.

    ``maps_with_tracking``: the keyframes stage tracks the camera itself (mapping from estimated
    poses), so the tracker's settings (``localization``) shape it too; with ground-truth mapping
    they do not, and a localization change leaves the map alone.
    """
    sections = STAGE_CONFIG_SECTIONS.get(stage, ALL_SECTIONS)
    if stage == "keyframes" and maps_with_tracking:
        sections = sections + ("localization",)
    return sections


def maps_with_tracking(cfg: PipelineConfig, has_ground_truth: bool | None) -> bool:
    """Whether the keyframes stage will track (``mapping.pose_source`` resolved as
    :func:`atlas_pipeline.mapping.keyframes.uses_ground_truth` does; ``auto`` tracks when the
    dataset has no ground truth, or when that is unknown)."""
    src = cfg.mapping.pose_source
    return src == "estimated" or (src == "auto" and not has_ground_truth)


def config_section_hashes(cfg: PipelineConfig, stage: str, maps_with_tracking: bool = False) -> dict[str, str]:
    """``{section: section_hash}`` of the sections that shape ``stage``."""
    return {s: section_hash(getattr(cfg, s)) for s in stage_sections(stage, maps_with_tracking)}


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def combined_config_hash(section_hashes: Mapping[str, str]) -> str:
    return _digest(dict(section_hashes))[:16]


def input_fingerprint(stage: str, code_version: str, partition: str, section_hashes: Mapping[str, str],
                      upstream_data_versions: Mapping[str, str], extra: Mapping[str, Any] | None = None) -> str:
    """Hash of everything that determines ``stage``'s output: equal fingerprints, equal artifacts."""
    return _digest({
        "stage": stage, "code_version": code_version, "partition": partition,
        "config": dict(section_hashes), "inputs": dict(upstream_data_versions), "extra": dict(extra or {}),
    })


def data_version(content_hash: str, config_hash: str) -> str:
    """Data version of an artifact: its content hash with the config hash folded in (24 hex)."""
    return hashlib.sha256(f"{content_hash}:{config_hash}".encode()).hexdigest()[:24]


def dataset_signature(root: Path) -> str:
    """Cheap identity of a dataset folder on disk: name, size and modification time of every file
    (no file is read). A dataset whose files are edited, added or removed gets a new signature."""
    root = Path(root)
    if not root.is_dir():
        return "missing"
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(filenames):
            if name.startswith("."):
                continue
            p = Path(dirpath) / name
            st = p.stat()
            h.update(f"{p.relative_to(root).as_posix()}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:32]


def files_intact(directory: Path, files: Mapping[str, Mapping[str, Any]]) -> bool:
    """True when every recorded file exists with its recorded bytes.

    Size and modification time equal to the record count as unchanged (no read); otherwise the
    file is hashed and compared with the recorded sha256.
    """
    for name, rec in files.items():
        p = Path(directory) / name
        try:
            st = p.stat()
        except FileNotFoundError:
            return False
        if st.st_size != rec.get("bytes"):
            return False
        if rec.get("mtime_ns") == st.st_mtime_ns:
            continue
        if sha256_file(p) != rec.get("sha256"):
            return False
    return True

"""Dataset registry: named datasets (one Dagster partition each) and where their frames come from.

Two YAML files are merged: ``configs/datasets.yaml`` (tracked presets; an installed package reads its
own copy) and a local file for the user's own folders (``configs/datasets.local.yaml`` of the checkout,
git-ignored, or of ``$ATLAS_GS_HOME`` / the working directory when installed; ``$ATLAS_LOCAL_REGISTRY``
overrides it).
"""

from __future__ import annotations

import dataclasses

import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import yaml

from atlas_pipeline.config import configs_dir, load_yaml_file, project_root
from atlas_pipeline.errors import ConfigError, DatasetError
from atlas_pipeline.io_utils import write_text_atomic
from atlas_pipeline.sensors.camera import TUM_CAMERAS, CameraIntrinsics
from atlas_pipeline.sensors.layouts import (
    CAMERA_PRESETS,
    DEFAULT_FPS,
    KIND_CAMERA_PRESET,
    MAX_FPS,
    RECORDING_KINDS,
    SEQUENCE_RE,
    detect_kind,
    load_recording,
    recording_exists,
)
from atlas_pipeline.sensors.tum import file_problem

logger = logging.getLogger(__name__)

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.sensors.tum import FrameManifest

LOCAL_REGISTRY_ENV = "ATLAS_LOCAL_REGISTRY"  # the user's registry file, instead of configs/datasets.local.yaml
# Partition keys become folder names under artifacts/: keep them to a safe alphabet.
DATASET_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")

__all__ = [
    "DATASET_NAME_RE",
    "DatasetEntry",
    "validate_dataset_name",
    "registry_files",
    "local_registry_path",
    "data_dir",
    "load_registry",
    "register_local_dataset",
    "check_dataset_folder",
    "camera_from_intrinsics",
    "resolve_camera",
    "camera_presets",
    "default_camera_spec",
    "detect_kind",
    "bag_cache_root",
    "read_dataset_manifest",
    "load_dataset",
    "ensure_dataset_files",
    "dataset_on_disk",
    "files_missing",
    "needs_download",
    "recording_bytes",
    "registered_entry",
    "registered_entries",
    "dataset_from_spec",
    "recording_kind",
    "intrinsics_camera",
    "availability",
    "not_on_disk_reason",
]


def validate_dataset_name(name: str, where: str = "") -> str:
    """Return ``name`` if it is a safe dataset name, else raise ConfigError (prefixed by ``where``)."""
    if not isinstance(name, str) or not DATASET_NAME_RE.match(name):
        raise ConfigError(
            f"{where + ': ' if where else ''}invalid dataset name {name!r}: use 1-64 lower-case letters, digits, '-' or '_', "
            "starting with a letter or digit"
        )
    return name


@dataclass(frozen=True)
class DatasetEntry:
    """One registered dataset.

    Attributes:
        name: registry key and partition key.
        kind: ``synthetic`` (generated) or a recording layout: ``tum``, ``7scenes``, ``replica``,
            ``scannet``, ``bag`` (see :mod:`atlas_pipeline.sensors.layouts`).
        path: folder of the frames (a ``.bag`` file for ROS 1 bags), absolute once resolved.
        camera: intrinsics of ``tum``, ``7scenes``, ``replica`` entries (a preset by default); of
            ``bag`` entries only when the bag has no camera_info; None for ``scannet`` (read from
            its ``intrinsic/`` files) and ``synthetic`` (derived from ``params``).
        url: archive to download when ``path`` does not exist (``tum`` only).
        sha256: optional checksum of the archive.
        params: generator parameters for ``synthetic`` entries; the layout's options for
            recordings (``fps``, ``sequence``, ``rgb_topic``, ``depth_topic``, ``camera_info_topic``).
        source_file: registry file the entry came from.
        extends: a second visit: the name of the entry whose world this recording is localized in
            and mapped into (the ``revisit_bundle`` asset); that entry must be a first visit.
    """

    name: str
    kind: Literal["synthetic", "tum", "7scenes", "replica", "scannet", "bag"]
    path: Path
    camera: CameraIntrinsics | None = None
    url: str | None = None
    sha256: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    source_file: str = ""
    extends: str | None = None

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "kind": self.kind, "path": str(self.path)}
        if self.extends:
            d["extends"] = self.extends
        if self.camera is not None:
            d["camera"] = self.camera.to_dict()
        if self.url:
            d["url"] = self.url
        if self.params:
            d["params"] = dict(self.params)
        return d


def local_registry_path() -> Path:
    """The user's registry file: ``$ATLAS_LOCAL_REGISTRY``, else ``configs/datasets.local.yaml`` of
    the user-state folder (:func:`~atlas_pipeline.config.project_root`: the checkout, or
    ``$ATLAS_GS_HOME`` / the working directory for an installed package; never the package)."""
    env = os.environ.get(LOCAL_REGISTRY_ENV)
    return Path(env) if env else project_root() / "configs" / "datasets.local.yaml"


def registry_files() -> list[Path]:
    """The registry files in merge order (later entries override earlier ones): the built-in
    ``datasets.yaml`` (the checkout's ``configs/`` or the installed package's copy), then the local file.

    The local file may be absent (no local entries yet: ``dataset add`` creates it); a path that is
    there but no regular file (a folder, a FIFO) is a ConfigError naming it and where it was set,
    never read as "no local entries".
    """
    files = [configs_dir() / "datasets.yaml"]
    local = local_registry_path()
    problem = file_problem(local)
    if problem is None:
        files.append(local)
    elif problem != "not found":
        where = (f"{LOCAL_REGISTRY_ENV}={local}" if os.environ.get(LOCAL_REGISTRY_ENV)
                 else f"the local dataset registry {local}")
        example = local / "datasets.local.yaml" if problem == "is a directory" else "datasets.local.yaml"
        raise ConfigError(f"{where}: {problem}; it must name the registry's YAML file (such as {example}), "
                          "which `atlas-gs dataset add` creates")
    return files


def data_dir() -> Path:
    """Where downloaded and generated datasets live (``$ATLAS_DATA_DIR`` or ``<project>/data``)."""
    from atlas_pipeline.io_utils import env_folder

    env = os.environ.get("ATLAS_DATA_DIR")
    return env_folder("ATLAS_DATA_DIR", env) if env else project_root() / "data"


def bag_cache_root() -> Path:
    """Where bags are converted into TUM folders (``<data>/bag_imports``)."""
    return data_dir() / "bag_imports"


def camera_presets() -> dict[str, CameraIntrinsics]:
    """Every camera preset by name: TUM's (``freiburg1/2/3``, ``default``), ``7scenes``, ``replica``."""
    return {**TUM_CAMERAS, **CAMERA_PRESETS}


def default_camera_spec(kind: str) -> str | None:
    """The camera preset a recording of ``kind`` gets when none is given (None: read from the data)."""
    return KIND_CAMERA_PRESET.get(kind)


def resolve_camera(spec: Any, where: str) -> CameraIntrinsics:
    """A camera from a preset name (``freiburg1`` ..., ``7scenes``, ``replica``) or an inline mapping."""
    if isinstance(spec, str):
        key = spec.lower()
        key = {"fr1": "freiburg1", "fr2": "freiburg2", "fr3": "freiburg3"}.get(key, key)
        presets = camera_presets()
        if key not in presets:
            raise ConfigError(f"{where}: unknown camera preset {spec!r}; known: {sorted(presets)}")
        return presets[key]
    if isinstance(spec, dict):
        try:
            return CameraIntrinsics.from_dict(spec)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from exc
    raise ConfigError(f"{where}: camera must be a preset name or a mapping, got {spec!r}")


def camera_from_intrinsics(text: str, width: int, height: int, depth_scale: float,
                           where: str = "--intrinsics") -> dict[str, Any]:
    """An inline camera mapping from ``"fx fy cx cy"`` and the image size (checked: 4 finite numbers
    that describe a camera of that size, :class:`CameraIntrinsics`)."""
    parts = str(text).replace(",", " ").split()
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        vals = []
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"{where} needs 4 finite numbers (fx fy cx cy), got {text!r}")
    fx, fy, cx, cy = vals
    camera = {"width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy, "depth_scale": depth_scale}
    try:
        CameraIntrinsics.from_dict(camera)  # range and meaning checks, naming the field
    except ConfigError as exc:
        raise ConfigError(f"{where} {text!r} with a {width}x{height} image: {exc}") from None
    return camera


_SYNTH_KEYS = {"seed", "n_frames", "width", "height", "fx", "fy", "cx", "cy", "fps"} | {  # + sensor / motion model
    "orbit_rate_deg_per_s", "loop_revolutions", "pan_rate_deg_per_s", "shake_m", "shake_deg", "look_at_height_m",
    "depth_noise_a_m",
    "depth_noise_b_per_m", "depth_noise_angle_m", "depth_noise_corr_px", "inverse_depth_step_per_m",
    "depth_lateral_noise_px", "edge_dropout_prob", "projector_baseline_m", "dark_dropout_luma", "shiny_dropout_deg",
    "grazing_dropout_deg", "rgb_shift_x_px", "rgb_shift_y_px", "motion_blur_samples", "exposure_time_s",
    "exposure_drift", "white_balance_drift", "rgb_noise_std", "dropped_frame_rate", "colour_delay_s",
    "place", "route", "suite_speed_m_per_s", "light_level"}
_SYNTH_TEXT_KEYS = {"place"}  # the other synthetic keys are numbers


# Registry keys of each recording kind besides kind and path; camera: "preset" when it has a
# default preset, "optional" when only used as a fallback, absent when the data holds it.
_RECORDING_KEYS: dict[str, set[str]] = {
    "tum": {"camera", "url", "sha256"},
    "7scenes": {"camera", "sequence", "fps"},
    "replica": {"camera", "fps"},
    "scannet": {"fps"},
    "bag": {"camera", "rgb_topic", "depth_topic", "camera_info_topic"},
}
_TOPIC_RE = re.compile(r"^/?[A-Za-z0-9_~{}][A-Za-z0-9_/ {}~.-]{0,254}$")  # ROS topic names (+ RealSense's spaces)


def _entry_path(raw: dict, where: str) -> Path:
    try:
        path = Path(str(raw["path"])).expanduser()
    except RuntimeError as exc:  # "~user" of an unknown user
        raise ConfigError(f"{where}.path: {exc}") from None
    return path if path.is_absolute() else data_dir() / path


def _layout_params(kind: str, raw: dict, where: str) -> dict[str, Any]:
    params: dict[str, Any] = {}
    if "fps" in raw:
        v = raw["fps"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < v <= MAX_FPS):
            raise ConfigError(f"{where}.fps: must be a number in (0, {MAX_FPS:g}] (default {DEFAULT_FPS:g})")
        params["fps"] = float(v)
    if "sequence" in raw:
        v = raw["sequence"]
        if not (isinstance(v, str) and SEQUENCE_RE.match(v)):
            raise ConfigError(f"{where}.sequence: must name a seq-XX folder of the scene, got {v!r}")
        params["sequence"] = v
    for key in ("rgb_topic", "depth_topic", "camera_info_topic"):
        if key in raw:
            v = raw[key]
            if not (isinstance(v, str) and _TOPIC_RE.match(v)):
                raise ConfigError(f"{where}.{key}: must be a ROS topic name, got {v!r}")
            params[key] = v
    return params


def _parse_entry(name: str, raw: Any, source: Path) -> DatasetEntry:
    where = f"{source}: datasets.{name}"
    validate_dataset_name(name, f"{source}: datasets")  # a hand-edited registry: which file holds it
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: must be a mapping")
    if "extends" in raw:
        raw = dict(raw)
        extends = raw.pop("extends")
        if not isinstance(extends, str):
            raise ConfigError(f"{where}.extends: must be the name of another dataset, got {extends!r}")
        validate_dataset_name(extends, f"{where}.extends")
        if extends == name:
            raise ConfigError(f"{where}.extends: a dataset cannot extend its own world")
        return dataclasses.replace(_parse_entry(name, raw, source), extends=extends)
    bad_keys = [k for k in raw if not isinstance(k, str)]
    if bad_keys:
        raise ConfigError(f"{where}: keys must be names, got {bad_keys[0]!r}")
    if "path" in raw and not (isinstance(raw["path"], str) and raw["path"].strip() and "\0" not in raw["path"]):
        raise ConfigError(f"{where}.path: must be a non-empty folder path, got {raw['path']!r}")
    kind = raw.get("kind")
    if kind == "synthetic":
        unknown = set(raw) - {"kind", "path"} - _SYNTH_KEYS
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
        params = {k: raw[k] for k in _SYNTH_KEYS if k in raw}
        for k, v in params.items():
            if k in _SYNTH_TEXT_KEYS:
                if not isinstance(v, str):
                    raise ConfigError(f"{where}.{k}: must be a name, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"{where}.{k}: must be a number")
        path = Path(raw.get("path", name))
        path = path if path.is_absolute() else data_dir() / path
        return DatasetEntry(name, "synthetic", path, params=params, source_file=str(source))
    if kind in _RECORDING_KEYS:
        unknown = set(raw) - {"kind", "path"} - _RECORDING_KEYS[kind]
        if unknown:
            hint = " (scannet reads its camera from intrinsic/)" if kind == "scannet" and "camera" in unknown else ""
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} for kind {kind}{hint}")
        if "path" not in raw:
            raise ConfigError(f"{where}: 'path' is required")
        preset = default_camera_spec(kind)
        spec = raw.get("camera", preset)
        camera = resolve_camera(spec, f"{where}.camera") if spec is not None else None
        path = _entry_path(raw, where)
        url = raw.get("url")
        if url is not None and not (isinstance(url, str) and re.match(r"^https?://", url)):
            raise ConfigError(f"{where}.url: must be an http(s) URL")
        sha = raw.get("sha256")
        if sha is not None and not (isinstance(sha, str) and re.match(r"^[0-9a-f]{64}$", sha)):
            raise ConfigError(f"{where}.sha256: must be 64 lower-case hex digits")
        return DatasetEntry(name, kind, path, camera=camera, url=url, sha256=sha,
                            params=_layout_params(kind, raw, where), source_file=str(source))
    raise ConfigError(f"{where}: kind must be one of {['synthetic', *RECORDING_KINDS]}, got {kind!r}")


def load_registry(files: list[Path] | None = None) -> dict[str, DatasetEntry]:
    """Merge the registry files into ``{name: DatasetEntry}`` (insertion-ordered)."""
    entries: dict[str, DatasetEntry] = {}
    for path in files if files is not None else registry_files():
        data = load_yaml_file(path) or {}
        if not isinstance(data, dict) or not isinstance(data.get("datasets", {}), dict):
            raise ConfigError(f"{path}: expected a top-level 'datasets:' mapping")
        extra = set(data) - {"datasets"}
        if extra:
            raise ConfigError(f"{path}: unknown top-level key(s) {sorted(map(str, extra))}")
        for name, raw in (data.get("datasets") or {}).items():
            entries[str(name)] = _parse_entry(str(name), raw, path)
    for e in entries.values():
        if e.extends is None:
            continue
        where = f"{e.source_file}: datasets.{e.name}.extends"
        first = entries.get(e.extends)
        if first is None:
            raise ConfigError(f"{where}: no dataset named {e.extends!r} is registered")
        if first.extends is not None:
            raise ConfigError(f"{where}: {e.extends!r} is itself a second visit (it extends {first.extends!r}); "
                              f"name the first visit, {first.extends!r}")
    return entries


def revisits(entries: dict[str, DatasetEntry]) -> dict[str, str]:
    """``{second visit: first visit}`` of the entries with ``extends``."""
    return {e.name: e.extends for e in entries.values() if e.extends is not None}


def read_dataset_manifest(entry: DatasetEntry, max_frames: int | None = None, root: Path | None = None):
    """The :class:`~atlas_pipeline.sensors.tum.FrameManifest` of a registered recording (files on
    disk; synthetic entries are read as the TUM folder they are generated into)."""
    root = Path(root) if root is not None else entry.path
    if entry.kind == "synthetic":
        from atlas_pipeline.sensors.synthetic import SyntheticSpec
        from atlas_pipeline.sensors.tum import load_tum_sequence

        return load_tum_sequence(root, SyntheticSpec(**entry.params).camera(), entry.name, max_frames)
    return load_recording(entry.kind, root, entry.camera, entry.name, max_frames, entry.params,
                          bag_cache_root=bag_cache_root())


def check_dataset_folder(folder: Path, camera: CameraIntrinsics | None, name: str = "dataset", kind: str = "tum",
                         params: dict[str, Any] | None = None) -> None:
    """Check a recording whole before it is registered: its lists, poses and intrinsics parse,
    every image it uses exists with the camera's size and type (headers), and the first RGB-D
    frame decodes (a bag is converted here, once).

    Raises DatasetError naming the file (and line) at fault.
    """
    entry = DatasetEntry(name, kind, Path(folder), camera=camera, params=dict(params or {}))  # type: ignore[arg-type]
    manifest = read_dataset_manifest(entry)
    manifest.read_rgb(0)
    manifest.read_depth_m(0, allow_empty=True)


def register_local_dataset(
    name: str,
    path: str | Path,
    camera: str | dict[str, Any] | None = None,
    registry_path: Path | None = None,
    check: Callable[[DatasetEntry], None] | None = None,
    replace: bool = False,
    kind: str | None = None,
    params: dict[str, Any] | None = None,
) -> DatasetEntry:
    """Add a recording (a folder, or a ``.bag`` file) to the local registry file.

    ``kind`` is detected from the layout when not given (:func:`detect_kind`); ``camera`` defaults
    to the kind's preset (TUM ``default``, ``7scenes``, ``replica``; ScanNet and bags read theirs).
    ``params``: the kind's options (``fps``, ``sequence``, ``rgb_topic`` ...).

    A name that is already registered (a preset of ``configs/datasets.yaml`` or a local entry) is
    refused unless ``replace``. The whole recording is checked first (``check(entry)``, by default
    :func:`check_dataset_folder`) so a typo or a broken recording never becomes a partition that
    fails later. The registry file is rewritten atomically.
    """
    validate_dataset_name(name)
    reg = registry_path or local_registry_path()
    existing = load_registry([p for p in registry_files() if p != reg] + ([reg] if reg.is_file() else []))
    if name in existing and not replace:
        e = existing[name]
        raise ConfigError(f"dataset '{name}' is already registered ({e.kind} at {e.path}, from {e.source_file}); "
                          "choose another name, or pass --replace to re-point it")
    folder = Path(path).expanduser().resolve()
    if kind is None:
        if not folder.exists():
            raise DatasetError(folder, "dataset folder not found")
        kind = detect_kind(folder)
        if kind is None:
            raise DatasetError(folder, "cannot tell the layout (TUM: rgb.txt + depth.txt; 7-Scenes: "
                                       "frame-*.color.*; Replica: results/ + traj.txt; ScanNet: color/ depth/ "
                                       "pose/ intrinsic/; bag: *.bag or metadata.yaml + .db3/.mcap); give --kind")
        logger.info("%s: detected layout %s", folder, kind)
    if kind not in RECORDING_KINDS:
        raise ConfigError(f"kind must be one of {list(RECORDING_KINDS)}, got {kind!r}")
    entry_raw: dict[str, Any] = {"kind": kind, "path": str(folder)}
    if camera is not None:
        entry_raw["camera"] = camera
    elif default_camera_spec(kind) is not None:
        entry_raw["camera"] = default_camera_spec(kind)
    entry_raw.update({k: v for k, v in (params or {}).items() if v is not None})
    entry = _parse_entry(name, entry_raw, reg)  # validates camera and options before any frame is read
    if check is not None:
        check(entry)
    else:
        check_dataset_folder(folder, entry.camera, name, entry.kind, entry.params)
    data: dict[str, Any] = {"datasets": {}}
    if reg.is_file():
        loaded = load_yaml_file(reg) or {}
        if not isinstance(loaded, dict) or not isinstance(loaded.get("datasets") or {}, dict):
            raise ConfigError(f"{reg}: expected a top-level 'datasets:' mapping")
        data = {"datasets": dict(loaded.get("datasets") or {})}
    if name in existing:
        logger.warning("dataset '%s' re-pointed from %s to %s (--replace)", name, existing[name].path, folder)
    data["datasets"][name] = entry_raw
    header = "# Local datasets registered with `atlas-gs dataset add` (not tracked by git).\n"
    write_text_atomic(reg, header + yaml.safe_dump(data, sort_keys=False))
    logger.info("registered dataset %s (%s) -> %s in %s", name, kind, folder, reg)
    return entry


def dataset_on_disk(entry: DatasetEntry) -> bool:
    """Whether a run can build the entry without the network: a synthetic entry (generated on
    demand) or a recording whose files are on disk. Only these are offered as partitions."""
    return entry.kind == "synthetic" or recording_exists(entry.kind, entry.path)


def files_missing(entry: DatasetEntry) -> DatasetError:
    """The error for an entry whose recording is not on disk, with the commands that mend it: a
    preset's download, else putting the recording back or pointing the entry where it is now."""
    what = "is missing" if not os.path.lexists(entry.path) else f"is there but is not a {entry.kind} recording"
    if entry.url:
        fix = f"`atlas-gs dataset fetch {entry.name}` (or `atlas-gs run {entry.name}`) downloads them"
    else:
        fix = (f"put the recording back at {entry.path}, or register where it is now: "
               f"`atlas-gs dataset add {entry.name} PATH --replace`; then `atlas-gs status {entry.name}`")
    return DatasetError(entry.path, f"dataset '{entry.name}' is no partition: its files are not there "
                                    f"(the path {what}); {fix}")


def recording_bytes(entry: DatasetEntry) -> int:
    """Bytes of the entry's files on disk (its folder, followed into subfolders but not through
    links; a bag file's own size; 0 when absent): how much a run of it has to read, the estimate
    ``run --all`` starts the longest runs first by."""
    import os

    path = Path(entry.path)
    if path.is_file():
        return path.stat().st_size
    total, stack = 0, [path]
    while stack:
        try:
            with os.scandir(stack.pop()) as it:
                for e in it:
                    if e.is_dir(follow_symlinks=False):
                        stack.append(Path(e.path))
                    elif e.is_file(follow_symlinks=False):
                        total += e.stat(follow_symlinks=False).st_size
        except OSError:  # absent or unreadable: the run reports it, this is an estimate
            continue
    return total


def needs_download(entry: DatasetEntry) -> bool:
    """A download preset whose frames are not on disk yet (``atlas-gs dataset fetch`` makes them)."""
    return bool(entry.url) and not dataset_on_disk(entry)


def ensure_dataset_files(entry: DatasetEntry, log: Callable[[str], None] | None = None) -> Path:
    """Make the entry's frames exist on disk: generate synthetic data or download an archive."""
    log = log or logger.info
    if entry.kind == "synthetic":
        from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset

        spec = SyntheticSpec(**entry.params)
        return generate_synthetic_dataset(entry.path, spec)
    if recording_exists(entry.kind, entry.path):
        return entry.path
    if entry.url:
        from atlas_pipeline.sensors.download import download_tum_archive

        log(f"{entry.name}: not on disk yet, downloading {entry.url} into {entry.path}")
        if not entry.sha256:
            logger.warning("%s: no sha256 registered for %s; the download cannot be verified", entry.name, entry.url)
        return download_tum_archive(entry.url, entry.path, sha256=entry.sha256, log=log)
    raise DatasetError(entry.path, f"dataset folder of '{entry.name}' not found and no url to download it from")


def load_dataset(entry: DatasetEntry, cfg: PipelineConfig, log: Callable[[str], None] | None = None) -> FrameManifest:
    """The pipeline's first stage: make the dataset's files exist (generate / download) and read its
    frame manifest, whatever the layout (TUM, 7-Scenes, Replica, ScanNet, bag: ``entry.kind``)."""
    root = ensure_dataset_files(entry, log)
    return read_dataset_manifest(entry, cfg.dataset.max_frames, root)


# An --intrinsics camera's size and depth scale when neither the options nor the kind's preset give
# them: the VGA frame of every supported RGB-D sensor, depth in millimetres.
FALLBACK_WIDTH_PX = 640
FALLBACK_HEIGHT_PX = 480
FALLBACK_DEPTH_UNITS_PER_M = 1000.0
# What each layout looks like on disk, for the error that asks for --kind.
LAYOUT_HINTS = ("TUM: rgb.txt + depth.txt; 7-Scenes: frame-*.color.*; Replica: results/ + traj.txt; "
                "ScanNet: color/ depth/ pose/ intrinsic/; bag: *.bag or metadata.yaml + .db3/.mcap")
# A partition name derived from a folder or file name: at most this many characters.
MAX_DERIVED_NAME_CHARS = 64


def registered_entry(name: str, registry: dict[str, DatasetEntry] | None = None) -> DatasetEntry:
    """The registry entry called ``name``, or a ConfigError listing the registered names."""
    registry = load_registry() if registry is None else registry
    if name not in registry:
        raise ConfigError(f"dataset '{name}' is not registered; known: {', '.join(registry)}")
    return registry[name]


def registered_entries(names: list[str], registry: dict[str, DatasetEntry]) -> list[DatasetEntry]:
    """The entries of ``names`` (each a valid dataset name), or one ConfigError naming every unknown one."""
    names = [validate_dataset_name(n) for n in names]
    unknown = [n for n in names if n not in registry]
    if unknown:
        raise ConfigError(f"dataset(s) {', '.join(unknown)} not registered; known: {', '.join(registry)}")
    return [registry[n] for n in names]


def dataset_from_spec(spec: str, camera: str | None = None, camera_option: str = "--camera") -> DatasetEntry:
    """A registered dataset name, or the path of a recording (folder, or ``.bag`` file) whose layout
    is detected (TUM, 7-Scenes, Replica, ScanNet, bag), as an unregistered entry named after the
    path, with the kind's camera preset unless ``camera`` names one."""
    registry = load_registry()
    if spec in registry:
        return registry[spec]
    p = Path(spec).expanduser()
    if not p.exists():
        raise ConfigError(f"'{spec}' is neither a registered dataset ({', '.join(registry)}) nor a folder")
    kind = detect_kind(p)
    if kind is None:
        raise ConfigError(f"'{spec}' is not a recording of a known layout (TUM, 7-Scenes, Replica, ScanNet, bag); "
                          "register it with `atlas-gs dataset add NAME PATH --kind KIND`")
    stem = p.resolve().stem if p.is_file() else p.resolve().name
    name = "".join(c if c.isalnum() or c in "-_" else "-" for c in stem.lower())[:MAX_DERIVED_NAME_CHARS] or "dataset"
    spec_cam = camera or default_camera_spec(kind)
    return DatasetEntry(name=name.strip("-_") or "dataset", kind=kind, path=p.resolve(),  # type: ignore[arg-type]
                        camera=resolve_camera(spec_cam, camera_option) if spec_cam else None)


def recording_kind(path: Path, kind: str | None = None) -> str:
    """``kind`` when given, else the layout detected at ``path``; a DatasetError that lists the
    layouts when there is none to detect."""
    kind = kind or detect_kind(path)
    if kind is None:
        raise DatasetError(path, "not found" if not path.exists() else
                           f"cannot tell the layout ({LAYOUT_HINTS}); give --kind")
    return kind


def intrinsics_camera(kind: str, intrinsics: str, width_px: int | None = None, height_px: int | None = None,
                      depth_units_per_m: float | None = None) -> dict[str, Any]:
    """An inline camera from ``"fx fy cx cy"``: the image size and depth scale not given are the
    kind's preset's (a recording of that sensor), else the VGA / millimetre fallbacks."""
    for option, value in (("--width", width_px), ("--height", height_px)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value <= 0):
            raise ConfigError(f"{option} must be a positive whole number of pixels, got {value!r}")
    if depth_units_per_m is not None and not (math.isfinite(depth_units_per_m) and depth_units_per_m > 0):
        raise ConfigError(f"--depth-scale must be a finite positive number of raw depth units per metre (TUM "
                          f"5000, millimetres 1000), got {depth_units_per_m!r}")
    preset = default_camera_spec(kind)
    base = resolve_camera(preset, "--kind") if preset else None
    # "is None", not "or": a 0 given is an error above, never the default in disguise
    width = width_px if width_px is not None else (base.width if base else FALLBACK_WIDTH_PX)
    height = height_px if height_px is not None else (base.height if base else FALLBACK_HEIGHT_PX)
    scale = depth_units_per_m if depth_units_per_m is not None else (
        base.depth_scale if base else FALLBACK_DEPTH_UNITS_PER_M)
    return camera_from_intrinsics(intrinsics, width, height, scale)


def availability(entry: DatasetEntry) -> str:
    """Where the entry's frames stand: ``present``, ``generated on demand`` (synthetic),
    ``not fetched`` (a download preset) or ``MISSING``."""
    if entry.path.exists():
        return "present"
    if entry.kind == "synthetic":
        return "generated on demand"
    return "not fetched" if entry.url else "MISSING"


def not_on_disk_reason(entry: DatasetEntry) -> str:
    """Why an entry is no partition, with the command that mends it when there is one."""
    return f"not fetched (`atlas-gs dataset fetch {entry.name}`)" if entry.url else f"no files at {entry.path}"

"""``atlas-gs``: the command line over the library and the Dagster definitions.

It lives in the Dagster layer because ``run`` executes the Dagster job; the paper-style commands
only call ``atlas_pipeline``.

Paper-style commands (``build``, ``localize``, ``log-transitions``, ``demo-video``) call the library
directly on a world folder. ``run`` materializes every asset of a dataset partition through Dagster
(recorded in ``$DAGSTER_HOME``, default ``<project>/.dagster_home``, so the web UI shows it).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.config import PipelineConfig, load_profile, parse_set_overrides, project_root
from atlas_pipeline.errors import AtlasError, ConfigError, DatasetError
from atlas_pipeline.io_utils import check_output_dir, check_output_file, check_writable
from atlas_pipeline.geometry import pose_from_tq, tq_from_pose
from atlas_pipeline.sensors.camera import TUM_CAMERAS
from atlas_pipeline.sensors.registry import (
    DatasetEntry,
    camera_from_intrinsics,
    files_missing,
    load_dataset,
    load_registry,
    local_registry_path,
    recording_bytes,
    register_local_dataset,
    resolve_camera,
    validate_dataset_name,
)
# Imported with the module, as the stage functions always were: pandas then loads before logging is
# configured, so its import-time INFO lines stay out of the command's stderr.
from atlas_pipeline.transition_log.transitions import log_transitions

logger = logging.getLogger("atlas_gs.cli")

EXIT_ERROR = 2  # a clear error (bad input, refused output, failed write): nothing half-done was left
EXIT_INCOMPLETE = 3  # the command wrote its report but could not finish (e.g. frames not in this world)
# The reader of stdout went away (`atlas-gs dataset list | head -1`): 128 + SIGPIPE, the status a
# shell reports for any tool a closed pipe ended, and no message (the reader wanted no more).
EXIT_BROKEN_PIPE = 141

ASSET_ORDER = ["raw_dataset", "fused_frames", "keyframes", "gaussian_world", "localization_report",
               "transitions", "demo_videos", "render_evaluation", "world_bundle"]


# ---- output: one short log format, Dagster's chatter off unless -v, progress bars -------------------

# Third-party loggers that say nothing a user of atlas-gs needs, even with -v (numba's DEBUG lines
# alone are thousands a compile).
MUTED_LOGGERS = ("numba", "matplotlib", "PIL", "asyncio", "urllib3", "filelock", "fsspec", "grpc", "websockets",
                 "sqlalchemy")  # sqlalchemy: every SQL statement of the instance's database
# Dagster's own loggers and its database migrations': shown with -v only (instance notices, migration lines).
DAGSTER_LOGGERS = ("dagster", "alembic")
WARNINGS_LOGGER = "py.warnings"  # where logging.captureWarnings sends them (-v)
RUN_LOGGER = "atlas_gs.run"  # the CLI's view of Dagster run events (stage summaries; all events with -v)
# Loggers whose INFO lines the default (quiet) output keeps: the command's own.
QUIET_INFO_LOGGERS = ("atlas_gs.cli", RUN_LOGGER)
DAGSTER_META_ATTR = "dagster_meta"  # what Dagster's log manager attaches to the records it passes on
SECONDS_PER_MS = 1e-3


def _out(text: str) -> None:
    """A result on stdout, after any progress bar is cleared from the terminal."""
    from atlas_pipeline.progress import current_terminal

    term = current_terminal()
    if term is not None:
        term.clear()
    print(text, flush=True)


def _took(seconds: float) -> str:
    from atlas_pipeline.progress import format_duration

    return f"{seconds:.1f} s" if seconds < 60 else format_duration(seconds)


def _dagster_error(ev: Any) -> str:
    """The message of a failed step's error (the cause's, where the step wrapped one)."""
    err = getattr(ev.event_specific_data, "error", None)
    if err is None:
        return "failed"
    return (err.cause.message if err.cause else err.message).strip()


class _CliFormatter(logging.Formatter):
    """``message`` for INFO, ``warning: message`` otherwise; Dagster's records as
    ``step: message`` (``step EVENT: message`` for its events) instead of its 110-character prefix."""

    def __init__(self, verbose: bool):
        super().__init__()
        self.verbose = verbose

    def format(self, record: logging.LogRecord) -> str:
        text = getattr(record, "atlas_text", None)
        if text is None:
            meta = getattr(record, DAGSTER_META_ATTR, None)
            if isinstance(meta, dict) and "orig_message" in meta:
                ev = meta.get("dagster_event")
                text = str(meta["orig_message"])
                if ev is not None:
                    text = f"{ev.event_type_value}: {text}"
                    if ev.is_failure and self.verbose:
                        text += f": {_dagster_error(ev)}"
                if meta.get("step_key"):
                    text = f"{meta['step_key']}: {text}"
            else:
                text = record.getMessage()
        if record.exc_info and self.verbose:
            text += "\n" + self.formatException(record.exc_info)
        return text if record.levelno == logging.INFO else f"{record.levelname.lower()}: {text}"


class _CliHandler(logging.Handler):
    """Writes records below the progress bar (:class:`atlas_pipeline.progress.Terminal`); decides
    what the quiet default shows, and turns Dagster's step events into one line per stage."""

    def __init__(self, terminal: Any, verbose: bool, prefix: str = ""):
        super().__init__(logging.DEBUG)
        self.terminal = terminal
        self.verbose = verbose
        self.prefix = prefix
        self.setFormatter(_CliFormatter(verbose))
        self._reused: dict[str, bool] = {}
        self._warned: set[str] = set()

    def _shown(self, record: logging.LogRecord) -> bool:
        name = record.name
        if any(name == m or name.startswith(m + ".") for m in MUTED_LOGGERS) and record.levelno < logging.WARNING:
            return False
        meta = getattr(record, DAGSTER_META_ATTR, None)
        if isinstance(meta, dict) and meta.get("dagster_event") is not None:
            return self._dagster_event(record, meta["dagster_event"])
        if name == WARNINGS_LOGGER:
            # once each, on one line ("file:line: Category: message"; the source line left out),
            # however many times and from wherever Dagster raises it
            first = record.getMessage().strip().splitlines()[0] if record.getMessage().strip() else ""
            if first in self._warned:
                return False
            self._warned.add(first)
            record.atlas_text = first
            return True
        if self.verbose:
            return True
        if any(name == d or name.startswith(d + ".") for d in DAGSTER_LOGGERS):
            return record.levelno >= logging.ERROR  # instance notices and migrations: -v only
        if record.levelno >= logging.WARNING:
            return True
        return any(name == q or name.startswith(q + ".") for q in QUIET_INFO_LOGGERS) and not isinstance(meta, dict)

    def _dagster_event(self, record: logging.LogRecord, ev: Any) -> bool:
        """Dagster's events: all with -v; else a line per finished pipeline stage, a failed step,
        a failed check."""
        kind = ev.event_type_value
        if kind == "ASSET_MATERIALIZATION" and ev.asset_key is not None and len(ev.asset_key.path) == 1:
            reused = ev.event_specific_data.materialization.metadata.get("reused")
            self._reused[ev.asset_key.path[-1]] = bool(reused is not None and reused.value)
        if self.verbose:
            return True
        step = ev.step_key or ""
        if kind == "STEP_SUCCESS" and step in ASSET_ORDER:
            ms = getattr(ev.event_specific_data, "duration_ms", None)
            took = f"  {_took(ms * SECONDS_PER_MS)}" if ms is not None else ""
            record.atlas_text = f"{step:<20s} {'reused' if self._reused.get(step) else 'computed'}{took}"
            record.levelno, record.levelname = logging.INFO, "INFO"
            return True
        if kind == "STEP_FAILURE":
            record.atlas_text = f"{step} failed: {_dagster_error(ev)}"
            record.levelno, record.levelname = logging.ERROR, "ERROR"
            return True
        if kind == "ASSET_CHECK_EVALUATION" and not ev.event_specific_data.passed:
            d = ev.event_specific_data
            record.atlas_text = f"check {d.asset_key.to_user_string()}:{d.check_name} failed: {d.description or ''}".strip()
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            return True
        return False

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if self._shown(record):
                self.terminal.write_line(self.prefix + self.format(record))
        except Exception:  # noqa: BLE001 - logging must never break the command
            self.handleError(record)


class _CliOutput:
    """The command's stderr for the duration of ``main``: one handler on the root logger, levels of
    Dagster's and third-party loggers, warnings (ignored; with -v shown once, as log lines) and
    the progress terminal. Everything is restored on exit (``main`` may run many times in a process).
    ``prefix`` starts every line (a partition's name, when several run at once)."""

    def __init__(self, verbose: bool, prefix: str = ""):
        self.verbose = verbose
        self.prefix = prefix

    def __enter__(self) -> "_CliOutput":
        import warnings

        from atlas_pipeline.progress import Terminal, use_terminal

        self.terminal = Terminal(sys.stderr)
        self.handler = _CliHandler(self.terminal, self.verbose, self.prefix)
        root = logging.getLogger()
        self._levels = {n: logging.getLogger(n).level for n in ("", *MUTED_LOGGERS, *DAGSTER_LOGGERS, RUN_LOGGER)}
        root.setLevel(logging.DEBUG if self.verbose else logging.INFO)
        for n in MUTED_LOGGERS:
            logging.getLogger(n).setLevel(logging.WARNING)
        for n in DAGSTER_LOGGERS:
            logging.getLogger(n).setLevel(logging.DEBUG if self.verbose else logging.WARNING)
        logging.getLogger(RUN_LOGGER).setLevel(logging.DEBUG)  # step events are DEBUG: summaries need them
        root.addHandler(self.handler)
        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        # Dagster's BetaWarning / PreviewWarning / deprecations: nothing for a user to act on by default
        warnings.simplefilter("once" if self.verbose else "ignore")
        logging.captureWarnings(self.verbose)
        self._terminal_ctx = use_terminal(self.terminal)
        self._terminal_ctx.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._terminal_ctx.__exit__(None, None, None)
        logging.captureWarnings(False)
        self._warnings.__exit__(None, None, None)
        logging.getLogger().removeHandler(self.handler)
        for n, level in self._levels.items():
            logging.getLogger(n).setLevel(level)


def _run_logger_defs() -> dict[str, Any]:
    """The job's loggers for a run started by the CLI: Dagster's records go to the ``atlas_gs.run``
    logger (the CLI's format and filter) instead of Dagster's coloured console logger. The run's
    event log, which the web UI shows, is written by the instance either way."""
    from dagster import logger as dagster_logger

    @dagster_logger(description="atlas-gs command line: Dagster's records in the CLI's format")
    def atlas_cli(_init_context):
        return logging.getLogger(RUN_LOGGER)

    return {"console": atlas_cli}


def _config(args: argparse.Namespace) -> PipelineConfig:
    from assets.resources import resolve_profile

    cfg = load_profile(resolve_profile(args.profile))  # --profile, else $ATLAS_PROFILE, else default
    overrides = _overrides(args)
    return cfg.with_overrides(overrides, "--set") if overrides else cfg


def _dataset(spec: str, camera: str | None = None) -> DatasetEntry:
    """A registered dataset name, or the path of a recording (folder, or ``.bag`` file) whose
    layout is detected (TUM, 7-Scenes, Replica, ScanNet, bag), with the kind's camera preset
    unless ``camera`` names one."""
    from atlas_pipeline.sensors.registry import default_camera_spec, detect_kind

    registry = load_registry()
    if spec in registry:
        return registry[spec]
    p = Path(spec).expanduser()
    if p.exists():
        kind = detect_kind(p)
        if kind is None:
            raise ConfigError(f"'{spec}' is not a recording of a known layout (TUM, 7-Scenes, Replica, ScanNet, bag); "
                              "register it with `atlas-gs dataset add NAME PATH --kind KIND`")
        stem = p.resolve().stem if p.is_file() else p.resolve().name
        name = "".join(c if c.isalnum() or c in "-_" else "-" for c in stem.lower())[:64] or "dataset"
        spec_cam = camera or default_camera_spec(kind)
        return DatasetEntry(name=name.strip("-_") or "dataset", kind=kind, path=p.resolve(),  # type: ignore[arg-type]
                            camera=resolve_camera(spec_cam, "--camera") if spec_cam else None)
    raise ConfigError(f"'{spec}' is neither a registered dataset ({', '.join(registry)}) nor a folder")


def _default_dagster_home() -> Path:
    from assets.runs import prepare_dagster_home

    return prepare_dagster_home(project_root() / ".dagster_home")


# ---- commands ---------------------------------------------------------------------------------


def _prepare_output_dir(output: str, kind: str, inputs: list[Any], force: bool) -> Path:
    """Apply the output policy and check writability before any expensive work."""
    out = Path(output).expanduser()
    check_output_dir(out, kind, inputs, force)
    check_writable(out.parent)
    return out


def cmd_build(args: argparse.Namespace) -> int:
    from atlas_pipeline.localization.localizer import tracking_map
    from atlas_pipeline.mapping.mapper import build_gaussian_world, extend_saved_world, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.scene_memory.bundle import BUNDLE_KIND, load_world_bundle, parent_reference, write_world_bundle
    from atlas_pipeline.scene_memory.metadata import bundle_lineage, bundle_metadata

    cfg = _config(args)
    entry = _dataset(args.input, args.camera)
    inputs = [entry.path, args.extend]
    out = _prepare_output_dir(args.output, BUNDLE_KIND, inputs, args.force)
    if args.extend:
        load_world_bundle(args.extend)  # every listed file verified (world.npz, surfels.npz ...) before any work
    manifest = load_dataset(entry, cfg)
    fused = fuse(manifest, cfg)

    parent = None
    if args.extend:
        parent = parent_reference(args.extend)  # checks it is a bundle
        world, n_new_keyframes = extend_saved_world(args.extend, manifest, fused, cfg)
    else:
        keyframes = select_keyframes_stage(manifest, fused, cfg)
        world = build_gaussian_world(fused, keyframes, cfg, manifest=manifest)
        n_new_keyframes = len(keyframes.indices)
    lineage = bundle_lineage("atlas-gs build", partition=entry.name, run_id=None, profile=cfg.profile,
                             config_overrides=_overrides(args), parent=parent)
    meta = bundle_metadata(entry.name, entry.name, world, manifest, cfg, lineage)
    write_world_bundle(out, world.field, meta, extras=(world,), surfels=tracking_map(world), inputs=inputs)
    logger.info("wrote world with %d Gaussians to %s", len(world.field), out)
    _out(json.dumps({"world": str(out.resolve()), "n_gaussians": len(world.field),
                      "n_keyframes": int(n_new_keyframes), "map_id": world.map_id,
                      "parent": parent}, indent=2, default=str))
    return 0


def _start_pose(args: argparse.Namespace) -> np.ndarray | None:
    """``--start-pose`` as a ``T_world_cam``, or None; where localization then starts is
    :func:`atlas_pipeline.scene_memory.metadata.start_pose`'s decision."""
    if not args.start_pose:
        return None
    vals = _numbers(args.start_pose, 7, "--start-pose", "tx ty tz qx qy qz qw")
    if np.linalg.norm(vals[3:]) < 1e-9:
        raise ConfigError("--start-pose: the quaternion qx qy qz qw has zero length")
    return pose_from_tq(np.array(vals[:3]), np.array(vals[3:]))


def cmd_relocalize(args: argparse.Namespace) -> int:
    """Place single frames in a saved world with no initial pose; print pose, confidence and, where
    the dataset has ground truth, the error (meaningful when the world shares its frame)."""
    from atlas_pipeline.localization.places import place_index
    from atlas_pipeline.localization.relocalize import Relocalizer
    from atlas_pipeline.localization.tracker import RGBDTracker, pose_change
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle

    cfg = _config(args)
    bundle = load_world_bundle(args.world)
    manifest = load_dataset(_dataset(args.input, args.camera), cfg)
    frames = args.frame if args.frame else list(range(manifest.n_frames))
    bad = [i for i in frames if not 0 <= i < manifest.n_frames]
    if bad:
        raise ConfigError(f"--frame {bad[0]} is outside 0..{manifest.n_frames - 1}")
    voxel = float(bundle.metadata.get("gaussians", {}).get("voxel_size_m", cfg.mapping.voxel_size_m))
    tracker = RGBDTracker(manifest.camera, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m))
    model, priors = bundle.tracking_model(voxel), bundle_keyframe_poses(bundle.metadata)
    reloc = Relocalizer(tracker, model, priors, places=place_index(model, manifest.camera, tracker, priors))
    rows = []
    for i in frames:
        fp = tracker.prepare(manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True))
        r = reloc.relocalize_fast(fp)  # the place index first (milliseconds), the full search if it finds nothing
        if not r.ok:
            r = reloc.relocalize(fp)
        row: dict[str, Any] = {"frame": i, "timestamp_s": float(manifest.timestamps_s[i]), "ok": bool(r.ok),
                               "confidence": round(r.confidence, 4), "source": r.source,
                               "inlier_fraction": round(r.inlier_fraction, 4)}
        if np.isfinite(r.T_world_cam).all():
            t, q = tq_from_pose(r.T_world_cam)
            row.update({"position_xyz": [round(float(v), 6) for v in t], "quat_xyzw": [round(float(v), 6) for v in q]})
            if manifest.has_gt[i]:
                dt_m, dr_deg = pose_change(manifest.T_world_cam_gt[i], r.T_world_cam)
                row.update({"error_t_m": round(dt_m, 4), "error_rot_deg": round(dr_deg, 3)})
        rows.append(row)
        logger.info("frame %d: %s (confidence %.2f, from %s hypothesis)", i, "placed" if r.ok else "not placed",
                    r.confidence, r.source)
    _out(json.dumps({"world": str(Path(args.world).resolve()), "frames": rows,
                      "n_placed": sum(r["ok"] for r in rows)}, indent=2))
    return 0


def cmd_evaluate_trajectory(args: argparse.Namespace) -> int:
    """ATE and RPE of a TUM-format trajectory against ground truth (TUM's conventions)."""
    from atlas_pipeline.localization.metrics import evaluate_trajectories, read_tum_trajectory

    t_e, P = read_tum_trajectory(Path(args.estimated))
    t_g, G = read_tum_trajectory(Path(args.groundtruth))
    res = evaluate_trajectories(t_e, P, t_g, G, max_dt_s=args.max_dt, rpe_delta_s=args.delta)
    if res["n_matched"] < 3:
        raise ConfigError(f"only {res['n_matched']} poses of {args.estimated} have a ground-truth pose within "
                          f"{args.max_dt} s in {args.groundtruth}: nothing to evaluate")
    _out(json.dumps(res, indent=2))
    return 0


def cmd_localize(args: argparse.Namespace) -> int:
    from atlas_pipeline.localization.localizer import localize_sequence
    from atlas_pipeline.scene_memory.bundle import (
        bundle_keyframe_poses,
        check_bundle_update,
        load_world_bundle,
        update_world_bundle,
    )
    from atlas_pipeline.scene_memory.metadata import start_pose

    cfg = _config(args)
    bundle = load_world_bundle(args.world)  # verifies every file the bundle lists
    entry = _dataset(args.input, args.camera)
    # Whether the report may go into this bundle is known now, not after every frame is localized.
    check_bundle_update(args.world, entry.name, bundle.map_id, drop_transitions=args.drop_transitions,
                        meta=bundle.metadata)
    check_writable(Path(args.world).parent)
    manifest = load_dataset(entry, cfg)
    T0, anchor = start_pose(bundle.metadata, entry.name, _start_pose(args), relocalize=args.relocalize)
    if anchor >= manifest.n_frames:
        raise ConfigError(f"anchor frame {anchor} is beyond the {manifest.n_frames} frames loaded")
    voxel = float(bundle.metadata.get("gaussians", {}).get("voxel_size_m", cfg.mapping.voxel_size_m))
    # The world's own recording is never a mismatch (the world was built from it), as in the graph.
    own = bundle.metadata.get("dataset", {}).get("name") == entry.name
    report = localize_sequence(manifest, bundle.tracking_model(voxel), cfg.localization,
                               T0, anchor, bundle.map_id, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
                               prior_poses=bundle_keyframe_poses(bundle.metadata), stop_on_mismatch=not own)
    update_world_bundle(args.world, localization=report, drop_transitions=args.drop_transitions)
    _out(json.dumps({"world": str(Path(args.world).resolve()), **{  # to_json: unknown numbers are null
        k: (round(v, 6) if isinstance(v, float) else v) for k, v in report.to_json()["summary"].items()}}, indent=2))
    if report.summary.get("outcome", "complete") != "complete":
        # The report (what was tried, what failed) is in the bundle; the command itself failed.
        logger.error("%s", report.summary.get("stopped_reason") or "localization stopped early")
        return EXIT_INCOMPLETE
    return 0


def cmd_log_transitions(args: argparse.Namespace) -> int:
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import check_bundle_update, update_world_bundle, verify_bundle_files

    cfg = _config(args)
    world = Path(args.world)
    meta = verify_bundle_files(world)
    if not (world / "localization.json").is_file():
        raise ConfigError(f"{world}: no localization.json; run `atlas-gs localize --world {world} --input {args.input}` first")
    report = LocalizationReport.load(world)
    entry = _dataset(args.input, args.camera)
    if report.dataset != entry.name:
        raise ConfigError(f"{world}/localization.json is for dataset '{report.dataset}', not '{entry.name}'")
    check_bundle_update(world, transitions_of={"dataset": entry.name, "map_id": report.map_id}, meta=meta)
    if cfg.transitions.pose_source == "ground_truth":  # refresh GT from the dataset, not the report
        manifest = load_dataset(entry, cfg)
        report.T_world_cam_gt = manifest.T_world_cam_gt
    table = log_transitions(report, entry.name, int(meta.get("n_gaussians", 0)), cfg)
    update_world_bundle(world, transitions=table)
    _out(json.dumps({"transitions": str((world / "transitions.parquet").resolve()), "rows": table.num_rows}, indent=2))
    return 0


def cmd_demo_video(args: argparse.Namespace) -> int:
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import load_world_bundle
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    from atlas_pipeline.viz.demo import orbit_trajectory, render_video
    from atlas_pipeline.viz.video import is_atlas_video

    cfg = _config(args)
    out = Path(args.output).expanduser()
    if out.suffix.lower() != ".mp4":
        raise ConfigError(f"--output {args.output}: demo videos are MP4 files; give a name ending in .mp4")
    check_output_file(out, [args.world], args.force, is_ours=is_atlas_video)
    check_writable(out.parent)
    bundle = load_world_bundle(args.world)
    dataset = bundle.metadata.get("dataset") or {}
    cam = CameraIntrinsics.from_dict(dataset["camera"]) if "camera" in dataset else TUM_CAMERAS["default"]
    if args.mode == "trajectory":
        if not (Path(args.world) / "localization.json").is_file():
            raise ConfigError(f"{args.world}: trajectory mode needs localization.json; run `atlas-gs localize` first")
        poses = LocalizationReport.load(Path(args.world)).T_world_cam
        poses = poses[np.isfinite(poses).all(axis=(1, 2))]  # frames never placed have no pose to render from
        if len(poses) == 0:
            raise ConfigError(f"{args.world}/localization.json: no frame was placed in this world; nothing to render")
    else:
        from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses

        # framed from where the recording camera stood (the bundle's keyframes)
        poses = orbit_trajectory(bundle.field, cfg, bundle_keyframe_poses(bundle.metadata), camera_K=cam.K,
                                 image_size=(cam.width, cam.height))
    render_video(bundle.field, poses, cam.K, cam.width, cam.height, cfg, out, args.mode)
    _out(json.dumps({"video": str(out.resolve()), "mode": args.mode}, indent=2))
    return 0


def _numbers(text: str, n: int, option: str, names: str) -> list[float]:
    """``n`` finite numbers from a space-separated option value, or a ConfigError naming the option."""
    parts = str(text).replace(",", " ").split()
    if len(parts) != n:
        raise ConfigError(f"{option} needs {n} numbers ({names}), got {len(parts)}: {text!r}")
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        raise ConfigError(f"{option} needs {n} numbers ({names}), got {text!r}") from None
    if not all(np.isfinite(vals)):
        raise ConfigError(f"{option}: every number must be finite, got {text!r}")
    return vals


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    return parse_set_overrides(getattr(args, "set", None), "--set")


def _dagster_setup(args: argparse.Namespace):
    """DAGSTER_HOME, the definitions for the run's profile (``--profile``, else ``$ATLAS_PROFILE``,
    else ``default``), the validated ``--set`` overrides, the instance, the partitions to run
    (registered datasets on disk: the definitions' partitions, read from the registry here)."""
    _default_dagster_home()
    from dagster import DagsterInstance

    from assets.definitions import build_definitions, loaded_partitions
    from assets.resources import atlas_config
    from assets.runs import reap_dead_runs

    overrides = _overrides(args)
    atlas = atlas_config(args.profile, overrides)  # the whole config validated: bad keys fail here, naming the key
    registry = load_registry()
    partitions = list(registry) if getattr(args, "all", False) else [validate_dataset_name(args.dataset)]
    for p in partitions:
        if p not in registry:
            raise ConfigError(f"dataset '{p}' is not registered; known: {', '.join(registry)}")
    if getattr(args, "func", None) is cmd_run:  # `status` only reads; a run fetches what it needs first
        partitions = [p for p in partitions if _fetch(registry[p], skip_on_error=getattr(args, "all", False))]
    defs = build_definitions(profile=args.profile)
    loaded = set(loaded_partitions(defs))
    for p in [p for p in partitions if p not in loaded]:  # not on disk: a preset not fetched, files gone
        missing = files_missing(registry[p])
        if not getattr(args, "all", False):
            raise missing
        logger.warning("%s left out: %s", p, missing)
    partitions = [p for p in partitions if p in loaded]
    instance = DagsterInstance.get()
    reap_dead_runs(instance)  # runs left STARTED by a killed process are marked failed
    return defs, instance, partitions, atlas, overrides


def _fetch(entry: DatasetEntry, skip_on_error: bool = False) -> bool:
    """Download a preset whose frames are not on disk (with a progress bar), so that it can become a
    partition before its run; True when the entry's data is there now. ``skip_on_error``
    (``--all``): a failed download is a warning and the dataset is left out, not the end of the command."""
    from atlas_pipeline.errors import DatasetError
    from atlas_pipeline.sensors.registry import ensure_dataset_files, needs_download

    if not needs_download(entry):
        return True
    try:
        ensure_dataset_files(entry)
    except DatasetError as exc:
        if not skip_on_error:
            raise
        logger.warning("%s left out: %s", entry.name, exc)
        return False
    logger.info("%s: downloaded into %s", entry.name, entry.path)
    return True


def run_request(profile: str, overrides: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """Run config and tags of a run with ``--set`` ``overrides``: the overrides as the ``atlas``
    resource's config (the other fields keep the profile's values) and as tags ``atlas/set/KEY``."""
    config: dict[str, Any] = {}
    for dotted, value in overrides.items():
        section, key = dotted.split(".", 1)
        config.setdefault(section, {})[key] = list(value) if isinstance(value, tuple) else value
    tags = {"atlas/profile": profile, **{f"atlas/set/{k}": json.dumps(v) for k, v in overrides.items()}}
    return ({"resources": {"atlas": {"config": config}}} if config else {}), tags


def cmd_run(args: argparse.Namespace) -> int:
    """Materialize the assets of one or more partitions through Dagster (all, or only stale ones).

    JSON output (``--json``, or stdout not a terminal) is one document: the partition's summary
    object, or with ``--all`` a list of them in registry order (``[]`` when nothing was run)."""
    from assets.definitions import artifacts_root
    from assets.runs import compute_log_mirrors_detached
    from assets.staleness import stale_assets, stale_selection

    defs, instance, partitions, atlas, overrides = _dagster_setup(args)
    asked = getattr(args, "concurrency", None)
    if asked is not None and asked < 1:
        raise ConfigError(f"--concurrency must be at least 1, got {asked}")
    concurrency = min(asked or default_concurrency(), len(partitions))
    if concurrency > 1:  # --all: several partitions at a time, each run in its own process
        return _run_concurrently(args, partitions, concurrency)
    # Dagster's records in the CLI's format (quiet by default); the run log in the UI is unchanged
    job = defs.resolve_job_def("atlas_gs_all").with_logger_defs(_run_logger_defs())
    run_config, tags = run_request(atlas.profile, overrides)
    run_config = {**run_config, "loggers": {"console": {}}}  # a logger runs only when the run config names it
    failed = 0
    as_json, many = _json_output(args), bool(getattr(args, "all", False))
    docs: list[dict[str, Any]] = []  # --all --json: every partition's summary, printed as one list

    def report(summary: dict[str, Any], words: str) -> None:
        if as_json and many:
            docs.append(summary)
        else:
            _out(json.dumps(summary, indent=2) if as_json else words)

    for p in first_visits_first(partitions, load_registry()):
        root = artifacts_root()
        selection = None
        if args.stale_only:
            stale = stale_assets(defs, instance, p, atlas)
            for a, reasons in stale.items():
                logger.info("%s [%s] stale: %s", a, p, "; ".join(reasons))
            if not stale:
                current = {"partition": p, "stale": [], "ran": False}
                if (root / "world_bundle" / p / "metadata.json").is_file():  # only a path that exists
                    current["world_bundle"] = str(root / "world_bundle" / p)
                report(current, f"{p}: all {len(ASSET_ORDER)} assets current, nothing to run"
                       + (f"\n  world bundle  {current['world_bundle']}" if "world_bundle" in current else ""))
                continue
            selection = stale_selection(stale)
        try:
            with compute_log_mirrors_detached():  # Ctrl-C reaches the run, which stops them, not them
                result = _execute_partition(args, job, defs, instance, p, selection, run_config, tags)
        finally:
            defs.resources["artifact_io"].unlock_partition(p)
        summary = {"partition": p, "success": result.success, "run_id": result.run_id, **ran(result)}
        # Only paths that exist (a failed run must not point at output it did not write).
        bundle_dir = root / "world_bundle" / p
        if (bundle_dir / "metadata.json").is_file():
            summary["world_bundle"] = str(bundle_dir)
        if (bundle_dir / "transitions.parquet").is_file():
            summary["transitions"] = str(bundle_dir / "transitions.parquet")
        summary["videos"] = [str(x) for x in sorted((root / "demo_videos" / p).glob("*.mp4"))]
        if args.stale_only:
            summary["stale"] = sorted(stale)
        loc_path = root / "localization_report" / p / "localization.json"
        if result.success and loc_path.is_file():
            loc = json.loads(loc_path.read_text())["summary"]
            summary["localization"] = {k: loc.get(k) for k in ("n_tracked", "n_lost", "n_relocalized", "ate_rmse_m", "rpe_trans_rmse_m_per_s")}
        if not result.success:
            failed += 1
            for ev in result.all_events:
                if ev.is_failure and ev.step_key:
                    err = ev.event_specific_data.error if hasattr(ev.event_specific_data, "error") else None
                    summary.setdefault("errors", []).append(
                        f"{ev.step_key}: {err.cause.message.strip() if err and err.cause else (err.message.strip() if err else 'failed')}")
            for ev in result.all_events:
                if ev.event_type_value == "ASSET_CHECK_EVALUATION" and not ev.event_specific_data.passed:
                    d = ev.event_specific_data
                    summary.setdefault("failed_checks", []).append(
                        f"{d.asset_key.to_user_string()}:{d.check_name}: {d.description or ''}".strip())
        report(summary, _run_words(summary))
    if as_json and many:
        _out(json.dumps(docs, indent=2))
    return 1 if failed else 0


# ---- run: partitions in parallel, steps on another executor (README "Parallel and distributed runs")

MAX_DEFAULT_CONCURRENCY = 4  # default --concurrency: the cores, at most this (each run holds a sequence)
NUMBA_THREADS_ENV = "NUMBA_NUM_THREADS"


def default_concurrency() -> int:
    return max(1, min(os.cpu_count() or 1, MAX_DEFAULT_CONCURRENCY))


def _execute_partition(args: argparse.Namespace, job, defs, instance, p: str, selection, run_config, tags):
    """One partition's run on the chosen executor (``--executor``, else ``$ATLAS_EXECUTOR``): in this
    process (the default), or with steps in other processes (multiprocess, Dask) through Dagster's
    ``execute_job`` on a job each step process rebuilds; then this process holds the partition lock
    for the whole run and is the process the run is tagged with."""
    from assets.definitions import executor_name
    from assets.resources import resolve_profile
    from assets.runs import launcher_tags

    chosen = executor_name(getattr(args, "executor", None))
    tags = {**tags, **launcher_tags()}
    if chosen == "in_process":
        return job.execute_in_process(partition_key=p, instance=instance, raise_on_error=False,
                                      asset_selection=selection, run_config=run_config, tags=tags)
    from dagster import build_reconstructable_job, execute_job

    store = defs.resources["artifact_io"]
    store.hold_partition(p, f"atlas-gs run (pid {os.getpid()}, executor {chosen})")
    recon = build_reconstructable_job("assets.definitions", "atlas_gs_all_job", reconstructable_kwargs={
        "artifacts_dir": store.root, "profile": resolve_profile(args.profile), "executor": chosen,
        "dask_scheduler": getattr(args, "dask_scheduler", None)})
    return execute_job(recon, instance, run_config=run_config, tags={**tags, "dagster/partition": p},
                       asset_selection=selection)


class _Captured:
    """A worker's stdout: kept to be printed by the parent in partition order; a terminal when the
    parent's is (so the output format is the parent's)."""

    def __init__(self, tty: bool):
        import io

        self._buf, self._tty = io.StringIO(), tty

    def write(self, text: str) -> int:
        return self._buf.write(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self._tty

    def getvalue(self) -> str:
        return self._buf.getvalue()


def worker_start_method() -> str:
    """How ``--all`` starts its workers: ``fork`` on Linux while this process has not started
    Numba's parallel runtime, so each worker starts with the parent's imports (Dagster and the
    command line: about 3 s of CPU a worker otherwise); else ``spawn``. GNU OpenMP, Numba's threading
    layer here, cannot be used in a child forked after the parent used it, and ``atlas-gs run
    --all`` only reaches the pool before any kernel has run unless it generated a dataset first.
    The threads the parent does hold (OpenBLAS's, Arrow's pool and jemalloc's) re-initialise after
    a fork through their own at-fork handlers."""
    import multiprocessing

    if not sys.platform.startswith("linux") or "fork" not in multiprocessing.get_all_start_methods():
        return "spawn"
    numba_parallel = sys.modules.get("numba.np.ufunc.parallel")
    started = numba_parallel is not None and getattr(numba_parallel, "_is_initialized", True)
    return "spawn" if started else "fork"


class _CoreShare:
    """A pool worker's share of the cores now: all of them divided among the runs still going
    (``unfinished``, a counter in shared memory that each worker lowers when a run ends), so the
    last runs get the cores the finished ones left instead of leaving them idle."""

    def __init__(self, unfinished, concurrency: int, cores: int):
        self.unfinished, self.concurrency, self.cores = unfinished, concurrency, cores

    def __call__(self) -> int:
        running = max(1, min(self.concurrency, self.unfinished.value))
        return max(1, self.cores // running)


_POOL_SHARE: _CoreShare | None = None  # set in a pool worker whose kernels follow the share


def _init_worker(share: _CoreShare | None) -> None:
    """A pool worker's start: its kernels follow ``share`` (None: ``$NUMBA_NUM_THREADS`` as set)."""
    global _POOL_SHARE
    _POOL_SHARE = share
    if share is not None:
        from atlas_pipeline.cores import kernel_threads, use_core_share

        use_core_share(share)
        kernel_threads()  # before any kernel: the stages before the first rasterizer call too


def _run_in_worker(args: argparse.Namespace, tty: bool) -> tuple[int, str]:
    """``atlas-gs run`` of one partition in a pool process: (exit code, its stdout)."""
    import contextlib

    from assets.runs import interrupts_end_the_command

    root = logging.getLogger()
    for inherited in [h for h in root.handlers if isinstance(h, _CliHandler)]:
        root.removeHandler(inherited)  # a forked worker's copy of the parent's: every line twice
    out = _Captured(tty)
    with _CliOutput(args.verbose, prefix=f"{args.dataset}: "), contextlib.redirect_stdout(out):
        try:
            if _POOL_SHARE is not None:
                from atlas_pipeline.cores import kernel_threads

                kernel_threads()  # this run's share from its start
            with interrupts_end_the_command(say=False):  # Ctrl-C reaches the whole group: the parent says it
                code = int(cmd_run(args) or 0)
        except AtlasError as exc:
            logger.error("%s", exc)
            code = EXIT_ERROR
        finally:
            if _POOL_SHARE is not None:
                with _POOL_SHARE.unfinished.get_lock():
                    _POOL_SHARE.unfinished.value -= 1
    return code, out.getvalue()


def first_visits_first(partitions: list[str], registry) -> list[str]:
    """``partitions`` in their order, except that a second visit (registry ``extends``) runs after
    the first visit it extends when both are in the list."""
    chosen = set(partitions)
    return sorted(partitions, key=lambda p: registry[p].extends in chosen)


def longest_first(sizes: list[int]) -> list[int]:
    """Indices of ``sizes`` largest first, ties in their order: with more partitions than workers,
    a long recording started last would run on alone at the end (longest processing time first,
    the classic list-scheduling rule)."""
    return sorted(range(len(sizes)), key=lambda k: -sizes[k])


def _run_concurrently(args: argparse.Namespace, partitions: list[str], concurrency: int) -> int:
    """Up to ``concurrency`` partitions at a time, each an ordinary Dagster run (recorded in
    ``$DAGSTER_HOME``) in a worker process of a bounded pool; results printed in partition order.
    Each worker's kernels get its share of the cores, re-read as runs end (:class:`_CoreShare`;
    unless ``$NUMBA_NUM_THREADS`` is set), so parallel runs do not oversubscribe them and the
    last ones use the cores the others left. The largest recordings start first (:func:`longest_first`)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    logger.info("running %d partitions, %d at a time", len(partitions), concurrency)
    tty = sys.stdout.isatty()
    jobs = [argparse.Namespace(**{**vars(args), "all": False, "dataset": p, "concurrency": 1}) for p in partitions]
    registry = load_registry()
    order = longest_first([recording_bytes(registry[p]) for p in partitions])
    # The library's modules are not imported here first: the workers import what their stages
    # need at the same time, on both cores, where importing them here would run alone (four
    # partitions finished 0.5-1 s sooner without it, timed with benchmarks/bench_parallel.py's runs).
    from assets.definitions import executor_name

    context = multiprocessing.get_context(worker_start_method())
    cores = os.cpu_count() or 1
    user_set = bool(os.environ.get(NUMBA_THREADS_ENV))
    in_process = executor_name(getattr(args, "executor", None)) == "in_process"
    # Each worker's kernels use the cores divided among the runs still going (unless the user set
    # $NUMBA_NUM_THREADS): no oversubscription while the pool is full, no idle core at its end.
    share = _CoreShare(context.Value("i", len(jobs)), concurrency, cores) if in_process and not user_set else None
    # Steps run in other processes (--executor multiprocess) read a fixed share from the environment.
    fixed = not in_process and not user_set
    if fixed:
        os.environ[NUMBA_THREADS_ENV] = str(max(1, cores // concurrency))
    worst = 0
    as_json = _json_output(args)
    docs: list[dict[str, Any]] = []  # JSON: the workers' summaries, printed as one list (as a serial --all)
    try:
        with ProcessPoolExecutor(max_workers=concurrency, mp_context=context, initializer=_init_worker,
                                 initargs=(share,)) as pool:
            # A second visit extends its first visit's world: it starts once that run has ended.
            first_of = {k: partitions.index(registry[p].extends) for k, p in enumerate(partitions)
                        if registry[p].extends in partitions}
            futures = {k: pool.submit(_run_in_worker, jobs[k], tty) for k in order if k not in first_of}
            for k in (k for k in order if k in first_of):
                futures[first_of[k]].result()
                futures[k] = pool.submit(_run_in_worker, jobs[k], tty)
            for k in range(len(jobs)):  # results in partition order
                code, text = futures[k].result()
                if as_json:
                    docs.append(_worker_summary(partitions[k], code, text))
                elif text:
                    sys.stdout.write(text)
                    sys.stdout.flush()
                worst = max(worst, code)
    finally:
        if fixed:
            os.environ.pop(NUMBA_THREADS_ENV, None)
    if as_json:
        _out(json.dumps(docs, indent=2))
    return worst


def _worker_summary(partition: str, code: int, text: str) -> dict[str, Any]:
    """A pool worker's JSON summary of its partition; one saying it failed when the worker printed
    none (an error before its run, logged on stderr)."""
    try:
        doc = json.loads(text)
    except ValueError:
        doc = None
    if isinstance(doc, dict):
        return doc
    return {"partition": partition, "success": False, "exit_code": code,
            "errors": ["no summary: see the log on stderr"], **({"output": text} if text.strip() else {})}


def _json_output(args: argparse.Namespace) -> bool:
    """JSON for ``--json``, and for a stdout that is not a terminal (scripts, pipes: the output
    ``run`` always had); words for a person at a terminal."""
    return bool(getattr(args, "json", False)) or not sys.stdout.isatty()


def _run_words(summary: dict[str, Any]) -> str:
    """A run's result for a person: what ran, the outputs that exist (marked when an earlier run
    wrote them), errors and failed checks."""
    p, ok = summary["partition"], summary["success"]
    done = set(summary.get("recomputed", [])) | set(summary.get("reused", []))
    head = (f"{p}: {len(summary.get('recomputed', []))} assets computed, {len(summary.get('reused', []))} reused"
            if ok else f"{p}: run failed")
    lines = [f"{head} (run {summary['run_id']})"]
    outputs = [("world bundle", summary.get("world_bundle"), "world_bundle"),
               ("transitions", summary.get("transitions"), "transitions"),
               *[("video", v, "demo_videos") for v in summary.get("videos", [])]]
    for label, path, asset in outputs:
        if path:
            earlier = "" if asset in done else "  (from an earlier run)"
            lines.append(f"  {label:<13s} {path}{earlier}")
    loc = summary.get("localization")
    if loc:
        ate = loc.get("ate_rmse_m")
        lines.append(f"  localization  {loc.get('n_tracked')} tracked, {loc.get('n_lost')} lost, "
                     f"{loc.get('n_relocalized')} relocalized" + (f", ATE {ate * 1000:.1f} mm" if ate is not None else ""))
    lines += [f"  error: {e}" for e in summary.get("errors", [])]
    lines += [f"  failed check: {c}" for c in summary.get("failed_checks", [])]
    return "\n".join(lines)


def ran(result) -> dict[str, list[str]]:
    """``recomputed`` and ``reused`` pipeline assets of a run (settings/* and observations left out)."""
    out: dict[str, list[str]] = {"recomputed": [], "reused": []}
    for ev in result.all_events:
        if ev.event_type_value == "ASSET_MATERIALIZATION" and len(ev.asset_key.path) == 1:
            md = ev.event_specific_data.materialization.metadata
            out["reused" if md.get("reused") is not None and md["reused"].value else "recomputed"].append(
                ev.asset_key.path[-1])
    return {k: sorted(v) for k, v in out.items()}


def cmd_status(args: argparse.Namespace) -> int:
    """Print which assets of the partition(s) are stale or missing, and why; runs nothing."""
    from assets.staleness import stale_assets

    defs, instance, partitions, atlas, _ = _dagster_setup(args)
    stale = {p: stale_assets(defs, instance, p, atlas) for p in partitions}
    # The run that recomputes them: the same partition, profile and overrides as this status
    options = "".join(f" {o} {shlex.quote(v)}" for o, vs in (("--profile", [args.profile] if args.profile else []),
                                                            ("--set", args.set or [])) for v in vs)
    _out(json.dumps(stale, indent=2) if args.json else "\n".join(_status_words(p, s, options) for p, s in stale.items()))
    return 0


def _status_words(partition: str, stale: dict[str, list[str]], options: str = "") -> str:
    """``synthetic: all 9 assets current``, or the stale / missing assets in pipeline order with why
    and the command that recomputes them (``options``: the profile and overrides status was given)."""
    if not stale:
        return f"{partition}: all {len(ASSET_ORDER)} assets current"
    lines = [f"{partition}: {len(stale)} of {len(ASSET_ORDER)} assets would be recomputed "
             f"(`atlas-gs run {partition} --stale-only{options}` runs them)"]
    width = max(len(a) for a in stale)
    for asset in sorted(stale, key=lambda a: ASSET_ORDER.index(a) if a in ASSET_ORDER else len(ASSET_ORDER)):
        lines.append(f"  {asset:<{width}s}  {'; '.join(stale[asset])}")
    return "\n".join(lines)


def cmd_import_ply(args: argparse.Namespace) -> int:
    """A Gaussian-splat PLY made elsewhere (3DGS layout) as a world bundle this pipeline can
    localize in, relocalize against, render and extend."""
    from atlas_pipeline.scene_memory.bundle import BUNDLE_KIND, write_world_bundle
    from atlas_pipeline.scene_memory.metadata import bundle_lineage
    from atlas_pipeline.scene_memory.ply import read_gaussian_ply

    if not (np.isfinite(args.voxel) and args.voxel > 0):
        raise ConfigError(f"--voxel must be a finite number > 0, got {args.voxel}")
    src = Path(args.ply)
    _prepare_output_dir(args.output, BUNDLE_KIND, [src], args.force)
    field = read_gaussian_ply(src)  # refuses missing properties, NaN/inf, short files
    meta = {
        "name": src.stem, "partition": None,
        "dataset": None,
        "gaussians": {"voxel_size_m": float(args.voxel), "isotropic": field.is_isotropic, "n_keyframes": 0,
                      "pose_source": "imported"},
        "imported_from": {"path": str(src.resolve()), "bytes": src.stat().st_size},
        "lineage": bundle_lineage("atlas-gs import-ply"),
    }
    out = write_world_bundle(args.output, field, meta, inputs=[src])
    _out(json.dumps({"world": str(Path(out).resolve()), "n_gaussians": len(field),
                      "anisotropic": not field.is_isotropic}, indent=2))
    return 0


def _world_folder(spec: str) -> Path:
    """A bundle folder, or the name of a partition whose Dagster world bundle is on disk."""
    target = Path(spec).expanduser()
    if target.is_dir():
        return target
    from assets.io_managers import artifacts_root

    try:
        name = validate_dataset_name(spec)
    except AtlasError:
        raise ConfigError(f"'{spec}' is neither a bundle folder nor a partition with a world bundle "
                          "(no such folder)") from None
    target = artifacts_root() / "world_bundle" / name
    if not target.is_dir():
        raise ConfigError(f"'{spec}' is neither a bundle folder nor a partition with a world bundle "
                          f"(looked in {target})")
    return target


def cmd_export(args: argparse.Namespace) -> int:
    """A world for other tools: a COLMAP model or nerfstudio transforms.json with the frames (GPU
    trainers), a TSDF mesh, or a ROS occupancy grid; the library decides what and how."""
    from atlas_pipeline.interop.exports import DEFAULT_POSES, check_format, write_export
    from atlas_pipeline.interop.frames import check_frame_step, check_pose_source, source_from_bundle
    from atlas_pipeline.interop.mesh import check_voxel
    from atlas_pipeline.interop.occupancy import check_resolution

    fmt = check_format(args.format)
    poses = check_pose_source(args.poses or DEFAULT_POSES[fmt])
    step = check_frame_step(args.frame_step)
    check_voxel(args.voxel)
    check_resolution(args.resolution)
    world = _world_folder(args.world)
    dataset = _dataset(args.input, args.camera) if args.input else None
    _prepare_output_dir(args.output, "export", [world, dataset.path if dataset else None], args.force)
    src = source_from_bundle(world, poses, dataset, step)
    summary = write_export(args.output, src, fmt, args.force, inputs=(world,), voxel_m=args.voxel,
                           resolution_m=args.resolution)
    keys = ("format", "pose_source", "n_images", "n_points3D", "n_vertices", "n_triangles", "n_free", "n_occupied")
    _out(json.dumps({"output": str(Path(args.output).expanduser().resolve()), "world": str(world.resolve()),
                     **{k: summary[k] for k in keys if k in summary}}, indent=2))
    return 0


def cmd_lineage(args: argparse.Namespace) -> int:
    """Print the lineage of a world bundle (a folder, or a partition's Dagster bundle)."""
    from atlas_pipeline.scene_memory.bundle import format_lineage, read_lineage

    target = Path(args.bundle).expanduser()
    if not target.is_dir():
        from assets.io_managers import artifacts_root

        name = validate_dataset_name(args.bundle)
        target = artifacts_root() / "world_bundle" / name
        if not target.is_dir():
            raise ConfigError(f"'{args.bundle}' is neither a bundle folder nor a partition with a world bundle "
                              f"(looked in {target})")
    lin = read_lineage(target)
    if not args.show_config and not args.json:
        lin = {k: v for k, v in lin.items() if k != "config"}
    _out(json.dumps(lin, indent=2) if args.json else format_lineage(lin))
    return 0


def cmd_dataset(args: argparse.Namespace) -> int:
    from atlas_pipeline.errors import DatasetError
    from atlas_pipeline.sensors.registry import default_camera_spec, detect_kind

    if args.dataset_cmd == "list":
        for name, e in load_registry().items():
            present = "present" if e.path.exists() else ("generated on demand" if e.kind == "synthetic" else
                                                         "not fetched" if e.url else "MISSING")
            _out(f"{name:24s} {e.kind:10s} {present:22s} {e.path}")
        return 0
    if args.dataset_cmd == "fetch":
        from atlas_pipeline.sensors.registry import dataset_on_disk, ensure_dataset_files

        reg = load_registry()
        if args.name not in reg:
            raise ConfigError(f"dataset '{args.name}' is not registered; known: {', '.join(reg)}")
        entry = reg[args.name]
        if not dataset_on_disk(entry) and not entry.url:
            raise DatasetError(entry.path, f"dataset folder of '{entry.name}' not found and no url to download it from")
        was_there = dataset_on_disk(entry) and entry.path.exists()
        path = ensure_dataset_files(entry)  # generates a synthetic one, downloads a preset (progress bar)
        # On disk now: a partition of the definitions as they load from now on (assets.definitions).
        _out(json.dumps({"dataset": entry.name, "path": str(path), "fetched": not was_there,
                         "partition_added": dataset_on_disk(entry)}, indent=2))
        return 0
    if args.dataset_cmd == "add":
        path = Path(args.path).expanduser()
        kind = args.kind or detect_kind(path)
        if kind is None:
            raise DatasetError(path, "not found" if not path.exists() else
                               "cannot tell the layout (TUM: rgb.txt + depth.txt; 7-Scenes: frame-*.color.*; "
                               "Replica: results/ + traj.txt; ScanNet: color/ depth/ pose/ intrinsic/; bag: *.bag "
                               "or metadata.yaml + .db3/.mcap); give --kind")
        camera: Any = args.camera  # None: the kind's preset (TUM default, 7scenes, replica) or the data's own
        if args.intrinsics:
            preset = default_camera_spec(kind)
            base = resolve_camera(preset, "--kind") if preset else None
            width = args.width or (base.width if base else 640)
            height = args.height or (base.height if base else 480)
            scale = args.depth_scale or (base.depth_scale if base else 1000.0)
            camera = camera_from_intrinsics(args.intrinsics, width, height, scale)
        params = {"fps": args.fps, "sequence": args.sequence, "rgb_topic": args.rgb_topic,
                  "depth_topic": args.depth_topic}
        entry = register_local_dataset(args.name, path, camera, replace=args.replace, kind=kind,
                                       params={k: v for k, v in params.items() if v is not None})
        _out(json.dumps({"registered": entry.describe(), "registry": str(local_registry_path()),
                          "partition_added": entry.name}, indent=2))
        return 0
    if args.dataset_cmd == "sync":  # kept for scripts: the definitions read the registry as they load
        from atlas_pipeline.sensors.registry import dataset_on_disk

        reg = load_registry()
        names = [validate_dataset_name(n) for n in (args.names or reg)]
        unknown = [n for n in names if n not in reg]
        if unknown:
            raise ConfigError(f"dataset(s) {', '.join(unknown)} not registered; known: {', '.join(reg)}")
        _out(json.dumps({
            "partitions": [n for n in names if dataset_on_disk(reg[n])],
            "not_partitions": {n: ("not fetched (`atlas-gs dataset fetch " + n + "`)" if reg[n].url else
                                   f"no files at {reg[n].path}") for n in names if not dataset_on_disk(reg[n])},
        }, indent=2))
        return 0
    if args.dataset_cmd == "show":
        reg = load_registry()
        if args.name not in reg:
            raise ConfigError(f"dataset '{args.name}' is not registered")
        _out(json.dumps(reg[args.name].describe(), indent=2))
        return 0
    return 2


def cmd_ui(args: argparse.Namespace) -> int:
    home = _default_dagster_home()
    os.chdir(project_root())
    # A checkout has workspace.yaml; an installed copy loads the definitions module itself.
    where = ["-w", "workspace.yaml"] if Path("workspace.yaml").is_file() else ["-m", "assets.definitions"]
    cmd = ["dagster", "dev", *where, "-h", args.host, "-p", str(args.port)]
    logger.info("DAGSTER_HOME=%s; starting %s", home, " ".join(cmd))
    os.execvp(cmd[0], cmd)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="atlas-gs", description="Atlas-GS: RGB-D to a persistent 3D Gaussian world.")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="more output: library and Dagster log lines, Dagster's run events, warnings, debug")
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--profile", default=None,
                        help="config profile name (configs/NAME.yaml) or YAML path (default: $ATLAS_PROFILE, else default)")
        sp.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override one config value, e.g. --set localization.photometric_weight=0.5")
        sp.add_argument("--camera", default=None, help="camera preset for a folder --input (freiburg1/2/3, default)")

    b = sub.add_parser("build", help="build a world bundle from a dataset")
    common(b)
    b.add_argument("--input", required=True, help="registered dataset name or TUM-layout folder")
    b.add_argument("--output", required=True, help="world bundle folder to write (new, empty, or an earlier bundle)")
    b.add_argument("--force", action="store_true",
                   help="if --output is a folder atlas-gs did not write, move it aside (never deleted) instead of refusing")
    b.add_argument("--extend", default=None, metavar="BUNDLE",
                   help="keep mapping into the world of this earlier bundle, recorded as the lineage parent: "
                        "the first frame is relocalized in it, then frames are tracked and keyframes merged "
                        "(with mapping.pose_source ground_truth: merged at their ground-truth poses)")
    b.set_defaults(func=cmd_build)

    ip = sub.add_parser("import-ply", help="make a world bundle from a Gaussian-splat PLY (3DGS layout)")
    ip.add_argument("ply")
    ip.add_argument("--output", required=True, help="bundle folder to write (new, empty, or an earlier bundle)")
    ip.add_argument("--force", action="store_true", help="move a foreign --output folder aside instead of refusing")
    ip.add_argument("--voxel", type=float, default=0.02,
                    help="map resolution assumed when tracking against it (m), default 0.02")
    ip.set_defaults(func=cmd_import_ply)

    rl = sub.add_parser("relocalize", help="place frames in a saved world with no initial pose")
    common(rl)
    rl.add_argument("--world", required=True)
    rl.add_argument("--input", required=True)
    rl.add_argument("--frame", type=int, action="append", default=[], help="frame index (repeatable; default: all)")
    rl.set_defaults(func=cmd_relocalize)

    ev = sub.add_parser("evaluate-trajectory", help="ATE and RPE of a TUM trajectory file against ground truth")
    ev.add_argument("estimated", help="TUM file: timestamp tx ty tz qx qy qz qw")
    ev.add_argument("groundtruth", help="TUM file, e.g. a dataset's groundtruth.txt")
    ev.add_argument("--max-dt", type=float, default=0.02, help="timestamp association tolerance (s), TUM's 0.02")
    ev.add_argument("--delta", type=float, default=1.0, help="RPE interval in seconds")
    ev.set_defaults(func=cmd_evaluate_trajectory)

    lo = sub.add_parser("localize", help="localize a dataset's frames against a world bundle")
    common(lo)
    lo.add_argument("--world", required=True)
    lo.add_argument("--input", required=True)
    lo.add_argument("--start-pose", default=None, help="'tx ty tz qx qy qz qw' of the first frame in the world")
    lo.add_argument("--relocalize", action="store_true",
                    help="ignore the world's anchor: find the first frame's pose by relocalization")
    lo.add_argument("--drop-transitions", action="store_true",
                    help="remove the bundle's transitions.parquet of another dataset (refused otherwise)")
    lo.set_defaults(func=cmd_localize)

    t = sub.add_parser("log-transitions", help="write transitions.parquet into a localized world bundle")
    common(t)
    t.add_argument("--world", required=True)
    t.add_argument("--input", required=True)
    t.set_defaults(func=cmd_log_transitions)

    d = sub.add_parser("demo-video", help="render an orbit or trajectory MP4 of a world bundle")
    common(d)
    d.add_argument("--world", required=True)
    d.add_argument("--output", required=True, help="MP4 file to write (new, or a video atlas-gs wrote)")
    d.add_argument("--force", action="store_true", help="move a foreign --output file aside instead of refusing")
    d.add_argument("--mode", choices=["orbit", "trajectory"], default="orbit")
    d.set_defaults(func=cmd_demo_video)

    def dagster_args(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("dataset", nargs="?", default="synthetic", help="partition (registered dataset), default synthetic")
        sp.add_argument("--all", action="store_true", help="every registered dataset")
        sp.add_argument("--profile", default=None,
                        help="config profile for the run (default: $ATLAS_PROFILE, else default)")
        sp.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override one config value, e.g. --set localization.photometric_weight=0.5")

    r = sub.add_parser("run", help="materialize a dataset partition through Dagster (current artifacts are reused)")
    dagster_args(r)
    r.add_argument("--stale-only", action="store_true",
                   help="materialize only the stale or missing assets (nothing when all are current)")
    r.add_argument("--json", action="store_true",
                   help="print the result as JSON (the default when stdout is not a terminal)")
    r.add_argument("--concurrency", type=int, default=None, metavar="N",
                   help=f"with --all: partitions run at a time, each in its own process (default: the cores, "
                        f"at most {MAX_DEFAULT_CONCURRENCY}; 1: one after another)")
    r.add_argument("--executor", default=None, choices=["in_process", "multiprocess", "dask"],
                   help="where a run's steps execute (default: $ATLAS_EXECUTOR, else in_process)")
    r.add_argument("--dask-scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="with --executor dask: the scheduler of a running cluster (default: "
                        "$ATLAS_DASK_SCHEDULER, else a local cluster started for the run)")
    r.set_defaults(func=cmd_run)

    st = sub.add_parser("status", help="which assets of a partition are stale or missing, and why")
    dagster_args(st)
    st.add_argument("--json", action="store_true", help="machine-readable: {partition: {asset: [reasons]}}")
    st.set_defaults(func=cmd_status)

    ex = sub.add_parser("export", help="a world for other tools: COLMAP / nerfstudio (GPU trainers), a mesh, an "
                                       "occupancy grid")
    ex.add_argument("world", help="world bundle folder, or a partition name (its Dagster world bundle)")
    ex.add_argument("--format", required=True, choices=["colmap", "nerfstudio", "mesh", "occupancy"])
    ex.add_argument("--output", required=True, help="folder to write (new, empty, or an export atlas-gs wrote)")
    ex.add_argument("--force", action="store_true", help="move a foreign --output folder aside instead of refusing")
    ex.add_argument("--poses", default=None, choices=["auto", "keyframes", "estimated", "ground_truth"],
                    help="which frames at which poses (default: auto for colmap/nerfstudio -- the localization's "
                         "placed frames if the bundle has one, else the keyframes; keyframes for mesh/occupancy)")
    ex.add_argument("--input", default=None, help="the frames' recording (registered name or folder), when the "
                                                  "bundle's own dataset is elsewhere")
    ex.add_argument("--camera", default=None, help="camera preset for a folder --input (freiburg1/2/3, default)")
    ex.add_argument("--frame-step", type=int, default=1, help="export every N-th of those frames (default 1)")
    ex.add_argument("--voxel", type=float, default=0.02, help="mesh: TSDF voxel size in metres (default 0.02)")
    ex.add_argument("--resolution", type=float, default=0.05,
                    help="occupancy: cell size in metres (default 0.05)")
    ex.set_defaults(func=cmd_export)

    li = sub.add_parser("lineage", help="print the lineage of a world bundle")
    li.add_argument("bundle", help="bundle folder, or a partition name (its Dagster world bundle)")
    li.add_argument("--json", action="store_true", help="machine-readable JSON (includes the resolved config)")
    li.add_argument("--show-config", action="store_true", help="also print the resolved config")
    li.set_defaults(func=cmd_lineage)

    ds = sub.add_parser("dataset", help="list, show or register datasets (partitions)")
    dsub = ds.add_subparsers(dest="dataset_cmd", required=True)
    dsub.add_parser("list", help="registered datasets")
    sy = dsub.add_parser("sync", help="which registered datasets (or NAMES) are partitions and why the others are "
                                      "not; nothing to do before Dagster's own commands (the definitions read the "
                                      "registry as they load)")
    sy.add_argument("names", nargs="*")
    sh = dsub.add_parser("show", help="one dataset's registry entry")
    sh.add_argument("name")
    fe = dsub.add_parser("fetch", help="download a preset's frames (or generate a synthetic dataset), making it a "
                                       "partition; a preset is not a partition before this (or its first run)")
    fe.add_argument("name")
    add = dsub.add_parser("add", help="register a recording (TUM, 7-Scenes, Replica, ScanNet folder or a "
                                      "ROS/RealSense bag) as a dataset (adds a partition)")
    add.add_argument("name")
    add.add_argument("path", help="the recording's folder, or a .bag file")
    add.add_argument("--kind", default=None, choices=["tum", "7scenes", "replica", "scannet", "bag"],
                     help="layout (default: detected from the folder)")
    add.add_argument("--camera", default=None,
                     help="camera preset: freiburg1/2/3, default, 7scenes, replica (default: the kind's preset; "
                          "ScanNet and bags read theirs)")
    add.add_argument("--intrinsics", default=None, help="'fx fy cx cy' instead of a preset")
    add.add_argument("--width", type=int, default=None, help="with --intrinsics (default: the kind's preset, 640)")
    add.add_argument("--height", type=int, default=None, help="with --intrinsics (default: the kind's preset, 480)")
    add.add_argument("--depth-scale", type=float, default=None,
                     help="raw depth units per metre, with --intrinsics (default: the kind's, TUM 5000)")
    add.add_argument("--fps", type=float, default=None, help="frame rate of 7-Scenes / Replica / ScanNet (default 30)")
    add.add_argument("--sequence", default=None, help="7-Scenes: the seq-XX folder when PATH is the scene folder")
    add.add_argument("--rgb-topic", default=None, help="bag: colour topic (default: detected)")
    add.add_argument("--depth-topic", default=None, help="bag: depth topic (default: detected)")
    add.add_argument("--replace", action="store_true",
                     help="re-point an already registered name (a preset or a local entry) at this folder")
    ds.set_defaults(func=cmd_dataset)

    ui = sub.add_parser("ui", help="start the Dagster web UI (dagster dev) with the project's DAGSTER_HOME")
    ui.add_argument("--host", default="127.0.0.1")
    ui.add_argument("--port", type=int, default=3000)
    ui.set_defaults(func=cmd_ui)

    from assets.cli_view import add_view_command

    add_view_command(sub)
    # -v after the command too (`atlas-gs run synthetic -v`); SUPPRESS keeps a -v given before it
    parsers = list(sub.choices.values()) + list(dsub.choices.values())
    for sp in parsers:
        sp.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="more output (as before the command)")
    return p


def _stdout_closed() -> int:
    """``EXIT_BROKEN_PIPE`` after stdout's reader went away, quietly (Python's recipe for SIGPIPE,
    docs.python.org/3/library/signal.html#note-on-sigpipe): stdout is pointed at devnull, so
    flushing what is left of it at exit cannot raise (and print "Broken pipe") again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # a stdout without a file descriptor (an in-process caller's)
        pass
    return EXIT_BROKEN_PIPE


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)  # --help prints here
    except BrokenPipeError:
        return _stdout_closed()
    from assets.runs import interrupts_end_the_command, signal_dispositions_kept

    with _CliOutput(args.verbose), signal_dispositions_kept():  # a Dagster run changes them (assets.runs)
        try:
            with interrupts_end_the_command():  # Ctrl-C: one line, status 130
                return int(args.func(args) or 0)
        except AtlasError as exc:
            logger.error("%s", exc)
            return EXIT_ERROR
        except BrokenPipeError:  # before OSError: a closed stdout is no error of the command's
            return _stdout_closed()
        except OSError as exc:  # an OS error the library did not wrap: still name the path
            where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f) or "(no path given by the OS)"
            logger.error("%s: %s", where, exc.strerror or exc)
            return EXIT_ERROR
        except Exception as exc:
            from assets.runs import instance_storage_error

            if (line := instance_storage_error(exc)) is None:
                raise
            logger.error("%s", line)
            return EXIT_ERROR


def command() -> int:
    """The ``atlas-gs`` executable: :func:`main`, then a quick exit. Everything the command wrote is
    closed and renamed into place by then; freezing the objects it leaves keeps the interpreter's
    final garbage collection from walking them one by one (Dagster's, SQLAlchemy's and the
    plotting modules' object graphs: about 0.4 s of every command). Tests call :func:`main`."""
    import gc

    code = main()
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        code = _stdout_closed()
    sys.stderr.flush()
    gc.freeze()
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(command())

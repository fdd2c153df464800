"""Which frames of a world's recording go to another tool, at which poses, and their pixels.

A world bundle stores its Gaussians, the keyframes' indices and poses, and (after ``localize``)
every frame's estimated pose; it stores no images or depth. The frames are read from the recording
each keyframe names (:mod:`atlas_pipeline.scene_memory.recordings`: the folder recorded in
``metadata.json``, else the registered dataset of its name), checked against its content hash, so
an export never pairs poses with other frames. A world extended with other recordings has
keyframes of each: a recording that is not available (not on disk, not registered, or with other
frames) has its keyframes left out with one warning naming it. Files of the bundle's own recording
are named ``frame_000123.png``; those of another recording carry its tag
(``<name>-<hash8>_frame_000123.png``), so no two exported frames share a name.

Pose sources (:data:`POSE_SOURCES`):

* ``keyframes``: the frames the world was mapped from, at their mapping poses;
* ``estimated``: every frame ``localization.json`` placed (``anchor``, ``tracked``,
  ``relocalized``; lost frames carry only a prediction and are left out);
* ``ground_truth``: every frame with ground truth, only for a world mapped at ground-truth poses
  (the Gaussians are then in the ground truth's frame);
* ``auto``: ``estimated`` when the bundle has a localization, else ``keyframes``.

Undistortion: a camera with lens distortion (TUM fr1/fr2) has its colour resampled bilinearly and
its depth by nearest neighbour onto the same K without distortion, so every export is a plain
pinhole camera (Inria's ``train.py`` takes nothing else).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.errors import AtlasError, ConfigError, DatasetError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["POSE_SOURCES", "PLACED_STATUSES", "ExportSource", "source_from_bundle", "source_from_world",
           "pinhole_camera", "undistorted_rgb", "undistorted_depth_m", "frame_name", "frame_file_name"]

POSE_SOURCES = ("auto", "keyframes", "estimated", "ground_truth")
PLACED_STATUSES = ("anchor", "tracked", "relocalized")  # a lost frame's pose is only the motion model's guess
FRAME_NAME_DIGITS = 6


def frame_name(index: int, suffix: str = ".png") -> str:
    """``frame_000123.png``: the file name of dataset frame ``index`` in every export."""
    return f"frame_{int(index):0{FRAME_NAME_DIGITS}d}{suffix}"


def frame_file_name(index: int, tag: str = "", suffix: str = ".png") -> str:
    """:func:`frame_name`, prefixed by a recording's ``tag`` (``a-1b2c3d4e_frame_000123.png``)
    when the frame is not one of the bundle's own recording."""
    return f"{tag}_{frame_name(index, suffix)}" if tag else frame_name(index, suffix)


@dataclass
class ExportSource:
    """A world and the frames that go with it.

    Frame ``k`` of the export is frame ``frame_indices[k]`` of the recording
    ``recordings[frame_recording[k]]``; read it with :meth:`pinhole_rgb` / :meth:`pinhole_depth_m`
    (or :meth:`manifest_of`), never by indexing ``manifest`` with ``frame_indices``, which holds
    only when every frame is one of ``manifest``'s (:attr:`single_recording`).

    Attributes:
        field: the Gaussians (points for COLMAP's ``points3D``, the mesh preview ...).
        manifest: the main recording (the bundle's own when its frames are exported); its camera
            is every frame's (recordings with another pinhole camera are never mixed in).
        frame_indices: ``[M]`` index of each frame in its recording.
        T_world_cam: ``[M, 4, 4]`` camera-to-world (OpenCV camera: x right, y down, z forward).
        pose_source: ``keyframes``, ``estimated`` or ``ground_truth``.
        map_id: the world's id.
        recordings: the recordings the frames come from (default ``[manifest]``; the first is
            ``manifest``).
        frame_recording: ``[M]`` index of each frame's recording into ``recordings`` (default 0).
        recording_tags: per recording, the tag its frames' file names carry ("" for plain
            ``frame_000123.png``; default "" for the first, a tag of each other).
    """

    field: GaussianField
    manifest: FrameManifest
    frame_indices: np.ndarray
    T_world_cam: np.ndarray
    pose_source: str
    map_id: str = ""
    notes: list[str] = field(default_factory=list)
    recordings: list[FrameManifest] | None = None
    frame_recording: np.ndarray | None = None
    recording_tags: list[str] | None = None

    def __post_init__(self) -> None:
        self.frame_indices = np.asarray(self.frame_indices, np.int64)
        self.T_world_cam = np.asarray(self.T_world_cam, np.float64)
        if self.recordings is None:
            self.recordings = [self.manifest]
        if self.recordings[0] is not self.manifest:
            raise AtlasError("ExportSource: recordings[0] must be the main manifest")
        self.frame_recording = (np.zeros(len(self.frame_indices), np.int64) if self.frame_recording is None
                                else np.asarray(self.frame_recording, np.int64).reshape(-1))
        if self.recording_tags is None:
            from atlas_pipeline.scene_memory.recordings import recording_record, recording_tag

            self.recording_tags = [""] + [recording_tag(recording_record(m), j)
                                          for j, m in enumerate(self.recordings) if j]
        if len(self.frame_indices) == 0:
            raise AtlasError(f"no frames with a {self.pose_source} pose to export")
        if self.T_world_cam.shape != (len(self.frame_indices), 4, 4) or not np.isfinite(self.T_world_cam).all():
            raise AtlasError(f"{self.pose_source} poses must be finite 4x4 matrices, one per frame")
        if len(self.frame_recording) != len(self.frame_indices) or len(self.recording_tags) != len(self.recordings) \
                or self.frame_recording.min() < 0 or self.frame_recording.max() >= len(self.recordings):
            raise AtlasError("ExportSource: frame_recording must name one of the recordings for every frame, "
                             "and recording_tags hold one tag per recording")
        for j, m in enumerate(self.recordings):
            mine = self.frame_indices[self.frame_recording == j]
            if len(mine) and (mine.min() < 0 or mine.max() >= m.n_frames):
                raise AtlasError(f"frame indices {mine.min()}..{mine.max()} are outside the "
                                 f"{m.n_frames} frames of dataset '{m.dataset}'")
            if j and not same_pinhole(m.camera, self.manifest.camera):
                raise AtlasError(f"dataset '{m.dataset}' was taken with another camera than '{self.manifest.dataset}': "
                                 "one export holds one pinhole camera")
        names = [self.frame_name(k) for k in range(len(self.frame_indices))]
        if len(set(names)) != len(names):
            raise AtlasError("ExportSource: two exported frames would share a file name (the same frame of one "
                             "recording listed twice)")

    @property
    def single_recording(self) -> bool:
        """Whether every frame is one of ``manifest``'s (``frame_indices`` index it)."""
        return len(self.recordings) == 1

    @property
    def camera(self) -> CameraIntrinsics:
        """The pinhole camera every exported frame is on (:meth:`pinhole_rgb`'s grid)."""
        return pinhole_camera(self.manifest.camera)

    def manifest_of(self, k: int) -> FrameManifest:
        """The recording export frame ``k`` is a frame of (at index ``frame_indices[k]``)."""
        return self.recordings[int(self.frame_recording[k])]

    def frame_name(self, k: int, suffix: str = ".png") -> str:
        """The file name of export frame ``k``: ``frame_000123.png``, or with its recording's tag."""
        return frame_file_name(int(self.frame_indices[k]), self.recording_tags[int(self.frame_recording[k])], suffix)

    def pinhole_rgb(self, k: int) -> np.ndarray:
        """``[H, W, 3]`` uint8 colour of export frame ``k`` on :attr:`camera`'s grid (undistorted)."""
        m = self.manifest_of(k)
        return undistorted_rgb(m.read_rgb(int(self.frame_indices[k])), m.camera)

    def pinhole_depth_m(self, k: int) -> np.ndarray:
        """``[H, W]`` float32 depth (m, 0: no reading) of export frame ``k`` on :attr:`camera`'s grid."""
        m = self.manifest_of(k)
        return undistorted_depth_m(m.read_depth_m(int(self.frame_indices[k]), allow_empty=True), m.camera)

    def recordings_summary(self) -> list[dict[str, Any]]:
        """Per recording: its name, content hash, file-name tag and number of frames exported."""
        return [{"name": m.dataset, "content_hash": m.content_hash or None, "tag": self.recording_tags[j],
                 "n_frames": int((self.frame_recording == j).sum())} for j, m in enumerate(self.recordings)]

    def thinned(self, step: int) -> "ExportSource":
        """Every ``step``-th frame (the first kept)."""
        if step == 1:
            return self
        return ExportSource(self.field, self.manifest, self.frame_indices[::step], self.T_world_cam[::step],
                            self.pose_source, self.map_id, self.notes, self.recordings,
                            self.frame_recording[::step], self.recording_tags)


def check_frame_step(step: Any, option: str = "--frame-step") -> int:
    """``step`` as a positive integer, else a ConfigError naming ``option``."""
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise ConfigError(f"{option} must be an integer >= 1, got {step!r}")
    return int(step)


def check_pose_source(poses: str, option: str = "--poses") -> str:
    if poses not in POSE_SOURCES:
        raise ConfigError(f"{option} must be one of {', '.join(POSE_SOURCES)}, got {poses!r}")
    return poses


def same_pinhole(a: CameraIntrinsics, b: CameraIntrinsics) -> bool:
    """Whether undistorted frames of cameras ``a`` and ``b`` lie on one pinhole grid (size, K)."""
    return (a.width, a.height, a.fx, a.fy, a.cx, a.cy) == (b.width, b.height, b.fx, b.fy, b.cx, b.cy)


def source_from_world(field: GaussianField, manifest: FrameManifest, keyframe_indices: np.ndarray,
                      T_world_cam_keyframes: np.ndarray, localization: Any = None, poses: str = "auto",
                      world_pose_source: str | None = None, map_id: str = "",
                      recordings: list[dict[str, Any]] | None = None,
                      keyframe_recording: np.ndarray | None = None) -> ExportSource:
    """The frames of a world in memory (the Dagster assets' inputs): see the module docstring for
    ``poses``; ``localization`` is a ``LocalizationReport`` of ``manifest``'s frames or None.
    ``recordings`` / ``keyframe_recording``: the world's record of which recording each keyframe
    comes from (``GaussianWorld.recordings`` / ``keyframe_recording``; None: all ``manifest``'s):
    keyframes of other recordings are left out with a warning, never read from ``manifest``."""
    poses = check_pose_source(poses)
    if poses == "auto":
        poses = "estimated" if localization is not None else "keyframes"
    if poses == "keyframes":
        idx = np.asarray(keyframe_indices, np.int64)
        T = np.asarray(T_world_cam_keyframes, np.float64)
        if keyframe_recording is not None:
            from atlas_pipeline.scene_memory.recordings import recording_index, recording_label, recording_record

            rec_idx = np.asarray(keyframe_recording, np.int64)
            own = recording_index(list(recordings or []), recording_record(manifest))
            for j in sorted(set(rec_idx.tolist()) - {own}):
                logger.warning("%d keyframes of recording %s left out: this export reads the frames of '%s' only",
                               int((rec_idx == j).sum()), recording_label(recordings[j]), manifest.dataset)
            keep = rec_idx == own
            idx, T = idx[keep], T[keep]
        return ExportSource(field, manifest, idx, T, "keyframes", map_id)
    if poses == "estimated":
        if localization is None:
            raise ConfigError("--poses estimated: this world has no localization (localization.json); run "
                              "`atlas-gs localize` first, or export --poses keyframes")
        T = np.asarray(localization.T_world_cam, np.float64)
        placed = np.array([s in PLACED_STATUSES for s in localization.status]) & np.isfinite(T).all(axis=(1, 2))
        if len(T) != manifest.n_frames:
            raise AtlasError(f"the localization has {len(T)} frames, dataset '{manifest.dataset}' {manifest.n_frames}")
        idx = np.flatnonzero(placed)
        return ExportSource(field, manifest, idx, T[idx], "estimated", map_id)
    # ground truth: only meaningful where the Gaussians live in the ground truth's frame
    if world_pose_source != "ground_truth":
        raise ConfigError(f"--poses ground_truth: this world was mapped from {world_pose_source or 'unknown'} poses, "
                          "so its Gaussians are not in the ground truth's frame; export --poses estimated or keyframes")
    idx = np.flatnonzero(manifest.has_gt)
    return ExportSource(field, manifest, idx, manifest.T_world_cam_gt[idx], "ground_truth", map_id)


def _given_manifest(dataset: Any, records: list[dict[str, Any]]) -> tuple[FrameManifest, int | None]:
    """The frames of ``dataset`` (a ``DatasetEntry`` the caller resolved: ``--input``) and the
    index of the record in ``records`` that is its recording by content (None: none is). A record
    of fewer frames than the dataset has is compared with that many of its frames."""
    from atlas_pipeline.scene_memory.recordings import recording_index, recording_record
    from atlas_pipeline.sensors.registry import ensure_dataset_files, read_dataset_manifest

    if dataset.kind == "synthetic":
        ensure_dataset_files(dataset)  # generated from its spec, deterministically: never a download
    manifest = read_dataset_manifest(dataset, None)
    j = recording_index(records, recording_record(manifest)) if manifest.content_hash else None
    if j is None:
        for n in sorted({r.get("n_frames") for r in records if isinstance(r.get("n_frames"), int)
                         and 0 < r["n_frames"] < manifest.n_frames}):
            part = read_dataset_manifest(dataset, n)
            j = recording_index(records, recording_record(part)) if part.content_hash else None
            if j is not None:
                return part, j
    return manifest, j


# A localization's frame times and a recording's agree to this (s): the same frames, not others.
REPORT_TIME_TOLERANCE_S = 1e-3


def _frames_of_report(manifest: FrameManifest, report: Any) -> bool:
    """Whether ``manifest`` holds the frames ``report`` (a ``LocalizationReport``) placed: its
    recording's content hash when the report records one, else the same frame times."""
    want = (report.recording or {}).get("content_hash")
    if want:
        return manifest.content_hash == want
    n = len(report.timestamps_s)
    # rtol 0: a relative tolerance of Unix times (~1.3e9 s) would let frames hours apart pass
    return manifest.n_frames >= n and bool(np.allclose(manifest.timestamps_s[:n], report.timestamps_s,
                                                       rtol=0.0, atol=REPORT_TIME_TOLERANCE_S))


def _is_report_recording(dataset: Any, report: Any) -> bool:
    """Whether ``dataset`` (a ``DatasetEntry``) is, by content, the recording ``report`` placed."""
    rec = report.recording or {}
    return bool(rec.get("content_hash")) and _given_manifest(dataset, [rec])[1] is not None


def _bundle_manifest(meta: dict[str, Any], report: Any, dataset: Any) -> FrameManifest:
    """The manifest of the recording the bundle's ``dataset`` names, or (``report``: a
    ``LocalizationReport``) of the recording that localization placed: the recording the report
    records, the bundle's dataset or one of its ``recordings`` of that name, else the registered
    dataset of that name, each taken only when it holds the report's frames; or ``dataset`` (a ``DatasetEntry`` the caller
    resolved: ``--input``). Content hashes are checked where the bundle records them."""
    from atlas_pipeline.scene_memory.recordings import open_recording

    ds = meta.get("dataset") if isinstance(meta.get("dataset"), dict) else {}
    name = report.dataset if report is not None else ds.get("name")
    if dataset is not None and report is not None:
        # the report's frames may be the first ones of --input (localized with dataset.max_frames):
        # read again at the report's frame count, they are told by its content hash
        rec = report.recording or {}
        manifest, _ = _given_manifest(dataset, [rec] if rec.get("content_hash") else [])
        if not _frames_of_report(manifest, report):
            raise DatasetError(dataset.path, f"the frames of dataset '{dataset.name}' are not the ones the world's "
                                             f"localization placed ('{report.dataset}'): poses would be paired with "
                                             "other images")
        return manifest
    if dataset is not None:
        want = ds.get("content_hash")
        manifest, j = _given_manifest(dataset, [ds] if want else [])
        if want and manifest.content_hash and j is None:
            raise DatasetError(dataset.path, f"the frames of dataset '{dataset.name}' are not the ones this world was "
                                             "built from (content hash differs): poses would be paired with other images")
        return manifest
    if not name:
        raise DatasetError("metadata.json", "the world names no dataset (an imported PLY?): give the frames' "
                                            "recording with --input DATASET")
    if report is None:
        candidates = [dict(ds)]
    else:  # the recordings of the bundle that bear the report's name (told apart by their frames), then the registry's
        recs = meta.get("recordings") if isinstance(meta.get("recordings"), list) else []
        named = [r for r in [ds, *recs] if isinstance(r, dict) and r.get("name") == name] + [{"name": name}]
        named = ([dict(report.recording)] if report.recording else []) + named
        candidates = list({(r.get("root"), r.get("content_hash")): r for r in reversed(named)}.values())[::-1]
    reasons = []
    for record in candidates:
        manifest, why = open_recording(record)
        if manifest is None:
            reasons.append(why)
        elif report is not None and not _frames_of_report(manifest, report):
            reasons.append(f"{manifest.root} holds other frames than the localization placed")
        else:
            return manifest
    where = next((r.get("root") for r in candidates if r.get("root")), None) or name
    raise DatasetError(where, f"the frames of dataset '{name}' are not available ({'; '.join(dict.fromkeys(reasons))}): "
                              "give them with --input DATASET")


def _keyframe_source(b: Any, dataset: Any) -> ExportSource:
    """The keyframes of the loaded bundle ``b``, each with the frames of its own recording: an
    unavailable recording's keyframes are left out (one warning each), a keyframe listed twice
    (the same frame of one recording mapped by two sessions) is exported once, at its first pose."""
    from atlas_pipeline.scene_memory.recordings import (bundle_keyframe_sources, is_unknown, open_recording,
                                                        recording_index, recording_label, recording_tag)

    meta = b.metadata
    where = Path(b.directory) / "metadata.json"
    ks = bundle_keyframe_sources(meta, where)
    used = sorted(set(ks.recording.tolist()))
    opened: dict[int, FrameManifest] = {}
    why: dict[int, str] = {}
    if dataset is not None:
        manifest, j = _given_manifest(dataset, ks.recordings)
        if j is None and any(ks.recordings[u].get("content_hash") for u in used):
            names = ", ".join(recording_label(ks.recordings[u]) for u in used)
            raise DatasetError(dataset.path, f"the frames of dataset '{dataset.name}' are not the ones this world was "
                                             f"built from (its content hash is none of its keyframes' recordings: "
                                             f"{names}): poses would be paired with other images")
        if j is None:  # an older world without hashes: the given frames stand for its named recordings
            opened = {u: manifest for u in used if not is_unknown(ks.recordings[u])}
        else:
            opened[j] = manifest
    for u in used:
        if u not in opened and is_unknown(ks.recordings[u]) and ks.unknown_reason:
            why[u] = ks.unknown_reason
        elif u not in opened:
            m, reason = open_recording(ks.recordings[u])
            if m is None:
                why[u] = reason
            else:
                opened[u] = m
    own = recording_index(ks.recordings, meta["dataset"]) if isinstance(meta.get("dataset"), dict) else None
    available = [u for u in used if u in opened]
    if not available:
        if not used:
            raise DatasetError(where, "this world has no keyframes (imported from a PLY?), so no frames at keyframe "
                                      "poses: localize a recording in it (`atlas-gs localize`) and export --poses "
                                      "estimated")
        if all(is_unknown(ks.recordings[u]) for u in used):  # no frames may stand for them, given or found
            raise DatasetError(where, f"{why[used[0]]}; no keyframe can be exported at its pose: restore the parent "
                                      "bundle where lineage.parent.path says, or localize a recording in this world "
                                      "(`atlas-gs localize`) and export --poses estimated")
        first = ks.recordings[used[0]]
        raise DatasetError(first.get("root") or first.get("name") or where,
                           "the frames of no recording of this world's keyframes are available ("
                           + "; ".join(f"{recording_label(ks.recordings[u])}: {why[u]}" for u in used)
                           + "): give them with --input DATASET")
    main = own if own in opened else available[0]
    for u in available:
        if u != main and not same_pinhole(opened[u].camera, opened[main].camera):
            why[u] = f"taken with another camera than '{opened[main].dataset}' (one export holds one pinhole camera)"
            del opened[u]
    for u in used:
        if u in why:
            logger.warning("%d keyframes of recording %s left out of the export: %s",
                           int((ks.recording == u).sum()), recording_label(ks.recordings[u]), why[u])
    order = [main] + [u for u in used if u in opened and u != main]
    slot = {u: k for k, u in enumerate(order)}
    keep, seen = [], set()
    for k, (i, u) in enumerate(zip(ks.indices.tolist(), ks.recording.tolist())):
        if u in slot and (u, i) not in seen:
            seen.add((u, i))
            keep.append(k)
    n_twice = sum(1 for u in ks.recording.tolist() if u in slot) - len(keep)
    if n_twice:
        logger.info("%d keyframes are frames another keyframe already is (one recording mapped twice): each frame "
                    "is exported once, at its first keyframe's pose", n_twice)
    keep = np.asarray(keep, np.int64)
    tags = ["" if u == own else recording_tag(ks.recordings[u], u) for u in order]
    return ExportSource(b.field, opened[main], ks.indices[keep], ks.T_world_cam[keep], "keyframes", b.map_id,
                        recordings=[opened[u] for u in order],
                        frame_recording=np.array([slot[u] for u in ks.recording[keep].tolist()], np.int64),
                        recording_tags=tags)


def source_from_bundle(bundle_dir: str | Path, poses: str = "auto", dataset: Any = None,
                       frame_step: int = 1) -> ExportSource:
    """The frames of the world bundle at ``bundle_dir`` (every listed file verified first)."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    poses = check_pose_source(poses)
    frame_step = check_frame_step(frame_step)
    b = load_world_bundle(bundle_dir)
    meta = b.metadata
    report = LocalizationReport.load(b.directory) if "localization.json" in meta["files"] else None
    if poses == "auto":  # the localization's frames, unless --input gives another recording's
        poses = ("estimated" if report is not None and (dataset is None or dataset.name == report.dataset
                                                        or _is_report_recording(dataset, report))
                 else "keyframes")
    if poses == "keyframes":
        return _keyframe_source(b, dataset).thinned(frame_step)
    manifest = _bundle_manifest(meta, report if poses == "estimated" else None, dataset)
    src = source_from_world(b.field, manifest, np.zeros(0, np.int64), np.zeros((0, 4, 4)),
                            report if poses == "estimated" else None, poses,
                            (meta.get("gaussians") or {}).get("pose_source"), b.map_id)
    return src.thinned(frame_step)


# ---- pixels ------------------------------------------------------------------------------------


def pinhole_camera(camera: CameraIntrinsics) -> CameraIntrinsics:
    """``camera`` without lens distortion (the K every export writes)."""
    return CameraIntrinsics(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                            camera.depth_scale)


@functools.lru_cache(maxsize=4)
def _distorted_pixels(camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the undistorted image lies in the raw one: ``(u [H, W], v [H, W])``
    float64 (the radial-tangential model of ``camera.distortion``, k1 k2 p1 p2 [k3])."""
    k = list(camera.distortion) + [0.0] * (5 - len(camera.distortion))
    k1, k2, p1, p2, k3 = k
    x = (np.arange(camera.width, dtype=np.float64) - camera.cx) / camera.fx
    y = (np.arange(camera.height, dtype=np.float64) - camera.cy) / camera.fy
    x, y = np.meshgrid(x, y)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd * camera.fx + camera.cx, yd * camera.fy + camera.cy


def undistorted_rgb(rgb: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """``[H, W, 3]`` uint8 on ``pinhole_camera(camera)``'s grid (bilinear; outside the raw image: 0)."""
    if not camera.distortion:
        return rgb
    u, v = _distorted_pixels(camera)
    h, w = rgb.shape[:2]
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 < w - 1) & (v0 < h - 1)
    u0c, v0c = np.clip(u0, 0, w - 2), np.clip(v0, 0, h - 2)
    fu, fv = (u - u0c)[..., None], (v - v0c)[..., None]
    img = rgb.astype(np.float64)
    out = ((1 - fu) * (1 - fv) * img[v0c, u0c] + fu * (1 - fv) * img[v0c, u0c + 1]
           + (1 - fu) * fv * img[v0c + 1, u0c] + fu * fv * img[v0c + 1, u0c + 1])
    return np.where(inside[..., None], np.clip(np.rint(out), 0, 255), 0).astype(np.uint8)


def undistorted_depth_m(depth_m: np.ndarray, camera: CameraIntrinsics) -> np.ndarray:
    """``[H, W]`` float32 on ``pinhole_camera(camera)``'s grid: nearest neighbour, so no depth is
    ever blended across an object's edge (outside the raw image: 0, no reading)."""
    if not camera.distortion:
        return depth_m
    u, v = _distorted_pixels(camera)
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    h, w = depth_m.shape
    inside = (ui >= 0) & (vi >= 0) & (ui < w) & (vi < h)
    return np.where(inside, depth_m[np.clip(vi, 0, h - 1), np.clip(ui, 0, w - 1)], 0).astype(np.float32)

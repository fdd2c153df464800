"""Interactive browser viewer of a world bundle, built on viser (the viewer of nerfstudio and gsplat).

What the scene shows:

* the bundle's Gaussians as splats (viser's WebGL Gaussian-splat renderer, sorted in the browser);
* the keyframes the world was mapped from as camera frusta, each with a thumbnail of its image when
  the dataset's frames are on disk and unchanged (checked against the content hash the bundle
  records), else as bare frusta;
* the estimated trajectory of the bundle's localization report (or ``--report``) and the
  ground-truth trajectory, in the world frame;
* lost frames as red markers, relocalized frames as orange ones;
* the world's triangle mesh (vertex colours) and its 2D occupancy grid (a quad on the floor:
  free, occupied, unknown), from export folders or computed from the keyframes
  (:mod:`atlas_pipeline.viz.viewer_layers`);
* a frame slider moving a yellow camera along the trajectory, with that frame's image and its
  localization status; reset-view and splat-size controls; a switch per layer
  (:mod:`atlas_pipeline.viz.viewer_controls`, which also says how the orbit is kept in the room).

Keyframe frusta are thinned: at most :data:`MAX_FRUSTA`, evenly spread, smaller as more are drawn,
so a recording's fan of keyframes does not cover the room; the slider shows any frame in full.

Page size: the Gaussians as the bundle holds them (32 bytes each), plus at most
:data:`MAX_FRUSTA` thumbnails of :data:`THUMBNAIL_MAX_WIDTH_PX` px, a mesh of at most
:data:`~atlas_pipeline.viz.viewer_layers.MAX_MESH_TRIANGLES` triangles (~3 MB), an occupancy
texture of at most :data:`~atlas_pipeline.viz.viewer_layers.MAX_OCCUPANCY_PX` px a side, the
trajectories (a few dozen bytes a frame) and one frame thumbnail at a time, sent when the slider
moves.

Every input goes through the verified loaders: the bundle through
:func:`~atlas_pipeline.scene_memory.bundle.load_world_bundle` (schema and checksums of every listed
file), a report through :func:`load_report_checked`; nothing is unpickled.

The server binds a loopback address only (``127.0.0.1`` by default): it has no authentication, and
what it serves (the map of a recorded place and its camera images) is as private as the
recording. Binding another address needs ``allow_remote=True`` from library code; the CLI offers
no such switch. viser's "share URL" (a public tunnel through viser's own relay) is switched off for
the same reason. A loopback address alone does not keep other web sites out: any page open in the
user's browser may open a websocket to ``127.0.0.1``, so the websocket handshake is refused unless
the page's ``Origin`` is a loopback one (the viewer's own page; :data:`ALLOWED_ORIGIN_HOSTS`).

Conventions: ``T_world_cam`` ``[4, 4]`` camera-to-world (OpenCV camera axes: x right, y down,
z forward, as viser's frusta), metres; quaternions are ``quat_xyzw`` in our arrays and ``wxyz`` only
where viser takes them.
"""

from __future__ import annotations

import contextlib
import io
import ipaddress
import logging
import math
import re
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from atlas_pipeline.errors import AtlasError, BundleFormatError, ConfigError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.geometry import quat_xyzw_to_rotmat, rotmat_to_quat_xyzw
from atlas_pipeline.viz import viewer_controls as controls
from atlas_pipeline.viz.viewer_layers import MeshLayer, OccupancyLayer, layer_summary, load_layers, mesh_glb
from atlas_pipeline.localization.sequence import (
    STATUS_ANCHOR,
    STATUS_LOST,
    STATUS_NOT_ATTEMPTED,
    STATUS_RELOCALIZED,
    STATUS_TRACKED,
)

__all__ = [
    "ViewerData", "ViewerHandle", "load_viewer_data", "load_report_checked", "build_scene", "serve",
    "run_viewer", "splat_covariances", "is_loopback_host", "DEFAULT_HOST",
]

logger = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
# Colours (RGB, 0-255) of the scene's layers; distinct from each other on viser's light background.
ESTIMATED_RGB = (30, 100, 235)      # blue: the localization estimate
GROUND_TRUTH_RGB = (20, 170, 60)    # green: ground truth
KEYFRAME_RGB = (120, 60, 200)       # purple: keyframe frusta
LOST_RGB = (230, 25, 25)            # red: lost frames
RELOCALIZED_RGB = (255, 140, 0)     # orange: relocalized frames
# Trajectory lines keep a fixed on-screen width whatever the zoom (world-unit lines vanish when
# the room is seen whole and cover the view up close).
TRAJECTORY_WIDTH_PX = 3.0
# Frusta and markers are sized from the world's extent (a desk and a building differ 100-fold).
FRUSTUM_SIZE_FRACTION = 0.03
FRUSTUM_SIZE_RANGE_M = (0.015, 0.5)
MAX_FRUSTA = 12  # keyframes drawn as frusta (evenly spread); the slider reaches every frame
MARKER_SIZE_FRACTION = 0.012
# Thumbnails: small enough that hundreds travel over the websocket in a second or two.
THUMBNAIL_MAX_WIDTH_PX = 160
THUMBNAIL_JPEG_QUALITY = 80
# Variances below float16's smallest subnormal (viser ships covariances as float16) would become
# 0 and make a degenerate splat; 0.5 mm is far below any Gaussian a 2 cm map holds.
MIN_SPLAT_SIGMA_M = 5e-4
MAX_SPLAT_SIGMA_M = 200.0  # float16's largest value is 65504 (m^2): no map Gaussian comes near
# Robust extent: the 2nd..98th percentile box of the Gaussian centres (floaters far out would
# otherwise set the frustum size and the starting view).
EXTENT_PERCENTILES = (2.0, 98.0)
REPORT_TIME_TOLERANCE_S = 1e-3  # a report's frame times and its recording's agree to this
MAX_REPORT_BYTES = 256 * 1024 * 1024  # a localization.json of a 100k-frame session is ~40 MB
KNOWN_STATUSES = (STATUS_ANCHOR, STATUS_TRACKED, STATUS_RELOCALIZED, STATUS_LOST, STATUS_NOT_ATTEMPTED)


# ---- what is shown -------------------------------------------------------------------------------


@dataclass
class ViewerData:
    """Everything the scene shows, loaded and checked.

    Attributes:
        world_dir: the bundle folder.
        field: the Gaussians.
        metadata: the bundle's validated metadata.json.
        keyframe_indices: ``[K]`` frame index of each keyframe in its dataset.
        T_world_cam_keyframes: ``[K, 4, 4]`` keyframe poses.
        keyframe_images: ``K`` thumbnails ``[h, w, 3]`` uint8, None where not available.
        camera_fov_y_rad, camera_aspect: the dataset camera's vertical field of view and width /
            height (frustum shape); a 4:3, 60-degree camera when the bundle names none.
        status: ``N`` per-frame statuses of the report (empty without one).
        T_world_cam_est: ``[N, 4, 4]`` estimated poses (NaN rows: never placed).
        T_world_cam_gt: ``[N, 4, 4]`` ground truth in the world frame (NaN where unknown), or None.
        ground_truth_note: how the ground truth got into the world frame (or why there is none).
        report_source: the folder the localization report was read from ("" without one).
        report_timestamps_s: ``[N]`` the report's frame times, or None.
        keyframe_manifest, report_manifest: the recordings of the bundle's dataset and of the
            report's frames when on disk and unchanged (the slider's images), else None.
        keyframe_manifests: ``K`` the recording each keyframe is a frame of (an extended world's
            keyframes come from several), None where it is not available.
        mesh, occupancy: the layers (:mod:`atlas_pipeline.viz.viewer_layers`), or None.
        notes: what could not be shown and why (logged, and listed in the viewer's panel).
    """

    world_dir: Path
    field: GaussianField
    metadata: dict[str, Any]
    keyframe_indices: np.ndarray
    T_world_cam_keyframes: np.ndarray
    keyframe_images: list[np.ndarray | None]
    camera_fov_y_rad: float = math.radians(60.0)
    camera_aspect: float = 4.0 / 3.0
    status: list[str] = field(default_factory=list)
    T_world_cam_est: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    T_world_cam_gt: np.ndarray | None = None
    ground_truth_note: str = ""
    report_source: str = ""
    report_timestamps_s: np.ndarray | None = None
    keyframe_manifest: Any = None
    report_manifest: Any = None
    keyframe_manifests: list[Any] = field(default_factory=list)
    mesh: MeshLayer | None = None
    occupancy: OccupancyLayer | None = None
    notes: list[str] = field(default_factory=list)


def _note(data_notes: list[str], msg: str, *args: Any) -> None:
    text = msg % args if args else msg
    logger.info("%s", text)
    data_notes.append(text)


def load_report_checked(directory: str | Path):
    """A :class:`~atlas_pipeline.localization.localizer.LocalizationReport` from ``directory``
    (``localization.json``, and ``trajectory_groundtruth.tum`` when present), with every field
    checked: a malformed file is a BundleFormatError naming it, never a KeyError or a crash later."""
    from atlas_pipeline.localization.localizer import LocalizationReport

    directory = Path(directory)
    if directory.is_file() and directory.name == "localization.json":
        directory = directory.parent
    path = directory / "localization.json"
    if not path.is_file():
        raise ConfigError(f"{directory}: no localization.json there (write one with `atlas-gs localize`)")
    size = path.stat().st_size
    if size > MAX_REPORT_BYTES:
        raise BundleFormatError(path, f"is {size} bytes, more than any localization report ({MAX_REPORT_BYTES})")
    try:
        report = LocalizationReport.load(directory)
    except AtlasError:
        raise
    except RecursionError as exc:
        raise BundleFormatError(path, "JSON nested too deeply") from exc
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        # json errors and UnicodeDecodeError are ValueErrors; a missing key or a list where a number
        # belongs lands here too.
        raise BundleFormatError(path, f"not a localization report atlas-gs can read ({type(exc).__name__}: "
                                      f"{str(exc)[:200]})") from exc
    n = report.n_frames
    if not isinstance(report.dataset, str) or not isinstance(report.map_id, str):
        raise BundleFormatError(path, "dataset and map_id must be strings")
    if report.timestamps_s.shape != (n,) or not np.isfinite(report.timestamps_s).all():
        raise BundleFormatError(path, "every frame needs a finite timestamp_s")
    if len(report.status) != n or not all(isinstance(s, str) for s in report.status):
        raise BundleFormatError(path, "frames must each have a status string")
    unknown = sorted({s for s in report.status if s not in KNOWN_STATUSES})
    if unknown:
        raise BundleFormatError(path, f"unknown frame status {unknown[0][:40]!r} (known: {', '.join(KNOWN_STATUSES)})")
    for name in ("T_world_cam", "T_world_cam_gt"):
        T = getattr(report, name)
        if T.shape != (n, 4, 4):
            raise BundleFormatError(path, f"{name} has shape {T.shape}, expected ({n}, 4, 4)")
        bad = ~np.isfinite(T).all(axis=(1, 2))
        T[bad] = np.nan  # a pose with any non-finite entry is an unknown pose
    return report


def _dataset_manifest(name: str | None, root: str | None, camera: dict | None, content_hash: str | None,
                      n_frames: int | None, notes: list[str]):
    """The dataset's frame manifest when its files are on disk (registered name, or the bundle's
    recorded root) and, where the bundle records one, its content hash matches; else None with a
    note. Never downloads, generates or converts anything."""
    from atlas_pipeline.sensors.camera import CameraIntrinsics
    from atlas_pipeline.sensors.layouts import detect_kind
    from atlas_pipeline.sensors.registry import DatasetEntry, load_registry, read_dataset_manifest

    if not name:
        _note(notes, "the bundle names no dataset: keyframe frusta without images")
        return None
    try:
        entry = load_registry().get(name)
    except AtlasError as exc:
        logger.warning("dataset registry unreadable (%s); looking for '%s' at its recorded folder only", exc, name)
        entry = None
    where = Path(root) if root and Path(root).exists() else (entry.path if entry is not None else None)
    if where is None or not Path(where).exists():
        _note(notes, "frames of dataset '%s' are not on disk (%s): keyframe frusta without images",
              name, where or "no folder recorded")
        return None
    try:
        if entry is None:
            kind = detect_kind(where)
            if kind is None:
                _note(notes, "%s is not a recording of a known layout: keyframe frusta without images", where)
                return None
            cam = CameraIntrinsics.from_dict(camera) if camera else None
            entry = DatasetEntry(name=name, kind=kind, path=Path(where), camera=cam)  # type: ignore[arg-type]
        if entry.kind == "bag":
            # Reading a bag converts it first (minutes for a long one): not a viewer's job.
            _note(notes, "dataset '%s' is a bag recording: keyframe frusta without images", name)
            return None
        manifest = read_dataset_manifest(entry, n_frames, Path(where))
    except AtlasError as exc:
        _note(notes, "frames of dataset '%s' could not be read (%s): keyframe frusta without images", name, exc)
        return None
    if content_hash and manifest.content_hash and manifest.content_hash != content_hash:
        _note(notes, "frames of dataset '%s' at %s changed since the world was built (content hash differs): "
                     "keyframe frusta without images", name, where)
        return None
    return manifest


def _keyframe_manifests(meta: dict[str, Any], where: Path, n: int, own_manifest: Any, notes: list[str]) -> list[Any]:
    """``n`` recordings, one per keyframe: the one each keyframe names in ``meta`` (the bundle's
    dataset's manifest ``own_manifest`` for its own), None where it is not on disk or holds other
    frames (with a note)."""
    from atlas_pipeline.scene_memory.recordings import bundle_keyframe_sources, recording_index

    try:
        ks = bundle_keyframe_sources(meta, where)
    except AtlasError as exc:
        _note(notes, "keyframe images not shown: %s", exc)
        return [None] * n
    if len(ks) != n:
        return [None] * n
    ds = meta.get("dataset")
    own = recording_index(ks.recordings, ds) if isinstance(ds, dict) else None
    opened: dict[int, Any] = {}
    for u in sorted(set(ks.recording.tolist())):
        r = ks.recordings[u]
        if u == own:
            opened[u] = own_manifest
        elif not r.get("name") and not r.get("root"):
            _note(notes, "%d keyframes come from a recording this world does not record: frusta without images",
                  int((ks.recording == u).sum()))
            opened[u] = None
        else:
            opened[u] = _dataset_manifest(r.get("name"), r.get("root"), r.get("camera"), r.get("content_hash"),
                                          r.get("n_frames"), notes)
    return [opened[u] for u in ks.recording.tolist()]


def _same_frame_times(manifest: Any, rep: Any) -> bool:
    """Whether the report ``rep``'s frames are the first frames of ``manifest``, by their times
    (within :data:`REPORT_TIME_TOLERANCE_S`; no relative tolerance: Unix times are ~1.3e9 s)."""
    n = rep.n_frames
    return manifest.n_frames >= n and bool(np.allclose(manifest.timestamps_s[:n], rep.timestamps_s, rtol=0.0,
                                                       atol=REPORT_TIME_TOLERANCE_S))


def _thumbnail(rgb: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` uint8 to at most THUMBNAIL_MAX_WIDTH_PX wide, by block averaging (no aliasing
    of fine texture as plain striding would give)."""
    f = max(1, math.ceil(rgb.shape[1] / THUMBNAIL_MAX_WIDTH_PX))
    h, w = rgb.shape[0] // f * f, rgb.shape[1] // f * f
    blocks = rgb[:h, :w].reshape(h // f, f, w // f, f, 3).astype(np.float32)
    return np.clip(blocks.mean(axis=(1, 3)) + 0.5, 0, 255).astype(np.uint8)


def _keyframes(metadata: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(indices [K], T_world_cam [K, 4, 4])`` from metadata ``keyframes`` (checked)."""
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses

    poses = bundle_keyframe_poses(metadata)
    raw = (metadata.get("keyframes") or {}).get("indices", [])
    try:
        idx = np.asarray(raw, np.int64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as exc:
        raise BundleFormatError("metadata.json", "keyframes.indices must be a list of frame numbers") from exc
    if len(idx) != len(poses):
        # Poses are still worth drawing; the images need the index of each.
        logger.warning("metadata keyframes: %d indices for %d poses; keyframe images are not shown",
                       len(idx), len(poses))
        idx = np.full(len(poses), -1, np.int64)
    return idx, poses


def _ground_truth_in_world(T_est: np.ndarray, T_gt: np.ndarray, status: list[str],
                           same_frame: bool) -> tuple[np.ndarray | None, str]:
    """Ground truth ``T_gt`` ``[N, 4, 4]`` moved into the world frame (None when it cannot be), and
    how: as is when the world was mapped in its frame (``same_frame``), else by the rigid ATE
    alignment onto the estimates ``T_est`` ``[N, 4, 4]`` (which localization put in the world frame)."""
    from atlas_pipeline.localization.metrics import align_rigid

    known_gt = np.isfinite(T_gt).all(axis=(1, 2))
    if not known_gt.any():
        return None, "no ground truth for these frames"
    if same_frame:
        return T_gt, "world frame (the world was mapped at this sequence's ground-truth poses)"
    ok = known_gt & np.isfinite(T_est).all(axis=(1, 2)) & np.array([s != STATUS_ANCHOR for s in status], bool)
    if ok.sum() < 3:
        return None, "ground truth is in another frame and fewer than 3 placed frames tie it to the world"
    return (align_rigid(T_gt[ok], T_est[ok]) @ T_gt,
            "aligned onto the estimate (ATE alignment; the world was not mapped in its frame)")


def load_viewer_data(world_dir: str | Path, report: str | Path | None = None, read_dataset: bool = True,
                     layers: tuple[str | Path, ...] | list[str | Path] = (),
                     compute_layers: bool = False) -> ViewerData:
    """Load and check what the viewer shows: the bundle at ``world_dir`` (checksums verified), its
    localization report (``report``: a folder with ``localization.json``; default the bundle's own),
    with ``read_dataset`` the keyframe thumbnails and the ground truth from the dataset's frames
    when they are on disk and unchanged (bundles keep neither), and the mesh and occupancy layers
    from the export folders ``layers``, the missing ones computed from the keyframes when
    ``compute_layers`` and ``read_dataset`` (:func:`~atlas_pipeline.viz.viewer_layers.load_layers`)."""
    from atlas_pipeline.scene_memory.bundle import load_world_bundle
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    world_dir = Path(world_dir)
    bundle = load_world_bundle(world_dir)  # schema + every listed file's size and sha256
    meta = bundle.metadata
    idx, T_kf = _keyframes(meta)
    data = ViewerData(world_dir, bundle.field, meta, idx, T_kf, [None] * len(T_kf))
    ds = meta.get("dataset") or {}
    if not isinstance(ds, dict):
        ds = {}
    cam_dict = ds.get("camera") if isinstance(ds.get("camera"), dict) else None
    if cam_dict:
        try:
            cam = CameraIntrinsics.from_dict(cam_dict)
            data.camera_fov_y_rad = 2.0 * math.atan(cam.height / (2.0 * cam.fy))
            data.camera_aspect = cam.width / cam.height
        except ConfigError as exc:
            _note(data.notes, "metadata dataset.camera unusable (%s): frusta drawn with a 60-degree 4:3 camera", exc)
            cam_dict = None
    n_frames = ds.get("n_frames") if isinstance(ds.get("n_frames"), int) and ds.get("n_frames") > 0 else None
    name = ds.get("name") if isinstance(ds.get("name"), str) else None
    root = ds.get("root") if isinstance(ds.get("root"), str) else None
    content_hash = ds.get("content_hash") if isinstance(ds.get("content_hash"), str) else None

    manifest = None
    if read_dataset and len(T_kf):
        manifest = _dataset_manifest(name, root, cam_dict, content_hash, n_frames, data.notes)
    elif len(T_kf):
        _note(data.notes, "dataset not read: keyframe frusta without images")
    data.keyframe_manifest = manifest
    data.keyframe_manifests = (_keyframe_manifests(meta, world_dir / "metadata.json", len(T_kf), manifest, data.notes)
                               if read_dataset and len(T_kf) else [None] * len(T_kf))
    for k in controls.thinned_indices(len(T_kf), MAX_FRUSTA):  # images on the frusta drawn
        m, i = data.keyframe_manifests[k], int(idx[k])  # frame i of keyframe k's own recording
        if m is None or not 0 <= i < m.n_frames:
            continue
        try:
            data.keyframe_images[k] = _thumbnail(m.read_rgb(i))
        except (AtlasError, OSError) as exc:
            logger.warning("keyframe %d (frame %d of '%s'): image not shown (%s)", k, i, m.dataset, exc)

    # The localization report: --report, else the bundle's own (verified with the bundle).
    rep_dir = Path(report) if report is not None else (world_dir if "localization.json" in meta["files"] else None)
    if rep_dir is None:
        _note(data.notes, "no localization report in the bundle: no trajectories "
                          "(run `atlas-gs localize`, or give --report)")
    else:
        rep = load_report_checked(rep_dir)
        data.report_source = str(rep_dir)
        if rep.map_id and bundle.map_id and rep.map_id != bundle.map_id:
            logger.warning("the report at %s was made in world %s, this bundle is world %s: its poses may be in "
                           "another frame", rep_dir, rep.map_id, bundle.map_id)
        data.status = list(rep.status)
        data.T_world_cam_est = rep.T_world_cam
        data.report_timestamps_s = rep.timestamps_s
        # the report's frames: the bundle's dataset, or another recording of its keyframes (an
        # extended world's parent's), whichever holds frames at the report's times
        opened = [m for m in [manifest, *data.keyframe_manifests] if m is not None and m.dataset == rep.dataset]
        data.report_manifest = next((m for m in opened if _same_frame_times(m, rep)), None)
        r = rep.recording or {}
        if data.report_manifest is None and read_dataset and (r.get("root") or r.get("name")):
            # the recording the report names (by content), e.g. one localized in an imported world
            m = _dataset_manifest(r.get("name"), r.get("root"), r.get("camera"), r.get("content_hash"),
                                  r.get("n_frames"), [])
            data.report_manifest = m if m is not None and _same_frame_times(m, rep) else None
        T_gt = rep.T_world_cam_gt
        if not np.isfinite(T_gt).all(axis=(1, 2)).any():
            # Bundles keep no ground truth: take it from the dataset when its frames are on disk.
            gt_manifest = data.report_manifest or (manifest if (manifest is not None and rep.dataset == name) else None)
            if gt_manifest is None and read_dataset:
                gt_manifest = _dataset_manifest(rep.dataset, root if rep.dataset == name else None,
                                                cam_dict if rep.dataset == name else None,
                                                content_hash if rep.dataset == name else None, None, [])
            if gt_manifest is not None and _same_frame_times(gt_manifest, rep):
                T_gt = gt_manifest.T_world_cam_gt[:rep.n_frames]
        gaussians_info = meta.get("gaussians") if isinstance(meta.get("gaussians"), dict) else {}
        same_frame = gaussians_info.get("pose_source") == "ground_truth" and rep.dataset == name
        data.T_world_cam_gt, data.ground_truth_note = _ground_truth_in_world(rep.T_world_cam, T_gt, rep.status,
                                                                             same_frame)
        if data.T_world_cam_gt is None:
            _note(data.notes, "ground truth not shown: %s", data.ground_truth_note)
    if layers or (compute_layers and read_dataset):
        data.mesh, data.occupancy = load_layers(world_dir, [Path(p) for p in layers], compute_layers and read_dataset,
                                                data.notes)
    return data


# ---- the viser scene ----------------------------------------------------------------------------


def splat_covariances(scales_m: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Covariances ``[N, 3, 3]`` (m^2) of Gaussians with standard deviations ``scales_m`` ``[N, 3]``
    along their local axes and orientation ``quat_xyzw`` ``[N, 4]`` (local to world):
    ``R diag(s^2) R^T``, which is what viser's ``add_gaussian_splats`` takes."""
    R = quat_xyzw_to_rotmat(np.asarray(quat_xyzw, np.float64))  # [N, 3, 3]
    s = np.clip(np.asarray(scales_m, np.float64), MIN_SPLAT_SIGMA_M, MAX_SPLAT_SIGMA_M)  # [N, 3]
    return np.einsum("nij,nj,nkj->nik", R, s * s, R).astype(np.float32)


def _wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix ``[3, 3]`` to viser's ``wxyz`` quaternion ``[4]``."""
    q = rotmat_to_quat_xyzw(R)
    return np.array([q[3], q[0], q[1], q[2]])


def _extent(data: ViewerData) -> tuple[np.ndarray, float]:
    """Centre ``[3]`` and diagonal (m) of the robust box around the Gaussians (keyframes as a
    fallback), at least 1 m so an empty or tiny world still gets visible frusta."""
    pts = data.field.positions.astype(np.float64)
    if len(pts) == 0:
        pts = data.T_world_cam_keyframes[:, :3, 3] if len(data.T_world_cam_keyframes) else np.zeros((1, 3))
    lo, hi = np.percentile(pts, EXTENT_PERCENTILES, axis=0)
    return np.median(pts, axis=0), float(max(np.linalg.norm(hi - lo), 1.0))


def _segments(points: np.ndarray) -> np.ndarray:
    """Line segments ``[M, 2, 3]`` joining consecutive finite points of ``points`` ``[N, 3]`` (a
    NaN point breaks the line: frames never placed are not bridged)."""
    ok = np.isfinite(points).all(axis=1)
    both = ok[:-1] & ok[1:]
    return np.stack([points[:-1][both], points[1:][both]], axis=1).astype(np.float32)


def _up_direction(T_world_cam: np.ndarray) -> np.ndarray:
    """World up ``[3]`` from keyframe poses: cameras are held upright, so their image "up" (-y)
    averages to the world's up; +z when that average is too weak (no keyframes, a spinning camera)."""
    if len(T_world_cam):
        up = -T_world_cam[:, :3, 1].mean(axis=0)
        if np.linalg.norm(up) > 0.3:
            return up / np.linalg.norm(up)
    return np.array([0.0, 0.0, 1.0])


def build_scene(server: Any, data: ViewerData) -> dict[str, Any]:
    """Fill ``server`` (a ``viser.ViserServer``) with the scene of ``data``; returns a summary (what
    was drawn: counts per layer, the ground truth's frame, the notes)."""
    scene = server.scene
    centre, diag_m = _extent(data)
    up = _up_direction(data.T_world_cam_keyframes)
    scene.set_up_direction(tuple(float(v) for v in up))
    f = data.field
    handles: dict[str, list[Any]] = {"Gaussians": [], "Mesh": [], "Occupancy": [], "Trajectories": [],
                                     "Keyframes": [], "Lost / relocalized": []}

    splats, covariances = None, None
    if len(f):
        covariances = splat_covariances(f.scales, f.rotations_xyzw)  # [N, 3, 3]
        splats = scene.add_gaussian_splats(
            "/world/gaussians",
            centers=f.positions.astype(np.float32),  # [N, 3]
            covariances=covariances,
            rgbs=f.colors,  # [N, 3] uint8
            opacities=f.opacities.reshape(-1, 1).astype(np.float32),  # [N, 1]
        )
        handles["Gaussians"].append(splats)
    if data.mesh is not None:
        handles["Mesh"].append(scene.add_glb("/world/mesh", mesh_glb(data.mesh), cast_shadow=False,
                                             receive_shadow=False))
    if data.occupancy is not None:
        occ = data.occupancy
        handles["Occupancy"].append(scene.add_image(
            "/world/occupancy", occ.rgba, occ.width_m, occ.height_m, format="png", cast_shadow=False,
            receive_shadow=False, wxyz=_wxyz(occ.T_world_quad[:3, :3]), position=occ.T_world_quad[:3, 3]))

    drawn = controls.thinned_indices(len(data.T_world_cam_keyframes), MAX_FRUSTA)
    if len(drawn) < len(data.T_world_cam_keyframes):
        _note(data.notes, "%d keyframes: %d of them drawn as frusta (the slider reaches every frame)",
              len(data.T_world_cam_keyframes), len(drawn))
    frustum_m = controls.frustum_size(diag_m, len(drawn), FRUSTUM_SIZE_FRACTION, FRUSTUM_SIZE_RANGE_M)
    n_images = 0
    for k in drawn:
        T, img = data.T_world_cam_keyframes[k], data.keyframe_images[k]
        n_images += img is not None
        handles["Keyframes"].append(scene.add_camera_frustum(
            f"/keyframes/kf_{k:05d}", fov=data.camera_fov_y_rad, aspect=data.camera_aspect, scale=frustum_m,
            color=KEYFRAME_RGB, image=img, format="jpeg", jpeg_quality=THUMBNAIL_JPEG_QUALITY,
            wxyz=_wxyz(T[:3, :3]), position=T[:3, 3], thickness=1.0, thickness_units="screen",
            cast_shadow=False, receive_shadow=False))

    est_xyz = data.T_world_cam_est[:, :3, 3]  # [N, 3], NaN rows: never placed
    gt_xyz = data.T_world_cam_gt[:, :3, 3] if data.T_world_cam_gt is not None else np.zeros((0, 3))
    for name, xyz, rgb in (("estimated", est_xyz, ESTIMATED_RGB), ("ground_truth", gt_xyz, GROUND_TRUTH_RGB)):
        seg = _segments(xyz) if len(xyz) > 1 else np.zeros((0, 2, 3), np.float32)
        if len(seg):
            handles["Trajectories"].append(scene.add_line_segments(
                f"/trajectories/{name}", points=seg, colors=rgb, thickness=TRAJECTORY_WIDTH_PX,
                thickness_units="screen"))

    status = np.array(data.status, dtype=object)
    marker_m = max(MARKER_SIZE_FRACTION * diag_m, 0.01)
    shown: dict[str, int] = {}
    for label, rgb in ((STATUS_LOST, LOST_RGB), (STATUS_RELOCALIZED, RELOCALIZED_RGB)):
        sel = status == label if len(status) else np.zeros(0, bool)
        # A lost frame's estimate may be unknown (NaN): mark it where ground truth puts it.
        xyz = np.where(np.isfinite(est_xyz).all(axis=1, keepdims=True), est_xyz,
                       gt_xyz if len(gt_xyz) == len(est_xyz) else np.nan)[sel]
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        shown[label] = int(len(xyz))
        if int(sel.sum()) > len(xyz):
            _note(data.notes, "%d %s frames have no known position and are not marked",
                  int(sel.sum()) - len(xyz), label)
        if len(xyz):
            handles["Lost / relocalized"].append(scene.add_point_cloud(
                f"/frames/{label}", points=xyz.astype(np.float32), colors=rgb, point_size=marker_m,
                point_shape="circle", point_shading="flat"))

    view = controls.orbit_view(f.positions, data.T_world_cam_keyframes[:, :3, 3], centre, diag_m, up,
                               EXTENT_PERCENTILES)
    server.initial_camera.position = tuple(float(v) for v in view.position)
    server.initial_camera.look_at = tuple(float(v) for v in view.pivot)
    server.initial_camera.up = tuple(float(v) for v in up)
    controls.install_camera_limits(server, view)

    summary = {
        "world": str(data.world_dir), "map_id": data.metadata.get("map_id"), "n_gaussians": len(f),
        "n_keyframes": len(data.T_world_cam_keyframes), "n_keyframe_images": int(n_images),
        "n_frusta": int(len(drawn)),
        "n_frames": len(data.status), "n_estimated_poses": int(np.isfinite(est_xyz).all(axis=1).sum()),
        "n_ground_truth_poses": int(np.isfinite(gt_xyz).all(axis=1).sum()),
        "ground_truth_frame": data.ground_truth_note or None, "report": data.report_source or None,
        "n_lost_marked": shown[STATUS_LOST], "n_relocalized_marked": shown[STATUS_RELOCALIZED],
        **layer_summary(data.mesh, data.occupancy),
        "start_view": {"position": view.position.tolist(), "look_at": view.pivot.tolist(), "radius_m": view.radius_m},
        "notes": list(data.notes),
    }
    track = controls.frame_track(data.T_world_cam_est, data.T_world_cam_gt, data.status, data.report_timestamps_s,
                                 data.report_manifest, data.T_world_cam_keyframes, data.keyframe_indices,
                                 data.keyframe_manifests)
    widgets = _add_panel(server, summary, handles)
    widgets["frame"] = controls.add_frame_slider(
        server, track, data.camera_fov_y_rad, data.camera_aspect, frustum_m, marker_m, _thumbnail,
        {STATUS_LOST: LOST_RGB, STATUS_RELOCALIZED: RELOCALIZED_RGB, STATUS_TRACKED: ESTIMATED_RGB})
    widgets.update(controls.add_view_controls(server, view, splats, covariances))
    if summary["notes"]:
        server.gui.add_markdown("  \n".join(f"- {n}" for n in summary["notes"]))
    summary["widgets"] = widgets
    summary["view"] = view
    return summary


def _add_panel(server: Any, summary: dict[str, Any], handles: dict[str, list[Any]]) -> dict[str, Any]:
    """The side panel's legend with the counts, and a switch per layer drawn; returns the switches
    by layer name."""
    gui = server.gui

    def swatch(rgb: tuple[int, int, int]) -> str:
        return f"<span style='color:rgb{rgb}'>&#9632;</span>"

    lines = [
        f"**{summary['n_gaussians']:,} Gaussians**, map `{summary['map_id']}`",
        f"{swatch(KEYFRAME_RGB)} {summary['n_keyframes']} keyframes ({summary['n_frusta']} drawn, "
        f"{summary['n_keyframe_images']} with images)",
        f"{swatch(ESTIMATED_RGB)} estimated trajectory: {summary['n_estimated_poses']} of {summary['n_frames']} frames",
        f"{swatch(GROUND_TRUTH_RGB)} ground truth: {summary['n_ground_truth_poses']} frames",
        f"{swatch(LOST_RGB)} lost: {summary['n_lost_marked']}  {swatch(RELOCALIZED_RGB)} relocalized: "
        f"{summary['n_relocalized_marked']}",
    ]
    if summary["n_mesh_triangles"]:
        lines.append(f"mesh: {summary['n_mesh_triangles']:,} triangles (of {summary['n_mesh_source_triangles']:,})")
    if summary["occupancy_cells"]:
        c = summary["occupancy_cells"]
        lines.append(f"occupancy: {c['free']:,} free, {c['occupied']:,} occupied, {c['unknown']:,} unknown cells")
    gui.add_markdown("  \n".join(lines))
    boxes: dict[str, Any] = {}
    with gui.add_folder("Layers"):
        for layer, hs in handles.items():
            if not hs:
                continue
            box = gui.add_checkbox(layer, initial_value=True)

            def toggle(_event: Any, hs: list[Any] = hs, box: Any = box) -> None:
                for h in hs:
                    h.visible = box.value

            box.on_update(toggle)
            boxes[layer] = box
    return boxes



# ---- the server ---------------------------------------------------------------------------------


# The hosts (as a browser writes them in an ``Origin`` header) whose pages may open the viewer's
# websocket: loopback ones, any port (the viewer moves to the next port when its own is taken). Any
# other origin (a web site in another tab, a DNS-rebinding name for 127.0.0.1) is refused at the
# handshake (HTTP 403); a client that sends no ``Origin`` (not a browser: a script on this machine)
# is let in, as anything local could read the bundle's files anyway.
ALLOWED_ORIGIN_HOSTS = (r"127(\.\d{1,3}){3}", "localhost", r"\[::1\]")


def allowed_origins(host: str) -> list[Any]:
    """The ``Origin`` values the websocket of a viewer bound to ``host`` accepts (the ``origins`` of
    ``websockets``' server): none, or ``http(s)://`` a loopback host (or ``host`` itself, for a
    viewer bound elsewhere with ``allow_remote``) with any port."""
    hosts = list(ALLOWED_ORIGIN_HOSTS)
    if not is_loopback_host(host):
        hosts.append(re.escape(f"[{host.strip('[]')}]" if ":" in host else host))
    return [None, re.compile(rf"https?://({'|'.join(hosts)})(:\d+)?")]


@contextlib.contextmanager
def _origin_checked_websocket(origins: list[Any]) -> Iterator[list[bool]]:
    """While the viewer's server starts: viser's websocket server gets ``origins`` (viser has no
    option for it). Yields a one-item list that becomes ``[True]`` once viser's server took them;
    the caller refuses to serve when it did not (a viser that no longer starts its server through
    ``websockets.asyncio.server.serve``)."""
    import websockets.asyncio.server as ws_server

    original = ws_server.serve
    applied = [False]

    def serve(handler: Any, *args: Any, **kwargs: Any) -> Any:
        if getattr(handler, "__module__", "").startswith("viser.") and kwargs.get("origins") is None:
            kwargs["origins"] = origins
            applied[0] = True
        return original(handler, *args, **kwargs)

    ws_server.serve = serve
    try:
        yield applied
    finally:
        ws_server.serve = original


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` names this machine only (127.0.0.0/8, ::1, ``localhost``)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass
class ViewerHandle:
    """A running viewer: ``url``, the ``viser.ViserServer`` and the scene summary; ``stop()`` (or
    leaving a ``with`` block) shuts the server down."""

    server: Any
    url: str
    summary: dict[str, Any]

    def stop(self) -> None:
        with _quiet_stdout():
            self.server.stop()

    def __enter__(self) -> "ViewerHandle":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """viser prints a banner of its URLs and a "server stopped" line on stdout with rich; we log
    and print our own line instead (one format, and the URL we print is the one that works)."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def _refuse_share_url(*_args: Any, **_kwargs: Any) -> None:
    logger.warning("share URL refused: it would publish this viewer through viser's public relay")
    return None


def serve(world_dir: str | Path, host: str = DEFAULT_HOST, port: int = 0, report: str | Path | None = None,
          read_dataset: bool = True, allow_remote: bool = False, data: ViewerData | None = None,
          layers: tuple[str | Path, ...] | list[str | Path] = (), compute_layers: bool = True) -> ViewerHandle:
    """Start a viewer of the bundle at ``world_dir`` on ``host:port`` (``port`` 0: a free one) and
    return its handle; the server runs in background threads until ``handle.stop()``.

    ``host`` must be a loopback address unless ``allow_remote``: the viewer has no authentication
    and serves the map and camera images of a recorded place to whoever connects. Its websocket
    takes pages from a loopback origin or from ``host`` itself (:func:`allowed_origins`), so a
    remote viewer must be bound to the name or address its browsers use, not a wildcard
    (``0.0.0.0``). ``data`` (from :func:`load_viewer_data`) skips loading; ``layers`` (export
    folders) and ``compute_layers`` go to it otherwise.
    """
    import viser

    if not is_loopback_host(host) and not allow_remote:
        raise ConfigError(f"--host {host}: the viewer binds loopback addresses only (127.0.0.1, ::1, localhost); "
                          "it has no authentication, and serves the map and camera images of a recorded place. "
                          "To look from another machine, forward the port (ssh -L PORT:127.0.0.1:PORT host)")
    if not 0 <= int(port) <= 65535:
        raise ConfigError(f"--port {port}: must be 0 (any free port) to 65535")
    if data is None:
        data = load_viewer_data(world_dir, report, read_dataset, layers, compute_layers)
    with _quiet_stdout(), _origin_checked_websocket(allowed_origins(host)) as checked:
        server = viser.ViserServer(host=host, port=int(port), label="atlas-gs", verbose=False)
    try:
        if not checked[0]:
            raise AtlasError(f"viser {getattr(viser, '__version__', '?')} started its websocket server in a way "
                             "atlas-gs cannot give an Origin check; refusing to serve the map to any web page "
                             "that asks (install viser 1.x as pinned in pyproject.toml)")
        server.request_share_url = _refuse_share_url  # a browser's share button calls this
        server.gui.configure_theme(show_share_button=False, control_width="medium")
        summary = build_scene(server, data)
    except BaseException:
        with _quiet_stdout():
            server.stop()
        raise
    bound = server.get_port()
    if port and bound != int(port):
        logger.warning("port %d is taken: the viewer listens on %d instead", port, bound)
    url_host = f"[{host.strip('[]')}]" if ":" in host else host
    url = f"http://{url_host}:{bound}/"
    summary["url"] = url
    logger.info("viewer of %s at %s (%d Gaussians, %d keyframes)", world_dir, url, summary["n_gaussians"],
                summary["n_keyframes"])
    return ViewerHandle(server, url, summary)


def run_viewer(world_dir: str | Path, host: str = DEFAULT_HOST, port: int = 0, report: str | Path | None = None,
               read_dataset: bool = True, allow_remote: bool = False,
               announce: Callable[[str], None] = print, stop_event: threading.Event | None = None,
               layers: tuple[str | Path, ...] | list[str | Path] = (), compute_layers: bool = True) -> int:
    """Serve the viewer and block until Ctrl-C, SIGTERM (``docker stop``, ``kill``) or ``stop_event``;
    the server is always stopped before returning 0. ``announce`` receives the line naming the URL
    (the CLI prints it on stdout); ``layers`` and ``compute_layers`` as for :func:`serve`."""
    handle = serve(world_dir, host, port, report, read_dataset, allow_remote, layers=layers,
                   compute_layers=compute_layers)
    stop_event = stop_event or threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():  # signal handlers live in the main thread
        previous = signal.signal(signal.SIGTERM, lambda *_: stop_event.set())
    try:
        announce(f"atlas-gs viewer of {Path(world_dir).resolve()}: open {handle.url}  (Ctrl-C to stop)")
        while not stop_event.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        handle.stop()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    logger.info("viewer stopped")
    return 0

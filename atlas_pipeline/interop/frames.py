"""Which frames of a world's recording go to another tool, at which poses, and their pixels.

A world bundle stores its Gaussians, the keyframes' indices and poses, and (after ``localize``)
every frame's estimated pose; it stores no images or depth. The frames are read from the bundle's
dataset (by registry name, else the folder recorded in ``metadata.json``), checked against the
content hash the bundle records, so an export never pairs poses with other frames.

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
           "pinhole_camera", "undistorted_rgb", "undistorted_depth_m", "frame_name"]

POSE_SOURCES = ("auto", "keyframes", "estimated", "ground_truth")
PLACED_STATUSES = ("anchor", "tracked", "relocalized")  # a lost frame's pose is only the motion model's guess
FRAME_NAME_DIGITS = 6


def frame_name(index: int, suffix: str = ".png") -> str:
    """``frame_000123.png``: the file name of dataset frame ``index`` in every export."""
    return f"frame_{int(index):0{FRAME_NAME_DIGITS}d}{suffix}"


@dataclass
class ExportSource:
    """A world and the frames that go with it.

    Attributes:
        field: the Gaussians (points for COLMAP's ``points3D``, the mesh preview ...).
        manifest: the recording the frames come from.
        frame_indices: ``[M]`` indices into ``manifest``.
        T_world_cam: ``[M, 4, 4]`` camera-to-world (OpenCV camera: x right, y down, z forward).
        pose_source: ``keyframes``, ``estimated`` or ``ground_truth``.
        map_id: the world's id.
    """

    field: GaussianField
    manifest: FrameManifest
    frame_indices: np.ndarray
    T_world_cam: np.ndarray
    pose_source: str
    map_id: str = ""
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.frame_indices = np.asarray(self.frame_indices, np.int64)
        self.T_world_cam = np.asarray(self.T_world_cam, np.float64)
        if len(self.frame_indices) == 0:
            raise AtlasError(f"no frames with a {self.pose_source} pose to export")
        if self.T_world_cam.shape != (len(self.frame_indices), 4, 4) or not np.isfinite(self.T_world_cam).all():
            raise AtlasError(f"{self.pose_source} poses must be finite 4x4 matrices, one per frame")
        if self.frame_indices.min() < 0 or self.frame_indices.max() >= self.manifest.n_frames:
            raise AtlasError(f"frame indices {self.frame_indices.min()}..{self.frame_indices.max()} are outside the "
                             f"{self.manifest.n_frames} frames of dataset '{self.manifest.dataset}'")

    def thinned(self, step: int) -> "ExportSource":
        """Every ``step``-th frame (the first kept)."""
        if step == 1:
            return self
        return ExportSource(self.field, self.manifest, self.frame_indices[::step], self.T_world_cam[::step],
                            self.pose_source, self.map_id, self.notes)


def check_frame_step(step: Any, option: str = "--frame-step") -> int:
    """``step`` as a positive integer, else a ConfigError naming ``option``."""
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise ConfigError(f"{option} must be an integer >= 1, got {step!r}")
    return int(step)


def check_pose_source(poses: str, option: str = "--poses") -> str:
    if poses not in POSE_SOURCES:
        raise ConfigError(f"{option} must be one of {', '.join(POSE_SOURCES)}, got {poses!r}")
    return poses


def source_from_world(field: GaussianField, manifest: FrameManifest, keyframe_indices: np.ndarray,
                      T_world_cam_keyframes: np.ndarray, localization: Any = None, poses: str = "auto",
                      world_pose_source: str | None = None, map_id: str = "") -> ExportSource:
    """The frames of a world in memory (the Dagster assets' inputs): see the module docstring for
    ``poses``; ``localization`` is a ``LocalizationReport`` of ``manifest``'s frames or None."""
    poses = check_pose_source(poses)
    if poses == "auto":
        poses = "estimated" if localization is not None else "keyframes"
    if poses == "keyframes":
        return ExportSource(field, manifest, keyframe_indices, T_world_cam_keyframes, "keyframes", map_id)
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


def _bundle_manifest(meta: dict[str, Any], report_dataset: str | None, dataset: Any) -> FrameManifest:
    """The manifest of the recording the bundle names (or ``dataset``: a ``DatasetEntry`` the
    caller resolved), its content hash checked against the bundle's."""
    from atlas_pipeline.sensors.registry import DatasetEntry, ensure_dataset_files, load_registry, read_dataset_manifest
    from atlas_pipeline.sensors.layouts import detect_kind

    ds = meta.get("dataset") or {}
    name = report_dataset or ds.get("name")
    if dataset is None:
        if not name:
            raise DatasetError("metadata.json", "the world names no dataset (an imported PLY?): give the frames' "
                                                "recording with --input DATASET")
        entry = load_registry().get(name)
        root = Path(ds["root"]) if ds.get("root") and name == ds.get("name") else None
        if entry is None:
            if root is None or not root.exists():
                raise DatasetError(root or name, f"the frames of dataset '{name}' are not on disk and it is not "
                                                 "registered: give them with --input DATASET")
            kind = detect_kind(root)
            if kind is None:
                raise DatasetError(root, "is not a recording of a known layout; give the frames with --input DATASET")
            cam = CameraIntrinsics.from_dict(ds["camera"]) if ds.get("camera") else None
            entry = DatasetEntry(name=name, kind=kind, path=root, camera=cam)  # type: ignore[arg-type]
    else:
        entry = dataset
    if entry.kind == "synthetic":
        ensure_dataset_files(entry)  # generated from its spec, deterministically: never a download
    manifest = read_dataset_manifest(entry, None)
    want = ds.get("content_hash") if name == ds.get("name") else None
    if want and manifest.content_hash and manifest.content_hash != want:
        raise DatasetError(entry.path, f"the frames of dataset '{entry.name}' are not the ones this world was built "
                                       "from (content hash differs): poses would be paired with other images")
    return manifest


def source_from_bundle(bundle_dir: str | Path, poses: str = "auto", dataset: Any = None,
                       frame_step: int = 1) -> ExportSource:
    """The frames of the world bundle at ``bundle_dir`` (every listed file verified first)."""
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle

    poses = check_pose_source(poses)
    frame_step = check_frame_step(frame_step)
    b = load_world_bundle(bundle_dir)
    meta = b.metadata
    report = LocalizationReport.load(b.directory) if "localization.json" in meta["files"] else None
    manifest = _bundle_manifest(meta, report.dataset if report is not None and poses in ("auto", "estimated")
                                else None, dataset)
    kf = meta.get("keyframes") or {}
    kf_idx = np.asarray(kf.get("indices", []), np.int64)
    kf_T = bundle_keyframe_poses(meta)
    if len(kf_idx) != len(kf_T):
        raise DatasetError(Path(bundle_dir) / "metadata.json", "keyframes.indices and keyframes.T_world_cam differ "
                                                               "in length")
    if report is not None and report.dataset != manifest.dataset:
        report = None if poses == "auto" else report
    src = source_from_world(b.field, manifest, kf_idx, kf_T, report, poses,
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

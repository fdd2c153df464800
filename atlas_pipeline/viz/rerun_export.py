"""A Rerun recording (``.rrd``) of a world bundle and its sequence, for robotics users' tooling.

What the recording holds (entity paths, ``world`` is the bundle's frame, metres):

* ``world/gaussians``: the Gaussians (``GaussianSplats3D``: centres, per-axis scales, ``quat_xyzw``
  rotations, colour with the opacity as alpha), static;
* ``world/keyframes``: the keyframe camera centres, static;
* ``world/trajectory/estimated`` and ``world/trajectory/ground_truth``: the localization report's
  placed poses and the ground truth in the world frame (as the viewer aligns it), static lines;
* on the ``frame`` timeline (and ``time``, the sequence's timestamps): ``world/camera`` (the
  estimated ``T_world_cam``; frames never placed have none), ``world/camera/image`` (the pinhole,
  the RGB image, JPEG-compressed, and the depth in metres), ``status`` (the frame's tracking status
  as a text log: warnings for lost frames) and ``status/lost`` (1 for lost frames, else 0).

Inputs come through the viewer's checked loaders (:func:`atlas_pipeline.viz.viewer.load_viewer_data`:
the bundle's checksums verified, the report's fields checked); the frames are read only when the
dataset is on disk and unchanged. The file is written under a temporary name beside the target and
renamed into place.

Open it with ``rerun FILE.rrd`` (``pip install rerun-sdk``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import numpy as np

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.io_utils import atomic_path
from atlas_pipeline.progress import Progress

__all__ = ["export_rerun", "RRD_APPLICATION_ID"]

logger = logging.getLogger(__name__)

RRD_APPLICATION_ID = "atlas-gs"
# RGB frames are stored as JPEG: a 640x480 frame is ~0.9 MB raw, ~60 kB at this quality.
RRD_JPEG_QUALITY = 85
OPACITY_TO_ALPHA = 255.0  # GaussianSplats3D takes the opacity as the colour's alpha byte


def _positions(T_world_cam: np.ndarray) -> np.ndarray:
    """Camera centres ``[M, 3]`` of the finite poses of ``T_world_cam`` ``[N, 4, 4]``."""
    ok = np.isfinite(T_world_cam).all(axis=(1, 2))
    return T_world_cam[ok, :3, 3]


def export_rerun(world_dir: str | Path, out_path: str | Path, report: str | Path | None = None,
                 read_dataset: bool = True, frame_step: int = 1,
                 log: Callable[[str], None] | None = None) -> Path:
    """Write a Rerun recording of the bundle at ``world_dir`` (and its sequence) to ``out_path``.

    Args:
        world_dir: a world bundle folder.
        out_path: the ``.rrd`` file to write (its folder must exist; an existing file there is
            replaced only if it is a Rerun recording, see the CLI's output rules).
        report: folder with the ``localization.json`` to record (default: the bundle's own).
        read_dataset: read the dataset's frames (RGB, depth) when they are on disk and unchanged.
        frame_step: record every ``frame_step``-th frame of the sequence.

    Returns: ``out_path``.
    """
    import rerun as rr

    from atlas_pipeline.viz.viewer import _dataset_manifest, load_viewer_data

    if frame_step < 1:
        raise ConfigError(f"frame_step must be >= 1, got {frame_step}")
    out_path = Path(out_path)
    data = load_viewer_data(world_dir, report=report, read_dataset=read_dataset)
    ds = data.metadata.get("dataset") if isinstance(data.metadata.get("dataset"), dict) else {}
    manifest = None
    if read_dataset and len(data.status):
        manifest = _dataset_manifest(ds.get("name"), ds.get("root"), ds.get("camera"), ds.get("content_hash"),
                                     ds.get("n_frames"), [])

    rec = rr.RecordingStream(RRD_APPLICATION_ID, recording_id=str(data.metadata.get("map_id") or "atlas-gs"))
    with atomic_path(out_path) as tmp:
        rec.save(str(tmp))
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)  # OpenCV camera axes
        f = data.field
        rgba = np.concatenate([f.colors.astype(np.uint8),
                               np.clip(np.round(f.opacities * OPACITY_TO_ALPHA), 0, 255).astype(np.uint8)[:, None]],
                              axis=1)
        rec.log("world/gaussians", rr.GaussianSplats3D(centers=f.positions, scales=f.scales,
                                                       quaternions=f.rotations_xyzw, colors=rgba), static=True)
        if len(data.T_world_cam_keyframes):
            rec.log("world/keyframes", rr.Points3D(_positions(data.T_world_cam_keyframes)), static=True)
        if len(data.T_world_cam_est):
            rec.log("world/trajectory/estimated", rr.LineStrips3D([_positions(data.T_world_cam_est)]), static=True)
        if data.T_world_cam_gt is not None:
            rec.log("world/trajectory/ground_truth", rr.LineStrips3D([_positions(data.T_world_cam_gt)]), static=True)

        n = len(data.status)
        timestamps = manifest.timestamps_s if manifest is not None else None
        if manifest is not None:
            cam = manifest.camera
            rec.log("world/camera/image", rr.Pinhole(image_from_camera=cam.K, resolution=[cam.width, cam.height]),
                    static=True)
        frames = range(0, n, frame_step)
        progress = Progress("recording frames", len(frames), log)
        for i in frames:
            rec.set_time("frame", sequence=i)
            if timestamps is not None and i < len(timestamps):
                rec.set_time("time", duration=float(timestamps[i]))
            status = data.status[i]
            lost = status == "lost"
            rec.log("status", rr.TextLog(status, level="WARN" if lost else "INFO"))
            rec.log("status/lost", rr.Scalars(1.0 if lost else 0.0))
            T = data.T_world_cam_est[i]
            if np.isfinite(T).all():
                rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            if manifest is not None and i < manifest.n_frames:
                rec.log("world/camera/image/rgb", rr.Image(manifest.read_rgb(i)).compress(jpeg_quality=RRD_JPEG_QUALITY))
                rec.log("world/camera/image/depth", rr.DepthImage(manifest.read_depth_m(i, allow_empty=True), meter=1.0))
            progress.update()
        rec.flush()
        rec.disconnect()  # closes the file sink: every chunk is on disk before the rename
    logger.info("wrote %s (%d frames)", out_path, len(frames))
    return out_path

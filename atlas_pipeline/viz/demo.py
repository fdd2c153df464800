"""The demo videos: an orbit around the world, a replay of the estimated trajectory, and real |
render side by side, rendered with the CPU Gaussian rasterizer into H.264 MP4s
(:mod:`atlas_pipeline.viz.video`), along camera paths from :mod:`atlas_pipeline.viz.camera_paths`."""

from __future__ import annotations

import contextlib
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from atlas_pipeline.errors import ArtifactError
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.io_utils import write_json_atomic
from atlas_pipeline.safe_arrays import load_json_object_checked

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

LogFn = Callable[[str], None]

__all__ = ["DemoVideos", "render_demo_videos", "render_video", "render_side_by_side_video", "orbit_trajectory",
           "write_bundle_video"]


@dataclass
class DemoVideos:
    """The rendered demo videos (orbit, trajectory, and real | render side by side) and how they were made."""

    orbit: Path
    trajectory: Path
    n_orbit_frames: int
    n_trajectory_frames: int
    size: tuple[int, int]
    side_by_side: Path | None = None

    def save(self, directory: Path) -> list[Path]:
        """Move the videos into ``directory`` (same file system: a rename) and describe them."""
        out = []
        sources = set()
        for attr in ("orbit", "trajectory", "side_by_side"):
            src = getattr(self, attr)
            if src is None:
                continue
            dst = directory / src.name
            if src.resolve() != dst.resolve():
                sources.add(src.parent)
                shutil.move(str(src), dst)
            setattr(self, attr, dst)
            out.append(dst)
        for folder in sources:  # the render's scratch folder, now empty: leave nothing behind
            with contextlib.suppress(OSError):
                folder.rmdir()
        out.append(write_json_atomic(directory / "videos.json", {
            "orbit": self.orbit.name, "trajectory": self.trajectory.name,
            "side_by_side": self.side_by_side.name if self.side_by_side else None,
            "n_orbit_frames": self.n_orbit_frames, "n_trajectory_frames": self.n_trajectory_frames,
            "size": list(self.size), "codec": "h264", "pixel_format": "yuv420p",
        }))
        return out

    @classmethod
    def load(cls, directory: Path) -> "DemoVideos":
        path = directory / "videos.json"
        if not path.is_file():
            raise ArtifactError(f"{directory}: videos.json missing")
        d = load_json_object_checked(path)  # bounded size, an object, errors naming the file
        sbs = d.get("side_by_side")
        return cls(directory / d["orbit"], directory / d["trajectory"], int(d["n_orbit_frames"]),
                   int(d["n_trajectory_frames"]), tuple(d["size"]), directory / sbs if sbs else None)


def _render_size(width: int, height: int, K: np.ndarray, scale: float) -> tuple[int, int, np.ndarray]:
    """Video size (even, for yuv420p) and the intrinsics scaled to it (pixel centres kept)."""
    from atlas_pipeline.gaussian_world.raster import scale_camera

    return scale_camera(K, width, height, scale, multiple=2)


def orbit_trajectory(field: GaussianField, cfg: PipelineConfig, T_world_cam_keyframes: np.ndarray | None = None,
                     *, camera_K: np.ndarray | None = None, image_size: tuple[int, int] | None = None) -> np.ndarray:
    """``[n, 4, 4]`` ``T_world_cam`` poses of the orbit video (``video.orbit_frames`` of them).

    Given the poses the world was recorded from (``[K, 4, 4]``: the keyframes, or the estimated
    trajectory; non-finite poses are skipped), the camera circles what they looked at, at their
    distance and height, over the directions the map supports (a full orbit or a back-and-forth
    arc), never inside or behind geometry; else it flies through them (see
    :func:`atlas_pipeline.viz.camera_paths.plan_camera_path`). Without them: a circle around the
    world's centre, each pose pulled in until it is in free space. ``camera_K`` / ``image_size``
    (the video's camera) set the field of view the checks use.
    """
    from atlas_pipeline.viz.camera_paths import plan_camera_path

    vc = cfg.video
    path = plan_camera_path(field, T_world_cam_keyframes, vc.orbit_frames, cfg.mapping.voxel_size_m, K=camera_K,
                            image_size=image_size, fallback_height_m=vc.orbit_height_m,
                            fallback_radius_scale=vc.orbit_radius_scale)
    logger.info("orbit video path: %s", path.summary())
    return path.T_world_cam


def render_video(field: GaussianField, poses_se3: np.ndarray, camera_K: np.ndarray, width: int, height: int,
                 cfg: PipelineConfig, path: Path, label: str, log: LogFn | None = None) -> tuple[int, tuple[int, int]]:
    """Render ``field`` from every finite pose of ``poses_se3`` ``[n, 4, 4]`` into an MP4 at ``path``."""
    from atlas_pipeline.gaussian_world.render import render_field
    from atlas_pipeline.progress import Progress
    from atlas_pipeline.viz.video import write_mp4

    if len(field) == 0:
        raise ValueError("cannot render an empty world")
    w, h, K = _render_size(width, height, camera_K, cfg.video.scale)
    poses = poses_se3[np.isfinite(poses_se3).all(axis=(1, 2))]

    def frames():
        progress = Progress(f"rendering {label} video", len(poses), log)
        for T in poses:
            r = render_field(field, T, K, w, h)
            progress.update()
            yield r.rgb

    path.parent.mkdir(parents=True, exist_ok=True)
    return write_mp4(frames(), path, fps=cfg.video.fps), (w, h)


def render_side_by_side_video(field: GaussianField, manifest: FrameManifest, poses_se3: np.ndarray,
                              cfg: PipelineConfig, path: Path, log: LogFn | None = None) -> int:
    """MP4 of real frame | render from its estimated pose, for every frame with a finite pose,
    at the dataset's frame size (frames read one at a time). A colour image taken at another time
    than its depth image is shown beside a render at the trajectory's pose at the colour's time
    (``localization.colour_delay_compensation``, as the render evaluation)."""
    from atlas_pipeline.gaussian_world.render import render_field
    from atlas_pipeline.perception.colour_timing import colour_time_poses
    from atlas_pipeline.progress import Progress
    from atlas_pipeline.viz.video import side_by_side, write_mp4

    if len(field) == 0:
        raise ValueError("cannot render an empty world")
    cam = manifest.camera
    idx = np.flatnonzero(np.isfinite(poses_se3).all(axis=(1, 2)))
    colour_poses = colour_time_poses(poses_se3, manifest, idx) if cfg.localization.colour_delay_compensation else {}

    def frames():
        progress = Progress("rendering side-by-side video", len(idx), log)
        for i in idx:
            r = render_field(field, colour_poses.get(int(i), poses_se3[i]), cam.K, cam.width, cam.height)
            progress.update()
            yield side_by_side(manifest.read_rgb(int(i)), r.rgb)

    path.parent.mkdir(parents=True, exist_ok=True)
    return write_mp4(frames(), path, fps=cfg.video.fps)


def render_demo_videos(field: GaussianField, trajectory_se3: np.ndarray, camera_K: np.ndarray,
                       width: int, height: int, cfg: PipelineConfig, out_dir: Path, name: str,
                       log: LogFn | None = None, manifest: FrameManifest | None = None) -> DemoVideos:
    """Orbit (around what the recorded camera looked at, framed from where it stood: see
    :func:`orbit_trajectory`), trajectory (replay of the estimated poses) and, given the sequence's
    ``manifest``, real | render side by side along the trajectory."""
    orbit_path = out_dir / f"{name}_orbit.mp4"
    traj_path = out_dir / f"{name}_trajectory.mp4"
    orbit = orbit_trajectory(field, cfg, trajectory_se3, camera_K=camera_K, image_size=(width, height))
    n_orbit, size = render_video(field, orbit, camera_K, width, height, cfg, orbit_path, "orbit", log)
    n_traj, _ = render_video(field, trajectory_se3, camera_K, width, height, cfg, traj_path, "trajectory", log)
    sbs_path = None
    if manifest is not None:
        sbs_path = out_dir / f"{name}_side_by_side.mp4"
        render_side_by_side_video(field, manifest, trajectory_se3, cfg, sbs_path, log)
    return DemoVideos(orbit_path, traj_path, n_orbit, n_traj, size, sbs_path)


def write_bundle_video(world: str | Path, cfg: PipelineConfig, video: str | Path, mode: str = "orbit",
                       force: bool = False) -> Path:
    """An MP4 at ``video`` of the world bundle at ``world`` (``atlas-gs demo-video``): ``orbit``, a
    path framed from where the recording camera stood, or ``trajectory``, the poses of its
    ``localization.json``. The output policy (an MP4 name, never a file the project did not write
    unless ``force``, a writable folder) is checked before the bundle is read."""
    from atlas_pipeline.errors import ConfigError
    from atlas_pipeline.io_utils import check_output_file, check_writable
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import bundle_keyframe_poses, load_world_bundle
    from atlas_pipeline.sensors.camera import TUM_CAMERAS, CameraIntrinsics
    from atlas_pipeline.viz.video import is_atlas_video

    world, video = Path(world), Path(video).expanduser()
    if video.suffix.lower() != ".mp4":
        raise ConfigError(f"--output {video}: demo videos are MP4 files; give a name ending in .mp4")
    check_output_file(video, [world], force, is_ours=is_atlas_video)
    check_writable(video.parent)
    bundle = load_world_bundle(world)
    dataset = bundle.metadata.get("dataset") or {}
    cam = CameraIntrinsics.from_dict(dataset["camera"]) if dataset.get("camera") else TUM_CAMERAS["default"]
    if mode == "trajectory":
        if not (world / "localization.json").is_file():
            raise ConfigError(f"{world}: trajectory mode needs localization.json; run `atlas-gs localize` first")
        poses = LocalizationReport.load(world).T_world_cam
        poses = poses[np.isfinite(poses).all(axis=(1, 2))]  # frames never placed have no pose to render from
        if len(poses) == 0:
            raise ConfigError(f"{world}/localization.json: no frame was placed in this world; nothing to render")
    else:
        poses = orbit_trajectory(bundle.field, cfg, bundle_keyframe_poses(bundle.metadata), camera_K=cam.K,
                                 image_size=(cam.width, cam.height))
    render_video(bundle.field, poses, cam.K, cam.width, cam.height, cfg, video, mode)
    return video

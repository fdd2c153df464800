"""Readers of RGB-D recording layouts other than TUM, each giving the same :class:`FrameManifest`.

=========  ==========================================================  ==================  ===========
kind       layout                                                      depth               time
=========  ==========================================================  ==================  ===========
tum        ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (tum.py)    16-bit PNG / 5000   list files
7scenes    ``seq-XX/frame-NNNNNN.{color.png|color.jpg,depth.png,       16-bit PNG, mm,     n / fps
           pose.txt}``                                                 65535 = no reading
replica    ``results/frameNNNNNN.jpg``, ``results/depthNNNNNN.png``,   16-bit PNG / 6553.5 n / fps
           ``traj.txt`` (NICE-SLAM / iMAP release)
scannet    ``color/N.jpg``, ``depth/N.png``, ``pose/N.txt``,           16-bit PNG, mm      n / fps
           ``intrinsic/intrinsic_{color,depth}.txt`` (SensReader)
bag        ROS 1 ``.bag`` / ROS 2 folder, RealSense ``.bag`` (bags.py:  converted to mm     header stamps
           converted once into a TUM folder)
=========  ==========================================================  ==================  ===========

Frame numbers (``NNNNNN``) come from the file names: frames are ordered by them and frame ``n`` is
at ``n / fps`` seconds (the three layouts carry no timestamps; ``fps`` defaults to
:data:`DEFAULT_FPS` and is a registry key). Poses are camera-to-world 4x4 matrices in the OpenCV
camera convention (x right, y down, z forward), which is what these releases store.

Assumptions, said once here:

* 7-Scenes: colour and depth of the Kinect are *not* registered in the release; like every RGB-D
  pipeline that uses it we treat them as registered with the published depth intrinsics (preset
  ``7scenes``), so colour can be misaligned against depth by a few pixels.
* ScanNet: colour (1296x968) and depth (640x480) come from registered cameras (same centre and
  orientation) and differ only in intrinsics and size; colour is resampled onto the depth camera
  (:func:`atlas_pipeline.sensors.images.resample_rgb`). The manifest's camera is the depth camera.
  Poses whose matrix holds ``-inf``/NaN (ScanNet's "tracking lost") give no ground truth.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from atlas_pipeline.errors import ConfigError, DatasetError
from atlas_pipeline.io_utils import sha256_files
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.images import check_depth_header, check_rgb_header, image_header
from atlas_pipeline.sensors.tum import (
    MAX_CAMERA_SPEED_M_PER_S,
    MAX_GLITCH_ROWS,
    MAX_GLITCHES_LOGGED,
    FrameManifest,
    _is_file,
    _iter_lines,
    _safe_member,
    screen_pose_jumps,
)

logger = logging.getLogger(__name__)

__all__ = [
    "KINDS",
    "RECORDING_KINDS",
    "DEFAULT_FPS",
    "SEVEN_SCENES_CAMERA",
    "REPLICA_CAMERA",
    "CAMERA_PRESETS",
    "KIND_CAMERA_PRESET",
    "detect_kind",
    "read_matrix_file",
    "read_trajectory_file",
    "load_7scenes_sequence",
    "load_replica_sequence",
    "load_scannet_sequence",
    "load_recording",
    "recording_exists",
]

KINDS = ("synthetic", "tum", "7scenes", "replica", "scannet", "bag")
RECORDING_KINDS = KINDS[1:]  # read from a folder or file the user has

# 7-Scenes, Replica and ScanNet exports carry no timestamps. 7-Scenes (Kinect v1) and ScanNet
# (Structure sensor) were captured at 30 Hz; Replica is rendered, and 30 Hz is what its SLAM
# benchmarks assume. The registry key ``fps`` overrides it.
DEFAULT_FPS = 30.0
MAX_FPS = 1000.0

# 7-Scenes (https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/): "principle
# point (320,240), focal length (585,585)" of the depth camera; depth in millimetres, 65535 where
# the Kinect gave no reading.
SEVEN_SCENES_DEPTH_SCALE = 1000.0
SEVEN_SCENES_DEPTH_INVALID = 65535
SEVEN_SCENES_CAMERA = CameraIntrinsics(640, 480, 585.0, 585.0, 320.0, 240.0, SEVEN_SCENES_DEPTH_SCALE, ())
# Replica as NICE-SLAM / iMAP ship it (NICE-SLAM configs/Replica/replica.yaml: H 680, W 1200,
# fx fy 600, cx 599.5, cy 339.5, png_depth_scale 6553.5).
REPLICA_DEPTH_SCALE = 6553.5
REPLICA_CAMERA = CameraIntrinsics(1200, 680, 600.0, 600.0, 599.5, 339.5, REPLICA_DEPTH_SCALE, ())
# ScanNet's SensReader exports depth as 16-bit PNG in millimetres (ScanNet README, "depth_shift 1000").
SCANNET_DEPTH_SCALE = 1000.0

CAMERA_PRESETS: dict[str, CameraIntrinsics] = {"7scenes": SEVEN_SCENES_CAMERA, "replica": REPLICA_CAMERA}
# The camera a kind gets when none is given (tum: TUM's "default"; scannet and bag read theirs).
KIND_CAMERA_PRESET: dict[str, str | None] = {"tum": "default", "7scenes": "7scenes", "replica": "replica",
                                             "scannet": None, "bag": None}

# A rotation of a pose file may be off orthonormal by rounding (files print 6-8 digits); beyond
# this it is not a rotation. Within it the matrix is projected onto the nearest rotation.
ROTATION_TOLERANCE = 1e-2
SEQUENCE_RE = re.compile(r"^seq-[0-9]{1,4}$")  # 7-Scenes sequence folder names

_7S_COLOUR_RE = re.compile(r"^frame-([0-9]{6})\.color\.(png|jpg)$")
_7S_DEPTH = "frame-{:06d}.depth.png"
_7S_POSE = "frame-{:06d}.pose.txt"
_REPLICA_COLOUR_RE = re.compile(r"^frame([0-9]{1,9})\.(jpg|png)$")
_REPLICA_DEPTH_RE = re.compile(r"^depth([0-9]{1,9})\.png$")
_SCANNET_COLOUR_RE = re.compile(r"^([0-9]{1,9})\.(jpg|png)$")
_SCANNET_DEPTH_RE = re.compile(r"^([0-9]{1,9})\.png$")


# ---- detection ----------------------------------------------------------------------------------


def _has(folder: Path, *names: str) -> bool:
    return all((folder / n).exists() for n in names)


def detect_kind(path: str | Path) -> str | None:
    """The recording kind of ``path`` from its layout, or None when it is none of them.

    ``bag``: a file ending ``.bag`` (ROS 1, RealSense) or a folder with ``metadata.yaml`` and a
    ``.db3`` / ``.mcap`` file (ROS 2); ``tum``: ``rgb.txt`` and ``depth.txt``; ``replica``:
    ``results/`` and ``traj.txt``; ``scannet``: ``color/``, ``depth/``, ``pose/``, ``intrinsic/``;
    ``7scenes``: ``frame-*.color.*`` files, or a scene folder of ``seq-XX`` folders holding them.
    """
    p = Path(path)
    try:
        if p.is_file():
            return "bag" if p.suffix.lower() == ".bag" else None
        if not p.is_dir():
            return None
        if (p / "metadata.yaml").is_file() and any(q.suffix in (".db3", ".mcap") for q in p.iterdir()):
            return "bag"
        if _has(p, "rgb.txt", "depth.txt"):
            return "tum"
        if (p / "results").is_dir() and (p / "traj.txt").is_file():
            return "replica"
        if all((p / d).is_dir() for d in ("color", "depth", "pose", "intrinsic")):
            return "scannet"
        if any(_7S_COLOUR_RE.match(q.name) for q in p.iterdir()):
            return "7scenes"
        if any(SEQUENCE_RE.match(q.name) and q.is_dir() and any(_7S_COLOUR_RE.match(r.name) for r in q.iterdir())
               for q in p.iterdir()):
            return "7scenes"
    except OSError:
        return None
    return None


# ---- text files: matrices and trajectories -------------------------------------------------------


def _numbers(path: Path, lineno: int, text: str) -> list[float]:
    try:
        return [float(x) for x in text.replace(",", " ").split()]
    except ValueError:
        bad = next(x for x in text.replace(",", " ").split() if not _is_float(x))
        raise DatasetError(path, f"not a number: {bad[:40]!r}", lineno) from None


def _is_float(x: str) -> bool:
    try:
        float(x)
        return True
    except ValueError:
        return False


def read_matrix_file(path: Path, rows: int = 4, cols: int = 4) -> np.ndarray:
    """A ``rows x cols`` matrix written as ``rows`` lines of ``cols`` numbers (7-Scenes / ScanNet
    pose and intrinsics files); blank lines are skipped. Values may be ``inf``/``nan`` (the caller
    decides). Errors name the file and line."""
    if not _is_file(path):
        raise DatasetError(path, "file not found")
    out: list[list[float]] = []
    for lineno, text in _iter_lines(path):
        if not text.strip():
            continue
        vals = _numbers(path, lineno, text)
        if len(vals) != cols:
            raise DatasetError(path, f"expected {cols} numbers, found {len(vals)}", lineno)
        if len(out) == rows:
            raise DatasetError(path, f"more than {rows} rows", lineno)
        out.append(vals)
    if len(out) != rows:
        raise DatasetError(path, f"expected {rows} rows of {cols} numbers, found {len(out)}")
    return np.array(out, dtype=np.float64)


def _check_pose(T: np.ndarray, path: Path, line: int | None) -> np.ndarray:
    """A camera-to-world 4x4 ``T`` checked (finite, last row 0 0 0 1, rotation within
    ``ROTATION_TOLERANCE``) and its rotation projected onto SO(3)."""
    if not np.all(np.isfinite(T)):
        raise DatasetError(path, "pose has a non-finite value", line)
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DatasetError(path, f"last row of the pose must be 0 0 0 1, got {T[3].tolist()}", line)
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        raise DatasetError(path, "pose rotation is not a rotation matrix (not orthonormal or a reflection)", line)
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def read_trajectory_file(path: Path) -> tuple[np.ndarray, list[int]]:
    """``traj.txt`` of the Replica release: one camera-to-world 4x4 per line (16 numbers, row
    major). Returns ``(T_world_cam [N, 4, 4], line numbers [N])``; blank lines are skipped."""
    if not _is_file(path):
        raise DatasetError(path, "trajectory file not found")
    poses, lines = [], []
    for lineno, text in _iter_lines(path):
        if not text.strip():
            continue
        vals = _numbers(path, lineno, text)
        if len(vals) != 16:
            raise DatasetError(path, f"expected 16 numbers (a 4x4 pose), found {len(vals)}", lineno)
        poses.append(_check_pose(np.array(vals, dtype=np.float64).reshape(4, 4), path, lineno))
        lines.append(lineno)
    if not poses:
        raise DatasetError(path, "no poses")
    return np.stack(poses), lines


def _intrinsics_file(path: Path) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of a ScanNet 4x4 intrinsics file (K in the top-left 3x3)."""
    M = read_matrix_file(path)
    if not np.all(np.isfinite(M)):
        raise DatasetError(path, "intrinsics have a non-finite value")
    fx, fy, cx, cy = M[0, 0], M[1, 1], M[0, 2], M[1, 2]
    if fx <= 0 or fy <= 0:
        raise DatasetError(path, f"focal lengths must be positive, got fx={fx} fy={fy}")
    if abs(M[0, 1]) > 1e-6 or abs(M[1, 0]) > 1e-6 or not np.allclose(M[2, :3], [0, 0, 1]):
        raise DatasetError(path, f"not a pinhole intrinsic matrix without skew: {M[:3, :3].tolist()}")
    return float(fx), float(fy), float(cx), float(cy)


# ---- helpers ------------------------------------------------------------------------------------


def _frames_by_number(folder: Path, pattern: re.Pattern[str], what: str) -> dict[int, str]:
    """``{frame number: file name}`` of the files of ``folder`` matching ``pattern`` (group 1 is
    the number); two files with one number (``0.jpg`` and ``0.png``) are an error."""
    out: dict[int, str] = {}
    try:
        names = sorted(p.name for p in folder.iterdir())
    except OSError as exc:
        raise DatasetError(folder, f"cannot list the folder ({exc.strerror or exc})") from None
    for name in names:
        m = pattern.match(name)
        if not m:
            continue
        n = int(m.group(1))
        if n in out:
            raise DatasetError(folder / name, f"{what} frame {n} is also {out[n]!r}")
        out[n] = name
    return out


def _frame_times(numbers: list[int], fps: float) -> np.ndarray:
    return np.asarray(numbers, dtype=np.float64) / float(fps)  # [N]


def _check_fps(fps: float) -> float:
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise ConfigError(f"fps must be a number in (0, {MAX_FPS:g}], got {fps!r}")
    return float(fps)


def _check_frame_speeds(T: np.ndarray, has: np.ndarray, numbers: list[int], fps: float,
                        pose_source: list[tuple[Path, int | None]]) -> tuple[np.ndarray, np.ndarray]:
    """Hold the poses of consecutive frames that both have one to a camera's speed, as TUM ground
    truth is (:func:`~atlas_pipeline.sensors.tum.screen_pose_jumps`).

    ``T`` ``[N, 4, 4]`` camera-to-world, ``has`` ``[N]``, ``numbers`` the frame numbers (frame ``n``
    at ``n / fps`` s), ``pose_source`` ``[N]`` the file (and line) each pose came from. A pose (or
    up to ``MAX_GLITCH_ROWS`` in a row) that jumps away faster than ``MAX_CAMERA_SPEED_M_PER_S``
    and back is a glitch: that frame gets no ground truth, with a warning naming it and its file.

    Returns:
        ``(T, has)``: copies, glitch frames without a pose (NaN, False).

    Raises:
        DatasetError: a jump the path goes on from, naming the later pose's file (and line), the
            earlier one, the distance, the time at ``fps`` and the speed.
    """
    T, has = T.copy(), has.copy()
    idx = np.flatnonzero(has)
    if len(idx) < 2:
        return T, has
    t = _frame_times([numbers[k] for k in idx], fps)
    c = T[idx, :3, 3]
    keep, glitches, jumps = screen_pose_jumps(t, c, lambda kept: (0, len(kept) - 1))  # every pose is read

    def where(k: int, other: int) -> str:
        (path_k, line_k), (path_o, _) = pose_source[k], pose_source[other]
        return f"line {line_k}" if path_k == path_o and line_k is not None else path_k.name

    if jumps:
        ja, jb = jumps[0]
        a, b = int(idx[ja]), int(idx[jb])
        step_m = float(np.linalg.norm(c[jb] - c[ja]))
        dt_s = float(t[jb] - t[ja])
        more = f"; {len(jumps) - 1} more such jump(s) follow" if len(jumps) > 1 else ""
        path_b, line_b = pose_source[b]
        raise DatasetError(path_b, f"the camera moves {step_m:.3g} m from frame {numbers[a]} ({where(a, b)}) to "
                                   f"frame {numbers[b]}, {dt_s:.3g} s later at {fps:g} fps (registry key fps): "
                                   f"{step_m / dt_s:.3g} m/s, faster than the {MAX_CAMERA_SPEED_M_PER_S:g} m/s any "
                                   f"hand-held or robot camera moves, and the path goes on from there (it does not "
                                   f"come back within {MAX_GLITCH_ROWS} frames){more}; these poses are not one "
                                   "camera's path: correct them, or the fps", line_b)
    def named(k: int) -> str:
        path, line = pose_source[k]
        return path.name if line is None else f"{path.name} line {line}"

    for g in glitches[:MAX_GLITCHES_LOGGED]:
        first, last = int(idx[g.first]), int(idx[g.last])
        frames, files = ((f"frame {numbers[first]}", named(first)) if first == last else
                         (f"frames {numbers[first]}-{numbers[last]}", f"{named(first)} - {named(last)}"))
        what = f"pose of {frames} ({files}) jumps" if first == last else f"poses of {frames} ({files}) jump"
        logger.warning("%s: the %s %.3g m away from frame %d and back at frame %d (%.3g m/s at %g fps, faster than "
                       "the %g m/s a camera moves): a glitch, left out (%s without ground truth)",
                       pose_source[first][0].parent, what, g.distance_m, numbers[int(idx[g.before])],
                       numbers[int(idx[g.after])], g.speed_m_per_s, fps, MAX_CAMERA_SPEED_M_PER_S, frames)
    if len(glitches) > MAX_GLITCHES_LOGGED:
        logger.warning("%s: %d more pose glitch(es) left out likewise", pose_source[int(idx[0])][0].parent,
                       len(glitches) - MAX_GLITCHES_LOGGED)
    dropped = idx[~keep]
    T[dropped] = np.nan
    has[dropped] = False
    return T, has


def _finish(dataset: str, root: Path, camera: CameraIntrinsics, numbers: list[int], fps: float,
            rgb_files: list[str], depth_files: list[str], T_gt: np.ndarray, has_gt: np.ndarray,
            hashed: list[Path], source: dict) -> FrameManifest:
    if len(numbers) < 2:
        raise DatasetError(root, f"need at least 2 RGB-D frames, found {len(numbers)}")
    t = _frame_times(numbers, fps)
    names = [p.relative_to(root).as_posix() if p.is_relative_to(root) else p.name for p in hashed]
    content_hash = sha256_files(hashed, names)
    logger.info("%s: %d RGB-D frames (%s), %d with ground truth, %.1f s at %g fps", dataset, len(numbers),
                source["layout"], int(has_gt.sum()), t[-1] - t[0], fps)
    return FrameManifest(dataset=dataset, root=root, camera=camera, timestamps_s=t, depth_timestamps_s=t.copy(),
                         rgb_files=rgb_files, depth_files=depth_files, T_world_cam_gt=T_gt, has_gt=has_gt,
                         content_hash=content_hash, source=source)


# ---- 7-Scenes -----------------------------------------------------------------------------------


def load_7scenes_sequence(root: str | Path, camera: CameraIntrinsics, dataset: str, max_frames: int | None = None,
                          fps: float = DEFAULT_FPS, sequence: str | None = None) -> FrameManifest:
    """Read one 7-Scenes sequence (``root`` is ``seq-XX``, or the scene folder with ``sequence``).

    Each ``frame-NNNNNN.color.png|jpg`` needs ``frame-NNNNNN.depth.png`` (uint16 mm, 65535 = no
    reading, read as 0); ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world) is its ground truth, a
    frame without one has none. Headers of every image are checked against ``camera``.
    """
    fps = _check_fps(fps)
    base = Path(root)
    if sequence is not None:
        if not (isinstance(sequence, str) and SEQUENCE_RE.match(sequence)):
            raise DatasetError(base, f"sequence must name a seq-XX folder, got {sequence!r}")
        base = base / sequence
    if not base.is_dir():
        raise DatasetError(base, "7-Scenes sequence folder not found")
    folder = base.resolve()
    colour = _frames_by_number(folder, _7S_COLOUR_RE, "colour")
    if not colour:
        seqs = sorted(p.name for p in folder.iterdir() if SEQUENCE_RE.match(p.name) and p.is_dir())
        hint = (f"; this looks like a scene folder: choose one of {seqs[:8]} (registry key 'sequence', --sequence)"
                if seqs else "")
        raise DatasetError(folder, f"no frame-NNNNNN.color.png|jpg files (expected 7-Scenes layout){hint}")
    numbers = sorted(colour)
    if max_frames is not None:
        numbers = numbers[:max_frames]
    rgb_files, depth_files, hashed = [], [], []
    pose_source: list[tuple[Path, int | None]] = []
    T = np.full((len(numbers), 4, 4), np.nan)
    has = np.zeros(len(numbers), bool)
    for k, n in enumerate(numbers):
        rgb = _safe_member(folder, colour[n], folder, None)
        depth_name = _7S_DEPTH.format(n)
        depth = _safe_member(folder, depth_name, folder, None)
        if not _is_file(depth):
            raise DatasetError(rgb, f"no depth image {depth_name} for this frame")
        check_rgb_header(rgb, camera.width, camera.height)
        check_depth_header(depth, camera.width, camera.height)
        pose = _safe_member(folder, _7S_POSE.format(n), folder, None)
        pose_source.append((pose, None))
        if _is_file(pose):
            T[k] = _check_pose(read_matrix_file(pose), pose, None)
            has[k] = True
            hashed.append(pose)
        rgb_files.append(colour[n])
        depth_files.append(depth_name)
        hashed += [rgb, depth]
    if not has.all():
        logger.info("%s: %d of %d frames have no pose file (no ground truth there)", folder, int((~has).sum()), len(has))
    T, has = _check_frame_speeds(T, has, numbers, fps, pose_source)
    return _finish(dataset, folder, camera, numbers, fps, rgb_files, depth_files, T, has, hashed,
                   {"layout": "7scenes", "path": str(folder), "max_frames": max_frames, "fps": fps,
                    "depth_invalid_raw": [SEVEN_SCENES_DEPTH_INVALID]})


# ---- Replica (NICE-SLAM / iMAP release) ---------------------------------------------------------


def load_replica_sequence(root: str | Path, camera: CameraIntrinsics, dataset: str, max_frames: int | None = None,
                          fps: float = DEFAULT_FPS) -> FrameManifest:
    """Read a Replica sequence as the RGB-D SLAM papers ship it: ``results/frameNNNNNN.jpg``,
    ``results/depthNNNNNN.png`` (uint16, ``depth_m = raw / 6553.5`` with the preset camera) and
    ``traj.txt``, whose line ``n + 1`` is the camera-to-world pose of frame ``n``."""
    fps = _check_fps(fps)
    folder = Path(root)
    if not folder.is_dir():
        raise DatasetError(folder, "Replica sequence folder not found")
    folder = folder.resolve()
    results = folder / "results"
    if not results.is_dir():
        raise DatasetError(results, "folder not found (expected Replica layout: results/, traj.txt)")
    traj_path = folder / "traj.txt"
    colour = _frames_by_number(results, _REPLICA_COLOUR_RE, "colour")
    depth = _frames_by_number(results, _REPLICA_DEPTH_RE, "depth")
    if not colour:
        raise DatasetError(results, "no frameNNNNNN.jpg colour images")
    poses, pose_lines = read_trajectory_file(traj_path)
    numbers = sorted(colour)
    if max_frames is not None:
        numbers = numbers[:max_frames]
    if numbers[-1] >= len(poses):
        n = numbers[-1]
        raise DatasetError(traj_path, f"has {len(poses)} poses; frame {colour[n]} needs pose line {n + 1}")
    if len(poses) != len(colour):
        logger.warning("%s: %d poses for %d colour frames", traj_path, len(poses), len(colour))
    rgb_files, depth_files, hashed = [], [], [traj_path]
    for n in numbers:
        if n not in depth:
            raise DatasetError(results / colour[n], f"no depth image depth{n:06d}.png for this frame")
        rgb = _safe_member(folder, f"results/{colour[n]}", results, None)
        dep = _safe_member(folder, f"results/{depth[n]}", results, None)
        check_rgb_header(rgb, camera.width, camera.height)
        check_depth_header(dep, camera.width, camera.height)
        rgb_files.append(f"results/{colour[n]}")
        depth_files.append(f"results/{depth[n]}")
        hashed += [rgb, dep]
    T = poses[numbers]
    has = np.ones(len(numbers), bool)
    T, has = _check_frame_speeds(T, has, numbers, fps, [(traj_path, pose_lines[n]) for n in numbers])
    return _finish(dataset, folder, camera, numbers, fps, rgb_files, depth_files, T, has, hashed,
                   {"layout": "replica", "path": str(folder), "max_frames": max_frames, "fps": fps})


# ---- ScanNet (SensReader export) -----------------------------------------------------------------


def load_scannet_sequence(root: str | Path, dataset: str, max_frames: int | None = None,
                          fps: float = DEFAULT_FPS) -> FrameManifest:
    """Read a ScanNet export: ``color/N.jpg``, ``depth/N.png`` (uint16 mm), ``pose/N.txt`` (4x4
    camera-to-world; ``-inf`` rows mean no pose), ``intrinsic/intrinsic_color.txt`` and
    ``intrinsic_depth.txt`` (4x4, K top-left).

    The manifest's camera is the depth camera (size of the depth images, ``intrinsic_depth``,
    depth scale 1000). When the colour images differ in size or intrinsics, ``source`` records the
    colour camera and :meth:`FrameManifest.read_rgb` resamples colour onto the depth camera
    (the two cameras are assumed registered, as ScanNet's exports are).
    """
    fps = _check_fps(fps)
    folder = Path(root)
    if not folder.is_dir():
        raise DatasetError(folder, "ScanNet export folder not found")
    folder = folder.resolve()
    for sub in ("color", "depth", "pose", "intrinsic"):
        if not (folder / sub).is_dir():
            raise DatasetError(folder / sub, "folder not found (expected ScanNet export: color/ depth/ pose/ intrinsic/)")
    kc = _intrinsics_file(folder / "intrinsic" / "intrinsic_color.txt")
    kd = _intrinsics_file(folder / "intrinsic" / "intrinsic_depth.txt")
    colour = _frames_by_number(folder / "color", _SCANNET_COLOUR_RE, "colour")
    depth = _frames_by_number(folder / "depth", _SCANNET_DEPTH_RE, "depth")
    if not colour:
        raise DatasetError(folder / "color", "no N.jpg colour images")
    numbers = sorted(colour)
    if max_frames is not None:
        numbers = numbers[:max_frames]
    if numbers[0] not in depth:
        raise DatasetError(folder / "color" / colour[numbers[0]], f"no depth image depth/{numbers[0]}.png for this frame")
    first_c = image_header(folder / "color" / colour[numbers[0]])
    first_d = image_header(folder / "depth" / depth[numbers[0]])
    try:
        camera = CameraIntrinsics(first_d.width, first_d.height, *kd, SCANNET_DEPTH_SCALE, ())
        colour_camera = CameraIntrinsics(first_c.width, first_c.height, *kc, SCANNET_DEPTH_SCALE, ())
    except Exception as exc:  # ConfigError from the range checks
        raise DatasetError(folder / "intrinsic", f"invalid camera: {exc}") from None
    rgb_files, depth_files = [], []
    pose_source: list[tuple[Path, int | None]] = []
    hashed = [folder / "intrinsic" / "intrinsic_color.txt", folder / "intrinsic" / "intrinsic_depth.txt"]
    T = np.full((len(numbers), 4, 4), np.nan)
    has = np.zeros(len(numbers), bool)
    for k, n in enumerate(numbers):
        if n not in depth:
            raise DatasetError(folder / "color" / colour[n], f"no depth image depth/{n}.png for this frame")
        rgb = _safe_member(folder, f"color/{colour[n]}", folder / "color", None)
        dep = _safe_member(folder, f"depth/{depth[n]}", folder / "depth", None)
        check_rgb_header(rgb, colour_camera.width, colour_camera.height)
        check_depth_header(dep, camera.width, camera.height)
        pose = _safe_member(folder, f"pose/{n}.txt", folder / "pose", None)
        pose_source.append((pose, None))
        if _is_file(pose):
            M = read_matrix_file(pose)
            if np.all(np.isfinite(M)):
                T[k] = _check_pose(M, pose, None)
                has[k] = True
            hashed.append(pose)
        rgb_files.append(f"color/{colour[n]}")
        depth_files.append(f"depth/{depth[n]}")
        hashed += [rgb, dep]
    if not has.all():
        logger.info("%s: %d of %d frames have no valid pose (no ground truth there)", folder, int((~has).sum()), len(has))
    T, has = _check_frame_speeds(T, has, numbers, fps, pose_source)
    same = (colour_camera.width, colour_camera.height, *kc) == (camera.width, camera.height, *kd)
    source = {"layout": "scannet", "path": str(folder), "max_frames": max_frames, "fps": fps}
    if not same:
        source["colour_camera"] = colour_camera.to_dict()
    return _finish(dataset, folder, camera, numbers, fps, rgb_files, depth_files, T, has, hashed, source)


# ---- dispatch -----------------------------------------------------------------------------------


def load_recording(kind: str, path: Path, camera: CameraIntrinsics | None, dataset: str,
                   max_frames: int | None = None, params: dict | None = None,
                   bag_cache_root: Path | None = None) -> FrameManifest:
    """The :class:`FrameManifest` of a recording of ``kind`` at ``path``. ``params`` holds the
    kind's registry options (``fps``, ``sequence``, ``rgb_topic``, ``depth_topic``,
    ``camera_info_topic``); ``bag_cache_root`` is where bags are converted (required for bags)."""
    params = dict(params or {})
    path = Path(path)
    if kind == "tum":
        from atlas_pipeline.sensors.tum import load_tum_sequence

        assert camera is not None
        return load_tum_sequence(path, camera, dataset, max_frames)
    if kind == "7scenes":
        return load_7scenes_sequence(path, camera or SEVEN_SCENES_CAMERA, dataset, max_frames,
                                     params.get("fps", DEFAULT_FPS), params.get("sequence"))
    if kind == "replica":
        return load_replica_sequence(path, camera or REPLICA_CAMERA, dataset, max_frames, params.get("fps", DEFAULT_FPS))
    if kind == "scannet":
        return load_scannet_sequence(path, dataset, max_frames, params.get("fps", DEFAULT_FPS))
    if kind == "bag":
        from atlas_pipeline.sensors.bags import load_bag_sequence

        if bag_cache_root is None:
            raise ValueError("bag_cache_root is required for bags")
        return load_bag_sequence(path, dataset, bag_cache_root, max_frames, camera=camera,
                                 rgb_topic=params.get("rgb_topic"), depth_topic=params.get("depth_topic"),
                                 camera_info_topic=params.get("camera_info_topic"))
    raise ValueError(f"unknown recording kind {kind!r}")


def recording_exists(kind: str, path: Path) -> bool:
    """Whether the recording's folder (or ROS 1 bag file) is there."""
    return path.is_file() if (kind == "bag" and path.suffix.lower() == ".bag") else path.is_dir()


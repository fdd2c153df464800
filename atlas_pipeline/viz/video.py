"""Camera paths for fly-around videos and browser-playable MP4 writing.

Videos are H.264 (libx264) in yuv420p with the ``moov`` atom at the front (``+faststart``): the
combination every browser plays, and one that can start playing before it is fully downloaded.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from atlas_pipeline.geometry import look_at
from atlas_pipeline.io_utils import atomic_path

__all__ = ["orbit_poses", "write_mp4", "side_by_side"]

logger = logging.getLogger(__name__)

# Written into every MP4's comment tag, so the output policy can tell our videos from a user's.
VIDEO_MARKER = "atlas-gs demo video"
_MARKER_SEARCH_BYTES = 1 << 20  # the moov box of a few-thousand-frame video fits well within this


def orbit_poses(
    center: np.ndarray,
    radius_m: float,
    height_m: float,
    n_frames: int,
    up=(0.0, 0.0, 1.0),
    start_angle_rad: float = 0.0,
) -> np.ndarray:
    """Camera poses on a circle around ``center``, all looking at it.

    The circle lies in the plane perpendicular to ``up`` at ``height_m`` above ``center`` and is
    walked once (360 degrees, counter-clockwise seen from above), with ``n_frames`` evenly spaced
    poses and no repeated end pose, so the video loops seamlessly. Angle 0 is the world x axis
    projected onto that plane (the y axis if ``up`` is along x).

    Args:
        center: ``[3]`` world point looked at.
        radius_m: horizontal distance of the camera from ``center`` (``>= 0``).
        height_m: camera height above ``center`` along ``up``.
        n_frames: number of poses (``>= 1``).
        up: ``[3]`` world up direction (need not be unit length).
        start_angle_rad: angle of the first pose.

    Returns:
        ``[n_frames, 4, 4]`` ``T_world_cam`` poses (OpenCV camera axes).
    """
    c = np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center: expected 3 finite values, got {center!r}")
    u = np.asarray(up, dtype=np.float64).reshape(-1)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-12:
        raise ValueError(f"up: expected a non-zero 3-vector, got {up!r}")
    if not (np.isfinite(radius_m) and radius_m >= 0):
        raise ValueError(f"radius_m must be >= 0, got {radius_m!r}")
    if not np.isfinite(height_m):
        raise ValueError(f"height_m must be finite, got {height_m!r}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    if radius_m == 0 and height_m == 0:
        raise ValueError("radius_m and height_m are both 0: the camera would sit on the centre")
    u = u / np.linalg.norm(u)
    # in-plane basis: world x (or y) with its up component removed
    ref = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - u * (ref @ u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    angles = start_angle_rad + 2.0 * np.pi * np.arange(int(n_frames)) / int(n_frames)
    poses = np.empty((int(n_frames), 4, 4), dtype=np.float64)
    for i, a in enumerate(angles):
        eye = c + radius_m * (np.cos(a) * e1 + np.sin(a) * e2) + height_m * u
        poses[i] = look_at(eye, c, u)
    return poses


def _pad_even(frame: np.ndarray) -> np.ndarray:
    """Pad ``[H, W, 3]`` to even H and W by repeating the last row/column (yuv420p needs even)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _check_frame(frame, index: int, shape=None, dtype=None) -> np.ndarray:
    a = np.asarray(frame)
    if shape is None:
        if a.dtype != np.uint8:
            raise ValueError(f"frame {index}: expected dtype uint8, got {a.dtype}")
        if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] == 0 or a.shape[1] == 0:
            raise ValueError(
                f"frame {index}: expected an RGB image [H, W, 3], got shape {list(a.shape)}"
            )
    else:
        if a.dtype != dtype:
            raise ValueError(
                f"frame {index}: dtype {a.dtype} differs from the first frame's {dtype}"
            )
        if a.shape != shape:
            raise ValueError(
                f"frame {index}: shape {list(a.shape)} differs from the first frame's {list(shape)}"
            )
    return np.ascontiguousarray(a)


def write_mp4(
    frames: Iterable[np.ndarray],
    path: str | Path,
    fps: float = 15.0,
    progress: Callable[[int], None] | None = None,
    crf: int = 20,
) -> int:
    """Write RGB frames as a browser-playable MP4 (H.264, yuv420p, +faststart).

    The video is written to a temporary ``.mp4`` next to ``path`` and renamed into place once
    complete, so ``path`` never holds a half-written file. Odd frame sizes are padded by one
    row/column (edge pixels repeated) rather than resized.

    Args:
        frames: iterable of ``[H, W, 3]`` uint8 RGB images, all the same size (consumed lazily).
        path: output file; its folder is created if missing.
        fps: frame rate.
        progress: called with the number of frames written so far after each frame.
        crf: x264 constant rate factor (0 lossless .. 51 worst; 18-23 is visually good).

    Returns:
        The number of frames written.

    Raises:
        ValueError: no frames, a frame that is not ``[H, W, 3]`` uint8, or frames of differing
            size/dtype. Nothing is left at ``path`` (or at the temporary file) in that case.
    """
    import imageio.v2 as imageio  # imported here: only video writing needs ffmpeg

    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    path = Path(path)
    it = iter(frames)
    try:
        first = next(it)
    except StopIteration:
        raise ValueError(f"{path}: no frames to write") from None
    first = _check_frame(first, 0)
    shape, dtype = first.shape, first.dtype
    if shape[0] % 2 or shape[1] % 2:
        logger.info("padding %dx%d frames to even size for yuv420p", shape[1], shape[0])

    # Same folder (atomic rename), hidden, ending in .mp4 so ffmpeg picks the container, and among
    # this process's staging (atomic_path): a command Ctrl-C ends removes it (ffmpeg stopped first).
    with atomic_path(path) as tmp:
        writer = imageio.get_writer(
            tmp,
            format="FFMPEG",
            mode="I",
            fps=float(fps),
            codec="libx264",
            pixelformat="yuv420p",
            macro_block_size=1,  # we pad to even ourselves; imageio would otherwise resize to x16
            quality=None,  # rate control given explicitly below
            ffmpeg_params=["-movflags", "+faststart", "-crf", str(int(crf)), "-preset", "medium",
                           "-metadata", f"comment={VIDEO_MARKER}"],
            ffmpeg_log_level="error",
        )
        n = 0
        try:
            frame = first
            while True:
                writer.append_data(_pad_even(frame))
                n += 1
                if progress is not None:
                    progress(n)
                try:
                    frame = next(it)
                except StopIteration:
                    break
                frame = _check_frame(frame, n, shape, dtype)
            writer.close()
        except BaseException:
            try:
                writer.close()
            except Exception:  # the original error matters more than a failed cleanup
                logger.debug("closing the ffmpeg writer after an error failed", exc_info=True)
            raise
    # the file's name only: its folder may be a staging folder the caller moves into place
    logger.info("wrote %s: %d frames (%dx%d, %.3g fps)", path.name, n, shape[1], shape[0], fps)
    return n


def is_atlas_video(path: str | Path) -> bool:
    """Whether ``path`` is an MP4 this project wrote (its ``comment`` tag holds :data:`VIDEO_MARKER`).

    With ``+faststart`` the tag sits in the ``moov`` box at the front; the tail is searched too for
    files remuxed without it. Used by the output policy: only our own videos are overwritten.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(_MARKER_SEARCH_BYTES)
            f.seek(max(0, size - _MARKER_SEARCH_BYTES))
            tail = f.read(_MARKER_SEARCH_BYTES)
    except OSError:
        return False
    key = VIDEO_MARKER.encode()
    return key in head or key in tail


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Two images next to each other, without resizing.

    Args:
        left, right: ``[H, W1, C]`` and ``[H, W2, C]`` images of the same height, channel count
            and dtype (typically ``[H, W, 3]`` uint8, giving ``[H, 2W, 3]``).

    Returns:
        ``[H, W1 + W2, C]`` image.
    """
    a = np.asarray(left)
    b = np.asarray(right)
    if a.ndim != 3 or b.ndim != 3:
        raise ValueError(
            f"expected two [H, W, C] images, got shapes {list(a.shape)} and {list(b.shape)}"
        )
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"image heights differ: {a.shape[0]} and {b.shape[0]}")
    if a.shape[2] != b.shape[2]:
        raise ValueError(f"channel counts differ: {a.shape[2]} and {b.shape[2]}")
    if a.dtype != b.dtype:
        raise ValueError(f"dtypes differ: {a.dtype} and {b.dtype}")
    return np.concatenate([a, b], axis=1)

"""RGB-D back-projection: depth pixels to coloured 3D points in the camera frame (paper section 5.1).

``p_cam = depth_m * K^-1 [u, v, 1]^T``, with lens distortion removed from the pixel rays first when
the camera has distortion coefficients (TUM freiburg1/2), so points are metrically right across the
whole image, not only near the centre.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import shutil
import tempfile
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from atlas_pipeline.config import FusionConfig, PipelineConfig
from atlas_pipeline.errors import ArtifactError, DatasetError
from atlas_pipeline.io_utils import atomic_path, write_json_atomic
from atlas_pipeline.progress import Progress
from atlas_pipeline.safe_arrays import (
    is_finite_number,
    load_json_object_checked,
    load_npz_checked,
    save_npz_deterministic,
)
from atlas_pipeline.sensors.camera import CameraIntrinsics
from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

__all__ = ["pixel_rays", "backproject", "FusedFrames", "FrameFuser", "fuse_frames", "fuse", "read_ahead",
           "check_usable_depth"]


def _undistort_normalized(xd: np.ndarray, yd: np.ndarray, dist: tuple[float, ...], iters: int = 10):
    """Invert the Brown-Conrady model (k1 k2 p1 p2 [k3]) by fixed-point iteration, as OpenCV does."""
    k1, k2, p1, p2 = dist[:4]
    k3 = dist[4] if len(dist) > 4 else 0.0
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


@functools.lru_cache(maxsize=16)
def pixel_rays(camera: CameraIntrinsics, stride: int = 1) -> np.ndarray:
    """Undistorted viewing rays with z = 1 for every ``stride``-th pixel: ``[H/stride, W/stride, 3]`` float32.

    Cached per (camera, stride): computing the inverse distortion is the expensive part.
    """
    v, u = np.mgrid[0:camera.height:stride, 0:camera.width:stride].astype(np.float64)
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    if camera.distortion:
        x, y = _undistort_normalized(x, y, camera.distortion)
    rays = np.stack([x, y, np.ones_like(x)], axis=-1).astype(np.float32)
    rays.setflags(write=False)  # shared through the cache
    return rays


def backproject(
    depth_m: np.ndarray,
    rgb: np.ndarray | None,
    camera: CameraIntrinsics,
    stride: int = 1,
    min_depth_m: float = 0.1,
    max_depth_m: float = 4.0,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Valid depth pixels to camera-frame points.

    Args:
        depth_m: ``[H, W]`` float32 metres, 0 = invalid.
        rgb: ``[H, W, 3]`` uint8 or None.
        stride: use every ``stride``-th pixel in u and v.

    Returns:
        ``(points_cam [M, 3] float32, colors [M, 3] uint8 or None)``.
    """
    rays = pixel_rays(camera, stride)
    z = depth_m[::stride, ::stride]
    valid = (z > min_depth_m) & (z < max_depth_m) & np.isfinite(z)
    pts = rays[valid] * z[valid][:, None]
    cols = rgb[::stride, ::stride][valid] if rgb is not None else None
    return pts.astype(np.float32, copy=False), cols


def _depth_in_range(depth_m: np.ndarray, min_depth_m: float, max_depth_m: float) -> bool:
    """Whether any pixel of ``depth_m`` ``[H, W]`` (metres) lies in the open range the points are
    taken from (as :func:`backproject` keeps them), at full resolution."""
    return bool(np.any((depth_m > min_depth_m) & (depth_m < max_depth_m)))


# Frames decoded ahead of the one being worked on. PNG decoding (a third of a 640x480 frame's
# tracking time, most of its fusion time) releases the GIL, so one reader thread overlaps it with
# tracking or back-projection; two frames in flight bound the memory to a few MB whatever the
# sequence length.
READ_AHEAD_FRAMES = 2


def read_ahead(manifest: FrameManifest, indices,
               on_frame: "Callable[[int, np.ndarray, np.ndarray], None] | None" = None,
               ) -> "Iterator[tuple[int, np.ndarray, np.ndarray]]":
    """Yield ``(frame_index, rgb [H, W, 3] uint8, depth_m [H, W] float32)`` for ``indices`` in order,
    each decoded by a reader thread while the caller works on the previous ones. Depth may be all
    zero (``allow_empty``: the tracker marks such a frame lost). A read error is raised at the frame
    it belongs to; frames not consumed are dropped when the caller stops early, and closing the
    iterator waits for the frame being read.

    ``on_frame(i, rgb, depth_m)``: work on each frame that does not need the caller's results
    (back-projection while tracking), run on the reader thread in frame order before the frame is
    yielded; its error is raised at that frame, as a read error is. A caller that stops early may
    find it ran for the frames read ahead too (their errors then go unseen)."""
    from concurrent.futures import ThreadPoolExecutor

    def read(i: int):
        rgb, depth = manifest.read_rgb(i), manifest.read_depth_m(i, allow_empty=True)
        if on_frame is not None:
            on_frame(i, rgb, depth)
        return rgb, depth

    order = list(indices)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="atlas-read") as pool:
        pending = [(i, pool.submit(read, i)) for i in order[:READ_AHEAD_FRAMES]]
        nxt = len(pending)
        try:
            while pending:
                i, fut = pending.pop(0)
                if nxt < len(order):
                    pending.append((order[nxt], pool.submit(read, order[nxt])))
                    nxt += 1
                rgb, depth = fut.result()
                yield i, rgb, depth
        finally:
            for _, fut in pending:
                fut.cancel()


# A recording is refused only when fewer of its frames than this have any depth pixel (fewer than
# MIN_DEPTH_FRAMES, or under MIN_DEPTH_SHARE of them): the rest are lost frames (reason no_depth).
MIN_DEPTH_FRAMES = 2
MIN_DEPTH_SHARE = 0.5


def check_usable_depth(manifest: FrameManifest, no_depth: list[int], out_of_range: list[int] | tuple[int, ...] = (),
                       depth_range_m: tuple[float, float] | None = None,
                       seen_m: tuple[float, float] | None = None) -> None:
    """Refuse a recording whose frames ``no_depth`` (depth images with no valid pixel) and
    ``out_of_range`` (readings, none within ``depth_range_m``; ``seen_m``: the nearest and farthest
    of those readings) leave too few with depth; otherwise say which frames will be lost."""
    n = manifest.n_frames
    usable = n - len(no_depth) - len(out_of_range)
    if out_of_range and (usable < MIN_DEPTH_FRAMES or usable < MIN_DEPTH_SHARE * n):
        lo, hi = depth_range_m if depth_range_m is not None else (float("nan"), float("nan"))
        seen = f" (from {seen_m[0]:.3g} to {seen_m[1]:.3g} m)" if seen_m is not None else ""
        empty = f", {len(no_depth)} none at all" if no_depth else ""
        raise DatasetError(manifest.root, f"recording '{manifest.dataset}': {len(out_of_range)} of its {n} depth "
                                          f"images have readings{seen} but none within the depth range "
                                          f"{lo:g}-{hi:g} m (fusion.min_depth_m, fusion.max_depth_m){empty}; "
                                          f"{usable} frames with usable depth are too few to map (first out of "
                                          f"range: {manifest.depth_path(out_of_range[0]).name}). Check the depth "
                                          f"scale ({manifest.camera.depth_scale:g} raw units per metre; `dataset "
                                          f"add --depth-scale`) or the depth range")
    if not no_depth:
        return
    first = manifest.depth_path(no_depth[0])
    if usable < MIN_DEPTH_FRAMES or usable < MIN_DEPTH_SHARE * n:
        raise DatasetError(first, f"{len(no_depth)} of the {n} depth images have no valid pixel (all zero; this "
                                  f"is the first): {usable} frames with depth are too few to map (at least "
                                  f"{max(MIN_DEPTH_FRAMES, math.ceil(MIN_DEPTH_SHARE * n))} needed)")
    shown = ", ".join(str(i) for i in no_depth[:10]) + (", ..." if len(no_depth) > 10 else "")
    logger.warning("%s: %d depth image(s) with no valid pixel (all zero; frames %s, first %s): those frames are "
                   "lost (no pose, transitions valid = False, reason no_depth)", manifest.dataset, len(no_depth),
                   shown, first.name)


# Frames per points chunk (``fused-NNNNN.npz``): at 640x480 and stride 2 a chunk is ~37 MB, which
# bounds what fusing or reading holds, whatever the sequence length (one array for a 1,200-frame
# sequence would be 904 MB).
FUSED_CHUNK_FRAMES = 32
FUSED_INDEX_FILE = "fused.npz"  # offsets and valid fractions of every frame (small)
FUSED_META_FILE = "fused.json"
FUSED_CHUNK_PATTERN = "fused-{:05d}.npz"
# Members (dtype kinds or exact dtype, ndim); shapes in FusedFrames.
_FUSED_INDEX_MEMBERS = {"offsets": ("iu", 1), "valid_fraction": ("f", 1)}
_FUSED_CHUNK_MEMBERS = {"points_cam": ("f", 2), "colors": (np.uint8, 2)}


@dataclass
class FusedFrames:
    """Coloured camera-frame points of every frame, in frame order.

    Points stay in the camera frame so this artifact does not depend on which poses (ground truth
    or estimated) the mapper uses later. They are held either in memory (``points_cam`` /
    ``colors``) or, as :func:`fuse_frames` and :meth:`load` give them, in chunks of
    ``chunk_frames`` frames on disk (``chunk_dir``), read one chunk at a time by :meth:`frame`: so
    no stage holds the points of the whole sequence.

    On disk (:meth:`save`): ``fused.npz`` (``offsets``, ``valid_fraction``), ``fused.json``
    (settings, counts, chunk size) and ``fused-00000.npz``... (``points_cam``, ``colors`` of the
    frames ``[k * chunk_frames, (k + 1) * chunk_frames)``), each readable with ``np.load``.

    Attributes:
        points_cam: ``[M, 3]`` float32, metres, camera frame of the frame they came from; None
            when the points live in ``chunk_dir``.
        colors: ``[M, 3]`` uint8 RGB (None likewise).
        offsets: ``[N + 1]`` int64; frame ``i`` owns rows ``offsets[i]:offsets[i+1]``.
        valid_fraction: ``[N]`` float32 share of sampled pixels with usable depth.
        stride, min_depth_m, max_depth_m: the settings that produced them.
        chunk_dir: folder of the chunk files, or None (in memory).
        chunk_frames: frames per chunk.
    """

    points_cam: np.ndarray | None
    colors: np.ndarray | None
    offsets: np.ndarray
    valid_fraction: np.ndarray
    stride: int
    min_depth_m: float
    max_depth_m: float
    chunk_dir: Path | None = None
    chunk_frames: int = FUSED_CHUNK_FRAMES
    _cache: dict = field(default_factory=dict, repr=False, compare=False)
    # Removes the temporary spool this object owns (fuse_frames); None for a loaded artifact.
    _spool_finalizer: weakref.finalize | None = field(default=None, repr=False, compare=False)

    @property
    def n_frames(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_points(self) -> int:
        return int(self.offsets[-1])

    @property
    def n_chunks(self) -> int:
        return -(-self.n_frames // self.chunk_frames)

    def _chunk(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Points and colours of chunk ``c`` (the last one read stays cached), checked against the index.
        The cache entry is one tuple, replaced whole: threads reading frames of different chunks
        never see one chunk's points with another's number."""
        cached = self._cache.get("chunk")
        if cached is not None and cached[0] == c:
            return cached[1], cached[2]
        path = self.chunk_dir / FUSED_CHUNK_PATTERN.format(c)
        z = load_npz_checked(path, _FUSED_CHUNK_MEMBERS, error_type=ArtifactError)
        pts, cols = z["points_cam"], z["colors"]
        a = int(self.offsets[c * self.chunk_frames])
        b = int(self.offsets[min((c + 1) * self.chunk_frames, self.n_frames)])
        if pts.shape != (b - a, 3) or cols.shape != pts.shape:
            raise ArtifactError(f"{path}: points_cam {list(pts.shape)} and colors {list(cols.shape)} must both be "
                                f"[{b - a}, 3] (the index's points of frames {c * self.chunk_frames}..)")
        if not np.isfinite(pts).all():
            raise ArtifactError(f"{path}: points_cam has NaN or infinite values")
        pts = pts.astype(np.float32, copy=False)
        self._cache["chunk"] = (c, pts, cols)
        return pts, cols

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(points_cam [Mi, 3], colors [Mi, 3])`` of frame ``i`` (views, no copy)."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} out of range [0, {self.n_frames})")
        a, b = int(self.offsets[i]), int(self.offsets[i + 1])
        if self.chunk_dir is None:
            return self.points_cam[a:b], self.colors[a:b]
        c = i // self.chunk_frames
        pts, cols = self._chunk(c)
        base = int(self.offsets[c * self.chunk_frames])
        return pts[a - base:b - base], cols[a - base:b - base]

    def _write_chunks(self, directory: Path) -> list[Path]:
        """The chunk files in ``directory``: written from memory, or linked (else copied) from ``chunk_dir``."""
        out = []
        for c in range(self.n_chunks):
            path = directory / FUSED_CHUNK_PATTERN.format(c)
            if self.chunk_dir is not None:
                src = self.chunk_dir / FUSED_CHUNK_PATTERN.format(c)
                if src.resolve() != path.resolve():
                    with atomic_path(path) as tmp:
                        try:  # same file system: no copy of what may be gigabytes
                            os.link(src, tmp)
                        except OSError:
                            shutil.copyfile(src, tmp)
            else:
                a = int(self.offsets[c * self.chunk_frames])
                b = int(self.offsets[min((c + 1) * self.chunk_frames, self.n_frames)])
                with atomic_path(path) as tmp:
                    save_npz_deterministic(tmp, points_cam=self.points_cam[a:b], colors=self.colors[a:b])
            out.append(path)
        return out

    def save(self, directory: Path) -> list[Path]:
        """Write the artifact into ``directory``. An object that owns its temporary spool hands the
        chunks over: the spool goes now and the object reads the saved chunks from then on, so the
        saved files' link counts (and change times, which identify them) do not move later."""
        directory.mkdir(parents=True, exist_ok=True)
        chunks = self._write_chunks(directory)
        if self._spool_finalizer is not None and self._spool_finalizer.alive:
            self._spool_finalizer()
            self._spool_finalizer, self.chunk_dir = None, directory
        path = directory / FUSED_INDEX_FILE
        with atomic_path(path) as tmp:
            save_npz_deterministic(tmp, offsets=self.offsets, valid_fraction=self.valid_fraction)
        meta = write_json_atomic(directory / FUSED_META_FILE, {
            "n_frames": self.n_frames, "n_points": self.n_points, "stride": self.stride,
            "min_depth_m": self.min_depth_m, "max_depth_m": self.max_depth_m,
            "chunk_frames": self.chunk_frames, "n_chunks": self.n_chunks,
        })
        return [path, meta, *chunks]

    @classmethod
    def load(cls, directory: Path) -> "FusedFrames":
        """Read :meth:`save`'s folder: the index and settings now (checked: dtypes, shapes, offsets
        that partition the points, every chunk file present), each chunk when a frame of it is read
        (checked then). A malformed file raises ``ArtifactError`` naming it."""
        path, meta_path = directory / FUSED_INDEX_FILE, directory / FUSED_META_FILE
        if not path.is_file() or not meta_path.is_file():
            raise ArtifactError(f"{directory}: fused frames missing {FUSED_INDEX_FILE} or {FUSED_META_FILE}")
        meta = load_json_object_checked(meta_path)
        stride, lo, hi = meta.get("stride"), meta.get("min_depth_m"), meta.get("max_depth_m")
        chunk_frames, n_points = meta.get("chunk_frames"), meta.get("n_points")
        for name, v in (("stride", stride), ("chunk_frames", chunk_frames)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ArtifactError(f"{meta_path}: {name} must be an integer >= 1, got {v!r}")
        if isinstance(n_points, bool) or not isinstance(n_points, int) or n_points < 0:
            raise ArtifactError(f"{meta_path}: n_points must be an integer >= 0, got {n_points!r}")
        if not (is_finite_number(lo) and is_finite_number(hi)):
            raise ArtifactError(f"{meta_path}: min_depth_m and max_depth_m must be finite numbers, got {lo!r}, {hi!r}")
        z = load_npz_checked(path, _FUSED_INDEX_MEMBERS, error_type=ArtifactError)
        offsets, valid = z["offsets"], z["valid_fraction"]
        n = len(valid)
        if offsets.shape != (n + 1,):
            raise ArtifactError(f"{path}: offsets {list(offsets.shape)} and valid_fraction {list(valid.shape)} "
                                "must be [N + 1] and [N]")
        if offsets[0] != 0 or int(offsets[-1]) != n_points or (np.diff(offsets.astype(np.int64)) < 0).any():
            raise ArtifactError(f"{path}: offsets must rise from 0 to the number of points ({n_points})")
        if not (np.isfinite(valid).all() and (valid >= 0).all() and (valid <= 1).all()):
            raise ArtifactError(f"{path}: valid_fraction must lie in [0, 1]")
        out = cls(points_cam=None, colors=None, offsets=offsets.astype(np.int64),
                  valid_fraction=valid.astype(np.float32), stride=stride, min_depth_m=float(lo),
                  max_depth_m=float(hi), chunk_dir=directory, chunk_frames=chunk_frames)
        missing = [FUSED_CHUNK_PATTERN.format(c) for c in range(out.n_chunks)
                   if not (directory / FUSED_CHUNK_PATTERN.format(c)).is_file()]
        if missing:
            raise ArtifactError(f"{directory}: fused frames missing chunk file(s) {', '.join(missing[:3])}")
        return out


class _ChunkSpool:
    """Writes the points of consecutive frames into chunk files of ``chunk_frames`` frames in a
    temporary folder this process creates (removed when the returned FusedFrames is collected)."""

    def __init__(self, chunk_frames: int):
        self.dir = Path(tempfile.mkdtemp(prefix="atlas-fused-"))
        self.chunk_frames = chunk_frames
        self.pts: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.n_chunks = 0

    def add(self, pts: np.ndarray, cols: np.ndarray) -> None:
        self.pts.append(pts.astype(np.float32, copy=False))
        self.cols.append(cols.astype(np.uint8, copy=False))
        if len(self.pts) == self.chunk_frames:
            self.flush()

    def flush(self) -> None:
        if not self.pts:
            return
        path = self.dir / FUSED_CHUNK_PATTERN.format(self.n_chunks)
        save_npz_deterministic(path, points_cam=np.concatenate(self.pts), colors=np.concatenate(self.cols))
        self.pts, self.cols = [], []
        self.n_chunks += 1


class FrameFuser:
    """Back-projects the frames of ``manifest``, given one at a time in order, into the chunk
    files of a :class:`FusedFrames` (settings of ``cfg``): the work of :func:`fuse_frames` per
    frame, for a pass that decodes the frames anyway (tracking) so each is decoded once. Used as a
    context manager: the temporary chunks go when the block ends without :meth:`finish` having
    handed them to its artifact (a failed pass, a refused finish, a pass left unfinished)."""

    def __init__(self, manifest: FrameManifest, cfg: FusionConfig, chunk_frames: int = FUSED_CHUNK_FRAMES):
        self.manifest, self.cfg = manifest, cfg
        cam = manifest.camera
        self._n_sampled = len(range(0, cam.height, cfg.stride)) * len(range(0, cam.width, cfg.stride))
        self._spool = _ChunkSpool(chunk_frames)
        self._counts: list[int] = []
        self._valid: list[float] = []
        self._no_depth: list[int] = []
        self._out_of_range: list[int] = []  # frames with readings, none within the depth range
        self._seen_m = (math.inf, -math.inf)  # nearest and farthest reading of those frames
        self._handed_over = False  # finish() gave the spool to its artifact, which removes it

    def __enter__(self) -> "FrameFuser":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._handed_over:
            shutil.rmtree(self._spool.dir, ignore_errors=True)

    def add(self, i: int, rgb: np.ndarray, depth_m: np.ndarray) -> None:
        """Frame ``i`` (the next one: frames come in order), ``rgb [H, W, 3]`` uint8, ``depth_m [H, W]``."""
        if i != len(self._counts):
            raise ValueError(f"FrameFuser: frame {i} given where frame {len(self._counts)} was due")
        if not np.any(depth_m > 0):
            self._no_depth.append(i)
        pts, cols = backproject(depth_m, rgb, self.manifest.camera, self.cfg.stride, self.cfg.min_depth_m,
                                self.cfg.max_depth_m)
        # Judged on every pixel, not the stride's: sparse depth (projected lidar, masked depth) can
        # have readings in range, none of them on the stride grid.
        if not len(pts) and i not in self._no_depth[-1:] and not _depth_in_range(depth_m, self.cfg.min_depth_m,
                                                                                   self.cfg.max_depth_m):
            read = depth_m[depth_m > 0]
            self._out_of_range.append(i)
            self._seen_m = (min(self._seen_m[0], float(read.min())), max(self._seen_m[1], float(read.max())))
        self._spool.add(pts, cols)
        self._counts.append(len(pts))
        self._valid.append(len(pts) / self._n_sampled)

    def check_depth(self) -> None:
        """:func:`check_usable_depth` of the frames given so far."""
        check_usable_depth(self.manifest, self._no_depth, self._out_of_range,
                           (self.cfg.min_depth_m, self.cfg.max_depth_m),
                           self._seen_m if self._out_of_range else None)

    def finish(self) -> FusedFrames:
        """The artifact of every frame of the sequence (all given); refused when too few have depth."""
        if len(self._counts) != self.manifest.n_frames:
            raise ValueError(f"FrameFuser: {len(self._counts)} of {self.manifest.n_frames} frames given")
        self._spool.flush()
        self.check_depth()
        offsets = np.zeros(len(self._counts) + 1, dtype=np.int64)
        np.cumsum(self._counts, out=offsets[1:])
        cfg = self.cfg
        out = FusedFrames(
            points_cam=None, colors=None, offsets=offsets, valid_fraction=np.asarray(self._valid, dtype=np.float32),
            stride=cfg.stride, min_depth_m=cfg.min_depth_m, max_depth_m=cfg.max_depth_m,
            chunk_dir=self._spool.dir, chunk_frames=self._spool.chunk_frames,
        )
        # The spool is ours (made here): it goes when the artifact object does, or when save() hands it over.
        out._spool_finalizer = weakref.finalize(out, shutil.rmtree, str(self._spool.dir), True)
        self._handed_over = True
        return out


def fuse_frames(manifest: FrameManifest, cfg: FusionConfig,
                log: Callable[[str], None] | None = None, chunk_frames: int = FUSED_CHUNK_FRAMES) -> FusedFrames:
    """Back-project every frame of ``manifest`` with the settings of ``cfg``, streaming: frames
    are decoded ahead by a reader thread (:func:`read_ahead`) and their points written in chunks
    of ``chunk_frames`` frames to a temporary folder, so memory holds one chunk whatever the
    sequence length. Frames with no depth at all are points-free frames, not errors, unless too
    many are (:func:`check_usable_depth`)."""
    progress = Progress("fusing frames", manifest.n_frames, log)
    with FrameFuser(manifest, cfg, chunk_frames) as fuser:
        for i, rgb, depth in read_ahead(manifest, range(manifest.n_frames)):
            fuser.add(i, rgb, depth)
            progress.update()
        return fuser.finish()


def fuse(manifest: FrameManifest, cfg: PipelineConfig, log: Callable[[str], None] | None = None) -> FusedFrames:
    """The fusion stage: :func:`fuse_frames` with the pipeline config's ``fusion`` section."""
    return fuse_frames(manifest, cfg.fusion, log)

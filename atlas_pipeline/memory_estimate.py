"""Peak memory of a run, estimated from its config and the recording's size before any stage runs.

The config's fixed maxima (``MAX_*`` in :mod:`atlas_pipeline.config`) stop typos of ten orders of
magnitude; this module stops settings that are each plausible but together need more memory than
the machine has (a 2 mm voxel makes nearly one voxel per keyframe point), before hours of work end in
the kernel's out-of-memory killer. :func:`check_memory` raises a :class:`ConfigError` naming the
field that drives the estimate, the stage, the bytes and what is available:

``mapping.voxel_size_m=0.002 would need about 86 GiB for the voxel maps and Gaussian fit of
synthetic-suite's 1,500 frames (640x480; 12 GiB available): raise mapping.voxel_size_m or lower
dataset.max_frames``

What scales, and what does not (each stage's peak; stages run one after another, so the run's
peak is the largest, not the sum):

* fused frames: chunks of ``FUSED_CHUNK_FRAMES`` frames, whatever the recording's length;
* voxel maps (the tracking map and the mapping statistics, ``VoxelGaussianBuilder``): one row per
  occupied voxel, :func:`estimated_voxels`;
* the keyframe fit: per-Gaussian state, Adam moments and the projection of one view, for the
  voxels' Gaussians times ``mapping.fit.densify_max_growth``; the keyframe images within the
  fit's own budgets (``fit_levels.LEVEL_MEMORY_BUDGET_BYTES``, ``mapper.FIT_INPUT_MEMORY_BUDGET_BYTES``);
* localization: the world as loaded, the tracker's surfels, per-frame records;
* videos: frames are rendered one at a time and streamed to ffmpeg (``viz.video.write_mp4``
  consumes them lazily), so ``video.orbit_frames`` adds only its poses; ``video.scale`` sets the
  render buffers.

The per-item byte counts are read off the arrays the code allocates (named below); the voxel
count is a model calibrated on the synthetic suite (docs/benchmarks.md: 2,000 frames, 862
keyframes, 257,669 voxels, 964 MB peak; this estimate gives 985k voxels and 2.4 GiB, 2.5x the peak),
so it errs on the large side for room-scale recordings. The available memory is Linux's
``MemAvailable``, or ``$ATLAS_MEMORY_AVAILABLE`` (bytes, or with a K/M/G/T suffix) where set; on
other systems the check is skipped.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from atlas_pipeline.config import PipelineConfig
from atlas_pipeline.errors import ConfigError

__all__ = ["RecordingShape", "StageEstimate", "AVAILABLE_MEMORY_ENV", "available_memory_bytes", "estimate_stages",
           "estimated_voxels", "estimated_keyframes", "check_memory", "check_entry_memory", "recording_shape",
           "shape_of_manifest"]

AVAILABLE_MEMORY_ENV = "ATLAS_MEMORY_AVAILABLE"  # bytes the check may count on (tests, containers, shared hosts)
MEMINFO = Path("/proc/meminfo")

# ---- the recording ---------------------------------------------------------------------------------
MANIFEST_BYTES_PER_FRAME = 512  # timestamps (3 x 8), pose (128), has_gt, two path strings (~150 each)
FRAME_RECORD_BYTES = 1024  # localization: pose, status, residuals and timings of one frame, with their lists
FRAME_DECODE_BYTES_PER_PIXEL = 32  # a decoded frame: uint8 RGB, float32 depth, float64 temporaries; two in flight
FRAMES_IN_FLIGHT = 4  # read-ahead (2) plus the frame being worked on and its copy
DEFAULT_FRAME_INTERVAL_S = 1.0 / 30.0  # when the timestamps do not tell (one frame)

# ---- keyframes: how fast a camera can move, so how often a keyframe can be due -------------------
MAX_CAMERA_SPEED_M_S = 1.0  # a walk; hand-held RGB-D recordings stay below (TUM fr1 fast: 0.4 m/s)
MAX_CAMERA_TURN_DEG_S = 90.0  # TUM fr1 360: about 40 deg/s

# ---- voxels ----------------------------------------------------------------------------------------
TYPICAL_DEPTH_M = 2.5  # the depth where a keyframe's points are spaced (indoor scenes: 1-4 m)
# Voxels after K keyframes of one place, with D voxels in one keyframe: D * K**exponent. Later
# keyframes see mostly surface already mapped (the suite: 121k voxels after 42 keyframes, 258k
# after 862: an exponent of 0.40-0.52); 0.6 leaves a margin. Voxels finer than the point spacing
# never merge two keyframes' points, and the count tends to one voxel per keyframe point.
KEYFRAME_GROWTH_EXPONENT = 0.6
# VoxelGaussianBuilder rows: ids 8, count 8, sum_xyz 24, sum_rgb 24, sum_sq 48, n_keyframes 4, weight 8
VOXEL_BYTES = 8 + 8 + 24 + 24 + 48 + 4 + 8
VOXEL_MAPS = 2  # the tracking map and the mapping statistics, both held by the world
VOXEL_MERGE_COPIES = 2  # a merge's numpy.insert makes each array's new copy before the old is freed
# to_field's temporaries per voxel: covariances and eigenvectors [3, 3] float64 (3 x 72), eigenvalues,
# scales, means, moments (24 + 24 + 24 + 48), the neighbourhood normals (24)
TO_FIELD_BYTES_PER_VOXEL = 3 * 72 + 24 + 24 + 24 + 48 + 24
# The tracker's surfel of a voxel: position, normal (float64), weights, appearance (128); in a
# saved world its far level (tracker.far_level: up to one copy per band of depth, most of it
# merged: 76 bytes a disk, about one disk per surfel over all bands) and a splat's per-surfel
# working memory kept between views (81 bytes a candidate, with 25 % headroom).
TRACKING_SURFEL_BYTES = 128 + 76 + 102

# ---- Gaussians --------------------------------------------------------------------------------------
# GaussianField: positions 24 (float64), scales 12, rotations 16, colours 3, opacities 4, ids 8
FIELD_BYTES_PER_GAUSSIAN = 24 + 12 + 16 + 3 + 4 + 8
SH_BYTES_PER_COEFFICIENT = 3 * 4  # sh_rest [N, K, 3] float32
FIT_PARAM_ROWS = 13  # fit_kernels._N_PARAM: position 3, log scale 3, rotation 3, opacity logit 1, colour 3
# FitState: pos, log_s, scl, col (4 x 12), quat 16, logit, opa (2 x 4), ids 8, n_steps 4, vs_sum 8,
# vs_cnt 4, anchors (28 when normal_offset_max_scales > 0: counted always)
FIT_STATE_BYTES_PER_GAUSSIAN = 4 * 12 + 16 + 2 * 4 + 8 + 4 + 8 + 4 + 28
FIT_ROW_BYTES = 4 * 4  # per parameter row: Adam m1, m2, the step's gradient and Adam's update (float32)
# raster.prepare_splats with keep_aux: valid 1, depth 8, features 40, box 16, aux 22 x 8, their
# sorted copies (56), sort scratch 4, tile starts 8
SPLAT_BYTES_PER_GAUSSIAN = 1 + 8 + 40 + 16 + 22 * 8 + 56 + 4 + 8
SPLAT_TILES_PER_GAUSSIAN = 4  # tiles a Gaussian's footprint overlaps, on average (16-pixel tiles)
TILE_PAIR_BYTES = 4 + 4 + 10 * 4  # tile id, tile slot, the backward pass's 10 float32 per pair
RENDER_BYTES_PER_PIXEL = 64  # RGB, depth, alpha, surface images, forward rows (7 float32), loss target
FIT_LEVELS = 2  # the coarse and the fit scale, each held within LEVEL_MEMORY_BUDGET_BYTES

# ---- the process ------------------------------------------------------------------------------------
BASE_PROCESS_BYTES = 512 << 20  # Python, NumPy, Numba's compiled kernels, Dagster


@dataclass(frozen=True)
class RecordingShape:
    """What the estimate needs of a recording: ``n_frames`` (after ``dataset.max_frames``), the
    depth image's ``width`` x ``height`` and focal length ``fx`` (px), the typical frame interval (s)."""

    n_frames: int
    width: int
    height: int
    fx: float
    frame_interval_s: float = DEFAULT_FRAME_INTERVAL_S


@dataclass(frozen=True)
class StageEstimate:
    """Peak bytes of one stage (``what``: its words in a message)."""

    stage: str
    what: str
    bytes: int


def shape_of_manifest(manifest: Any) -> RecordingShape:
    """The :class:`RecordingShape` of a :class:`~atlas_pipeline.sensors.tum.FrameManifest`."""
    ts = np.asarray(manifest.timestamps_s, np.float64)
    dt = float(np.median(np.diff(ts))) if len(ts) > 1 else DEFAULT_FRAME_INTERVAL_S
    cam = manifest.camera
    return RecordingShape(int(manifest.n_frames), int(cam.width), int(cam.height), float(cam.fx),
                          dt if math.isfinite(dt) and dt > 0 else DEFAULT_FRAME_INTERVAL_S)


def recording_shape(entry: Any, cfg: PipelineConfig) -> RecordingShape | None:
    """The shape of a registered dataset without generating it: a synthetic entry's from its spec,
    a recording on disk from its manifest (lists and image headers); None when it is not on disk
    (a preset not downloaded yet: the run checks it when ``raw_dataset`` has read it)."""
    from atlas_pipeline.sensors.registry import dataset_on_disk, read_dataset_manifest

    limit = cfg.dataset.max_frames
    if entry.kind == "synthetic":
        from atlas_pipeline.sensors.synthetic import SyntheticSpec

        spec = SyntheticSpec(**entry.params)
        n = spec.n_frames if limit is None else min(spec.n_frames, limit)
        return RecordingShape(n, spec.width, spec.height, float(spec.fx), 1.0 / spec.fps)
    if not dataset_on_disk(entry):
        return None
    return shape_of_manifest(read_dataset_manifest(entry, limit))


def estimated_keyframes(cfg: PipelineConfig, shape: RecordingShape) -> int:
    """Keyframes at most: a camera at ``MAX_CAMERA_SPEED_M_S`` / ``MAX_CAMERA_TURN_DEG_S`` makes one
    due every ``keyframe_translation_m`` or ``keyframe_rotation_deg`` of motion, whichever first."""
    m = cfg.mapping
    per_frame_m = MAX_CAMERA_SPEED_M_S * shape.frame_interval_s
    per_frame_deg = MAX_CAMERA_TURN_DEG_S * shape.frame_interval_s
    frames_per_keyframe = max(1.0, min(m.keyframe_translation_m / per_frame_m, m.keyframe_rotation_deg / per_frame_deg))
    return max(1, min(shape.n_frames, math.ceil(shape.n_frames / frames_per_keyframe)))


def estimated_voxels(cfg: PipelineConfig, shape: RecordingShape) -> int:
    """Occupied voxels of a voxel map: ``P`` points per keyframe (every ``fusion.stride``-th pixel),
    spaced ``s = TYPICAL_DEPTH_M * stride / fx`` apart; one keyframe fills ``D = P min(1, (s / v)^2)``
    voxels of size ``v``; K keyframes ``D * K**KEYFRAME_GROWTH_EXPONENT``, tending to ``D * K``
    (no two points in one voxel) as ``v`` falls below ``s``."""
    stride = cfg.fusion.stride
    v = cfg.mapping.voxel_size_m
    points = math.ceil(shape.height / stride) * math.ceil(shape.width / stride)
    spacing = TYPICAL_DEPTH_M * stride / max(shape.fx, 1e-9)
    per_keyframe = points * min(1.0, (spacing / v) ** 2)
    k = estimated_keyframes(cfg, shape)
    grown = k ** KEYFRAME_GROWTH_EXPONENT
    unmerged = max(0.0, 1.0 - (v / spacing) ** 2)  # share of later points that find no voxel taken
    return int(math.ceil(per_keyframe * (grown + (k - grown) * unmerged)))


def estimate_stages(cfg: PipelineConfig, shape: RecordingShape) -> list[StageEstimate]:
    """Peak bytes of each heavy stage (each includes ``BASE_PROCESS_BYTES`` and the manifest)."""
    from atlas_pipeline.gaussian_world.fit_levels import LEVEL_MEMORY_BUDGET_BYTES, _LEVEL_BYTES_PER_PIXEL
    from atlas_pipeline.gaussian_world.field import sh_rest_count
    from atlas_pipeline.mapping.mapper import FIT_INPUT_BYTES_PER_PIXEL, FIT_INPUT_MEMORY_BUDGET_BYTES
    from atlas_pipeline.perception.rgbd import FUSED_CHUNK_FRAMES

    n, pixels = shape.n_frames, shape.width * shape.height
    base = BASE_PROCESS_BYTES + n * MANIFEST_BYTES_PER_FRAME + FRAMES_IN_FLIGHT * pixels * FRAME_DECODE_BYTES_PER_PIXEL
    points = math.ceil(shape.height / cfg.fusion.stride) * math.ceil(shape.width / cfg.fusion.stride)
    fused = FUSED_CHUNK_FRAMES * points * (12 + 3) * 2  # a chunk's points_cam and colours, and its save

    voxels = estimated_voxels(cfg, shape)
    maps = voxels * VOXEL_BYTES * VOXEL_MAPS + voxels * VOXEL_BYTES * (VOXEL_MERGE_COPIES - 1)
    fit = cfg.mapping.fit
    k_fit = sh_rest_count(fit.sh_degree)
    fitting = fit.epochs > 0
    growth = fit.densify_max_growth if fitting and fit.densify_interval > 0 else 1.0
    gaussians = int(math.ceil(voxels * growth))
    field_bytes = FIELD_BYTES_PER_GAUSSIAN + k_fit * SH_BYTES_PER_COEFFICIENT
    splat = SPLAT_BYTES_PER_GAUSSIAN + SPLAT_TILES_PER_GAUSSIAN * TILE_PAIR_BYTES
    per_gaussian_fit = FIT_STATE_BYTES_PER_GAUSSIAN + (FIT_PARAM_ROWS + 3 * k_fit) * FIT_ROW_BYTES + splat + 2 * field_bytes
    keyframes = estimated_keyframes(cfg, shape)
    fit_pixels = int(pixels * fit.scale * fit.scale)
    images = 0
    if fitting:
        inputs = keyframes * pixels * FIT_INPUT_BYTES_PER_PIXEL
        images = (inputs if inputs <= FIT_INPUT_MEMORY_BUDGET_BYTES else pixels * FIT_INPUT_BYTES_PER_PIXEL)
        level = keyframes * fit_pixels * _LEVEL_BYTES_PER_PIXEL
        images += FIT_LEVELS * (level if level <= LEVEL_MEMORY_BUDGET_BYTES else fit_pixels * _LEVEL_BYTES_PER_PIXEL)
    world = (maps + voxels * TO_FIELD_BYTES_PER_VOXEL
             + (gaussians * per_gaussian_fit + fit_pixels * RENDER_BYTES_PER_PIXEL + images if fitting
                else voxels * field_bytes))
    loaded_world = voxels * VOXEL_BYTES * VOXEL_MAPS + gaussians * field_bytes
    localization = loaded_world + voxels * TRACKING_SURFEL_BYTES + n * FRAME_RECORD_BYTES
    video_pixels = int(pixels * cfg.video.scale * cfg.video.scale)
    videos = (gaussians * (field_bytes + splat) + video_pixels * RENDER_BYTES_PER_PIXEL
              + cfg.video.orbit_frames * 128 + n * 128)  # the orbit's and the trajectory's poses [n, 4, 4]
    return [StageEstimate("fused_frames", "fused frames", base + fused),
            StageEstimate("gaussian_world", "voxel maps and Gaussian fit", base + world),
            StageEstimate("localization_report", "localization", base + localization),
            StageEstimate("demo_videos", "videos", base + loaded_world + videos)]


def peak(cfg: PipelineConfig, shape: RecordingShape) -> StageEstimate:
    return max(estimate_stages(cfg, shape), key=lambda s: s.bytes)


# The settings that scale the estimate, each with what lowers it; the first one whose own value
# (against the default) accounts for most of the peak is named.
_DRIVERS: tuple[tuple[str, str], ...] = (
    ("mapping.voxel_size_m", "raise"),
    ("fusion.stride", "raise"),
    ("mapping.fit.densify_max_growth", "lower"),
    ("mapping.keyframe_translation_m", "raise"),
    ("mapping.keyframe_rotation_deg", "raise"),
    ("mapping.fit.sh_degree", "lower"),
    ("mapping.fit.scale", "lower"),
    ("video.scale", "lower"),
)


def _get(cfg: PipelineConfig, dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        node = getattr(node, part)
    return node


def _with_default(cfg: PipelineConfig, dotted: str) -> PipelineConfig | None:
    default = _get(PipelineConfig(), dotted)
    if _get(cfg, dotted) == default:
        return None
    try:
        return cfg.with_overrides({dotted: default}, "memory estimate")
    except ConfigError:  # another field's rule forbids the default here
        return None


def _size(n: float) -> str:
    gib = n / (1 << 30)
    if gib >= 10:
        return f"{gib:,.0f} GiB"
    if gib >= 1:
        return f"{gib:.1f} GiB"
    return f"{n / (1 << 20):,.0f} MiB"


_SUFFIX = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def available_memory_bytes() -> int | None:
    """``$ATLAS_MEMORY_AVAILABLE`` where set (``12G``, ``512MiB``, ``1000000``), else Linux's
    ``MemAvailable``; None where neither is known (the check is then skipped)."""
    raw = os.environ.get(AVAILABLE_MEMORY_ENV, "").strip()
    if raw:
        m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([kmgt]?)(?:i?b)?", raw, re.IGNORECASE)
        if not m:
            raise ConfigError(f"{AVAILABLE_MEMORY_ENV}={raw!r}: expected bytes, or a number with K, M, G or T (e.g. 12G)")
        return int(float(m.group(1)) * _SUFFIX[m.group(2).lower()])
    try:
        text = MEMINFO.read_text()
    except OSError:  # not Linux
        return None
    m = re.search(r"^MemAvailable:\s+(\d+)\s*kB", text, re.MULTILINE)
    return int(m.group(1)) * 1024 if m else None


def check_memory(cfg: PipelineConfig, shape: RecordingShape, dataset: str = "the recording",
                 available: int | None = None) -> StageEstimate:
    """Raise :class:`ConfigError` when the run's estimated peak exceeds ``available`` bytes
    (None: :func:`available_memory_bytes`; unknown: no check). The message names the setting whose
    value drives the estimate (the one whose default would lower it most), or, at default
    settings, the recording's length. Returns the peak stage's estimate."""
    top = peak(cfg, shape)
    available = available_memory_bytes() if available is None else available
    if available is None or top.bytes <= available:
        return top
    where = (f"for the {top.what} of {dataset}'s {shape.n_frames:,} frames ({shape.width}x{shape.height}; "
             f"{_size(available)} available)")
    best, best_bytes = None, top.bytes
    for dotted, direction in _DRIVERS:
        alt = _with_default(cfg, dotted)
        if alt is not None and (b := peak(alt, shape).bytes) < best_bytes:
            best, best_bytes = (dotted, direction), b
    if best is None:
        raise ConfigError(f"{dataset}'s {shape.n_frames:,} frames ({shape.width}x{shape.height}) would need about "
                          f"{_size(top.bytes)} for the {top.what} at these settings ({_size(available)} available): "
                          f"lower dataset.max_frames or raise mapping.voxel_size_m")
    dotted, direction = best
    raise ConfigError(f"{dotted}={_get(cfg, dotted)!r} would need about {_size(top.bytes)} {where}: "
                      f"{direction} {dotted} or {'lower ' if direction == 'raise' else ''}dataset.max_frames")


def check_entry_memory(cfg: PipelineConfig, entry: Any, available: int | None = None) -> StageEstimate | None:
    """:func:`check_memory` for a registered dataset before its run (:func:`recording_shape`);
    None when its size is not known yet (not on disk) or the available memory is unknown."""
    if available is None and available_memory_bytes() is None:
        return None
    shape = recording_shape(entry, cfg)
    return None if shape is None else check_memory(cfg, shape, entry.name, available)


def check_localization_memory(cfg: PipelineConfig, manifest: Any, n_gaussians: int,
                              available: int | None = None) -> int | None:
    """Before frames are tracked in a saved world of ``n_gaussians`` (``atlas-gs localize``): the
    world as loaded (its voxel maps taken as one voxel per Gaussian), its surfels and one record
    per frame. Raise :class:`ConfigError` naming ``dataset.max_frames`` when that exceeds the
    available memory; returns the estimate (None: available memory unknown)."""
    available = available_memory_bytes() if available is None else available
    if available is None:
        return None
    shape = shape_of_manifest(manifest)
    pixels = shape.width * shape.height
    need = (BASE_PROCESS_BYTES + shape.n_frames * (MANIFEST_BYTES_PER_FRAME + FRAME_RECORD_BYTES)
            + FRAMES_IN_FLIGHT * pixels * FRAME_DECODE_BYTES_PER_PIXEL
            + n_gaussians * (FIELD_BYTES_PER_GAUSSIAN + VOXEL_MAPS * VOXEL_BYTES + TRACKING_SURFEL_BYTES))
    if need > available:
        raise ConfigError(f"localizing {manifest.dataset}'s {shape.n_frames:,} frames in a world of {n_gaussians:,} "
                          f"Gaussians would need about {_size(need)} ({_size(available)} available): "
                          f"lower dataset.max_frames={cfg.dataset.max_frames!r}")
    return need

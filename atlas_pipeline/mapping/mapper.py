"""Incremental mapping: merge keyframes one by one into a voxel Gaussian world.

Also the pipeline's mapping stages (:func:`select_keyframes_stage`, :func:`fuse_and_select_keyframes`
when fusion and keyframes run in one pass, :func:`build_gaussian_world`:
voxel Gaussians, then fitted to the keyframe images) and the policy of extending a saved world
(:func:`extend_saved_world`).

Two depth ranges: the tracker sees depth within the fusion range (``fusion.max_depth_m``, 4 m), and
the world keeps those points, unweighted, as its tracking map (``GaussianWorld.tracking_voxels``); the
Gaussians are made from every keyframe point within the longer mapping range
(``mapping.max_depth_m``, 8 m: walls past 4 m are mapped instead of rendering as background),
each weighted by its inverse depth variance (:func:`depth_weight`), so a far, noisy reading moves a
voxel less than a near one, and the fit's depth term trusts far pixels less
(:func:`depth_loss_weight`); its coverage term asks for opacity at each reading's own depth
(:func:`coverage_band_m`), so the far Gaussians behind a silhouette cannot stand in for the near
surface the sensor measured there. Keyframe pixels the depth missed near a reading take that
reading's depth at a tenth of the weight (:func:`hole_fill_depth`), so the fit has Gaussians to
colour where the images show a surface and the depth does not."""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from collections.abc import Sequence
from typing import TYPE_CHECKING, Callable

import numpy as np

from atlas_pipeline.config import MappingConfig
from atlas_pipeline.gaussian_world.builder import MAX_CELL_VOXELS, GaussianWorld, VoxelGaussianBuilder
from atlas_pipeline.localization.tracker import SurfelCache
from atlas_pipeline.mapping import consistency
from atlas_pipeline.mapping.keyframes import KeyframeSet, build_keyframes, slam_keyframes, slam_poses, uses_ground_truth
from atlas_pipeline.perception.rgbd import FrameFuser, FusedFrames, check_usable_depth, fuse, read_ahead
from atlas_pipeline.progress import Progress
from atlas_pipeline.sensors.depth_noise import depth_sigma_m

if TYPE_CHECKING:
    from atlas_pipeline.config import PipelineConfig
    from atlas_pipeline.sensors.tum import FrameManifest

logger = logging.getLogger(__name__)

LogFn = Callable[[str], None]

__all__ = ["build_world", "extend_world", "extend_world_by_tracking", "extend_world_with_visit", "select_keyframes_stage",
           "fuse_and_select_keyframes", "build_gaussian_world", "extend_saved_world", "depth_sigma_m", "depth_weight",
           "depth_loss_weight", "coverage_band_m"]

def depth_weight(depth_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Inverse-variance weight in (0, 1] of points at ``depth_m`` (any shape) for the voxel merge:
    ``v^2 / (sigma_z^2 + v^2)``. A point's position error is the sensor's (``depth_sigma_m``) plus
    the map's own (one Gaussian stands for a whole voxel ``v``), so noise well below a voxel changes
    little (at 2 cm voxels: over 0.9 to 2 m, 0.67 at 3 m) and far points count as 1 / sigma_z^2 (0.03 at 8 m)."""
    var = depth_sigma_m(depth_m) ** 2 + voxel_size_m ** 2
    return voxel_size_m ** 2 / var


def depth_loss_weight(depth_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Per-pixel weight in (0, 1] of the fit's depth L1 term (``[H, W]`` float32, 0 where there is
    no reading): ``v / sqrt(sigma_z^2 + v^2)``, the scale of a Laplace residual of that std (an L1
    term is a Laplace likelihood; :func:`depth_weight` is the squared one, for means)."""
    d = np.asarray(depth_m)
    w = np.sqrt(depth_weight(d, voxel_size_m))
    return np.where(d > 0, w, 0.0).astype(np.float32)


# A reading's surface lies within this many standard deviations of its position error (sensor noise
# and map resolution, as depth_weight combines them) behind it: 3 sigma holds 99.7 % of a Gaussian error.
COVERAGE_BAND_SIGMAS = 3.0


def coverage_band_m(depth_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Per-pixel depth band (m, ``[H, W]`` float32, 0 where there is no reading) behind each reading
    within which a Gaussian counts as the measured surface for the fit's coverage term:
    ``COVERAGE_BAND_SIGMAS * sqrt(sigma_z^2 + v^2)`` (6 cm at 1 m, 7 cm at 3 m, 34 cm at 8 m with
    2 cm voxels). The reading says the first surface on the ray is there, so the Gaussians up to it
    must be opaque; a surface behind it (a far wall seen past a silhouette) must not stand in for it."""
    d = np.asarray(depth_m)
    band = COVERAGE_BAND_SIGMAS * np.sqrt(depth_sigma_m(d) ** 2 + voxel_size_m ** 2)
    return np.where(d > 0, band, 0.0).astype(np.float32)


def _mapping_points(fused: FusedFrames, k: int, cfg: MappingConfig, manifest: FrameManifest | None):
    """Camera-frame points ``[M, 3]`` and colours ``[M, 3]`` of keyframe ``k`` for the map: those
    within the mapping range (back-projected from its depth image out to ``cfg.max_depth_m`` when
    the sequence's ``manifest`` is given, else the fused points: the tracking range), and those of
    its pixels without depth at :func:`hole_fill_depth` (none without the ``manifest`` or with
    ``cfg.fill_depth_holes`` off). Returns ``((points, colours), (hole_points, hole_colours))``;
    the keyframe's images are read once for both."""
    from atlas_pipeline.perception.rgbd import backproject

    far = manifest is not None and cfg.max_depth_m > fused.max_depth_m
    fill = manifest is not None and cfg.fill_depth_holes
    if far or fill:
        depth, rgb = manifest.read_depth_m(k, allow_empty=True), manifest.read_rgb(k)
    if far:
        measured = backproject(depth, rgb, manifest.camera, fused.stride, fused.min_depth_m, cfg.max_depth_m)
    else:
        pts, cols = fused.frame(k)
        if cfg.max_depth_m < fused.max_depth_m:
            keep = pts[:, 2] < cfg.max_depth_m
            pts, cols = pts[keep], cols[keep]
        measured = (pts, cols)
    holes = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8))
    if fill:
        hi = max(cfg.max_depth_m, fused.max_depth_m)
        holes = backproject(hole_fill_depth(depth, fused.min_depth_m, hi), rgb, manifest.camera, fused.stride,
                            fused.min_depth_m, hi)
    return measured, holes


# Keyframe pixels the image shows but the depth missed (the registered depth's border bands, where
# the depth camera's view ends; dark or shiny surfaces) are given the depth of the nearest reading,
# when one lies within this fraction of the image width (32 px at 640), so the map holds something
# there for the fit to colour; held-out views of TUM teddy otherwise render those bands as
# background (0.7 % of their pixels, 28 % of their squared error).
HOLE_FILL_MAX_FRACTION = 0.05
# ... merged with this fraction of a measured point's weight: a guess must not move a voxel that
# measured points made.
HOLE_FILL_WEIGHT = 0.1


def hole_fill_depth(depth_m: np.ndarray, min_depth_m: float, max_depth_m: float) -> np.ndarray:
    """``[H, W]`` float32: for each pixel without a reading in ``(min_depth_m, max_depth_m)`` that
    lies within ``HOLE_FILL_MAX_FRACTION`` of the width of one, the nearest reading's depth; 0
    elsewhere (readings included)."""
    from scipy.ndimage import distance_transform_edt

    valid = (depth_m > min_depth_m) & (depth_m < max_depth_m) & np.isfinite(depth_m)
    out = np.zeros(depth_m.shape, np.float32)
    if not valid.any() or valid.all():
        return out
    dist, (iy, ix) = distance_transform_edt(~valid, return_indices=True)
    fill = ~valid & (dist <= HOLE_FILL_MAX_FRACTION * depth_m.shape[1])
    out[fill] = depth_m[iy[fill], ix[fill]]
    return out


# Largest merge cell for noisy far points (noise_cell_voxels), as the builder allows.
MAX_NOISE_CELL_VOXELS = MAX_CELL_VOXELS


def noise_cell_voxels(depth_m: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Merge cell per point, in voxels a side ``[M]``: the smallest power of two at least
    ``sigma_z / voxel_size_m`` (1 while the noise is under a voxel; 2 from about 3.6 m and 8 near
    8 m at 2 cm voxels, with the Kinect model), so a map's Gaussians are no finer than the depth
    that made them."""
    ratio = np.maximum(depth_sigma_m(depth_m) / voxel_size_m, 1.0)
    k = np.ceil(np.log2(ratio) - 1e-9).astype(np.int64)  # exact powers of two stay
    return np.minimum(np.left_shift(1, np.maximum(k, 0)), MAX_NOISE_CELL_VOXELS)


def _integrate_mapping(builder: VoxelGaussianBuilder, pts_cam: np.ndarray, cols: np.ndarray, T_world_cam: np.ndarray,
                       voxel_size_m: float, noise_cells: bool = True, weight_scale: float = 1.0) -> None:
    """Merge camera-frame points ``[M, 3]`` at ``T_world_cam [4, 4]`` with inverse-variance weights
    times ``weight_scale`` (and, with ``noise_cells``, into cells as wide as the depth noise:
    :func:`noise_cell_voxels`)."""
    if len(pts_cam) == 0:
        return
    pw = pts_cam.astype(np.float64) @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    z = pts_cam[:, 2]
    builder.integrate(pw, cols, weight_scale * depth_weight(z, voxel_size_m),
                      noise_cell_voxels(z, voxel_size_m) if noise_cells else None)


# Keyframes the Gaussians' statistics may lag behind the tracking map while both merge (each
# waits in the worker's queue holding only its number and pose).
MAP_MERGES_AHEAD = 2


def extend_world(world: GaussianWorld | None, fused: FusedFrames, keyframes: KeyframeSet,
                 cfg: MappingConfig, log: Callable[[str], None] | None = None,
                 manifest: FrameManifest | None = None) -> GaussianWorld:
    """Merge ``keyframes`` into ``world`` (a new world when None), one keyframe at a time.

    Each keyframe's camera-frame points are moved to the world with its mapping pose and added to
    the voxel statistics; ids of voxels seen before are kept. The tracking map takes the fused
    points (the fusion range, unweighted); the Gaussians' statistics take the keyframe's points
    within the mapping range (``cfg.max_depth_m``, read from its depth image in ``manifest``;
    without one, the fused points), weighted by inverse depth variance (:func:`depth_weight`).
    """
    import copy

    if world is not None and abs(world.tracking_voxels.voxel_size_m - cfg.voxel_size_m) > 1e-12:
        raise ValueError(
            f"cannot extend a world built with {world.tracking_voxels.voxel_size_m} m voxels using {cfg.voxel_size_m} m"
        )
    tracking = VoxelGaussianBuilder(cfg.voxel_size_m) if world is None else world.tracking_voxels
    if world is None:
        mapping = VoxelGaussianBuilder(cfg.voxel_size_m)
    else:  # a world saved before mapping had its own range: its tracking statistics seed the map's
        mapping = world.map_voxels if world.map_voxels is not None else copy.deepcopy(world.tracking_voxels)
    history = [] if world is None else list(world.history)
    progress = Progress("merging keyframes", len(keyframes.indices), log, unit="keyframes")
    # The tracking map keeps one copy of each surface (mapping.consistency); it needs the camera.
    surfels = SurfelCache(tracking) if manifest is not None else None
    n_refused = 0

    def merge_into_map(k: int, T: np.ndarray) -> int:
        """Keyframe ``k`` into the Gaussians' statistics; their voxel count after it."""
        measured, holes = _mapping_points(fused, k, cfg, manifest)
        _integrate_mapping(mapping, *measured, T, cfg.voxel_size_m, cfg.noise_adaptive_cells)
        _integrate_mapping(mapping, *holes, T, cfg.voxel_size_m, cfg.noise_adaptive_cells, HOLE_FILL_WEIGHT)
        return len(mapping)

    # The two maps take each keyframe in the same order, each on a thread of its own: the
    # Gaussians' statistics (and the reading of the keyframe's images they need) on a worker,
    # the tracking map (and its consistency test against itself) here.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="atlas-map") as worker:
        sizes = []
        try:
            for k in keyframes.indices:
                T = keyframes.T_world_cam[k]
                sizes.append(worker.submit(merge_into_map, int(k), T))
                if len(sizes) > MAP_MERGES_AHEAD:  # its error here, not after every keyframe
                    sizes[-1 - MAP_MERGES_AHEAD].result()
                pts, cols = fused.frame(int(k))
                if surfels is not None:
                    pts, cols, refused = consistency.agreeing_points(surfels.model(), pts, cols, T, manifest.camera)
                    n_refused += refused
                pw = pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
                tracking.integrate(pw, cols)
                progress.update()
            history += [size.result() for size in sizes]
        finally:
            for size in sizes:
                size.cancel()
    if n_refused:
        logger.info("tracking map: %d keyframe points left out where they contradict surfaces already mapped "
                    "(drift before a loop)", n_refused)
    prev_idx = np.zeros(0, np.int64) if world is None else world.keyframe_indices
    prev_T = np.zeros((0, 4, 4)) if world is None else world.T_world_cam_keyframes
    recordings, keyframe_recording = _joined_recordings(world, manifest, len(keyframes.indices))
    return GaussianWorld(
        field=mapping.to_field(),
        tracking_voxels=tracking,
        keyframe_indices=np.concatenate([prev_idx, keyframes.indices]).astype(np.int64),
        T_world_cam_keyframes=np.concatenate([prev_T, keyframes.T_world_cam[keyframes.indices]]),
        pose_source=keyframes.pose_source,
        history=np.asarray(history, dtype=np.int64),
        map_voxels=mapping,
        recordings=recordings,
        keyframe_recording=keyframe_recording,
    )


def _joined_recordings(world: GaussianWorld | None, manifest: FrameManifest | None, n_new: int):
    """``(recordings, [K] recording of each keyframe)`` of ``world`` (None: a new one) after
    ``n_new`` keyframes of ``manifest`` (None: a recording not known) are merged into it."""
    from atlas_pipeline.scene_memory.recordings import join_recordings, recording_record

    new = recording_record(manifest) if manifest is not None else None
    if world is None:
        return join_recordings([], np.zeros(0, np.int64) if new is not None else None, 0, new, n_new)
    return join_recordings(world.recordings, world.keyframe_recording, len(world.keyframe_indices), new, n_new)


def build_world(fused: FusedFrames, keyframes: KeyframeSet, cfg: MappingConfig,
                log: Callable[[str], None] | None = None, manifest: FrameManifest | None = None) -> GaussianWorld:
    """A new world from the keyframes of one sequence (``manifest``: map out to ``cfg.max_depth_m``)."""
    world = extend_world(None, fused, keyframes, cfg, log, manifest)
    logger.info("built world: %d Gaussians from %d keyframes (tracking map: %d voxels within %.1f m)",
                len(world.field), len(keyframes.indices), len(world.tracking_voxels), fused.max_depth_m)
    return world


def extend_world_by_tracking(world: GaussianWorld, manifest, mapping: MappingConfig, localization,
                             depth_range_m: tuple[float, float], fusion_stride: int,
                             log: Callable[[str], None] | None = None, places=None, depth_checked: bool = False):
    """A second session inside a saved world: the first frame is relocalized in ``world`` (no
    initial pose), then every frame is tracked against the world (by the world alone where it
    sees mostly the world) and keyframes are merged into a copy of its voxel statistics (ids of
    surfaces seen before are kept): into the tracking map only what the world lacks, into the
    Gaussians every point (:class:`SequenceTracker` with ``saved_world``). As along a fixed
    world, the motion model holds the camera where the surfaces leave a direction free.
    ``places``: the world's stored place index (used while it fits the map). ``depth_checked``:
    the recording's empty depth images were already reported (its fused frames were made), so
    they are not reported again.

    Returns ``(extended world, T_world_cam [N, 4, 4], status [N])``; ``world`` is not modified.
    Raises :class:`DatasetError` when no frame of the sequence can be placed in the world.
    """
    import copy

    from atlas_pipeline.errors import DatasetError
    from atlas_pipeline.localization.sequence import STATUS_LOST, SequenceTracker

    if abs(world.tracking_voxels.voxel_size_m - mapping.voxel_size_m) > 1e-12:
        raise ValueError(f"cannot extend a world built with {world.tracking_voxels.voxel_size_m} m voxels "
                         f"using {mapping.voxel_size_m} m")
    tracking = copy.deepcopy(world.tracking_voxels)
    map_voxels = copy.deepcopy(world.field_voxels)
    st = SequenceTracker(manifest.camera, localization, depth_range_m, builder=tracking,
                         keyframe_translation_m=mapping.keyframe_translation_m,
                         keyframe_rotation_deg=mapping.keyframe_rotation_deg, fusion_stride=fusion_stride,
                         prior_poses=world.T_world_cam_keyframes, one_surface=True, saved_world=True,
                         places=places)
    n = manifest.n_frames
    poses = np.full((n, 4, 4), np.nan)
    status: list[str] = []
    history = list(world.history)
    progress = Progress("tracking into the saved world", n, log)
    no_depth: list[int] = []
    out_of_range: list[int] = []  # readings, none within depth_range_m
    seen_m = (np.inf, -np.inf)  # the nearest and farthest reading of those frames
    for i, rgb, depth in read_ahead(manifest, range(n)):
        if not np.any(depth > 0):
            no_depth.append(i)
        elif not np.any((depth > depth_range_m[0]) & (depth < depth_range_m[1])):
            out_of_range.append(i)
            read = depth[depth > 0]
            seen_m = (min(seen_m[0], float(read.min())), max(seen_m[1], float(read.max())))
        est = st.process(i, rgb, depth, timestamp_s=float(manifest.timestamps_s[i]),
                         colour_delay_s=manifest.colour_delay_s(i))
        poses[i] = est.T_world_cam
        status.append(est.status)
        progress.update(extra=est.status)
    if not depth_checked:
        # a recording short of depth: that error names its images
        check_usable_depth(manifest, no_depth, out_of_range, depth_range_m, seen_m if out_of_range else None)
    if status.count(STATUS_LOST) == n:
        raise DatasetError(manifest.root, "no frame could be placed in the saved world (relocalization failed "
                                          "everywhere): is it a world of the same place?")
    if st.n_refused_points:
        logger.info("tracking map: %d keyframe points left out where the saved world already has a surface",
                    st.n_refused_points)
    idx = np.asarray(st.keyframe_indices, np.int64)
    # The tracker merged its keyframes' tracking-range points; the map takes them out to its own range.
    from atlas_pipeline.perception.rgbd import backproject

    for i in idx:
        pts, cols = backproject(manifest.read_depth_m(int(i), allow_empty=True), manifest.read_rgb(int(i)),
                                manifest.camera, fusion_stride, depth_range_m[0], max(mapping.max_depth_m, depth_range_m[1]))
        _integrate_mapping(map_voxels, pts, cols, poses[i], mapping.voxel_size_m, mapping.noise_adaptive_cells)
        history.append(len(map_voxels))
    recordings, keyframe_recording = _joined_recordings(world, manifest, len(idx))
    extended = GaussianWorld(
        field=map_voxels.to_field(), tracking_voxels=tracking, map_voxels=map_voxels,
        keyframe_indices=np.concatenate([world.keyframe_indices, idx]).astype(np.int64),
        T_world_cam_keyframes=np.concatenate([world.T_world_cam_keyframes, poses[idx]]) if len(idx) else world.T_world_cam_keyframes,
        pose_source="estimated", history=np.asarray(history, np.int64),
        recordings=recordings, keyframe_recording=keyframe_recording,
    )
    logger.info("extended world: %d -> %d Gaussians, %d new keyframes, %d frames lost, %d of %d placed by the "
                "saved world alone", len(world.field), len(extended.field), len(idx), status.count(STATUS_LOST),
                st.n_by_saved_world, n)
    return extended, poses, status


def select_keyframes_stage(manifest: FrameManifest, fused: FusedFrames, cfg: PipelineConfig,
                           log: LogFn | None = None) -> KeyframeSet:
    """The keyframes stage: mapping poses (ground truth or SLAM) and the keyframes among them."""
    return build_keyframes(manifest, fused, cfg.mapping, cfg.localization, log)


def fuse_and_select_keyframes(manifest: FrameManifest, cfg: PipelineConfig,
                              log: LogFn | None = None) -> tuple[FusedFrames, KeyframeSet]:
    """The fusion and keyframes stages (:func:`atlas_pipeline.perception.rgbd.fuse`, then
    :func:`select_keyframes_stage`) with each frame decoded once: when the poses come from SLAM,
    every frame is back-projected as the tracker reads it; with ground truth, fusion alone reads
    the frames. The same artifacts as the two stages run one after the other."""
    from atlas_pipeline.errors import DatasetError

    if uses_ground_truth(manifest, cfg.mapping):
        fused = fuse(manifest, cfg, log)
        return fused, select_keyframes_stage(manifest, fused, cfg, log)
    fusion = cfg.fusion
    with FrameFuser(manifest, fusion) as fuser:
        try:
            slam = slam_poses(manifest, cfg.mapping, cfg.localization, (fusion.min_depth_m, fusion.max_depth_m),
                              fusion.stride, log, on_frame=fuser.add)
        except DatasetError:
            fuser.check_depth()  # a recording short of depth: that error names its images
            raise
        fused = fuser.finish()
    return fused, slam_keyframes(slam)


# Full-resolution fit inputs per pixel: RGB uint8 (3 B), depth, its loss weight and coverage band (float32 each).
FIT_INPUT_BYTES_PER_PIXEL = 3 + 4 + 4 + 4
# Above this the keyframes' images and depths are read from disk at each use (a few reads each per
# fit) rather than held: ~150 keyframes at 640x480.
FIT_INPUT_MEMORY_BUDGET_BYTES = 512 << 20


def _keyframe_reads(n: int, read: Callable[[int], np.ndarray], in_memory: bool) -> Sequence:
    """``[read(0), ..., read(n - 1)]`` held in memory, or read on demand."""
    from atlas_pipeline.gaussian_world.optimize import OnDemandViews

    return [read(k) for k in range(n)] if in_memory else OnDemandViews(n, read)


def build_gaussian_world(fused: FusedFrames, keyframes: KeyframeSet, cfg: PipelineConfig,
                         log: LogFn | None = None, manifest: FrameManifest | None = None) -> GaussianWorld:
    """Merge the keyframes into a world; with the sequence's ``manifest``, then fit it to the
    keyframe images: colours first (``mapping.colour_refinement.iterations``, cheap), then every
    Gaussian parameter against colour and depth (``mapping.fit.epochs``)."""
    world = build_world(fused, keyframes, cfg.mapping, log, manifest)
    mc = cfg.mapping
    fit_colours = mc.colour_refinement.iterations > 0
    optimize = mc.fit.epochs > 0
    if manifest is None or not len(world.field) or not (fit_colours or optimize):
        return world
    from atlas_pipeline.scene_memory.recordings import keyframe_indices_of

    idx = [int(i) for i in keyframe_indices_of(world, manifest)]  # the fit reads each keyframe's images there
    if len(idx) != len(world.keyframe_indices):
        raise ValueError(f"the fit reads keyframe images from '{manifest.dataset}', but {len(world.keyframe_indices) - len(idx)} "
                         "keyframes of this world are frames of another recording")
    cam = manifest.camera
    # In memory while small; a long sequence's keyframes are read again at each use instead, so the
    # fit holds its downsampled working copies, not every raw frame.
    in_memory = len(idx) * cam.width * cam.height * FIT_INPUT_BYTES_PER_PIXEL <= FIT_INPUT_MEMORY_BUDGET_BYTES
    from atlas_pipeline.perception.colour_timing import colour_at_depth_time, colour_motion_in_trajectory

    compensate = mc.colour_delay_compensation

    def colour(k: int) -> np.ndarray:  # at the depth image's time, where the keyframe's pose is
        rgb = manifest.read_rgb(idx[k])
        motion = colour_motion_in_trajectory(keyframes.T_world_cam, manifest.timestamps_s, idx[k],
                                             manifest.colour_delay_s(idx[k])) if compensate else None
        if motion is None:
            return rgb
        return colour_at_depth_time(rgb, manifest.read_depth_m(idx[k], allow_empty=True), cam, motion)

    images = _keyframe_reads(len(idx), colour, in_memory)
    if fit_colours:
        from atlas_pipeline.gaussian_world.refine import refine_colours

        world.field = refine_colours(world.field, images, world.T_world_cam_keyframes, manifest.camera.K,
                                     mc.colour_refinement.iterations, mc.colour_refinement.scale, log)
    if optimize:
        from atlas_pipeline.gaussian_world.optimize import optimize_gaussians

        lo, hi = cfg.fusion.min_depth_m, max(mc.max_depth_m, cfg.fusion.max_depth_m)

        def depth(k: int) -> np.ndarray:  # the depth the map was built from: the mapping range
            d = manifest.read_depth_m(idx[k], allow_empty=True)
            return np.where((d >= lo) & (d <= hi), d, 0.0)

        depths = _keyframe_reads(len(idx), depth, in_memory)
        # far pixels trusted less
        weights = _keyframe_reads(len(idx), lambda k: depth_loss_weight(depths[k], mc.voxel_size_m), in_memory)
        # the measured surface itself must be opaque, not one behind it
        bands = _keyframe_reads(len(idx), lambda k: coverage_band_m(depths[k], mc.voxel_size_m), in_memory)
        res = optimize_gaussians(world.field, images, depths, list(world.T_world_cam_keyframes), manifest.camera.K,
                                 mc.fit, log, depth_weights=weights,
                                 coverage_bands_m=bands)
        world.field = res.field
        world.fit = res.record  # no timing: the record is content
    return world


def extend_saved_world(bundle_dir: str | Path, manifest: FrameManifest, fused: FusedFrames | None, cfg: PipelineConfig,
                       log: LogFn | None = None) -> tuple[GaussianWorld, int]:
    """Keep mapping a new sequence into the world saved in the bundle at ``bundle_dir`` (its
    ``world.npz`` voxel statistics): ``(extended world, number of new keyframes)``. ``fused``:
    the sequence's fused frames, or None (fused here when the ground-truth branch needs them).

    With ``mapping.pose_source`` ``ground_truth`` the new sequence's ground-truth poses are taken
    to share the saved world's frame and its keyframes are merged at them; otherwise (a second
    session) its first frame is relocalized in the saved world, then every frame is tracked and
    mapped into it (:func:`extend_world_by_tracking`). Raises :class:`ConfigError` when the bundle
    has no voxel statistics to extend.
    """
    from atlas_pipeline.errors import AtlasError, ConfigError
    from atlas_pipeline.scene_memory.bundle import read_place_index

    try:
        previous = GaussianWorld.load(Path(bundle_dir))
    except AtlasError as exc:
        raise ConfigError(f"{bundle_dir}: cannot extend this bundle, it has no voxel statistics "
                          f"(world.npz; bundles written by `atlas-gs build` have them): {exc}") from exc
    if previous.keyframe_recording is None:
        # a world saved before keyframes named their recording: its bundle's metadata says which,
        # where that can be proven (an older extended bundle's parent checked); unknown ones stay
        # unknown in the new bundle, never recorded as a guess
        from atlas_pipeline.scene_memory.bundle import read_metadata
        from atlas_pipeline.scene_memory.recordings import bundle_keyframe_sources, is_unknown

        ks = bundle_keyframe_sources(read_metadata(Path(bundle_dir)), Path(bundle_dir) / "metadata.json")
        if len(ks) == len(previous.keyframe_indices) and np.array_equal(ks.indices, previous.keyframe_indices):
            previous.recordings, previous.keyframe_recording = ks.recordings, ks.recording
            n_unknown = sum(int((ks.recording == j).sum()) for j, r in enumerate(ks.recordings) if is_unknown(r))
            if n_unknown:
                logger.warning("%d keyframes of %s are recorded in the new bundle as frames of an unknown recording "
                               "(never read by export, mesh or viewer): %s", n_unknown, bundle_dir,
                               ks.unknown_reason or "the bundle does not record their recording")
    return extend_world_with_visit(previous, manifest, fused, cfg, log, read_place_index(bundle_dir, manifest.camera))


def extend_world_with_visit(previous: GaussianWorld, manifest: FrameManifest, fused: FusedFrames | None,
                            cfg: PipelineConfig, log: LogFn | None = None, places=None) -> tuple[GaussianWorld, int]:
    """Keep mapping a new sequence into ``previous`` (not modified), as :func:`extend_saved_world`
    does for a saved bundle: ``(extended world, number of new keyframes)``. ``fused``: the
    sequence's fused frames, or None: only merging at ground-truth poses reads them (fused here
    then); tracking into the world reads the frames itself. ``places``: the stored place index
    of ``previous`` (None: made when first needed)."""
    if cfg.mapping.pose_source == "ground_truth":
        # Ground-truth poses of the new sequence are taken to share the parent's frame.
        fused = fuse(manifest, cfg, log) if fused is None else fused
        keyframes = select_keyframes_stage(manifest, fused, cfg, log)
        world = extend_world(previous, fused, keyframes, cfg.mapping, log, manifest)
    else:
        # A second session: relocalize in the saved world, then track and map into it.
        world, _, _ = extend_world_by_tracking(
            previous, manifest, cfg.mapping, cfg.localization, (cfg.fusion.min_depth_m, cfg.fusion.max_depth_m),
            cfg.fusion.stride, log, places, depth_checked=fused is not None)
    return world, len(world.keyframe_indices) - len(previous.keyframe_indices)

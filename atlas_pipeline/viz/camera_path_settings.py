"""The camera-path planner's thresholds: one documented settings object (``DEFAULT_SETTINGS``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CameraPathSettings", "DEFAULT_SETTINGS", "DEFAULT_K", "DEFAULT_IMAGE_SIZE"]

# Camera assumed when the intrinsics are not given: the Kinect v1 / TUM RGB-D default.
DEFAULT_K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
DEFAULT_IMAGE_SIZE = (640, 480)


@dataclass(frozen=True)
class CameraPathSettings:
    """How the planner builds its occupancy grid, checks poses, verifies a path by rendering, and
    plans orbits, arcs and fly-throughs. Each field is commented with what it bounds and why; the
    defaults are the project's (``DEFAULT_SETTINGS``)."""

    # occupancy
    # Gaussians fainter than this do not block the camera or its view (pruning leftovers, floaters).
    occ_min_opacity: float = 0.05
    # Percentiles of the means that bound the grid: a few stray far points do not blow it up.
    occ_bounds_percentiles: tuple = (0.5, 99.5)
    # The grid's voxel is at least the map voxel and at least the 75th percentile of the spacing
    # between neighbouring means, so a surface sampled sparsely (far from the sensor) has no holes
    # that rays leak through.
    occ_spacing_percentile: float = 75.0
    # Occupied voxels are dilated by this many voxels (a 3x3x3 neighbourhood): closes the remaining
    # pinholes and keeps the camera a little off the surface.
    occ_dilate_voxels: int = 1
    # At most this many cells (about 16 MB of booleans); the voxel grows when the map is larger.
    occ_max_cells: int = 16_000_000
    # Means used to estimate the spacing (a random subset: the KD-tree on all of them is not needed).
    occ_spacing_sample: int = 20_000

    # pose checks
    # A path camera keeps at least this far from the nearest Gaussian mean (metres) ...
    clearance_m: float = 0.25
    # ... or this share of the keyframes' median clearance, if that is smaller (a recording made in a
    # narrow space may never have been 0.25 m from a wall).
    clearance_keyframe_share: float = 0.6
    # The segment from the camera to its target must be free for this share of its length: nothing
    # right in front of the camera (a wall it stands behind). Nearer the target an object may hide
    # part of it, as objects did for the recording camera.
    los_min_free_share: float = 0.4
    # Cells of the coverage estimate (a grid over the field of view; see _SplatView).
    splat_grid: tuple = (32, 24)
    # Gaussians used for it (a random subset, each standing for N / n of them).
    splat_sample: int = 30_000
    # Means nearer the camera than this are not splatted (the renderer's default near plane).
    splat_near_m: float = 0.05
    # A path view must cover at least this share of the cells the keyframes' views covered (median):
    # the video should be as filled as the recording's views were.
    coverage_min_ratio: float = 0.8
    # A path view's median distance to the surface it sees is at least this share of the keyframes'
    # median: closer views magnify the Gaussians, and the renders blur.
    depth_min_ratio: float = 0.6
    # The camera stays in the box of the map's means and the keyframe centres, grown by this (metres).
    box_margin_m: float = 0.1

    # render verification
    # The chosen orbit / arc is rendered (VERIFY_FRAMES frames spread over it, this wide) and compared
    # with the keyframes rendered alike (at most VERIFY_KEYFRAMES of them): each frame must cover
    # this share of the keyframes' median coverage and be this sharp relative to their median.
    verify_width: int = 160
    verify_frames: int = 24
    verify_keyframes: int = 8
    verify_coverage_ratio: float = 0.85
    verify_sharpness_ratio: float = 0.75
    # Rounds of (plan, render, rule out the azimuths of failing frames) before the fly-through.
    verify_rounds: int = 3

    # orbit / arc planning
    # Target: the first hits of a small ray bundle around each keyframe's optical axis.
    target_bundle: int = 5  # 5 x 5 rays
    target_bundle_half_fov_share: float = 0.3  # within the central 30 % of the half field of view
    # Weight (per keyframe) of the point at the keyframes' viewing distance against the least-squares
    # convergence of their optical axes: small, so converging axes decide where they converge.
    target_prior_weight: float = 0.05
    # Weight of the keyframes' mean up against the direction perpendicular to their x axes.
    up_prior_weight: float = 0.01
    # Radii tried per pose, as shares of the keyframes' distance to the target (largest first). No
    # closer than 70 %: nearer, the target (the teddy) outgrows the frame and its Gaussians blur.
    shrink_steps: tuple = (1.0, 0.94, 0.88, 0.82, 0.76, 0.7)
    # A full orbit is tried only when the keyframes saw the target from all around: the largest gap
    # between their azimuths is at most this.
    full_orbit_max_gap_deg: float = 120.0
    # Arcs may reach this far beyond the keyframes' azimuth span on each side (degrees).
    arc_margin_deg: float = 40.0
    # An arc whose poses fail between the grid azimuths is trimmed by a grid step at each end, at
    # most this many times.
    arc_max_trims: int = 4
    # Azimuth step of the grid candidate paths are screened on before their poses are checked.
    angle_grid_deg: float = 3.0
    # The narrowest arc still worth calling a sweep (half-width, degrees); below it, fly through.
    min_arc_half_deg: float = 8.0
    # The centre orbit (no keyframes: its radius comes from the map's extent, not from where a camera
    # was) may be pulled in much further.
    centre_shrink_steps: tuple = tuple(np.round(np.linspace(1.0, 0.2, 17), 3))
    # Per-pose radius shares are smoothed along the path over this share of its frames (a sliding
    # minimum, then a mean over half of it), so the camera glides instead of jumping where a pose
    # shrank.
    shrink_smooth_share: float = 0.1
    # At most this many keyframe poses drive the planning (evenly subsampled): a whole trajectory
    # may be passed in place of the keyframes.
    max_planning_poses: int = 64

    # fly-through
    # Rotation counts as this many metres per radian when spacing frames along the path, so a camera
    # that mostly turns in place still moves evenly.
    fly_metres_per_rad: float = 0.5
    # At most this many poses are flown through (evenly subsampled): a dense trajectory passed in place
    # of the keyframes would otherwise carry its tracking jitter into the video.
    fly_max_poses: int = 32


DEFAULT_SETTINGS = CameraPathSettings()

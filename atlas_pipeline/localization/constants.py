"""Fixed tuning constants of the RGB-D tracker (:mod:`atlas_pipeline.localization.tracker` and its
Numba kernels, :mod:`atlas_pipeline.localization._kernels`).

What a user tunes per dataset lives in :class:`atlas_pipeline.config.LocalizationConfig`
(iterations, association gates, Huber threshold of depth, photometric weight, quality limits).
What is here is fixed by the sensor, the numerics or a measurement, and is the same for every run.
The kernels never read this module: every value reaches them as an argument (a Numba kernel cached
on disk would otherwise keep a stale copy of a changed constant).
"""

from __future__ import annotations

from dataclasses import dataclass

from atlas_pipeline.sensors import depth_noise

__all__ = ["TrackerConstants", "TRACKER_CONSTANTS"]


@dataclass(frozen=True)
class TrackerConstants:
    """Tracker constants; one instance, :data:`TRACKER_CONSTANTS`. Units are in the names."""

    # --- image pyramid ------------------------------------------------------------------------
    # Grey = ITU-R BT.601 luma of sRGB: the usual weights of RGB-D odometry (Open3D, DVO).
    luma_weights_rgb: tuple[float, float, float] = (0.299, 0.587, 0.114)
    # uint8 colour -> grey in [0, 1].
    max_colour_value: float = 255.0
    # A 2x2 depth block whose readings spread more than this (+ ``pyramid_depth_jump_fraction`` of
    # its depth) straddles an occluding edge; it is left invalid instead of averaging foreground and
    # background into a flying point. 3 cm: above the noise of a Kinect at 2 m, below a real step.
    pyramid_max_depth_jump_m: float = 0.03
    # The edge test's depth-proportional part (dimensionless): noise grows with depth.
    pyramid_depth_jump_fraction: float = 0.02

    # --- surfel model -------------------------------------------------------------------------
    # Disk radius in voxels: 0.8 covers the voxel's face (half-diagonal 0.71) so neighbours overlap.
    surfel_radius_voxels: float = 0.8
    # Voxels need this many points of their own (surfels_from_voxels' default) ...
    surfel_min_points: int = 1
    # ... and this many in their 3x3x3 neighbourhood for a plane fit (3 points span a plane).
    surfel_min_support: int = 3
    # Surfels from Gaussian centres alone (no voxel statistics): one centre per voxel, so demand
    # one more neighbour than the minimum for a less noisy normal.
    field_min_support: int = 4
    # Only Gaussians at least this opaque count as surface (fitted fields park faint ones off it) ...
    field_min_opacity: float = 0.5
    # ... unless fewer than this share of them are that opaque (a field of faint Gaussians only).
    field_min_solid_fraction: float = 0.25
    # Maps of fewer surfels are splatted without culling by chunk: testing the chunks would cost
    # about what looking at every surfel does.
    min_surfels_to_cull: int = 20_000
    # A saved world's far part (beyond any frame point's reach, from depth d on) is drawn from
    # coarser levels, in bands of depth (d, 2d], (2d, 4d] ... the last unbounded: band b draws the
    # surfels of each cell of 2^b times this many voxels as one disk, then, for the surfels left,
    # of half as many, down to 2. At the tracker's far clip a 160-pixel view's pixel spans more
    # than a voxel and grows with depth, so full-detail disks pile up per pixel: a multi-room
    # world seen through a door puts hundreds of thousands of them into a 19,200-pixel view ...
    far_level_cell_voxels: int = 4
    far_level_bands: int = 3
    # ... a cell of fewer surfels than this (a fringe, a lone speck) keeps them as they are ...
    far_level_min_members: int = 4
    # ... and so does one whose normals do not agree (a corner, an edge): the largest eigenvalue of
    # the mean of n n^T below this (1: all parallel; 0.95: about 13 degrees of spread).
    far_level_min_coherence: float = 0.95
    # Maps of fewer surfels than this have no far level: the whole of a small map costs little.
    far_level_min_surfels: int = 20_000
    # Largest disk footprint splatted, pixels: bounds the cost of a surfel right in front of the camera.
    splat_max_radius_px: int = 8
    # A ray meeting a disk at cos(incidence) below this (> ~81 deg off its normal) or from behind
    # is not splatted: grazing hits put the intersection far along the ray, off the true surface.
    splat_min_incidence_cos: float = 0.15
    # Visibility band of a model-view pixel: the disks met within this many sigma of depth noise
    # (the sensor model below) behind the nearest one are averaged with it ... A surface fused
    # from a few noisy frames is a layer of disks as thick as their noise; the nearest disk lies
    # about a sigma in front of the true surface, and a frame aligned to it alone is pulled
    # towards its camera by that much, an error each keyframe hands on to the next.
    splat_blend_sigmas: float = 3.0
    # ... or within this many voxels, when more: surfels are voxel means, so even noise-free
    # depth gives a layer about a voxel thick where neighbouring disks overlap.
    splat_blend_floor_voxels: float = 1.0

    # --- projections ----------------------------------------------------------------------------
    # Near clip of every projection (model view, reference image, splatting), m: below any RGB-D
    # sensor's minimum range, and keeps 1 / z finite.
    min_view_depth_m: float = 0.05

    # --- model view -----------------------------------------------------------------------------
    # The model view is rendered this many pyramid levels coarser than the finest tracking level:
    # 2 cm surfels are still resolved (a 160x120 view at 1 m has ~7 mm pixels), the splat costs a
    # quarter, and the point-to-plane residual uses the exact surfel plane whatever the pixel size
    # (measured on TUM teddy: ATE 5.2 vs 5.0 mm, tracking ~20 % faster) ...
    model_level_offset: int = 1
    # ... unless that view would be narrower than this (pixels): small images keep the finest level.
    model_min_width_px: int = 160
    # A tracking view (RGBDTracker.align with within_range) leaves out surfels farther than the
    # frame's depth range plus the association gate plus this margin, m: no frame point can match
    # them, even after the solve moved the pose, and in a map of many rooms they are most of what
    # the frustum holds (the rooms behind the walls).
    view_far_margin_m: float = 1.0
    # After the solve, the quality is graded against a view re-rendered at the final pose when the
    # pose moved this far from where the view was made (relocalization): the view's edges and
    # occlusions no longer match the frame beyond that.
    rerender_translation_m: float = 0.05
    rerender_rotation_deg: float = 5.0

    # --- residuals and weights -------------------------------------------------------------------
    # Nominal noise levels that scale intensity residuals to depth residuals, so
    # ``photometric_weight`` = 1 means "one sigma of intensity counts like one sigma of depth".
    sigma_depth_m: float = 0.01
    sigma_intensity: float = 0.05  # grey levels in [0, 1]
    # Huber threshold of the intensity residual, in ``sigma_intensity``s.
    huber_intensity_sigmas: float = 2.0
    # A reference pixel's depth must be within this of the point's depth in the reference camera,
    # m, or the reference sees another (occluding) surface there and the intensity is not compared.
    occlusion_gate_m: float = 0.05
    # Axial depth noise sigma(z) = A + B (z - Z0)^2 (sensors.depth_noise, the model mapping
    # uses too). The geometric residual of each point is weighted by (sigma(reference) / sigma(z))^2, so far,
    # noisy depth counts as the sensor says instead of pulling the pose with the weight of near,
    # precise depth.
    depth_noise_a_m: float = depth_noise.DEPTH_NOISE_A_M
    depth_noise_b_per_m: float = depth_noise.DEPTH_NOISE_B_PER_M
    depth_noise_z0_m: float = depth_noise.DEPTH_NOISE_Z0_M
    # Points nearer than this keep (about) full weight: sigma(reference) = sigma(this depth).
    depth_noise_reference_m: float = 1.0

    # --- Gauss-Newton -----------------------------------------------------------------------------
    # Fewer frame points than this at a level: the level is skipped (6 unknowns).
    min_points_per_level: int = 6
    # Fewer geometric correspondences than this: stop iterating (twice the 6 unknowns, so the
    # system is over-determined even with a few outliers).
    min_geometric_inliers: int = 12
    # Levenberg damping: the diagonal is scaled by (1 + this) and raised by ``diagonal_floor``, so
    # weakly constrained directions do not jump and a singular system still solves.
    levenberg_damping: float = 1e-4
    diagonal_floor: float = 1e-9
    # Trust region: one step moves at most this far at the finest level (doubling per level above
    # it) and turns at most ``max_step_rad`` (~1.1 deg), so an ill-conditioned early iterate cannot
    # throw the pose out of the basin.
    max_step_m: float = 0.02
    max_step_rad: float = 0.02
    # Motion prior (tracking along a fixed world): the camera centre is held to the motion
    # model's prediction with this share of the largest translation eigenvalue of the geometric
    # normal matrix. Directions the surfaces pin (eigenvalues near the largest) barely feel it;
    # a direction they leave free (a wall and the floor: a few percent) follows the prediction
    # instead of sliding wherever a doubled surface or the photometric term pulls it.
    motion_prior_share: float = 0.02
    # Converged when a step moves less than this (m) and turns less than this (rad) at the finest
    # level: 0.1 mm / 6 mdeg, a tenth of the best depth noise; smaller steps only polish within
    # the noise, at the cost of more iterations ...
    converged_step: float = 1e-4
    # ... and this many times more per coarser level, whose solution the finer levels refine.
    converged_step_level_factor: float = 4.0
    # At the finest level only every other pixel (a checkerboard) is aligned: neighbouring pixels
    # of the 2x2-averaged level are strongly correlated, half of them still give tens of thousands
    # of points for six unknowns, and the finest level is where the time goes (teddy, fr1, the
    # synthetic presets: same ATE within 0.04 cm, tracking 1.1-1.25x faster).
    finest_checkerboard: bool = True

    @property
    def photometric_scale(self) -> float:
        """Intensity residual -> depth residual weight ``(sigma_depth / sigma_intensity)^2``."""
        return (self.sigma_depth_m / self.sigma_intensity) ** 2

    @property
    def huber_intensity(self) -> float:
        """Huber threshold of the intensity residual (grey levels)."""
        return self.sigma_intensity * self.huber_intensity_sigmas

    @property
    def depth_noise_reference_sigma_m(self) -> float:
        """sigma(z) at ``depth_noise_reference_m``: the depth noise that keeps full weight."""
        dz = self.depth_noise_reference_m - self.depth_noise_z0_m
        return self.depth_noise_a_m + self.depth_noise_b_per_m * dz ** 2


TRACKER_CONSTANTS = TrackerConstants()

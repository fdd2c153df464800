"""Frame-to-model RGB-D tracking: hybrid geometric + photometric Gauss-Newton, coarse to fine.

Each frame is aligned to two references at once:

* the **model** (geometry): the world's voxel Gaussians as oriented disks (surfels: centre = voxel
  mean, normal = least-variance axis of the voxel's points), splatted into a view at the predicted
  pose. Residual: point-to-plane distance with projective association, as in KinectFusion /
  ElasticFusion. Because the model fuses every keyframe so far, this does not drift the way
  chained frame-to-frame odometry does.
* the **reference frame** (appearance): the last keyframe's intensity image. Residual: intensity
  difference at the point's projection (dense direct alignment, Kerl et al. 2013), which fixes the
  degrees of freedom geometry alone leaves weak (sliding along planes).

The initial guess comes from a constant-velocity motion model (falling back to the previous pose
when that aligns worse); the solve runs over an image pyramid (coarse levels first, wider
association distances). A frame whose alignment is poor (too few model correspondences, or a large
residual) is *lost*: its pose is a prediction and it is never merged into the map.

Shapes: ``T_*`` ``[4, 4]`` camera-to-world; ``depth_m`` ``[H, W]`` float32 metres (0 = none);
``rgb`` ``[H, W, 3]`` uint8.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from atlas_pipeline.config import LocalizationConfig
from atlas_pipeline.geometry import invert_se3, rotation_angle_rad, so3_exp
from atlas_pipeline.localization import _kernels as kn
from atlas_pipeline.perception.rgbd import _undistort_normalized
from atlas_pipeline.sensors.camera import CameraIntrinsics

logger = logging.getLogger(__name__)

__all__ = ["FramePyramid", "SurfelModel", "TrackResult", "RGBDTracker", "surfels_from_voxels"]

# Intensity residuals are scaled to depth residuals by these nominal noise levels, so
# ``photometric_weight`` = 1 means "one sigma of intensity counts like one sigma of depth".
_SIGMA_DEPTH_M = 0.01
# The model view is rendered one pyramid level coarser than the finest tracking level: 2 cm
# surfels are still resolved (a 160x120 view at 1 m has ~7 mm pixels), the splat costs a quarter,
# and the point-to-plane residual uses the exact surfel plane whatever the pixel size (measured on
# TUM teddy: ATE 5.2 vs 5.0 mm, tracking ~20 % faster). Small images keep the finest level.
_MODEL_LEVEL_OFFSET = 1
_MODEL_MIN_WIDTH = 160
_SIGMA_INTENSITY = 0.05
# Axial depth noise of a structured-light RGB-D camera (Kinect v1 class: TUM, 7-Scenes, ScanNet):
# sigma(z) = A + B (z - Z0)^2 (Nguyen, Izadi and Lovell 2012). The geometric residual of each point
# is weighted by (sigma(reference) / sigma(z))^2, so far, noisy depth counts as the sensor says
# instead of pulling the pose with the weight of near, precise depth.
DEPTH_NOISE_A_M = 0.0012
DEPTH_NOISE_B_PER_M = 0.0019
DEPTH_NOISE_Z0_M = 0.4
DEPTH_NOISE_REFERENCE_M = 1.0  # points nearer than this keep (about) full weight
_DEPTH_NOISE_ARGS = (DEPTH_NOISE_A_M, DEPTH_NOISE_B_PER_M, DEPTH_NOISE_Z0_M,
                     DEPTH_NOISE_A_M + DEPTH_NOISE_B_PER_M * (DEPTH_NOISE_REFERENCE_M - DEPTH_NOISE_Z0_M) ** 2)


@functools.lru_cache(maxsize=32)
def _level_rays(camera: CameraIntrinsics, level: int) -> np.ndarray:
    """Undistorted rays (z = 1) through the centres of the level-``level`` pixels: ``[h, w, 3]``."""
    s = 2 ** level
    h, w = camera.height // s, camera.width // s
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u = s * u + (s - 1) / 2.0
    v = s * v + (s - 1) / 2.0
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    if camera.distortion:
        x, y = _undistort_normalized(x, y, camera.distortion)
    rays = np.stack([x, y, np.ones_like(x)], axis=-1)
    rays.setflags(write=False)
    return rays


def _level_K(camera: CameraIntrinsics, level: int) -> tuple[float, float, float, float]:
    """Pinhole intrinsics of pyramid level ``level`` (block-centred pixel grid)."""
    s = 2 ** level
    return camera.fx / s, camera.fy / s, (camera.cx - (s - 1) / 2.0) / s, (camera.cy - (s - 1) / 2.0) / s


def _dist5(camera: CameraIntrinsics) -> np.ndarray:
    d = np.zeros(5)
    d[: len(camera.distortion)] = camera.distortion
    return d


@dataclass
class FramePyramid:
    """One RGB-D frame prepared for tracking.

    Attributes:
        depth: per level ``[h_l, w_l]`` float32 metres (0 = invalid), level 0 = full resolution.
        intensity: per level ``[h_l, w_l]`` float32 grey in [0, 1].
        grad: per level ``(gx, gy)`` of ``intensity``.
        rgb: ``[H, W, 3]`` uint8 colour image (kept for merging the frame into a map), or None.
    """

    camera: CameraIntrinsics
    depth: list[np.ndarray]
    intensity: list[np.ndarray]
    grad: list[tuple[np.ndarray, np.ndarray]]
    rgb: np.ndarray | None = None

    @classmethod
    def build(cls, rgb: np.ndarray | None, depth_m: np.ndarray, camera: CameraIntrinsics, n_levels: int,
              depth_range_m: tuple[float, float]) -> "FramePyramid":
        d = np.where((depth_m > depth_range_m[0]) & (depth_m < depth_range_m[1]), depth_m, 0).astype(np.float32)
        if rgb is None:
            g = np.zeros(d.shape, np.float32)
        else:
            g = (rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)) / 255.0
        depths, intens, grads = [d], [g], [kn.image_gradients(g)]
        for _ in range(1, n_levels):
            depths.append(kn.downsample_depth(depths[-1], 0.03))
            intens.append(kn.downsample_mean(intens[-1]))
            grads.append(kn.image_gradients(intens[-1]))
        return cls(camera, depths, intens, grads, rgb)

    def points(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points ``[M, 3]`` float64 and their intensities ``[M]`` at ``level``."""
        z = self.depth[level]
        valid = z > 0
        rays = _level_rays(self.camera, level)
        return rays[valid] * z[valid][:, None].astype(np.float64), self.intensity[level][valid].astype(np.float64)

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.depth[0]))


def surfels_from_voxels(ids: np.ndarray, count: np.ndarray, sum_xyz: np.ndarray, sum_sq: np.ndarray,
                        min_points: int = 1, min_support: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Surfel centres and normals from voxel statistics.

    Args:
        ids: ``[N]`` sorted uint64 voxel ids (:func:`pack_voxel_ids`); count ``[N]`` points per voxel;
            sum_xyz ``[N, 3]``; sum_sq ``[N, 6]`` (xx xy xz yy yz zz).
    Returns:
        ``(centres [M, 3], normals [M, 3])``: the voxel mean, and the least-variance axis of the
        points of the voxel *and its 26 neighbours* (a single voxel far from the camera holds a
        handful of noisy points, too few for a stable plane). Voxels with fewer than
        ``min_points`` points or a neighbourhood of fewer than ``min_support`` are left out.
    """
    from atlas_pipeline.gaussian_world._voxel_kernels import neighbourhood_surfels
    from atlas_pipeline.gaussian_world.builder import _BITS, _OFFSET, unpack_voxel_ids

    ids = np.ascontiguousarray(ids, np.uint64)
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    centres, normals, support = neighbourhood_surfels(
        ids, unpack_voxel_ids(ids), np.ascontiguousarray(count, np.float64), np.ascontiguousarray(sum_xyz, np.float64),
        np.ascontiguousarray(sum_sq, np.float64), _OFFSET, _BITS)
    keep = (count >= min_points) & (support >= min_support)
    return np.ascontiguousarray(centres[keep]), np.ascontiguousarray(normals[keep])


# surfels.npz members: (dtype kinds, ndim) -- centres [M, 3], normals [M, 3], radius_m scalar.
_SURFEL_MEMBERS = {"centres": ("f", 2), "normals": ("f", 2), "radius_m": ("f", 0)}


@dataclass
class SurfelModel:
    """The map as surfels: ``centres [M, 3]``, ``normals [M, 3]``, one disk radius (m)."""

    centres: np.ndarray
    normals: np.ndarray
    radius_m: float

    def __post_init__(self) -> None:
        # The map is what surfels.npz stores (float32). Rounding here too makes a map used in
        # memory (the Dagster graph) and the same map reloaded from a bundle (the CLI) identical,
        # so both routes track to the same poses bit for bit. The kernels compute in float64.
        self.centres = np.asarray(self.centres, np.float32).astype(np.float64)
        self.normals = np.asarray(self.normals, np.float32).astype(np.float64)
        self.radius_m = float(self.radius_m)

    @classmethod
    def from_builder(cls, builder, min_points: int = 1) -> "SurfelModel":
        c, n = surfels_from_voxels(builder.ids, builder.count, builder.sum_xyz, builder.sum_sq, min_points)
        # A disk of 0.8 voxel covers the voxel's face (half-diagonal 0.71) so neighbours overlap.
        return cls(c, n, 0.8 * builder.voxel_size_m)

    @classmethod
    def from_field(cls, positions: np.ndarray, voxel_size_m: float, opacities: np.ndarray | None = None,
                   min_opacity: float = 0.5) -> "SurfelModel":
        """Surfels from Gaussian centres ``[N, 3]`` alone (a bundle without ``surfels.npz``, e.g. an
        imported PLY): each centre is binned into its voxel, and normals come from the centres of
        the 3x3x3 voxel neighbourhood. With ``opacities [N]``, only Gaussians at least
        ``min_opacity`` opaque count: fitted fields park faint Gaussians off the surface."""
        from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder

        pts = np.asarray(positions, np.float64)
        if opacities is not None:
            solid = np.asarray(opacities) >= min_opacity
            if solid.sum() >= 0.25 * len(pts):  # not a field of faint Gaussians only
                pts = pts[solid]
        b = VoxelGaussianBuilder(voxel_size_m)
        if len(pts):
            b.integrate(pts, np.zeros((len(pts), 3)))
        c, n = surfels_from_voxels(b.ids, b.count, b.sum_xyz, b.sum_sq, 1, min_support=4)
        return cls(c, n, 0.8 * voxel_size_m)

    def __len__(self) -> int:
        return len(self.centres)

    def save(self, path: Path) -> Path:
        """``surfels.npz``: centres and normals ``[M, 3]`` float32, radius_m (no pickled objects)."""
        from atlas_pipeline.io_utils import atomic_path

        with atomic_path(Path(path)) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, centres=np.asarray(self.centres, np.float32),
                         normals=np.asarray(self.normals, np.float32), radius_m=np.float64(self.radius_m))
        return Path(path)

    @classmethod
    def load(cls, path: Path) -> "SurfelModel":
        """Read :meth:`save`'s file; a malformed one raises ``BundleFormatError`` naming it."""
        from atlas_pipeline.errors import BundleFormatError
        from atlas_pipeline.safe_arrays import load_npz_checked

        try:
            z = load_npz_checked(path, _SURFEL_MEMBERS)
        except BundleFormatError as exc:
            # keep one "<path>: " prefix: the inner message already names the file
            raise BundleFormatError(path, f"not a surfel map ({str(exc).removeprefix(f'{exc.path}: ')})") from exc
        c, n, r = z["centres"], z["normals"], float(z["radius_m"])
        if c.ndim != 2 or c.shape[1:] != (3,) or n.shape != c.shape:
            raise BundleFormatError(path, f"centres {list(c.shape)} and normals {list(n.shape)} must both be [M, 3]")
        if not (np.isfinite(c).all() and np.isfinite(n).all() and np.isfinite(r) and r > 0):
            raise BundleFormatError(path, "non-finite centres / normals or a non-positive radius_m")
        return cls(c.astype(np.float64), n.astype(np.float64), r)

    def render(self, T_world_cam: np.ndarray, camera: CameraIntrinsics, level: int) -> tuple[np.ndarray, np.ndarray]:
        """Model view ``(points_cam [h, w, 3], normals_cam [h, w, 3])`` at pyramid ``level`` (NaN = empty)."""
        s = 2 ** level
        fx, fy, cx, cy = _level_K(camera, level)
        return kn.splat_surfels(self.centres, self.normals, self.radius_m, np.ascontiguousarray(T_world_cam, np.float64),
                                fx, fy, cx, cy, camera.width // s, camera.height // s, 8)


@dataclass
class TrackResult:
    """Outcome of aligning one frame.

    Attributes:
        T_world_cam: ``[4, 4]`` estimate.
        inlier_fraction: share of the frame's finest-level points with a model correspondence.
        agreement: share of the points that land on the model view that are correspondences
            (low: the frame overlaps the map but does not fit it, i.e. a wrong pose).
        residual_m: RMS point-to-plane residual of those correspondences.
        n_points: finest-level points used.
        ok: alignment judged good (see :meth:`RGBDTracker.judge`).
    """

    T_world_cam: np.ndarray
    inlier_fraction: float
    residual_m: float
    n_points: int
    ok: bool
    iterations: int = 0
    agreement: float = float("nan")


class RGBDTracker:
    """Aligns frames to a :class:`SurfelModel` and a reference frame (see the module docstring)."""

    def __init__(self, camera: CameraIntrinsics, cfg: LocalizationConfig, depth_range_m: tuple[float, float]):
        self.camera = camera
        self.cfg = cfg
        self.depth_range_m = depth_range_m
        self.n_levels = len(cfg.iterations) + cfg.finest_level
        self.dist = _dist5(camera)
        coarser = cfg.finest_level + _MODEL_LEVEL_OFFSET
        self.model_level = coarser if camera.width // 2 ** coarser >= _MODEL_MIN_WIDTH else cfg.finest_level

    def prepare(self, rgb: np.ndarray | None, depth_m: np.ndarray) -> FramePyramid:
        return FramePyramid.build(rgb, depth_m, self.camera, self.n_levels, self.depth_range_m)

    def align(self, frame: FramePyramid, model: SurfelModel, T_init: np.ndarray,
              reference: tuple[FramePyramid, np.ndarray] | None = None) -> TrackResult:
        """Coarse-to-fine Gauss-Newton from ``T_init``; ``reference`` = (frame, its pose) for the
        photometric term (None: geometry only)."""
        cfg = self.cfg
        T = np.array(T_init, np.float64)
        fin = cfg.finest_level
        # One model view per frame, at the finest level and the initial pose; coarse levels project into it too.
        T_model = T.copy()
        mlev = self.model_level
        m_pts, m_nrm = model.render(T_model, self.camera, mlev)
        mfx, mfy, mcx, mcy = _level_K(self.camera, mlev)
        w_photo = cfg.photometric_weight * (_SIGMA_DEPTH_M / _SIGMA_INTENSITY) ** 2 if reference is not None else 0.0
        n_levels = len(cfg.iterations)
        total_it = 0
        stats = np.zeros(6)
        for li, iters in enumerate(cfg.iterations):
            level = fin + (n_levels - 1 - li)  # coarse first
            pts, inten = frame.points(level)
            if len(pts) < 6:
                continue
            # Association gate shrinks towards the finest level: wide basin first, precision last.
            max_dist = cfg.max_correspondence_m * (2.0 ** (n_levels - 1 - li)) / 2.0 ** (n_levels - 1)
            max_dist = max(max_dist, cfg.min_correspondence_m)
            if reference is not None:
                rf, T_ref = reference
                ref_I, (ref_gx, ref_gy), ref_D = rf.intensity[level], rf.grad[level], rf.depth[level]
                pK = _level_K(self.camera, level)
                T_ref = np.ascontiguousarray(T_ref, np.float64)
            else:
                ref_I = ref_gx = ref_gy = ref_D = np.zeros((1, 1), np.float32)
                pK = (1.0, 1.0, 0.0, 0.0)
                T_ref = np.eye(4)
            for _ in range(iters):
                H, g, stats = kn.accumulate_normal_equations(
                    pts, inten, T, m_pts, m_nrm, T_model, mfx, mfy, mcx, mcy,
                    max_dist, cfg.huber_depth_m,
                    ref_I, ref_gx, ref_gy, ref_D, T_ref, *pK, self.dist, w_photo, _SIGMA_INTENSITY * 2.0, 0.05,
                    *_DEPTH_NOISE_ARGS,
                )
                total_it += 1
                if stats[1] < 12:
                    break
                # Levenberg damping keeps weakly constrained directions from jumping.
                H[np.diag_indices(6)] *= 1.0 + 1e-4
                H[np.diag_indices(6)] += 1e-9
                try:
                    xi = -np.linalg.solve(H, g)
                except np.linalg.LinAlgError:
                    break
                if not np.all(np.isfinite(xi)):
                    break
                # Trust region: one step moves at most ~2 cm / ~1.1 deg per level above the
                # finest, so an ill-conditioned early iterate cannot throw the pose out of the basin.
                scale = max(np.linalg.norm(xi[:3]) / (0.02 * 2 ** (level - fin)), np.linalg.norm(xi[3:]) / 0.02, 1.0)
                xi = xi / scale
                dT = np.eye(4)
                dT[:3, :3] = so3_exp(xi[3:])
                dT[:3, 3] = xi[:3]
                T = dT @ T
                if np.linalg.norm(xi[:3]) < 1e-5 and np.linalg.norm(xi[3:]) < 1e-5:
                    break
        # Quality at the final pose, finest level, geometry only; a view re-rendered there when
        # the pose travelled far from the one the model view was made at (relocalization).
        moved_m, turned_deg = pose_change(T_model, T)
        if moved_m > 0.05 or turned_deg > 5.0:
            T_model = T.copy()
            m_pts, m_nrm = model.render(T_model, self.camera, mlev)
        pts, inten = frame.points(fin)
        _, _, stats = kn.accumulate_normal_equations(
            pts, inten, T, m_pts, m_nrm, T_model, mfx, mfy, mcx, mcy,
            cfg.min_correspondence_m, cfg.huber_depth_m,
            np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32),
            np.zeros((1, 1), np.float32), np.eye(4), 1.0, 1.0, 0.0, 0.0, self.dist, 0.0, 1.0, 0.05,
        )
        n = int(stats[5])
        frac = float(stats[1] / n) if n else 0.0
        agree = float(stats[1] / stats[6]) if stats[6] else 0.0
        res = float(np.sqrt(stats[4] / stats[1])) if stats[1] else float("nan")
        T = orthonormalize(T)
        return TrackResult(T, frac, res, n, self.judge(frac, res, agree), total_it, agree)

    def judge(self, inlier_fraction: float, residual_m: float, agreement: float = 1.0) -> bool:
        """Good alignment: enough of the frame explained by the map, the part of it that overlaps
        the map mostly agreeing with it, and a small residual."""
        return (inlier_fraction >= self.cfg.min_fitness and agreement >= self.cfg.min_agreement
                and np.isfinite(residual_m) and residual_m <= self.cfg.max_residual_m)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (SVD) in a pose ``[4, 4]``: round-off in chained products grows
    geometrically through a motion model's ``T_prev @ inv(T_prev2) @ T_prev``, so every
    estimate is snapped back onto SE(3)."""
    out = np.array(T, np.float64)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def predict_constant_velocity(T_prev: np.ndarray, T_prev2: np.ndarray | None) -> np.ndarray:
    """Constant-velocity prediction ``T_prev @ (T_prev2^-1 T_prev)`` (camera-frame increment)."""
    if T_prev2 is None:
        return T_prev.copy()
    return orthonormalize(T_prev @ (invert_se3(T_prev2) @ T_prev))


def pose_change(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """``(translation m, rotation deg)`` between two poses."""
    rel = invert_se3(T_a) @ T_b
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle_rad(rel[:3, :3])))

"""Camera paths for demo videos that frame the world: pure math on the Gaussians and keyframe poses.

:func:`plan_camera_path` returns ``[F, 4, 4]`` ``T_world_cam`` poses (camera-to-world, OpenCV camera
axes: x right, y down, z forward, as :func:`atlas_pipeline.geometry.look_at` and the renderer use)
and which kind of path it is:

* ``"orbit"``: 360 degrees around what the keyframes looked at, at their distance and height.
* ``"arc"``: the same circle, swept back and forth over the directions the keyframes saw the target
  from (plus a margin): a recording that saw one side of a scene has nothing mapped behind it, so
  a full circle would show empty space or the backs of surfaces.
* ``"flythrough"``: a smoothed replay of the keyframe poses (centripetal Catmull-Rom positions,
  SQUAD orientations), when no orbit or arc can be made valid. The recording camera was in free
  space by construction.
* ``"centre_orbit"``: no keyframe poses given: a circle around the map's centre (the old path),
  each pose pulled toward the centre until it is in free space and sees the centre.

Every orbit / arc pose is checked against the map (:class:`Occupancy`, a voxel grid of the
Gaussian means, and a coarse splat of the Gaussians into the view): the camera centre must be clear
of the map and inside the box spanned by the map and the keyframes, and the segment to its target
free for its first part (not behind a wall); a pose that is not is moved toward the target (its
radius shrunk, to 70 % at most) until it is. Its view must then be about as covered as the
keyframes' views and not much closer to the surface it sees than they were (closer views magnify
the Gaussians: blurred frames), else its azimuth is ruled out. Azimuths are screened on a grid
first; the path is the full orbit if every azimuth passes, else a back-and-forth arc over the
widest run of valid azimuths that holds the keyframes. Finally frames of the path are rendered small
with the project's renderer and compared with the keyframes rendered alike (coverage and
sharpness); the azimuths of failing frames are ruled out and the path planned again. With no valid
orbit or arc, the keyframes are flown through.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.geometry import (
    look_at,
    pose_from_tq,
    rotation_angle_rad,
    rotmat_to_quat_xyzw,
    slerp_xyzw,
    so3_exp,
    so3_log,
)
from atlas_pipeline.viz.camera_path_occupancy import Occupancy, build_occupancy
from atlas_pipeline.viz.camera_path_settings import (
    DEFAULT_IMAGE_SIZE, DEFAULT_K, DEFAULT_SETTINGS, CameraPathSettings,
)

__all__ = ["CameraPath", "CameraPathSettings", "DEFAULT_SETTINGS", "Occupancy", "plan_camera_path", "flythrough_poses",
           "build_occupancy", "image_sharpness",
           "PATH_ORBIT", "PATH_ARC", "PATH_FLYTHROUGH", "PATH_CENTRE_ORBIT"]

PATH_ORBIT = "orbit"
PATH_ARC = "arc"
PATH_FLYTHROUGH = "flythrough"
PATH_CENTRE_ORBIT = "centre_orbit"

# Path length floor between two keyframes (metres): coincident keyframes stay distinct knots.
_EPS_LEN_M = 1e-6


@dataclass
class CameraPath:
    """A planned camera path.

    Attributes:
        T_world_cam: ``[F, 4, 4]`` camera-to-world poses (OpenCV camera axes).
        kind: one of ``"orbit"``, ``"arc"``, ``"flythrough"``, ``"centre_orbit"``.
        target_world: ``[3]`` point looked at by orbits / arcs (``None`` for a fly-through).
        radius_m, height_m: the keyframes' horizontal distance to the target and height above it
            (along ``up_world``), before any per-pose shrinking.
        up_world: ``[3]`` unit up vector of the path (the keyframes' up, see ``_keyframe_up``).
        sweep_deg: azimuth range covered (360 for an orbit, 2 x half-width for an arc).
        n_shrunk: poses moved toward the target to become valid.
        notes: why the planner chose this kind (the candidates it rejected).
    """

    T_world_cam: np.ndarray
    kind: str
    target_world: np.ndarray | None = None
    radius_m: float = float("nan")
    height_m: float = float("nan")
    up_world: np.ndarray | None = None
    sweep_deg: float = 0.0
    n_shrunk: int = 0
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """JSON-ready description for logs and metadata (floats rounded)."""
        d: dict[str, Any] = {"kind": self.kind, "n_frames": int(len(self.T_world_cam))}
        if self.target_world is not None:
            d.update(target_world=[round(float(v), 3) for v in self.target_world],
                     radius_m=round(self.radius_m, 3), height_m=round(self.height_m, 3),
                     sweep_deg=round(self.sweep_deg, 1), n_shrunk=int(self.n_shrunk))
        if self.notes:
            d["notes"] = list(self.notes)
        return d


# ---------------------------------------------------------------------------------------------
# Ray bundles and views


def _fov_rad(K: np.ndarray | None, image_size: tuple[int, int] | None) -> tuple[float, float]:
    if K is None or image_size is None:
        K, image_size = DEFAULT_K, DEFAULT_IMAGE_SIZE
    w, h = image_size
    fx, fy = float(K[0, 0]), float(K[1, 1])
    return 2.0 * math.atan(0.5 * w / fx), 2.0 * math.atan(0.5 * h / fy)


def _bundle_dirs_cam(fov_rad: tuple[float, float], cols: int, rows: int, share: float = 1.0) -> np.ndarray:
    """``[cols * rows, 3]`` unit camera-frame directions on a grid over ``share`` of the field of view."""
    tx = math.tan(0.5 * fov_rad[0]) * share
    ty = math.tan(0.5 * fov_rad[1]) * share
    u = (np.arange(cols) + 0.5) / cols * 2.0 - 1.0
    v = (np.arange(rows) + 0.5) / rows * 2.0 - 1.0
    uu, vv = np.meshgrid(u * tx, v * ty)
    d = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass
class _ViewStats:
    coverage: np.ndarray  # [P] share of view cells the Gaussians cover (accumulated opacity > 0.5)
    depth_m: np.ndarray  # [P] median over covered cells of the nearest mean's depth (inf if none)


@dataclass
class _SplatView:
    """Cheap estimate of what a view sees: the Gaussians splatted into a coarse grid of cells.

    Each Gaussian adds its opacity times its projected area (``2 pi sigma^2 / z^2``, tangent-plane
    units) over the cell's area to the cell's optical depth (at most its opacity: one Gaussian covers
    one cell at most), so a cell's accumulated opacity ``1 - exp(-tau)`` follows what the renderer
    accumulates there, sparse far surfaces included. Occlusion does not matter for coverage; the
    nearest mean per cell gives the depth of the surface seen.
    """

    means_world: np.ndarray  # [n, 3] (a random subset of at most CameraPathSettings.splat_sample)
    area_opacity_m2: np.ndarray  # [n] opacity * 2 pi sigma^2
    opacity: np.ndarray  # [n]
    weight: float  # N / n: each sampled Gaussian stands for this many
    tan_half: tuple[float, float]  # tangents of the half fields of view (x, y)
    grid: tuple[int, int]  # cells (columns, rows) over the field of view
    near_m: float  # means nearer the camera are not splatted

    @classmethod
    def from_gaussians(cls, positions: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                       fov_rad: tuple[float, float], cfg: CameraPathSettings) -> "_SplatView":
        op = np.asarray(opacities, dtype=np.float64).reshape(-1)
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        sig = np.asarray(scales, dtype=np.float64).reshape(len(pos), -1).mean(axis=1)
        keep = (op >= cfg.occ_min_opacity) & np.isfinite(pos).all(axis=1) & np.isfinite(sig)
        pos, op, sig = pos[keep], op[keep], sig[keep]
        n_all = len(pos)
        if n_all > cfg.splat_sample:
            idx = np.random.default_rng(0).choice(n_all, cfg.splat_sample, replace=False)
            pos, op, sig = pos[idx], op[idx], sig[idx]
        weight = n_all / max(len(pos), 1)
        tan_half = (math.tan(0.5 * fov_rad[0]), math.tan(0.5 * fov_rad[1]))
        return cls(pos, op * 2.0 * np.pi * sig**2, op, weight, tan_half, cfg.splat_grid, cfg.splat_near_m)

    def stats(self, T_world_cam: np.ndarray) -> _ViewStats:
        """Coverage and surface depth of poses ``[P, 4, 4]``."""
        T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
        cols, rows = self.grid
        cell_area = (2.0 * self.tan_half[0] / cols) * (2.0 * self.tan_half[1] / rows)  # tangent units
        cov = np.zeros(len(T))
        depth = np.full(len(T), np.inf)
        for k, Tk in enumerate(T):
            p = (self.means_world - Tk[:3, 3]) @ Tk[:3, :3]  # [n, 3] camera frame
            z = p[:, 2]
            front = z > self.near_m
            zf = z[front]
            u = p[front, 0] / zf / self.tan_half[0]
            v = p[front, 1] / zf / self.tan_half[1]
            inside = (np.abs(u) < 1.0) & (np.abs(v) < 1.0)
            if not inside.any():
                continue
            zf = zf[inside]
            cell = (np.floor((v[inside] + 1.0) * 0.5 * rows).astype(np.int64) * cols
                    + np.floor((u[inside] + 1.0) * 0.5 * cols).astype(np.int64))
            contrib = np.minimum(self.area_opacity_m2[front][inside] / zf**2 / cell_area, self.opacity[front][inside])
            tau = np.bincount(cell, contrib, minlength=rows * cols) * self.weight
            covered = tau > math.log(2.0)  # accumulated opacity 1 - exp(-tau) > 0.5
            cov[k] = covered.mean()
            if covered.any():
                near = np.full(rows * cols, np.inf)
                np.minimum.at(near, cell, zf)
                depth[k] = float(np.median(near[covered]))
        return _ViewStats(cov, depth)


# ---------------------------------------------------------------------------------------------
# Planning


def _finite_poses(T: np.ndarray | None) -> np.ndarray:
    if T is None:
        return np.zeros((0, 4, 4))
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    return T[np.isfinite(T).all(axis=(1, 2))]


def _subsample(T: np.ndarray, n_max: int) -> np.ndarray:
    if len(T) <= n_max:
        return T
    return T[np.round(np.linspace(0, len(T) - 1, n_max)).astype(int)]


def _plane_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - up * (ref @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def _circular_span(angles_rad: np.ndarray) -> tuple[float, float, float]:
    """(centre, span, largest gap) of angles on the circle, radians: the span is the shortest arc
    holding every angle, the complement of the largest gap between neighbours."""
    a = np.sort(np.mod(angles_rad, 2.0 * np.pi))
    if len(a) == 1:
        return float(a[0]), 0.0, 2.0 * np.pi
    gaps = np.diff(np.concatenate([a, a[:1] + 2.0 * np.pi]))
    k = int(np.argmax(gaps))
    start = a[(k + 1) % len(a)]  # the arc starts after the largest gap
    span = 2.0 * np.pi - float(gaps[k])
    return float(start + 0.5 * span), span, float(gaps[k])


def _smooth_shrink(s: np.ndarray, frames: int, closed: bool) -> np.ndarray:
    """Sliding minimum over ``frames`` then mean over half of it (never above the sliding minimum's
    input at any pose, so a smoothed share is at most the share found valid there)."""
    if frames <= 1 or len(s) < 3:
        return s
    h = frames // 2
    mode = "wrap" if closed else "nearest"
    from scipy.ndimage import minimum_filter1d, uniform_filter1d

    m = minimum_filter1d(s, size=2 * h + 1, mode=mode)
    return uniform_filter1d(m, size=h + 1, mode=mode)


@dataclass
class _Checker:
    """Validity of path poses against the map, calibrated on the keyframes."""

    occ: Occupancy
    view: _SplatView | None
    clearance_min_m: float
    coverage_min: float  # absolute share of view cells
    depth_min_m: float
    los_min_free_share: float  # share of the segment to the target that must be free

    def geometry_ok(self, eyes_world: np.ndarray, target_world: np.ndarray) -> np.ndarray:
        """``[P]`` bool: camera centres ``[P, 3]`` in free space, in the box, seeing ``target_world``."""
        eyes = np.asarray(eyes_world, dtype=np.float64).reshape(-1, 3)
        ok = self.occ.in_box(eyes) & ~self.occ.is_occupied(eyes)
        ok &= self.occ.clearance_m(eyes) >= self.clearance_min_m
        idx = np.flatnonzero(ok)
        if len(idx):
            # Line of sight: nothing on the first part of the segment to the target.
            seg = target_world[None, :] - eyes[idx]
            dist = np.linalg.norm(seg, axis=1)
            hit = self.occ.first_hit_m(eyes[idx], seg / dist[:, None], dist)
            ok[idx[hit < self.los_min_free_share * dist]] = False
        return ok

    def view_ok(self, eyes_world: np.ndarray, target_world: np.ndarray, up_world: np.ndarray) -> np.ndarray:
        """``[P]`` bool: the views from ``eyes_world`` ``[P, 3]`` toward the target are about as covered
        as the keyframes' and not much closer to what they see."""
        eyes = np.asarray(eyes_world, dtype=np.float64).reshape(-1, 3)
        if self.view is None or not len(eyes):
            return np.ones(len(eyes), dtype=bool)
        st = self.view.stats(np.stack([look_at(e, target_world, up_world) for e in eyes]))
        return (st.coverage >= self.coverage_min) & (st.depth_m >= self.depth_min_m)

    def valid(self, eyes_world: np.ndarray, target_world: np.ndarray, up_world: np.ndarray) -> np.ndarray:
        ok = self.geometry_ok(eyes_world, target_world)
        idx = np.flatnonzero(ok)
        ok[idx] = self.view_ok(np.asarray(eyes_world).reshape(-1, 3)[idx], target_world, up_world)
        return ok


@dataclass
class _Circle:
    """The circle the orbit and arcs run on: around ``target`` in the plane perpendicular to ``up``.

    One radius and height for the whole circle, the keyframes' medians: following each keyframe's
    own distance would also replay its weaker views (a recording that drifted off its subject).
    """

    target: np.ndarray  # [3]
    up: np.ndarray  # [3] unit
    e1: np.ndarray  # [3] unit, azimuth 0
    e2: np.ndarray  # [3] unit, azimuth 90 degrees
    radius_m: float
    height_m: float
    shrink_steps: tuple[float, ...]  # radius shares tried per pose, largest first
    shrink_smooth_share: float  # share of the frames the per-pose shares are smoothed over

    def offsets(self, angles_rad: np.ndarray) -> np.ndarray:
        """``[A, 3]`` camera centre minus target at azimuths ``[A]`` (unshrunk)."""
        a = np.asarray(angles_rad, dtype=np.float64)
        return (self.radius_m * (np.cos(a)[:, None] * self.e1 + np.sin(a)[:, None] * self.e2)
                + self.height_m * self.up[None, :])

    def valid_shares(self, checker: _Checker, angles_rad: np.ndarray,
                     steps: tuple[float, ...] | None = None) -> np.ndarray:
        """``[A]`` per azimuth, the largest radius share of ``steps`` at which the pose clears the map
        and sees the target, if its view there also passes (NaN: no valid share). Only geometry
        pulls a camera in: pulling in to fill an emptier view would trade it for close-ups."""
        offs = self.offsets(angles_rad)
        share = np.full(len(offs), np.nan)
        todo = np.arange(len(offs))
        for s in self.shrink_steps if steps is None else steps:
            if not len(todo):
                break
            ok = checker.geometry_ok(self.target + s * offs[todo], self.target)
            share[todo[ok]] = s
            todo = todo[~ok]
        found = np.flatnonzero(~np.isnan(share))
        bad = ~checker.view_ok(self.target + share[found, None] * offs[found], self.target, self.up)
        share[found[bad]] = np.nan
        return share

    def poses(self, checker: _Checker, angles_rad: np.ndarray, steps: tuple[float, ...] | None = None,
              fill_invalid: float | None = None) -> tuple[np.ndarray, int] | None:
        """Poses ``[F, 4, 4]`` at azimuths ``[F]`` (a closed loop), each shrunk toward the target until
        valid, and how many were shrunk; ``None`` if some pose is valid at no radius of ``steps``
        (unless ``fill_invalid``: that share is used there)."""
        # A back-and-forth sweep visits each azimuth twice: check each once.
        uniq, inv = np.unique(np.round(np.asarray(angles_rad, np.float64), 9), return_inverse=True)
        share = self.valid_shares(checker, uniq, steps)[inv.reshape(-1)]
        if np.isnan(share).any():
            if fill_invalid is None:
                return None
            share = np.where(np.isnan(share), fill_invalid, share)
        smooth = _smooth_shrink(share, int(round(self.shrink_smooth_share * len(share))), closed=True)
        offs = self.offsets(angles_rad)
        # Keep the smoothed share where it is still valid; elsewhere the share found valid there.
        changed = np.flatnonzero(smooth != share)
        if len(changed):
            ok = checker.valid(self.target + smooth[changed, None] * offs[changed], self.target, self.up)
            share[changed[ok]] = smooth[changed[ok]]
        eyes = self.target + share[:, None] * offs
        return np.stack([look_at(e, self.target, self.up) for e in eyes]), int(np.sum(share < 1.0))


def _keyframe_target(occ: Occupancy, T_kf: np.ndarray, fov: tuple[float, float], max_dist_m: float,
                     cfg: CameraPathSettings) -> np.ndarray | None:
    """``[3]`` what the keyframes looked at; ``None`` if no ray around their optical axes hit the map.

    Each keyframe looked at the surface its central rays hit first, at its viewing distance ``d_k``
    (the median of those hits). The target is the point nearest all optical axes in least squares
    (where a recording that circles something converges), pulled toward the median of the points
    ``d_k`` along each axis, which alone fixes it when the axes are near parallel (a forward-facing
    recording).
    """
    dirs_cam = _bundle_dirs_cam(fov, cfg.target_bundle, cfg.target_bundle, cfg.target_bundle_half_fov_share)
    dirs = np.einsum("pij,rj->pri", T_kf[:, :3, :3], dirs_cam)  # [K, R, 3]
    origins = np.broadcast_to(T_kf[:, None, :3, 3], dirs.shape)
    hit = occ.first_hit_m(origins.reshape(-1, 3), dirs.reshape(-1, 3), max_dist_m).reshape(len(T_kf), -1)
    f = np.isfinite(hit)
    if not f.any():
        return None
    d_k = np.array([np.median(h[m]) if m.any() else np.nan for h, m in zip(hit, f)])  # [K]
    d_k = np.where(np.isfinite(d_k), d_k, np.nanmedian(d_k))
    eyes, z = T_kf[:, :3, 3], T_kf[:, :3, 2]  # [K, 3] centres and optical axes
    prior = np.median(eyes + d_k[:, None] * z, axis=0)
    P = np.eye(3)[None] - z[:, :, None] * z[:, None, :]  # [K, 3, 3] projections off each axis
    lam = cfg.target_prior_weight * len(T_kf)
    A = P.sum(axis=0) + lam * np.eye(3)
    b = np.einsum("kij,kj->i", P, eyes) + lam * prior
    return np.linalg.solve(A, b)


def _keyframe_up(T_kf: np.ndarray, prior_weight: float) -> np.ndarray:
    """``[3]`` unit up vector of the keyframes (TUM worlds have no fixed gravity axis).

    Their mean up (-y of the OpenCV camera) leans toward where they look when they look down or
    up, and an orbit around a leaning axis rolls the horizon. Hand-held cameras are rarely rolled,
    so their x axes are near perpendicular to gravity: the up vector is the direction most
    perpendicular to every x axis, pulled toward the mean up (which alone decides when the x axes
    are near parallel, e.g. a camera that never turned).
    """
    y_mean = -T_kf[:, :3, 1].mean(axis=0)
    y_mean /= max(np.linalg.norm(y_mean), 1e-12)
    xs = T_kf[:, :3, 0]  # [K, 3]
    M = xs.T @ xs / len(xs) + prior_weight * (np.eye(3) - np.outer(y_mean, y_mean))
    _, vecs = np.linalg.eigh(M)
    up = vecs[:, 0]
    return up if up @ y_mean >= 0 else -up


def plan_camera_path(world: GaussianField, T_world_cam_keyframes: np.ndarray | None, n_frames: int,
                     voxel_size_m: float, *, K: np.ndarray | None = None,
                     image_size: tuple[int, int] | None = None, fallback_height_m: float = 1.0,
                     fallback_radius_scale: float = 1.2, settings: CameraPathSettings = DEFAULT_SETTINGS) -> CameraPath:
    """A path of ``n_frames`` poses that frames the world (see the module docstring).

    Args:
        world: the Gaussians (means, scales and opacities are used).
        T_world_cam_keyframes: ``[K, 4, 4]`` poses the world was recorded from, in time order
            (keyframes, or a whole trajectory; non-finite poses are ignored); ``None`` or empty:
            a centre orbit as before.
        n_frames: number of poses (``>= 1``).
        voxel_size_m: the map's voxel size (the occupancy grid is at least this fine).
        K, image_size: ``[3, 3]`` intrinsics and ``(width, height)`` of the video, for the field of
            view the coverage checks use (Kinect v1's when not given).
        fallback_height_m, fallback_radius_scale: the centre orbit's height above the map centre and
            radius as a multiple of the map's horizontal half-extent (``video.orbit_height_m``,
            ``video.orbit_radius_scale``), used only without keyframe poses.
        settings: the planner's thresholds (:class:`CameraPathSettings`).

    Returns:
        :class:`CameraPath` with ``T_world_cam`` ``[n_frames, 4, 4]``.
    """
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    n_frames = int(n_frames)
    pos = np.asarray(world.positions, dtype=np.float64).reshape(-1, 3)
    opacities = world.opacities
    if len(pos) == 0:
        raise ValueError("cannot plan a camera path through an empty world")
    cfg = settings
    T_kf = _subsample(_finite_poses(T_world_cam_keyframes), cfg.max_planning_poses)
    fov = _fov_rad(K, image_size)
    occ = build_occupancy(pos, opacities, voxel_size_m, T_kf[:, :3, 3] if len(T_kf) else None, cfg)
    max_dist_m = float(np.linalg.norm(occ.box_max - occ.box_min))
    if len(T_kf) == 0:
        return _centre_orbit(occ, pos, n_frames, fallback_height_m, fallback_radius_scale, cfg)

    notes: list[str] = []
    target = _keyframe_target(occ, T_kf, fov, max_dist_m, cfg)
    if target is None:
        notes.append("no keyframe ray hit the map")
        return _flythrough(T_world_cam_keyframes, n_frames, notes, cfg)
    up = _keyframe_up(T_kf, cfg.up_prior_weight)
    e1, e2 = _plane_basis(up)
    offs = T_kf[:, :3, 3] - target  # [K, 3]
    h = offs @ up
    horiz = offs - h[:, None] * up
    r = np.linalg.norm(horiz, axis=1)
    radius_m, height_m = float(np.median(r)), float(np.median(h))
    if radius_m < 1e-3 and abs(height_m) < 1e-3:
        notes.append("keyframes sit on their target")
        return _flythrough(T_world_cam_keyframes, n_frames, notes, cfg)

    # Calibrate the checks on the keyframes themselves: the path should be as good as they were.
    view = _SplatView.from_gaussians(pos, world.scales, opacities, fov, cfg)
    kf_stats = view.stats(T_kf)
    kf_clear = occ.clearance_m(T_kf[:, :3, 3])
    kf_depth = kf_stats.depth_m[np.isfinite(kf_stats.depth_m)]
    checker = _Checker(
        occ, view,
        clearance_min_m=min(cfg.clearance_m, cfg.clearance_keyframe_share * float(np.median(kf_clear))),
        coverage_min=cfg.coverage_min_ratio * float(np.median(kf_stats.coverage)),
        depth_min_m=cfg.depth_min_ratio * float(np.median(kf_depth)) if len(kf_depth) else 0.0,
        los_min_free_share=cfg.los_min_free_share,
    )

    az = np.arctan2(horiz @ e2, horiz @ e1)  # [K] keyframe azimuths
    centre_az, span, gap = _circular_span(az[r > 1e-6] if np.any(r > 1e-6) else az)
    full = math.degrees(gap) <= cfg.full_orbit_max_gap_deg
    circle = _Circle(target, up, e1, e2, radius_m, height_m, cfg.shrink_steps, cfg.shrink_smooth_share)
    common = dict(target_world=target, radius_m=radius_m, height_m=height_m, up_world=up)
    step = math.radians(cfg.angle_grid_deg)
    # Screen on a grid of azimuths first (cheap; most failing paths fail there): the whole circle
    # when the keyframes saw the target from all around, else their span plus a margin.
    if full:
        n_grid = int(math.ceil(2.0 * math.pi / step))
        grid = centre_az + 2.0 * np.pi * (np.arange(n_grid) - n_grid // 2) / n_grid  # [G]
    else:
        n_side = int(math.ceil(min(math.pi - step, 0.5 * span + math.radians(cfg.arc_margin_deg)) / step))
        grid = centre_az + step * np.arange(-n_side, n_side + 1)
        notes.append(f"full orbit not tried: keyframes saw the target from {math.degrees(span):.0f} deg")
    grid_ok = ~np.isnan(circle.valid_shares(checker, grid))
    renders: _RenderCheck | None = None
    for _ in range(cfg.verify_rounds):
        sweep = _best_sweep(circle, checker, grid, grid_ok, full, az, n_frames, notes, cfg)
        if sweep is None:
            break
        poses, angles, kind, sweep_deg, n_shrunk = sweep
        # The geometric checks estimate what a view shows; the renderer says it.
        if renders is None:
            renders = _RenderCheck.from_keyframes(world, T_kf, K, image_size, cfg)
        idx = _spread_over_azimuths(angles, cfg.verify_frames)
        bad = idx[~renders.ok(poses[idx])]
        if not len(bad):
            return CameraPath(poses, kind, sweep_deg=sweep_deg, n_shrunk=n_shrunk, notes=notes, **common)
        notes.append(f"{kind} of {sweep_deg:.0f} deg: {len(bad)} of {len(idx)} rendered frames blurred or empty")
        # Rule out the azimuths of the failing frames (and the grid points around them).
        d = np.abs(np.angle(np.exp(1j * (grid[:, None] - angles[bad][None, :]))))  # [G, B]
        grid_ok &= ~np.any(d <= step, axis=1)
    notes.append("no valid orbit or arc: flying through the keyframes")
    return _flythrough(T_world_cam_keyframes, n_frames, notes, cfg)


def _spread_over_azimuths(angles_rad: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` frames spread evenly over the distinct azimuths of ``angles_rad``
    ``[F]`` (a back-and-forth sweep passes each azimuth twice)."""
    _, first = np.unique(np.round(angles_rad, 9), return_index=True)  # ordered by azimuth
    pick = np.unique(np.round(np.linspace(0, len(first) - 1, min(n, len(first)))).astype(int))
    return first[pick]


def _best_sweep(circle: "_Circle", checker: "_Checker", grid: np.ndarray, grid_ok: np.ndarray, full: bool,
                keyframe_az: np.ndarray, n_frames: int, notes: list[str], cfg: CameraPathSettings
                ) -> tuple[np.ndarray, np.ndarray, str, float, int] | None:
    """The orbit (when every grid azimuth is valid) or the best arc over the valid grid azimuths:
    ``(poses [F, 4, 4], azimuths [F], kind, sweep_deg, n_shrunk)``; ``None`` when there is none."""
    if full and grid_ok.all():
        angles = float(grid[len(grid) // 2]) + 2.0 * np.pi * np.arange(n_frames) / n_frames
        res = circle.poses(checker, angles)
        if res is not None:
            return res[0], angles, PATH_ORBIT, 360.0, res[1]
        notes.append("orbit: some pose has no valid radius")
    step = float(grid[1] - grid[0]) if len(grid) > 1 else math.radians(cfg.angle_grid_deg)
    # Arcs: the runs of valid grid azimuths, those holding the most keyframe azimuths first, then
    # the widest. A run is trimmed a step at each end while a pose between grid points fails.
    runs = _runs(grid_ok, circular=full, grid=grid, keyframe_az=keyframe_az)
    if not runs:
        return None
    i0, i1 = runs[0]  # a shorter run would show less of what the keyframes saw
    a0 = float(grid[i0])
    a1 = a0 + ((i1 - i0) % len(grid)) * step
    for _ in range(cfg.arc_max_trims):
        half = 0.5 * (a1 - a0)
        if half < math.radians(cfg.min_arc_half_deg):
            notes.append(f"arc of {2.0 * math.degrees(half):.0f} deg: under {2.0 * cfg.min_arc_half_deg:.0f} deg")
            return None
        # Back and forth, with smooth turnarounds; the last frame leads back into the first.
        angles = 0.5 * (a0 + a1) + half * np.sin(2.0 * np.pi * np.arange(n_frames) / n_frames)
        res = circle.poses(checker, angles)
        if res is not None:
            return res[0], angles, PATH_ARC, 2.0 * math.degrees(half), res[1]
        a0, a1 = a0 + step, a1 - step
    width_deg = math.degrees(float(((i1 - i0) % len(grid)) * step))
    notes.append(f"arc of {width_deg:.0f} deg: some pose has no valid radius")
    return None


@dataclass
class _RenderCheck:
    """Frames rendered small (the project's renderer) against the keyframes rendered alike."""

    world: GaussianField
    K: np.ndarray  # [3, 3] at the check size
    size: tuple[int, int]
    coverage_min: float
    sharpness_min: float

    @classmethod
    def from_keyframes(cls, world: GaussianField, T_kf: np.ndarray, K: np.ndarray | None,
                       image_size: tuple[int, int] | None, cfg: CameraPathSettings) -> "_RenderCheck":
        if K is None or image_size is None:
            K, image_size = DEFAULT_K, DEFAULT_IMAGE_SIZE
        s = cfg.verify_width / float(image_size[0])
        Ks = np.array(K, dtype=np.float64)
        Ks[:2] *= s
        Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5  # pixel centres kept
        Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
        size = (cfg.verify_width, max(1, int(round(image_size[1] * s))))
        chk = cls(world, Ks, size, 0.0, 0.0)
        cov, sharp = chk.measure(_subsample(T_kf, cfg.verify_keyframes))
        chk.coverage_min = cfg.verify_coverage_ratio * float(np.median(cov))
        chk.sharpness_min = cfg.verify_sharpness_ratio * float(np.median(sharp))
        return chk

    def measure(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coverage (share of pixels with accumulated opacity > 0.5) and sharpness (mean gradient
        magnitude of the grey image, 8-bit levels per pixel), ``[P]`` each, of poses ``[P, 4, 4]``."""
        from atlas_pipeline.gaussian_world.render import render_field

        f = self.world
        cov, sharp = [], []
        for T in np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4):
            r = render_field(f, T, self.K, self.size[0], self.size[1])
            cov.append(float(np.mean(r.alpha > 0.5)))
            sharp.append(image_sharpness(r.rgb))
        return np.array(cov), np.array(sharp)

    def ok(self, T_world_cam: np.ndarray) -> np.ndarray:
        cov, sharp = self.measure(T_world_cam)
        return (cov >= self.coverage_min) & (sharp >= self.sharpness_min)


def image_sharpness(rgb: np.ndarray) -> float:
    """Mean gradient magnitude of an ``[H, W, 3]`` image's grey levels (8-bit levels per pixel)."""
    g = np.asarray(rgb, dtype=np.float64).mean(axis=2)
    gx = np.diff(g, axis=1)[:-1, :]
    gy = np.diff(g, axis=0)[:, :-1]
    return float(np.mean(np.hypot(gx, gy)))


def _runs(ok: np.ndarray, circular: bool, grid: np.ndarray, keyframe_az: np.ndarray) -> list[tuple[int, int]]:
    """Runs ``(first, last)`` (inclusive indices, ``last < first`` when wrapping a circular grid) of
    True in ``ok`` ``[G]``, those holding the most keyframe azimuths first, then the longest."""
    n = len(ok)
    if not ok.any() or ok.all():
        return [(0, n - 1)] if ok.all() else []
    start = int(np.argmin(ok)) if circular else 0  # a circular grid: start at a False
    order = (np.arange(n) + start) % n
    runs: list[tuple[int, int]] = []
    i = 0
    while i < n:
        if ok[order[i]]:
            j = i
            while j + 1 < n and ok[order[j + 1]]:
                j += 1
            runs.append((int(order[i]), int(order[j])))
            i = j + 1
        else:
            i += 1
    half_step = 0.5 * abs(float(grid[1] - grid[0])) if n > 1 else 0.0

    def score(run: tuple[int, int]) -> tuple[int, int]:
        i0, i1 = run
        length = (i1 - i0) % n + 1
        rel = np.mod(keyframe_az - grid[i0] + half_step, 2.0 * np.pi)  # keyframes within the run's range
        return int(np.sum(rel <= length * 2.0 * half_step)), length

    return sorted(runs, key=score, reverse=True)


def _centre_orbit(occ: Occupancy, pos: np.ndarray, n_frames: int, height_m: float, radius_scale: float,
                  cfg: CameraPathSettings) -> CameraPath:
    """The old orbit around the map's robust centre (world z up, ``radius_scale`` times the map's
    horizontal half extent, ``height_m`` above the centre), each pose pulled toward the centre until
    it is clear of the map and sees the centre (to the nearest tried radius where none works)."""
    p5, p95 = np.percentile(pos, [5, 95], axis=0)
    centre = 0.5 * (p5 + p95)
    radius_m = radius_scale * max(float(np.linalg.norm((p95 - p5)[:2])) / 2.0, 0.5)
    up = np.array([0.0, 0.0, 1.0])
    circle = _Circle(centre, up, *_plane_basis(up), radius_m, height_m, cfg.shrink_steps, cfg.shrink_smooth_share)
    checker = _Checker(occ, None, cfg.clearance_m, 0.0, 0.0, cfg.los_min_free_share)
    angles = 2.0 * np.pi * np.arange(n_frames) / n_frames
    res = circle.poses(checker, angles, cfg.centre_shrink_steps, fill_invalid=cfg.centre_shrink_steps[-1])
    assert res is not None  # fill_invalid given
    return CameraPath(res[0], PATH_CENTRE_ORBIT, centre, radius_m, height_m, up, 360.0, res[1])


# ---------------------------------------------------------------------------------------------
# Fly-through


def _catmull_rom_centripetal(P: np.ndarray, seg: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Points ``[F, 3]`` on the centripetal Catmull-Rom spline through ``P`` ``[K, 3]`` (K >= 2),
    at local fraction ``a`` ``[F]`` in [0, 1] of segment ``seg`` ``[F]`` (from ``P[seg]`` to ``P[seg+1]``).
    The ends are extended by reflection, so the spline passes through every point."""
    ext = np.concatenate([2 * P[:1] - P[1:2], P, 2 * P[-1:] - P[-2:-1]])  # [K + 2, 3]
    p0, p1, p2, p3 = ext[seg], ext[seg + 1], ext[seg + 2], ext[seg + 3]

    def knot(pa, pb):  # centripetal: sqrt of the chord length, floored so coincident points stay apart
        return np.sqrt(np.maximum(np.linalg.norm(pb - pa, axis=1), _EPS_LEN_M))[:, None]

    t0 = np.zeros((len(seg), 1))
    t1 = t0 + knot(p0, p1)
    t2 = t1 + knot(p1, p2)
    t3 = t2 + knot(p2, p3)
    t = t1 + a[:, None] * (t2 - t1)
    # Barry-Goldman pyramid.
    A1 = ((t1 - t) * p0 + (t - t0) * p1) / (t1 - t0)
    A2 = ((t2 - t) * p1 + (t - t1) * p2) / (t2 - t1)
    A3 = ((t3 - t) * p2 + (t - t2) * p3) / (t3 - t2)
    B1 = ((t2 - t) * A1 + (t - t0) * A2) / (t2 - t0)
    B2 = ((t3 - t) * A2 + (t - t1) * A3) / (t3 - t1)
    return ((t2 - t) * B1 + (t - t1) * B2) / (t2 - t1)


def _flythrough(T_world_cam_keyframes: np.ndarray, n_frames: int, notes: list[str],
                cfg: CameraPathSettings) -> CameraPath:
    poses = flythrough_poses(_subsample(_finite_poses(T_world_cam_keyframes), cfg.fly_max_poses), n_frames, cfg)
    return CameraPath(poses, PATH_FLYTHROUGH, notes=notes)


def flythrough_poses(T_world_cam: np.ndarray, n_frames: int, cfg: CameraPathSettings = DEFAULT_SETTINGS) -> np.ndarray:
    """``[n_frames, 4, 4]`` poses gliding through ``T_world_cam`` ``[K, 4, 4]`` (time order; non-finite
    poses dropped) at an even pace, from the first pose to the last: positions on a centripetal
    Catmull-Rom spline through the keyframe centres, orientations on a SQUAD spline through the
    keyframe orientations (SLERP with Catmull-Rom-like tangents: no kinks at the keyframes)."""
    T = _finite_poses(T_world_cam)
    if len(T) == 0:
        raise ValueError("a fly-through needs at least one finite pose")
    n_frames = int(n_frames)
    if len(T) == 1 or n_frames == 1:
        return np.repeat(T[:1], n_frames, axis=0)
    P = T[:, :3, 3]  # [K, 3]
    R = T[:, :3, :3]  # [K, 3, 3]
    rel = np.einsum("kji,kjl->kil", R[:-1], R[1:])  # [K-1, 3, 3] R_k^T R_{k+1}
    seg_len = (np.linalg.norm(np.diff(P, axis=0), axis=1) + cfg.fly_metres_per_rad * rotation_angle_rad(rel)
               + _EPS_LEN_M)  # [K-1]
    knots = np.concatenate([[0.0], np.cumsum(seg_len)])
    s = np.linspace(0.0, knots[-1], n_frames)
    seg = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, len(T) - 2)
    a = np.clip((s - knots[seg]) / seg_len[seg], 0.0, 1.0)
    a[-1] = 1.0  # end exactly on the last pose
    pos = _catmull_rom_centripetal(P, seg, a)
    # SQUAD control rotations S_k = R_k exp(-(w_k+ + w_k-) / 4), w_k+- the axis-angle steps to the
    # neighbours (mirrored at the ends, where S_k = R_k).
    w_next = so3_log(rel)  # [K-1, 3]
    w_fwd = np.concatenate([w_next, w_next[-1:]])  # [K, 3] step to k+1 (body frame)
    w_bwd = np.concatenate([-w_next[:1], -w_next])  # [K, 3] step to k-1: log(R_k^T R_{k-1}) = -w_{k-1}+
    S = np.einsum("kij,kjl->kil", R, so3_exp(-(w_fwd + w_bwd) / 4.0))
    Q, QS = rotmat_to_quat_xyzw(R), rotmat_to_quat_xyzw(S)
    outer = slerp_xyzw(Q[seg], Q[seg + 1], a)
    inner = slerp_xyzw(QS[seg], QS[seg + 1], a)
    quat = slerp_xyzw(outer, inner, 2.0 * a * (1.0 - a))
    return pose_from_tq(pos, quat)

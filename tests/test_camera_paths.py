"""Camera paths for the demo videos (atlas_pipeline.viz.camera_paths): orbits that frame what the
keyframes looked at, stay in free space, render as sharp and as covered as the recording's own
views, and fall back to a fly-through of the keyframes where no orbit fits."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_pipeline.config import load_profile
from atlas_pipeline.gaussian_world.field import GaussianField
from atlas_pipeline.gaussian_world.render import render_gaussians
from atlas_pipeline.geometry import look_at, rotation_angle_rad
from atlas_pipeline.mapping.mapper import build_gaussian_world, select_keyframes_stage
from atlas_pipeline.perception.rgbd import fuse
from atlas_pipeline.viz.demo import orbit_trajectory
from atlas_pipeline.viz.camera_paths import (
    PATH_ARC,
    PATH_CENTRE_ORBIT,
    PATH_FLYTHROUGH,
    PATH_ORBIT,
    flythrough_poses,
    image_sharpness,
    plan_camera_path,
)
from tests.conftest import SMALL_SYNTH

# What every orbit frame must reach, relative to the median over renders from the keyframe poses
# ("as sharp as renders from real camera poses and mostly covered").
SHARPNESS_RATIO_MIN = 0.7
COVERAGE_RATIO_MIN = 0.8
# Frames per test path: enough to see every part of a sweep, few enough to render quickly.
N_FRAMES = 36
# A camera centre keeps at least this far from every true wall and object surface (metres).
CLEARANCE_MIN_M = 0.2


def _unfitted_cfg():
    # The fit changes how sharp renders are, not where the map is: skip it to keep the tests quick.
    return load_profile("default").with_overrides({"mapping.fit.epochs": 0,
                                                   "mapping.colour_refinement.iterations": 0})


def _world_from(manifest):
    cfg = _unfitted_cfg()
    fused = fuse(manifest, cfg)
    world = build_gaussian_world(fused, select_keyframes_stage(manifest, fused, cfg), cfg)
    assert world.pose_source == "ground_truth"  # the world frame is the scene frame
    return cfg, world


def _render_stats(field: GaussianField, poses: np.ndarray, K: np.ndarray, w: int, h: int):
    """Sharpness ``[P]`` (mean gradient magnitude) and coverage ``[P]`` (share of pixels with
    accumulated opacity > 0.5) of renders from ``poses`` ``[P, 4, 4]``."""
    sharp, cov = [], []
    for T in poses:
        r = render_gaussians(field.positions, field.scales, field.rotations_xyzw, field.colors, field.opacities,
                             T, K, w, h)
        sharp.append(image_sharpness(r.rgb))
        cov.append(float(np.mean(r.alpha > 0.5)))
    return np.array(sharp), np.array(cov)


# ---- (a) the synthetic room ---------------------------------------------------------------------

SYNTHETIC_WORLDS = {
    # the shared small sequence: 12 frames, 14 degrees of the path around the room
    "small": (None, None),
    # one turn around the room: the keyframes saw the objects from all around
    "loop": ({"n_frames": 48, "loop_revolutions": 1}, PATH_ORBIT),
    # 80 degrees of the path: an arc over what was seen
    "arc": ({"n_frames": 24, "fps": 10.0}, PATH_ARC),
}


@pytest.fixture(scope="module", params=sorted(SYNTHETIC_WORLDS))
def synthetic_world(request, small_manifest, tmp_path_factory):
    from atlas_pipeline.sensors.synthetic import SyntheticSpec, generate_synthetic_dataset
    from atlas_pipeline.sensors.tum import load_tum_sequence

    extra, expected_kind = SYNTHETIC_WORLDS[request.param]
    manifest = small_manifest
    if extra is not None:
        spec = SyntheticSpec(**{**SMALL_SYNTH, **extra})
        root = generate_synthetic_dataset(tmp_path_factory.mktemp("synth") / request.param, spec)
        manifest = load_tum_sequence(root, spec.camera(), request.param)
    cfg, world = _world_from(manifest)
    return request.param, expected_kind, manifest, cfg, world


def test_synthetic_orbit_frames_are_free_sharp_and_covered(synthetic_world):
    from atlas_pipeline.sensors.synthetic import build_scene

    name, expected_kind, manifest, cfg, world = synthetic_world
    cam = manifest.camera
    path = plan_camera_path(world.field, world.T_world_cam_keyframes, N_FRAMES, cfg.mapping.voxel_size_m,
                            K=cam.K, image_size=(cam.width, cam.height))
    if expected_kind is not None:
        assert path.kind == expected_kind, path.summary()
    T = path.T_world_cam
    assert T.shape == (N_FRAMES, 4, 4) and np.isfinite(T).all()
    assert np.allclose(np.einsum("fji,fjk->fik", T[:, :3, :3], T[:, :3, :3]), np.eye(3), atol=1e-9)

    # Free space by the scene's exact geometry (negative clearance: outside the room), and inside
    # the box of the map and the keyframe centres (a recording camera may stand beyond the surfaces
    # it mapped, with the unseen wall behind it).
    eyes = T[:, :3, 3]
    clearance = build_scene(SMALL_SYNTH["seed"]).clearance_m(eyes)
    assert clearance.min() > CLEARANCE_MIN_M, (path.summary(), clearance.min())
    kf_eyes = np.asarray(world.T_world_cam_keyframes)[:, :3, 3]
    lo = np.minimum(world.field.positions.min(axis=0), kf_eyes.min(axis=0))
    hi = np.maximum(world.field.positions.max(axis=0), kf_eyes.max(axis=0))
    assert np.all((eyes >= lo - 1e-9) & (eyes <= hi + 1e-9)), path.summary()

    # Every frame as sharp and as covered as the renders from the keyframe poses.
    kf_sharp, kf_cov = _render_stats(world.field, world.T_world_cam_keyframes, cam.K, cam.width, cam.height)
    sharp, cov = _render_stats(world.field, T, cam.K, cam.width, cam.height)
    sharp_ratio, cov_ratio = sharp / np.median(kf_sharp), cov / np.median(kf_cov)
    summary = (f"{name} {path.kind}: sharpness ratio min {sharp_ratio.min():.2f} median {np.median(sharp_ratio):.2f}, "
               f"coverage ratio min {cov_ratio.min():.2f} median {np.median(cov_ratio):.2f}")
    print(summary)
    assert sharp_ratio.min() >= SHARPNESS_RATIO_MIN, summary
    assert cov_ratio.min() >= COVERAGE_RATIO_MIN, summary


# ---- scenes made of Gaussians on box faces -------------------------------------------------------


def _box_surface(lo, hi, spacing_m: float, rng: np.random.Generator) -> np.ndarray:
    """``[N, 3]`` points on the six faces of the box ``[lo, hi]``, ``spacing_m`` apart."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    faces = []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        A, B = np.meshgrid(np.arange(lo[a], hi[a] + 1e-9, spacing_m), np.arange(lo[b], hi[b] + 1e-9, spacing_m),
                           indexing="ij")
        for v in (lo[axis], hi[axis]):
            p = np.empty((A.size, 3))
            p[:, a], p[:, b], p[:, axis] = A.ravel(), B.ravel(), v
            faces.append(p)
    p = np.concatenate(faces)
    return p + rng.normal(0.0, 0.05 * spacing_m, p.shape)


def _field(points: np.ndarray, sigma_m: float, rng: np.random.Generator) -> GaussianField:
    """Opaque isotropic Gaussians with a textured colour (renders need edges to be sharp)."""
    n = len(points)
    c = (127 + 60 * np.sin(7 * points[:, :1] + 3 * points[:, 1:2]) + 40 * np.sin(11 * points[:, 2:3] + np.arange(3))
         + rng.normal(0, 20, (n, 3)))
    rot = np.zeros((n, 4))
    rot[:, 3] = 1.0
    return GaussianField(points, np.full((n, 3), sigma_m), rot, np.clip(c, 0, 255).astype(np.uint8),
                         np.full(n, 0.9), np.arange(n, dtype=np.uint64))


ROOM_MIN, ROOM_MAX = np.array([-2.5, -2.0, 0.0]), np.array([2.5, 2.0, 2.5])
VOXEL_M = 0.05


@pytest.fixture(scope="module")
def box_room():
    """A 5 x 4 x 2.5 m room with a 0.6 m box in the middle, and keyframes circling the box at
    1.4 m height looking at it (from all around: ``T_world_cam`` ``[18, 4, 4]``)."""
    rng = np.random.default_rng(0)
    pts = np.concatenate([_box_surface(ROOM_MIN, ROOM_MAX, 0.05, rng),
                          _box_surface([-0.3, -0.3, 0.0], [0.3, 0.3, 0.8], 0.03, rng)])
    a = np.radians(np.arange(0, 360, 20))
    eyes = np.stack([1.5 * np.cos(a), 1.2 * np.sin(a), np.full_like(a, 1.4)], axis=1)
    kf = np.stack([look_at(e, [0.0, 0.0, 0.5], [0.0, 0.0, 1.0]) for e in eyes])
    return _field(pts, 0.03, rng), kf


def _inside_room(eyes: np.ndarray, margin_m: float) -> np.ndarray:
    return np.all((eyes > ROOM_MIN + margin_m) & (eyes < ROOM_MAX - margin_m), axis=1)


# ---- (b) the box room: the old centre orbit leaves it, the new one does not ----------------------


def test_old_centre_orbit_leaves_the_box_room_the_new_one_stays_inside(box_room):
    field, kf = box_room
    cfg = load_profile("default").with_overrides({"video.orbit_frames": N_FRAMES, "mapping.voxel_size_m": VOXEL_M})
    # The old path: around the map centre at 1.2 x its half extent, i.e. through the walls.
    p5, p95 = np.percentile(field.positions, [5, 95], axis=0)
    radius = cfg.video.orbit_radius_scale * max(float(np.linalg.norm((p95 - p5)[:2])) / 2.0, 0.5)
    from atlas_pipeline.viz.video import orbit_poses

    old = orbit_poses(0.5 * (p5 + p95), radius, cfg.video.orbit_height_m, N_FRAMES)
    assert not _inside_room(old[:, :3, 3], 0.0).all()

    poses = orbit_trajectory(field, cfg, kf)
    path = plan_camera_path(field, kf, N_FRAMES, VOXEL_M)
    assert np.allclose(poses, path.T_world_cam)
    assert path.kind == PATH_ORBIT, path.summary()
    eyes = path.T_world_cam[:, :3, 3]
    assert _inside_room(eyes, CLEARANCE_MIN_M).all()
    assert np.all(np.max(np.abs(eyes[:, :2]), axis=1) > 0.3 + CLEARANCE_MIN_M)  # not in the middle box
    # Looking at the box, upright: the optical axis through the target, the camera's up along z.
    to_target = path.target_world - eyes
    to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
    assert np.all(np.einsum("fi,fi->f", to_target, path.T_world_cam[:, :3, 2]) > 0.999)
    assert np.linalg.norm(path.target_world[:2]) < 0.3 and 0.0 < path.target_world[2] < 1.0
    assert np.all(np.abs(path.T_world_cam[:, 2, 0]) < 1e-6) and np.all(-path.T_world_cam[:, 2, 1] > 0.5)
    # At the keyframes' distance and height.
    assert abs(path.radius_m - np.median(np.linalg.norm(kf[:, :2, 3] - path.target_world[:2], axis=1))) < 0.1


def test_keyframes_on_one_side_give_an_arc_inside_the_room(box_room):
    field, kf = box_room
    path = plan_camera_path(field, kf[:5], N_FRAMES, VOXEL_M)  # 80 degrees of the circle
    assert path.kind == PATH_ARC, path.summary()
    assert 80.0 <= path.sweep_deg < 360.0
    assert _inside_room(path.T_world_cam[:, :3, 3], CLEARANCE_MIN_M).all()
    # A back-and-forth sweep: the video loops without a jump.
    steps = np.linalg.norm(np.diff(path.T_world_cam[:, :3, 3], axis=0, append=path.T_world_cam[:1, :3, 3]), axis=1)
    assert steps.max() < 3.0 * np.median(steps) + 1e-6


def test_up_vector_follows_the_keyframes_not_the_world_axes(box_room):
    """TUM worlds have an arbitrary gravity direction: rotate room and keyframes together, and the
    path turns with them."""
    from atlas_pipeline.geometry import so3_exp

    field, kf = box_room
    R = so3_exp(np.array([0.7, -0.4, 1.1]))
    rotated = GaussianField(field.positions @ R.T, field.scales, field.rotations_xyzw, field.colors,
                            field.opacities, field.ids)
    kf_r = kf.copy()
    kf_r[:, :3, :] = np.einsum("ij,fjk->fik", R, kf[:, :3, :])
    path = plan_camera_path(rotated, kf_r, N_FRAMES, VOXEL_M)
    assert path.kind == PATH_ORBIT, path.summary()
    assert np.degrees(np.arccos(np.clip(path.up_world @ (R @ [0.0, 0.0, 1.0]), -1, 1))) < 2.0
    eyes_room = path.T_world_cam[:, :3, 3] @ R  # back in the room's frame
    assert _inside_room(eyes_room, CLEARANCE_MIN_M).all()


def test_without_keyframes_the_centre_orbit_is_pulled_inside(box_room):
    field, _ = box_room
    path = plan_camera_path(field, None, N_FRAMES, VOXEL_M, fallback_height_m=0.3)
    assert path.kind == PATH_CENTRE_ORBIT
    assert _inside_room(path.T_world_cam[:, :3, 3], 0.1).all(), path.summary()
    assert path.n_shrunk == N_FRAMES


# ---- (c) a narrow corridor: no orbit fits, the keyframes are flown through -----------------------


@pytest.fixture(scope="module")
def corridor():
    """A 10 m long, 0.9 m wide corridor (x along it) and 8 keyframes walking 2.7 m down it."""
    rng = np.random.default_rng(1)
    field = _field(_box_surface([0.0, -0.45, 0.0], [10.0, 0.45, 2.2], 0.05, rng), 0.03, rng)
    xs = np.linspace(0.8, 3.5, 8)
    kf = np.stack([look_at([x, 0.02 * np.sin(3 * x), 1.4], [x + 5.0, 0.1 * np.cos(2 * x), 1.2], [0.0, 0.0, 1.0])
                   for x in xs])
    return field, kf


def test_corridor_falls_back_to_a_smooth_flythrough(corridor):
    field, kf = corridor
    path = plan_camera_path(field, kf, 60, VOXEL_M)
    assert path.kind == PATH_FLYTHROUGH, path.summary()
    T = path.T_world_cam
    eyes = T[:, :3, 3]
    assert T.shape == (60, 4, 4) and np.isfinite(T).all()
    # Through the keyframes: starts at the first, ends at the last, passes each centre.
    assert np.allclose(eyes[0], kf[0, :3, 3], atol=1e-9) and np.allclose(eyes[-1], kf[-1, :3, 3], atol=1e-9)
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    for c in kf[:, :3, 3]:
        assert np.linalg.norm(eyes - c, axis=1).min() <= 0.5 * steps.max() + 1e-6
    # Smooth: an even pace, no kinks, small turns, each view close to a keyframe's.
    assert steps.max() < 1.5 * np.median(steps)
    accel = np.linalg.norm(eyes[2:] - 2 * eyes[1:-1] + eyes[:-2], axis=1)
    assert accel.max() < 0.25 * np.median(steps)
    turn_deg = np.degrees(rotation_angle_rad(np.einsum("fji,fjk->fik", T[:-1, :3, :3], T[1:, :3, :3])))
    assert turn_deg.max() < 1.0
    axis_err = np.degrees(np.arccos(np.clip(np.einsum("fi,ki->fk", T[:, :3, 2], kf[:, :3, 2]).max(axis=1), -1, 1)))
    assert axis_err.max() < 3.0
    # The recorded cameras were in free space, and so is the path between them.
    assert np.all(np.abs(eyes[:, 1]) < 0.45 - 0.3)


def test_flythrough_poses_edge_cases():
    T = np.stack([look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]), look_at([1.0, 0.0, 0.0], [1.0, 1.0, 0.0])])
    nan = np.full((1, 4, 4), np.nan)
    one = flythrough_poses(np.concatenate([T[:1], nan]), 5)
    assert one.shape == (5, 4, 4) and np.allclose(one, T[0])
    two = flythrough_poses(np.concatenate([T[:1], nan, T[1:]]), 11)
    assert np.allclose(two[0], T[0]) and np.allclose(two[-1], T[1])
    assert np.allclose(np.einsum("fji,fjk->fik", two[:, :3, :3], two[:, :3, :3]), np.eye(3), atol=1e-9)
    with pytest.raises(ValueError):
        flythrough_poses(nan, 3)


def test_orbit_trajectory_without_keyframes_keeps_the_old_call():
    """The callers that pass only the field and the config still get ``video.orbit_frames`` poses."""
    rng = np.random.default_rng(2)
    field = _field(_box_surface(ROOM_MIN, ROOM_MAX, 0.1, rng), 0.05, rng)
    cfg = load_profile("default").with_overrides({"video.orbit_frames": 8})
    poses = orbit_trajectory(field, cfg)
    assert poses.shape == (8, 4, 4) and np.isfinite(poses).all()

"""Tests of the deterministic synthetic RGB-D generator (atlas_pipeline.sensors.synthetic)."""

from __future__ import annotations

import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from atlas_pipeline.errors import ConfigError
from atlas_pipeline.geometry import (
    interpolate_pose,
    invert_se3,
    pose_from_tq,
    rotation_angle_rad,
)
from atlas_pipeline.sensors import synthetic as syn
from atlas_pipeline.sensors.synthetic import (
    SyntheticSpec,
    build_scene,
    camera_path,
    generate_synthetic_dataset,
    render_synthetic_frame,
)


def tiny_spec(**kw) -> SyntheticSpec:
    """80x60 spec with the default field of view (the 640x480 intrinsics scaled by 1/8)."""
    base = dict(n_frames=8, width=80, height=60, fx=525.0 / 8, fy=525.0 / 8, cx=39.5, cy=29.5)
    base.update(kw)
    return SyntheticSpec(**base)


def read_list(path: Path) -> list[tuple[str, str]]:
    rows = []
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        ts, name = line.split()
        rows.append((ts, name))
    return rows


def read_gt(path: Path) -> np.ndarray:
    """``[N, 8]`` rows of timestamp tx ty tz qx qy qz qw."""
    rows = [
        [float(x) for x in line.split()]
        for line in path.read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert all(len(r) == 8 for r in rows)
    return np.array(rows)


def all_files(root: Path) -> dict[str, Path]:
    return {str(p.relative_to(root)): p for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, SyntheticSpec]:
    spec = tiny_spec()
    out = generate_synthetic_dataset(tmp_path_factory.mktemp("syn") / "ds", spec)
    return out, spec


def backproject(depth_m: np.ndarray, spec: SyntheticSpec, T_world_cam: np.ndarray):
    """World points ``[M, 3]`` and pixel coordinates ``(u [M], v [M])`` of valid depth pixels."""
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u]
    pc = np.stack([(u - spec.cx) / spec.fx * z, (v - spec.cy) / spec.fy * z, z], axis=1)
    pw = pc @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return pw, u, v


# ------------------------------------------------------------------------------------------------


def test_determinism_byte_identical(tmp_path):
    spec = tiny_spec()
    a = generate_synthetic_dataset(tmp_path / "a", spec)
    b = generate_synthetic_dataset(tmp_path / "b", spec)
    fa, fb = all_files(a), all_files(b)
    assert list(fa) == list(fb)
    assert len(fa) == 2 * spec.n_frames + 6  # images, 3 lists, spec json, .complete, .atlas-gs.json
    for name in fa:
        assert fa[name].read_bytes() == fb[name].read_bytes(), name


def test_different_seed_gives_different_data(tmp_path):
    a = generate_synthetic_dataset(tmp_path / "a", tiny_spec(n_frames=1))
    b = generate_synthetic_dataset(tmp_path / "b", tiny_spec(n_frames=1, seed=3))
    ra = iio.imread(a / read_list(a / "rgb.txt")[0][1])
    rb = iio.imread(b / read_list(b / "rgb.txt")[0][1])
    assert not np.array_equal(ra, rb)


def test_layout(dataset):
    root, spec = dataset
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = (root / name).read_text().splitlines()
        assert all(line.startswith("#") for line in lines[:3]) and not lines[3].startswith("#")
    assert "timestamp tx ty tz qx qy qz qw" in (root / "groundtruth.txt").read_text()

    rgb = read_list(root / "rgb.txt")
    depth = read_list(root / "depth.txt")
    assert len(rgb) == len(depth) == spec.n_frames
    t_rgb = np.array([float(t) for t, _ in rgb])
    t_depth = np.array([float(t) for t, _ in depth])
    assert t_rgb[0] == pytest.approx(1000.0)
    np.testing.assert_allclose(np.diff(t_rgb), 1.0 / spec.fps, atol=2e-6)
    np.testing.assert_allclose(t_depth - t_rgb, 0.003, atol=2e-6)  # associates within 20 ms
    for (ts, name), folder in [(r, "rgb") for r in rgb] + [(d, "depth") for d in depth]:
        assert len(ts.split(".")[1]) == 6
        assert name == f"{folder}/{ts}.png"
        assert (root / name).is_file()

    img = iio.imread(root / rgb[0][1])
    assert img.shape == (spec.height, spec.width, 3) and img.dtype == np.uint8
    dep = iio.imread(root / depth[0][1])
    assert dep.shape == (spec.height, spec.width) and dep.dtype == np.uint16
    assert dep.max() <= spec.max_depth_m * spec.depth_scale
    assert (dep > 0).mean() > 0.99  # inside a closed room every pixel has a return

    gt = read_gt(root / "groundtruth.txt")
    np.testing.assert_allclose(np.linalg.norm(gt[:, 4:], axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.diff(gt[:, 0]), 1.0 / spec.gt_rate_hz, atol=2e-6)
    assert gt[0, 0] < t_rgb[0] and gt[-1, 0] > t_depth[-1]  # covers the frames plus a margin


def test_files_match_render_at_rgb_timestamp(dataset):
    """Both images of a frame are the render at the rgb timestamp pose, depth quantised."""
    root, spec = dataset
    scene = build_scene(spec.seed)
    rgb_rows, depth_rows = read_list(root / "rgb.txt"), read_list(root / "depth.txt")
    for i in (0, spec.n_frames - 1):
        T = camera_path(spec, np.array([i / spec.fps]))[0]
        rgb, depth_m = render_synthetic_frame(spec, scene, T)
        assert rgb.shape == (spec.height, spec.width, 3) and depth_m.dtype == np.float32
        np.testing.assert_array_equal(iio.imread(root / rgb_rows[i][1]), rgb)
        raw = np.round(depth_m.astype(np.float64) * spec.depth_scale).astype(np.uint16)
        np.testing.assert_array_equal(iio.imread(root / depth_rows[i][1]), raw)


def test_groundtruth_is_the_camera_path(dataset):
    root, spec = dataset
    gt = read_gt(root / "groundtruth.txt")
    T_gt = pose_from_tq(gt[:, 1:4], gt[:, 4:])
    T_path = camera_path(spec, gt[:, 0] - 1000.0)
    np.testing.assert_allclose(T_gt[:, :3, 3], T_path[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(T_gt[:, :3, :3], T_path[:, :3, :3], atol=1e-5)


def test_depth_backprojects_onto_scene_surfaces(dataset):
    root, spec = dataset
    scene = build_scene(spec.seed)
    gt = read_gt(root / "groundtruth.txt")
    for ts, name in read_list(root / "depth.txt")[::3]:
        t_rgb = float(ts) - 0.003  # both images were rendered at the rgb timestamp pose
        depth_m = iio.imread(root / name).astype(np.float64) / spec.depth_scale
        # Pose from the ground-truth file, interpolated like a consumer would.
        k = np.searchsorted(gt[:, 0], t_rgb)
        T0 = pose_from_tq(gt[k - 1, 1:4], gt[k - 1, 4:])
        T1 = pose_from_tq(gt[k, 1:4], gt[k, 4:])
        T = interpolate_pose(gt[k - 1, 0], T0, gt[k, 0], T1, t_rgb)
        pw, _, _ = backproject(depth_m, spec, T)
        dist = np.abs(scene.clearance_m(pw))
        assert np.quantile(dist, 0.99) < 0.005
        # With the exact pose, floor points have world z = 0 within depth quantisation.
        T_exact = camera_path(spec, np.array([t_rgb - 1000.0]))[0]
        pw, _, _ = backproject(depth_m, spec, T_exact)
        # Floor pixels: low points that are not on (the bottom of) an object or a wall.
        wall_d = np.minimum(pw[:, :2] - scene.room_min[:2], scene.room_max[:2] - pw[:, :2])
        near_obj = wall_d.min(axis=1) < 0.01
        for obj in scene.objects:
            near_obj |= syn._object_distance(obj, pw) < 0.01
        floor = (pw[:, 2] < 0.02) & ~near_obj
        assert floor.sum() > 50
        assert np.abs(pw[floor, 2]).max() < 0.001
        assert np.abs(scene.clearance_m(pw)).max() < 0.002


def test_reprojection_between_views_agrees():
    """Depth and colour of frame 0 reprojected into frame 4 match frame 4 (view-independent)."""
    spec = tiny_spec(width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5)
    scene = build_scene(spec.seed)
    T0, T1 = camera_path(spec, np.array([0.0, 4.0 / spec.fps]))
    rgb0, d0 = render_synthetic_frame(spec, scene, T0)
    rgb1, d1 = render_synthetic_frame(spec, scene, T1)
    pw, u0, v0 = backproject(d0, spec, T0)
    pc = pw @ invert_se3(T1)[:3, :3].T + invert_se3(T1)[:3, 3]
    u = np.round(pc[:, 0] / pc[:, 2] * spec.fx + spec.cx).astype(int)
    v = np.round(pc[:, 1] / pc[:, 2] * spec.fy + spec.cy).astype(int)
    inside = (pc[:, 2] > 0.1) & (u >= 0) & (u < spec.width) & (v >= 0) & (v < spec.height)
    assert inside.mean() > 0.6
    z_obs = d1[v[inside], u[inside]]
    err = np.abs(z_obs - pc[inside, 2]) / pc[inside, 2]
    agree = err < 0.01  # 1 %: rounding to the nearest pixel on slanted surfaces, occlusions
    assert agree.mean() > 0.85
    c0 = rgb0[v0[inside], u0[inside]].astype(int)
    c1 = rgb1[v[inside], u[inside]].astype(int)
    diff = np.abs(c0 - c1)[agree].mean(axis=1)
    assert np.median(diff) < 8


def test_texture_has_gradients_and_is_spatially_correlated():
    spec = tiny_spec(width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5)
    scene = build_scene(spec.seed)
    rgb, _ = render_synthetic_frame(spec, scene, camera_path(spec, np.array([0.5]))[0])
    g = rgb.astype(np.float64).mean(axis=2)
    assert g.std() > 15
    gx, gy = np.diff(g, axis=1), np.diff(g, axis=0)
    # Gradients almost everywhere: most 4x4 blocks have a non-trivial gradient somewhere.
    mag = np.abs(gx[:-1, :]) + np.abs(gy[:, :-1])
    blocks = mag[: mag.shape[0] // 4 * 4, : mag.shape[1] // 4 * 4]
    blocks = blocks.reshape(mag.shape[0] // 4, 4, mag.shape[1] // 4, 4).max(axis=(1, 3))
    assert (blocks >= 2).mean() > 0.9
    # Not i.i.d. noise: neighbours strongly correlated, unlike the same pixels shuffled.
    corr = np.corrcoef(g[:, :-1].ravel(), g[:, 1:].ravel())[0, 1]
    assert corr > 0.8
    shuffled = np.random.default_rng(0).permutation(g.ravel()).reshape(g.shape)
    assert abs(np.corrcoef(shuffled[:, :-1].ravel(), shuffled[:, 1:].ravel())[0, 1]) < 0.2


def test_albedo_is_a_function_of_the_surface_point():
    scene = build_scene(0)
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-2, 2, 500), rng.uniform(-2, 2, 500), np.zeros(500)])
    sid = np.zeros(500, dtype=np.int64)
    a = syn._albedo(scene, P, sid)
    b = syn._albedo(scene, P[::-1].copy(), sid)[::-1]
    np.testing.assert_array_equal(a, b)  # per-point: independent of batch and order
    assert a.std(axis=0).min() > 0.03  # the floor is textured, not flat


def test_motion_is_tum_like():
    spec = SyntheticSpec()  # default: 60 frames at 30 fps; only the path is evaluated
    T = camera_path(spec, np.arange(spec.n_frames) / spec.fps)
    assert T.shape == (spec.n_frames, 4, 4)
    rel = np.einsum("nij,njk->nik", invert_se3(T[:-1]), T[1:])
    trans = np.linalg.norm(rel[:, :3, 3], axis=1)
    rot_deg = np.degrees(rotation_angle_rad(rel[:, :3, :3]))
    assert trans.min() > 0.005 and trans.max() < 0.10
    assert rot_deg.max() < 5.0
    fwd = T[:, :3, 2]
    yaw = np.degrees(np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0])))
    assert 60.0 <= yaw.max() - yaw.min() <= 120.0
    # Smooth: the pose at a frame time agrees with its neighbours' midpoint to first order.
    t = np.array([0.5 - 1e-3, 0.5, 0.5 + 1e-3])
    P = camera_path(spec, t)[:, :3, 3]
    assert np.linalg.norm(P[0] + P[2] - 2 * P[1]) < 1e-5


@pytest.mark.parametrize("seed", [0, 1, 2, 5, 11])
def test_camera_stays_clear_of_walls_and_objects(seed):
    spec = SyntheticSpec(seed=seed)
    scene = build_scene(seed)
    assert 4 <= len(scene.objects) <= 6
    kinds = {o.kind for o in scene.objects}
    assert {"box", "sphere"} <= kinds
    t = np.linspace(-1.0, 12.0, 1300)  # longer than one full orbit
    eye = camera_path(spec, t)[:, :3, 3]
    assert scene.clearance_m(eye).min() > 0.5
    # Objects look toward the room centre: the centre is in front of the camera.
    fwd = camera_path(spec, t[::50])[:, :3, 2]
    to_centre = np.array([0.0, 0.0, 0.6]) - camera_path(spec, t[::50])[:, :3, 3]
    assert np.all(np.sum(fwd * to_centre, axis=1) > 0)


def test_max_depth_zeroes_far_returns(tmp_path):
    spec = tiny_spec(n_frames=2, max_depth_m=3.0)
    root = generate_synthetic_dataset(tmp_path / "ds", spec)
    dep = iio.imread(root / read_list(root / "depth.txt")[0][1])
    assert dep.max() <= 3.0 * spec.depth_scale
    assert (dep == 0).any()  # the far walls are beyond 3 m


def test_spec_validation():
    with pytest.raises(ConfigError):
        SyntheticSpec(n_frames=0)
    with pytest.raises(ConfigError):
        SyntheticSpec(max_depth_m=20.0)  # 20 m * 5000 does not fit 16 bits
    with pytest.raises(ConfigError):
        SyntheticSpec(width=0)
    with pytest.raises(ConfigError):
        SyntheticSpec(seed=1.5)
    # YAML-style ints/floats are canonicalised: same spec, same hash.
    assert SyntheticSpec(fx=525, width=640.0) == SyntheticSpec()
    assert syn.spec_hash(SyntheticSpec(fx=525, seed=0.0)) == syn.spec_hash(SyntheticSpec())
    cam = SyntheticSpec().camera()
    assert (cam.width, cam.height, cam.fx, cam.cx) == (640, 480, 525.0, 319.5)
    assert cam.depth_scale == 5000.0 and cam.distortion == ()


def test_caching_and_replacement(tmp_path):
    out = tmp_path / "ds"
    spec = tiny_spec(n_frames=3)
    assert generate_synthetic_dataset(out, spec) == out
    before = {name: p.stat().st_mtime_ns for name, p in all_files(out).items()}
    marker = (out / ".complete").read_text().strip()
    assert marker == syn.spec_hash(spec)

    generate_synthetic_dataset(out, spec)  # complete and same spec: untouched
    assert {name: p.stat().st_mtime_ns for name, p in all_files(out).items()} == before

    other = tiny_spec(n_frames=4, seed=1)
    generate_synthetic_dataset(out, other)  # different spec: replaced
    assert (out / ".complete").read_text().strip() == syn.spec_hash(other)
    assert len(read_list(out / "rgb.txt")) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # no temp folders left


def test_foreign_folder_is_never_replaced(tmp_path):
    """A folder that is not a synthetic dataset (no .complete / marker) may hold a user's files:
    generation refuses it instead of replacing it; an earlier synthetic dataset is regenerated."""
    from atlas_pipeline.errors import OutputPolicyError

    out = tmp_path / "ds"
    (out / "rgb").mkdir(parents=True)
    (out / "rgb.txt").write_text("# someone's list\n")
    (out / "junk.bin").write_bytes(b"x")
    spec = tiny_spec(n_frames=2)
    with pytest.raises(OutputPolicyError, match="not written by atlas-gs"):
        generate_synthetic_dataset(out, spec)
    assert (out / "junk.bin").read_bytes() == b"x"
    other = tmp_path / "syn"
    generate_synthetic_dataset(other, tiny_spec(n_frames=3))
    generate_synthetic_dataset(other, spec)  # a different spec replaces our own dataset
    assert len(read_list(other / "rgb.txt")) == 2
    assert (other / ".complete").read_text().strip() == syn.spec_hash(spec)


def test_crash_leaves_no_partial_dataset(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = syn.render_synthetic_frame

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated crash")
        return real(*args, **kwargs)

    monkeypatch.setattr(syn, "render_synthetic_frame", flaky)
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="simulated crash"):
        generate_synthetic_dataset(out, tiny_spec(n_frames=5))
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []

    # An existing complete dataset survives a failed regeneration for another spec.
    monkeypatch.setattr(syn, "render_synthetic_frame", real)
    good = tiny_spec(n_frames=2)
    generate_synthetic_dataset(out, good)
    calls["n"] = 0
    monkeypatch.setattr(syn, "render_synthetic_frame", flaky)
    with pytest.raises(RuntimeError):
        generate_synthetic_dataset(out, tiny_spec(n_frames=5, seed=9))
    assert (out / ".complete").read_text().strip() == syn.spec_hash(good)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    assert os.listdir(out / "rgb")


def test_object_culling_does_not_change_the_image(monkeypatch):
    """Per-object screen rectangles are only an optimisation: identical output without them."""
    spec = tiny_spec(width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5)
    scene = build_scene(2)
    poses = camera_path(spec, np.array([0.0, 0.7, 1.9, 4.0]))
    fast = [render_synthetic_frame(spec, scene, T) for T in poses]
    monkeypatch.setattr(
        syn, "_screen_rect", lambda obj, R, o, spec: (slice(0, spec.height), slice(0, spec.width))
    )
    for T, (rgb, depth) in zip(poses, fast):
        rgb_ref, depth_ref = render_synthetic_frame(spec, scene, T)
        np.testing.assert_array_equal(rgb, rgb_ref)
        np.testing.assert_array_equal(depth, depth_ref)

"""Tests of the deterministic synthetic RGB-D generator (atlas_pipeline.sensors.synthetic)."""

from __future__ import annotations

import dataclasses
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
from atlas_pipeline.sensors import synthetic_colour as syn_colour
from atlas_pipeline.sensors import synthetic_kinect as syn_kinect
from atlas_pipeline.sensors import synthetic_path as syn_path
from atlas_pipeline.sensors import synthetic_raytrace as syn_raytrace
from atlas_pipeline.sensors import synthetic_scene as syn_scene
from atlas_pipeline.sensors import synthetic_spec as syn_spec
from atlas_pipeline.sensors import synthetic_textures as syn_textures
from atlas_pipeline.sensors import synthetic_writer as syn_writer
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
    assert t_depth[0] == pytest.approx(1000.0)
    np.testing.assert_allclose(np.diff(t_depth), 1.0 / spec.fps, atol=2e-6)
    np.testing.assert_array_equal(t_rgb, t_depth)  # taken together (colour_delay_s: 0)
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
    assert gt[0, 0] < t_depth[0] and gt[-1, 0] > t_rgb[-1]  # covers the frames plus a margin


def test_files_match_render_at_depth_timestamp(dataset):
    """Both images of a frame are the render at the depth timestamp pose (the frame time), depth
    quantised."""
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
        t_frame = float(ts)  # both images were rendered at the depth timestamp pose
        depth_m = iio.imread(root / name).astype(np.float64) / spec.depth_scale
        # Pose from the ground-truth file, interpolated like a consumer would.
        k = np.searchsorted(gt[:, 0], t_frame)
        T0 = pose_from_tq(gt[k - 1, 1:4], gt[k - 1, 4:])
        T1 = pose_from_tq(gt[k, 1:4], gt[k, 4:])
        T = interpolate_pose(gt[k - 1, 0], T0, gt[k, 0], T1, t_frame)
        pw, _, _ = backproject(depth_m, spec, T)
        dist = np.abs(scene.clearance_m(pw))
        assert np.quantile(dist, 0.99) < 0.005
        # With the exact pose, floor points have world z = 0 within depth quantisation.
        T_exact = camera_path(spec, np.array([t_frame - 1000.0]))[0]
        pw, _, _ = backproject(depth_m, spec, T_exact)
        # Floor pixels: low points that are not on (the bottom of) an object or a wall.
        wall_d = np.minimum(pw[:, :2] - scene.room_min[:2], scene.room_max[:2] - pw[:, :2])
        near_obj = wall_d.min(axis=1) < 0.01
        for obj in scene.objects:
            near_obj |= syn_scene._object_distance(obj, pw) < 0.01
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
    a = syn_textures._albedo(scene, P, sid)
    b = syn_textures._albedo(scene, P[::-1].copy(), sid)[::-1]
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

    monkeypatch.setattr(syn_writer, "render_synthetic_frame", flaky)
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="simulated crash"):
        generate_synthetic_dataset(out, tiny_spec(n_frames=5))
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []

    # An existing complete dataset survives a failed regeneration for another spec.
    monkeypatch.setattr(syn_writer, "render_synthetic_frame", real)
    good = tiny_spec(n_frames=2)
    generate_synthetic_dataset(out, good)
    calls["n"] = 0
    monkeypatch.setattr(syn_writer, "render_synthetic_frame", flaky)
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
        syn_raytrace, "_screen_rect", lambda obj, R, o, spec: (slice(0, spec.height), slice(0, spec.width))
    )
    for T, (rgb, depth) in zip(poses, fast):
        rgb_ref, depth_ref = render_synthetic_frame(spec, scene, T)
        np.testing.assert_array_equal(rgb, rgb_ref)
        np.testing.assert_array_equal(depth, depth_ref)


# ------------------------------------------------------------------------------------------------
# Realistic sensor model and hand-held / loop motion

# Content of the tiny default dataset (decoded pixels, lists, spec json, .complete): the default
# output must not change by accident. Version 1 (before the sensor model): 3caf139e..., spec hash
# 6cfa9911...; version 3 stamps depth with the render time, as colour, not 3 ms after it (file
# names, lists, generator version), the pixels are the same (test_files_match_render_at_depth_timestamp).
GOLDEN_TINY_DEFAULT_DIGEST = "fab4b4670003ff0c75f0d1b6a1e19880b1f5c68e843e0417f4ded7d02a6fc537"
GOLDEN_DEFAULT_SPEC_HASH = "3e9ed9d5c287909e381b50d92a95e44e3bff0e5e9d94ecaef49cc4dd9b1d7a55"


def content_digest(root: Path) -> str:
    """sha256 over the file names and contents, PNGs by their decoded pixels (independent of the
    zlib build); the output-policy marker ``.atlas-gs.json`` is left out."""
    import hashlib

    h = hashlib.sha256()
    for name, p in all_files(root).items():
        if name == ".atlas-gs.json":
            continue
        h.update(name.encode() + b"\0")
        if p.suffix == ".png":
            a = iio.imread(p)
            h.update(str((a.shape, a.dtype.str)).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        else:
            h.update(p.read_bytes())
    return h.hexdigest()


def test_default_output_is_unchanged(dataset):
    root, spec = dataset
    assert spec == tiny_spec() and not spec.sensor_model and not spec.custom_motion
    assert content_digest(root) == GOLDEN_TINY_DEFAULT_DIGEST
    assert syn.spec_hash(SyntheticSpec()) == GOLDEN_DEFAULT_SPEC_HASH
    info = (root / "synthetic_spec.json").read_text()
    assert "noise" not in info and "loop" not in info  # optional fields at default are left out


def tiny_preset(name: str, **kw) -> SyntheticSpec:
    """A preset of the registry at 80x60 (same field of view), few frames."""
    params = {k: v for k, v in syn.SYNTHETIC_PRESETS[name].items()
              if k not in ("n_frames", "width", "height", "fx", "fy", "cx", "cy")}
    return tiny_spec(**{"n_frames": 6, **params, **kw})


@pytest.mark.parametrize("name", sorted(syn.SYNTHETIC_PRESETS))
def test_preset_determinism_byte_identical(tmp_path, name):
    spec = tiny_preset(name)
    a = generate_synthetic_dataset(tmp_path / "a", spec)
    b = generate_synthetic_dataset(tmp_path / "b", spec)
    fa, fb = all_files(a), all_files(b)
    assert list(fa) == list(fb) and len(fa) == 2 * spec.n_frames + 6
    for n in fa:
        assert fa[n].read_bytes() == fb[n].read_bytes(), n
    clean = generate_synthetic_dataset(tmp_path / "clean", tiny_spec(n_frames=spec.n_frames))
    name0 = read_list(a / "rgb.txt")[0][1]
    assert not np.array_equal(iio.imread(a / name0), iio.imread(clean / read_list(clean / "rgb.txt")[0][1]))
    assert (a / ".complete").read_text().strip() == syn.spec_hash(spec) != syn.spec_hash(tiny_spec(n_frames=6))


def test_every_new_field_changes_the_hash():
    base = SyntheticSpec()
    h0 = syn.spec_hash(base)
    new_fields = [n for n in syn_spec._FIELD_DEFAULTS if n not in syn_spec._V1_FIELDS]
    assert len(new_fields) >= 20
    hashes = set()
    for n in new_fields:
        d = syn_spec._FIELD_DEFAULTS[n]
        special = {"loop_revolutions": 2, "motion_blur_samples": 3, "orbit_rate_deg_per_s": 20.0,
                   "pan_rate_deg_per_s": 60.0, "place": "suite"}
        v = special[n] if n in special else (d + 0.01 if isinstance(d, float) else d + 1)
        s = SyntheticSpec(**{n: v})
        assert syn_spec._spec_dict(s)[n] == v
        hashes.add(syn.spec_hash(s))
    assert h0 not in hashes and len(hashes) == len(new_fields)
    # YAML-style ints are canonicalised for the new fields too.
    assert syn.spec_hash(SyntheticSpec(shake_m=0, loop_revolutions=0.0)) == h0


def test_new_field_validation():
    with pytest.raises(ConfigError):
        SyntheticSpec(depth_noise_a_m=-0.001)
    with pytest.raises(ConfigError):
        SyntheticSpec(dropped_frame_rate=0.6)
    with pytest.raises(ConfigError):
        SyntheticSpec(loop_revolutions=1.5)
    with pytest.raises(ConfigError):
        SyntheticSpec(pan_rate_deg_per_s=30.0)  # slower than the 36 deg/s orbit: cannot pan back
    with pytest.raises(ConfigError):
        SyntheticSpec(shiny_dropout_deg=90.0)
    assert SyntheticSpec(rgb_shift_y_px=-1).rgb_shift_y_px == -1.0  # shifts may be negative


def test_registry_presets_match_the_python_presets():
    from atlas_pipeline.sensors.registry import load_registry

    reg = load_registry([Path(__file__).resolve().parents[1] / "configs" / "datasets.yaml"])
    assert next(iter(reg)) == "synthetic" and SyntheticSpec(**reg["synthetic"].params) == SyntheticSpec()
    for name, kw in syn.SYNTHETIC_PRESETS.items():
        assert reg[name].kind == "synthetic"
        assert SyntheticSpec(**reg[name].params) == SyntheticSpec(**kw), name
    loop = SyntheticSpec(**syn.SYNTHETIC_PRESETS["synthetic-loop"])
    assert (loop.n_frames, loop.width, loop.height) == (300, 320, 240)


@pytest.mark.parametrize("z_m", [1.0, 3.0])
def test_depth_noise_matches_the_kinect_model(z_m):
    """A fronto-parallel plane: written depth (noise + disparity + depth-scale quantisation) has
    the std of Nguyen et al.'s model within 30 %, no bias, and few distinct levels at range."""
    spec = SyntheticSpec(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5, **syn.KINECT_V1_SENSOR)
    shape = (240, 320)
    depth = np.full(shape, z_m, dtype=np.float32)
    out = syn.apply_depth_sensor_model(spec, depth, np.ones(shape), np.full(shape, 0.5), np.zeros(shape, bool), 3)
    written = np.round(out * spec.depth_scale) / spec.depth_scale
    v = written[written > 0]
    assert v.size == depth.size  # a bright plane seen head-on has no holes
    model = float(syn.depth_noise_sigma_m(spec, np.array(z_m)))
    assert model == pytest.approx(0.0012 + 0.0019 * (z_m - 0.4) ** 2)  # 1.9 mm at 1 m, 14 mm at 3 m
    assert abs(v.std() / model - 1.0) < 0.3
    assert abs(v.mean() - z_m) < 0.1 * model  # unbiased
    # Disparity quantisation: steps of q z^2 (2.9 mm at 1 m, 2.6 cm at 3 m).
    steps = np.diff(np.unique(v))
    assert np.median(steps) == pytest.approx(spec.inverse_depth_step_per_m * z_m * z_m, rel=0.1)
    # Block matching: neighbouring pixels share most of their error (an i.i.d. model does not).
    err = written - z_m
    assert np.corrcoef(err[:, :-1].ravel(), err[:, 1:].ravel())[0, 1] > 0.3
    white = dataclasses.replace(spec, depth_noise_corr_px=0.0)
    e2 = syn.apply_depth_sensor_model(white, depth, np.ones(shape), np.full(shape, 0.5), np.zeros(shape, bool), 3) - z_m
    assert abs(np.corrcoef(e2[:, :-1].ravel(), e2[:, 1:].ravel())[0, 1]) < 0.1
    assert abs(e2.std() / model - 1.0) < 0.3
    # Another frame index: other noise; the same one: the same noise.
    again = syn.apply_depth_sensor_model(spec, depth, np.ones(shape), np.full(shape, 0.5), np.zeros(shape, bool), 3)
    other = syn.apply_depth_sensor_model(spec, depth, np.ones(shape), np.full(shape, 0.5), np.zeros(shape, bool), 4)
    np.testing.assert_array_equal(out, again)
    assert not np.array_equal(out, other)


def test_depth_noise_grows_with_incidence_angle():
    spec = SyntheticSpec(**syn.KINECT_V1_SENSOR)
    c = np.cos(np.radians([0.0, 30.0, 60.0, 75.0]))
    s = syn.depth_noise_sigma_m(spec, np.full(4, 2.0), c)
    assert np.all(np.diff(s) > 0)
    theta = np.radians(60.0)
    expect = 0.0012 + 0.0019 * 1.6 ** 2 + 0.0001 / np.sqrt(2.0) * theta ** 2 / (np.pi / 2 - theta) ** 2
    assert s[2] == pytest.approx(expect, rel=1e-3)  # polynomial arccos: < 1e-4 rad error


def _sensor_and_clean(spec: SyntheticSpec, t: float = 0.5, index: int = 0):
    scene = build_scene(spec.seed)
    T = camera_path(spec, np.array([t]))[0]
    lay = syn_raytrace._render_layers(spec, scene, T)
    rgb, depth = syn_colour._sensor_frame(spec, scene, t, index)
    return lay, rgb, depth, scene, T


def test_missing_depth_at_edges_shadows_shiny_and_dark():
    spec = tiny_spec(width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5,
                     **syn.KINECT_V1_SENSOR)
    lay, _, depth, _, _ = _sensor_and_clean(spec, t=0.0)
    clean = lay.depth_m
    assert (clean > 0).all()
    edge = syn_kinect._depth_edges(clean)
    assert edge.any()
    missing = depth == 0
    assert missing[edge].mean() > 0.3  # occlusion boundaries lose many readings
    far_from_edges = ~syn_kinect._dilate(syn_kinect._dilate(edge))
    assert missing[far_from_edges].mean() < missing[edge].mean() / 3
    # Projector shadows: a band left of the foreground, on the background.
    shadow = syn_kinect._projector_shadow(clean, spec.fx, spec.projector_baseline_m)
    assert shadow.any() and missing[shadow].all()
    v, u = np.nonzero(shadow)
    right = np.clip(u + 3, 0, spec.width - 1)
    assert np.median(clean[v, right] - clean[v, u]) < 0  # nearer surface on the right of a shadow
    # Shiny spheres seen head-on and dark surfaces have no reading.
    head_on = lay.shiny & (lay.cos_incidence > np.cos(np.radians(spec.shiny_dropout_deg)))
    head_on &= ~syn_kinect._dilate(edge)  # edge pixels may read a jittered neighbour instead
    assert head_on.any() and missing[head_on].all()
    shape = clean.shape
    dark = syn.apply_depth_sensor_model(spec, clean, np.ones(shape), np.zeros(shape), np.zeros(shape, bool))
    assert (dark == 0).all()
    # An ideal sensor reads everything.
    ideal = syn.apply_depth_sensor_model(tiny_spec(), clean, lay.cos_incidence, np.zeros(shape), lay.shiny)
    np.testing.assert_array_equal(ideal, clean.astype(np.float64))


def test_colour_shift_blur_drift_and_noise():
    base = dict(width=160, height=120, fx=525.0 / 4, fy=525.0 / 4, cx=79.5, cy=59.5)
    scene = build_scene(0)
    T = camera_path(tiny_spec(**base), np.array([0.5]))[0]
    clean, _ = render_synthetic_frame(tiny_spec(**base), scene, T)
    # Misregistration: colour moves by (dx, dy) against depth; integer shifts are exact.
    rgb, _ = syn_colour._sensor_frame(tiny_spec(**base, rgb_shift_x_px=2.0, rgb_shift_y_px=-1.0), scene, 0.5, 0)
    np.testing.assert_array_equal(rgb[:-1, 2:], clean[1:, :-2])
    # Motion blur: the mean of sub-frame renders; smoother, same mean brightness.
    rgb, _ = syn_colour._sensor_frame(tiny_spec(**base, motion_blur_samples=5, exposure_time_s=0.03), scene, 0.5, 0)
    assert abs(rgb.mean() - clean.mean()) < 1.0
    grad = lambda im: np.abs(np.diff(im.astype(float).mean(axis=2), axis=1)).mean()  # noqa: E731
    assert grad(rgb) < 0.95 * grad(clean)
    # Sensor noise: ~2 levels of std.
    rgb, _ = syn_colour._sensor_frame(tiny_spec(**base, rgb_noise_std=2.0), scene, 0.5, 0)
    diff = rgb.astype(float) - clean
    interior = (clean > 5) & (clean < 250)
    assert diff[interior].std() == pytest.approx(2.0, rel=0.2)
    # Exposure and white balance drift over time: the gain changes, red and blue differently.
    spec = tiny_spec(**base, exposure_drift=0.15, white_balance_drift=0.05)
    gains = np.array([syn_colour._colour_gain(spec, t, 0.45) for t in np.linspace(0.0, 10.0, 41)])
    assert np.ptp(gains[:, 1]) > 0.1 and np.ptp(gains[:, 0] / gains[:, 1]) > 0.03
    assert np.ptp(gains[:, 2] / gains[:, 1]) > 0.03


def test_dropped_frames_leave_timestamp_gaps(tmp_path):
    spec = SyntheticSpec(**syn.SYNTHETIC_PRESETS["synthetic-loop"])
    t = syn.frame_times_s(spec)
    slots = np.round(np.diff(t) * spec.fps).astype(int)
    np.testing.assert_allclose(np.diff(t) * spec.fps, slots, atol=1e-9)  # still on the sensor clock
    assert t[0] == 0.0 and slots.min() == 1 and slots.max() <= 1 + syn_path._MAX_DROP_BURST
    assert 0.005 < (slots > 1).mean() < 0.1
    # The files carry the gaps; the first frames of a longer sequence are the same frames.
    tiny = tiny_spec(n_frames=12, dropped_frame_rate=0.3)
    root = generate_synthetic_dataset(tmp_path / "ds", tiny)
    ts = np.array([float(x) for x, _ in read_list(root / "depth.txt")])  # the frame times
    np.testing.assert_allclose(ts - 1000.0, syn.frame_times_s(tiny), atol=2e-6)
    assert np.diff(ts).max() > 1.5 / tiny.fps
    np.testing.assert_array_equal(syn.frame_times_s(tiny_spec(n_frames=20, dropped_frame_rate=0.3))[:12],
                                  syn.frame_times_s(tiny))


def _angular_rate_deg_s(spec: SyntheticSpec, t: np.ndarray) -> np.ndarray:
    T = camera_path(spec, t)
    rel = np.einsum("nij,njk->nik", invert_se3(T[:-1]), T[1:])
    return np.degrees(rotation_angle_rad(rel[:, :3, :3])) / np.diff(t)


def test_handheld_path_pans_at_60_deg_per_s_and_shakes():
    spec = SyntheticSpec(**syn.SYNTHETIC_PRESETS["synthetic-handheld"])
    dt = 0.005
    t = np.arange(0.0, syn.frame_times_s(spec)[-1], dt)
    w = _angular_rate_deg_s(spec, t)
    assert 55.0 <= w.max() <= 80.0  # pans at 60 deg/s (+ shake and wobble)
    run = longest = 0
    for fast in w > 50.0:
        run = run + 1 if fast else 0
        longest = max(longest, run)
    assert longest * dt >= 0.5  # sustained, not a spike
    # Frame to frame: ~2 deg and ~1.4 cm per frame where no frame was dropped.
    tf = syn.frame_times_s(spec)
    T = camera_path(spec, tf)
    rel = np.einsum("nij,njk->nik", invert_se3(T[:-1]), T[1:])
    single = np.isclose(np.diff(tf) * spec.fps, 1.0)
    rot = np.degrees(rotation_angle_rad(rel[single, :3, :3]))
    assert 1.7 < rot.max() < 2.7
    assert np.median(np.linalg.norm(rel[single, :3, 3], axis=1)) < 0.025
    # The shake: a few mm at 5-10 Hz on top of the smooth path.
    calm = SyntheticSpec(**{**syn.SYNTHETIC_PRESETS["synthetic-handheld"], "shake_m": 0.0, "shake_deg": 0.0})
    d = camera_path(spec, t)[:, :3, 3] - camera_path(calm, t)[:, :3, 3]
    assert 0.002 < np.abs(d).max() <= spec.shake_m + 1e-9
    spectrum = np.abs(np.fft.rfft(d[:, 0]))
    freq = np.fft.rfftfreq(d.shape[0], dt)
    assert 4.5 <= freq[np.argmax(spectrum)] <= 10.5
    assert scene_clearance_ok(spec, t)


def scene_clearance_ok(spec: SyntheticSpec, t: np.ndarray) -> bool:
    return bool(build_scene(spec.seed).clearance_m(camera_path(spec, t)[:, :3, 3]).min() > 0.5)


def test_loop_returns_to_its_start():
    spec = SyntheticSpec(**syn.SYNTHETIC_PRESETS["synthetic-loop"])
    tf = syn.frame_times_s(spec)
    T = camera_path(spec, tf)
    gap = np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3])
    assert 0.0005 < gap < 0.005  # a revisit within 5 mm, not the same pose
    assert np.degrees(rotation_angle_rad(T[-1, :3, :3].T @ T[0, :3, :3])) < 0.5
    fwd = T[:, :3, 2]
    yaw = np.degrees(np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0])))
    assert yaw[-1] - yaw[0] == pytest.approx(360.0, abs=3.0)  # one full turn around the room
    assert np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).sum() > 10.0
    assert scene_clearance_ok(spec, np.linspace(0.0, tf[-1], 600))
    # Two turns close too.
    spec2 = SyntheticSpec(n_frames=200, loop_revolutions=2)
    T2 = camera_path(spec2, syn.frame_times_s(spec2)[[0, -1]])
    assert np.linalg.norm(T2[1, :3, 3] - T2[0, :3, 3]) < 0.005


def test_default_motion_is_untouched_by_the_motion_code():
    """The generalised path with default parameters is the same orbit (to rounding), so presets
    that only change the sensor share the default path exactly (same code)."""
    spec = SyntheticSpec()
    t = np.linspace(0.0, 2.0, 25)
    m = syn_path._motion_of(spec)
    ph = syn_path._path_phases(spec.seed)
    general = np.array([syn_path._pose_at_motion(float(x), ph, m) for x in t])
    np.testing.assert_allclose(general, camera_path(spec, t), atol=1e-9)
    noisy = SyntheticSpec(**syn.SYNTHETIC_PRESETS["synthetic-noisy"])
    assert not noisy.custom_motion and noisy.sensor_model
    np.testing.assert_array_equal(camera_path(noisy, t), camera_path(spec, t))

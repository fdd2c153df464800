"""Spherical harmonics (view-dependent colour) end to end: the basis against the 3DGS constants,
the compiled stage against its NumPy reference, the renderer on analytic single-Gaussian cases and
against the reference renderer, degree 0 unchanged bit for bit, and exact round trips through
the 3DGS PLY (written by plyfile in the reference's layout), ATLASGS2 and bundles."""

from __future__ import annotations

import hashlib
import logging
import struct

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.geometry import look_at
from atlas_pipeline.gaussian_world import raster
from atlas_pipeline.gaussian_world._raster_reference import view_colors_reference as stage_reference
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize, sh_rest_count
from atlas_pipeline.gaussian_world.render import (
    render_field, render_field_reference, render_gaussians, render_gaussians_reference,
)
from atlas_pipeline.gaussian_world.sh import (
    COLOR_LEVELS, SH_C0, SH_C1, SH_C3, sh_basis_reference, view_colors, view_colors_reference,
)
from atlas_pipeline.scene_memory.binary import (
    atlasgs2_bytes_per_gaussian, read_atlasgs2, read_gaussian_binary, write_atlasgs2, write_gaussian_binary,
)
from atlas_pipeline.scene_memory.bundle import bundle_disk_bytes, load_world_bundle, write_world_bundle
from atlas_pipeline.scene_memory.ply import ply_bytes_per_gaussian, read_gaussian_ply, write_gaussian_ply

DEGREES = [1, 2, 3]
K_CAM = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
W, H = 64, 48


def _field(n: int, degree: int, seed: int = 0, sh_scale: float = 0.2) -> GaussianField:
    """A random canonical field of SH degree ``degree`` in front of a camera at the origin."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return canonicalize(GaussianField(
        np.c_[rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n), rng.uniform(1.0, 4.0, n)],
        np.exp(rng.uniform(np.log(0.02), np.log(0.2), (n, 3))), q / np.linalg.norm(q, axis=1, keepdims=True),
        rng.integers(0, 256, (n, 3)), rng.uniform(0.05, 1.0, n), np.arange(n, dtype=np.uint64) * 3 + 1,
        rng.normal(scale=sh_scale, size=(n, sh_rest_count(degree), 3))))


def _one(centre, degree: int, coeffs: dict[int, float], colour=(128, 128, 128), scale=0.3) -> GaussianField:
    """One opaque isotropic Gaussian of SH degree ``degree``: ``coeffs`` {basis index k >= 1: value},
    the same for all three channels."""
    sh = np.zeros((1, sh_rest_count(degree), 3), np.float32)
    for k, v in coeffs.items():
        sh[0, k - 1, :] = v
    return GaussianField(np.array([centre]), np.full((1, 3), scale), np.array([[0, 0, 0, 1.0]]),
                         np.array([colour]), np.array([1.0]), np.array([7], np.uint64), sh)


# ---- the basis and the colour stage ------------------------------------------------------------

def test_basis_is_orthonormal_over_the_sphere():
    """The 3DGS constants are those of the orthonormal real SH: mean of Y_j Y_k over the sphere is
    delta_jk / (4 pi) (Fibonacci-sphere quadrature)."""
    m = 200_000
    i = np.arange(m) + 0.5
    z = 1 - 2 * i / m
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    dirs = np.c_[r * np.cos(phi), r * np.sin(phi), z]
    Y = sh_basis_reference(dirs, 3)  # [m, 16]
    gram = 4 * np.pi * (Y.T @ Y) / m
    np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)
    assert Y[0, 0] == SH_C0


@pytest.mark.parametrize("degree", DEGREES)
def test_compiled_colour_stage_equals_the_reference_bit_for_bit(degree):
    f = _field(2000, degree, seed=degree, sh_scale=0.5)
    pos = f.positions
    centre = pos[0].astype(np.float64)  # a Gaussian at the camera centre: no direction, the degree-0 colour
    got = view_colors(pos, f.colors, f.sh_rest, centre)
    ref = view_colors_reference(pos, f.colors, f.sh_rest, centre)
    assert got.dtype == np.float32 and np.array_equal(got, ref.astype(np.float32))
    assert np.array_equal(got[0], f.colors[0].astype(np.float32))
    assert (got == 0).any() and (got > 255).any()  # clamped at 0 only, as 3DGS
    assert stage_reference is view_colors_reference  # the raster core's reference of the stage


def test_colour_is_3dgs_eval_sh_plus_half_in_colour_levels():
    """c(d) = max(0, 0.5 + C0 f_dc + sum_k Y_k(d) f_k) with the field's uint8 colour = 255 (0.5 + C0 f_dc)."""
    f = _field(300, 3, seed=9, sh_scale=0.3)
    centre = np.array([0.0, 0.5, -1.0])
    d = f.positions.astype(np.float64) - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f_dc = (f.colors / COLOR_LEVELS - 0.5) / SH_C0
    sh = np.concatenate([f_dc[:, None, :], f.sh_rest.astype(np.float64)], axis=1)  # [N, 16, 3]
    eval_sh = np.einsum("nk,nkc->nc", sh_basis_reference(d, 3), sh)
    expect = COLOR_LEVELS * np.maximum(eval_sh + 0.5, 0.0)
    np.testing.assert_allclose(view_colors(f.positions, f.colors, f.sh_rest, centre), expect, atol=1e-3)


# ---- the renderer ------------------------------------------------------------------------------

def _centre_pixel(field: GaussianField, eye, target) -> np.ndarray:
    r = render_field(field, look_at(np.asarray(eye, float), np.asarray(target, float)), K_CAM, W, H)
    return r.rgb[H // 2, W // 2].astype(int)


@pytest.mark.parametrize("eye, sign", [((-2.0, 0.0, 0.0), -1.0), ((2.0, 0.0, 0.0), 1.0)])
def test_degree_1_colour_follows_the_view_direction(eye, sign):
    """Y_3 = -C1 x: seen along +x (camera at -x) the colour drops by 255 C1 a, along -x it rises."""
    a = 0.4
    g = _one((0.0, 0.0, 0.0), 1, {3: a})
    colour = 128 + sign * COLOR_LEVELS * SH_C1 * a  # direction (mean - eye) / |.| = -sign x
    expect = np.floor(raster.ALPHA_MAX * colour + 0.5)  # one Gaussian at its centre: alpha 0.99, black behind
    assert np.all(np.abs(_centre_pixel(g, eye, (0, 0, 0)) - expect) <= 1)
    # a direction the coefficient does not see (y_cam along the up axis): the degree-0 colour
    side = _centre_pixel(g, (0.0, -2.0, 0.0), (0, 0, 0))
    assert np.all(np.abs(side - np.floor(raster.ALPHA_MAX * 128 + 0.5)) <= 1)


def test_degree_3_colour_along_the_axis():
    """Along +z only Y_2, Y_6, Y_12 are non-zero: Y_12 = C3[3] z (2 zz - 3 xx - 3 yy) = 2 C3[3]."""
    a = 0.3
    g = _one((0.0, 0.0, 2.0), 3, {12: a, 5: 0.7, 15: -0.4})  # Y_5 = C2[1] y z, Y_15 ~ x: zero on the axis
    colour = 128 + COLOR_LEVELS * 2 * SH_C3[3] * a
    r = render_field(g, np.eye(4), K_CAM, W, H)
    expect = np.floor(raster.ALPHA_MAX * colour + 0.5)
    assert np.all(np.abs(r.rgb[H // 2, W // 2].astype(int) - expect) <= 1)


@pytest.mark.parametrize("degree", [1, 3])
def test_renderer_matches_the_reference_renderer_with_sh(degree):
    f = _field(400, degree, seed=10 + degree)
    T = look_at(np.array([0.3, -0.2, -0.5]), np.array([0.0, 0.1, 2.5]), up=(0.0, -1.0, 0.0))
    fast = render_field(f, T, K_CAM, W, H, background=(30, 60, 90))
    ref = render_field_reference(f, T, K_CAM, W, H, background=(30, 60, 90))
    assert (ref.alpha > 0.5).mean() > 0.5
    assert np.abs(fast.rgb.astype(int) - ref.rgb.astype(int)).max() <= 2
    np.testing.assert_allclose(fast.alpha, ref.alpha, atol=2e-3)
    # and the SH changed the image: not the degree-0 render
    flat = render_gaussians(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, T, K_CAM, W, H,
                            background=(30, 60, 90))
    assert np.abs(fast.rgb.astype(int) - flat.rgb.astype(int)).max() > 10
    # bounded-memory batching does not change it
    small = render_field(f, T, K_CAM, W, H, background=(30, 60, 90), max_tile_pairs=50)
    assert np.array_equal(small.rgb, fast.rgb) and np.array_equal(small.depth_m, fast.depth_m)


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("rgb", "depth_m", "alpha", "depth_median_m"))


def test_degree_0_renders_bit_identically():
    f0 = _field(400, 1, seed=4)
    f0 = GaussianField(f0.positions, f0.scales, f0.rotations_xyzw, f0.colors, f0.opacities, f0.ids)
    T = look_at(np.array([0.2, 0.1, -0.4]), np.array([0.0, 0.0, 2.5]), up=(0.0, -1.0, 0.0))
    plain = render_gaussians(f0.positions, f0.scales, f0.rotations_xyzw, f0.colors, f0.opacities, T, K_CAM, W, H)
    assert f0.sh_degree == 0 and _same(render_field(f0, T, K_CAM, W, H), plain)
    # zero coefficients of any degree: the degree-0 image, bit for bit, through the SH path
    for degree in DEGREES:
        fz = GaussianField(f0.positions, f0.scales, f0.rotations_xyzw, f0.colors, f0.opacities, f0.ids,
                           np.zeros((len(f0), sh_rest_count(degree), 3)))
        assert _same(render_field(fz, T, K_CAM, W, H), plain)
    ref = render_gaussians_reference(f0.positions, f0.scales, f0.rotations_xyzw, f0.colors, f0.opacities, T,
                                     K_CAM, W, H)
    assert _same(render_field_reference(f0, T, K_CAM, W, H), ref)


# ---- the field ---------------------------------------------------------------------------------

def test_degree_0_map_id_is_unchanged_and_sh_changes_it():
    f = _field(50, 2, seed=1)
    f0 = GaussianField(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, f.ids)
    h = hashlib.sha256()  # the map id as it was computed before fields carried SH
    for name in ("ids", "positions", "scales", "rotations_xyzw", "colors", "opacities"):
        arr = getattr(f0, name)
        h.update(name.encode())
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    assert f0.content_hash() == h.hexdigest()
    assert f.content_hash() != f0.content_hash() and not f.equals(f0)
    assert f.subset(np.arange(10)).sh_rest.shape == (10, 8, 3) and canonicalize(f).equals(f)
    with pytest.raises(ValueError, match="sh_rest has shape"):
        GaussianField(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, f.ids, np.zeros((50, 4, 3)))


# ---- PLY ---------------------------------------------------------------------------------------

def _reference_ply(path, features_rest: np.ndarray, byte_order: str = "<"):
    """A PLY laid out as the reference's ``save_ply``: x y z nx ny nz f_dc_* f_rest_* opacity
    scale_* rot_*, ``f_rest`` = ``features_rest [N, K, 3]`` transposed to channel-major."""
    n, k, _ = features_rest.shape
    rng = np.random.default_rng(3)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{j}" for j in range(3 * k)] \
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    cols = np.concatenate([rng.normal(size=(n, 3)), np.zeros((n, 3)), rng.normal(scale=0.5, size=(n, 3)),
                           features_rest.transpose(0, 2, 1).reshape(n, -1),  # transpose(1, 2).flatten(1)
                           rng.normal(size=(n, 1)), np.log(rng.uniform(0.01, 0.1, (n, 3))), q], axis=1)
    rows = np.empty(n, dtype=[(p, "f4") for p in names])
    for j, p in enumerate(names):
        rows[p] = cols[:, j]
    PlyData([PlyElement.describe(rows, "vertex")], byte_order=byte_order).write(str(path))
    return path


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("degree", [1, 3])
def test_reference_layout_ply_keeps_its_sh_bit_for_bit(tmp_path, degree, byte_order):
    rest = np.random.default_rng(degree).normal(size=(20, sh_rest_count(degree), 3)).astype(np.float32)
    f = read_gaussian_ply(_reference_ply(tmp_path / "ref.ply", rest, byte_order))
    assert f.sh_degree == degree and np.array_equal(f.sh_rest, rest)


@pytest.mark.parametrize("degree", [1, 3])
def test_our_ply_round_trips_sh_in_the_reference_order(tmp_path, degree):
    f = _field(100, degree, seed=degree)
    p = write_gaussian_ply(f, tmp_path / "a.ply")
    k = sh_rest_count(degree)
    v = PlyData.read(str(p))["vertex"]
    names = [q.name for q in v.properties]
    assert names[names.index("f_dc_2") + 1:names.index("opacity")] == [f"f_rest_{j}" for j in range(3 * k)]
    for c in range(3):  # channel-major: all R coefficients, then G, then B
        for j in range(k):
            assert np.array_equal(v[f"f_rest_{c * k + j}"], f.sh_rest[:, j, c])
    g = read_gaussian_ply(p)
    assert g.equals(f)
    assert write_gaussian_ply(g, tmp_path / "b.ply").read_bytes() == p.read_bytes()
    assert p.stat().st_size - len(p.read_bytes().split(b"end_header\n")[0]) - 11 == 100 * ply_bytes_per_gaussian(degree)


def test_degree_0_ply_bytes_are_unchanged(tmp_path):
    f = _field(30, 1, seed=2)
    f0 = GaussianField(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, f.ids)
    data = write_gaussian_ply(f0, tmp_path / "a.ply").read_bytes()
    assert b"f_rest" not in data and len(data) - data.index(b"end_header\n") - 11 == 30 * 79


def _with_rest_names(path, names: list[str]):
    n = 3
    base = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
    tail = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = np.zeros(n, dtype=[(p, "f4") for p in base + names + tail])
    rows["rot_0"] = 1.0
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(path))
    return path


@pytest.mark.parametrize("names, problem", [
    ([f"f_rest_{j}" for j in range(10)], "10 f_rest_* properties: spherical harmonics of degree 1, 2 or 3 have"),
    ([f"f_rest_{j}" for j in range(6)], "6 f_rest_* properties"),
    ([f"f_rest_{j}" for j in range(8)] + ["f_rest_9"], "property 'f_rest_8' is missing"),
    ([f"f_rest_{j}" for j in range(8)] + ["f_rest_x"], "property 'f_rest_x': expected f_rest_<index>"),
])
def test_bad_sh_property_sets_name_the_file_and_property(tmp_path, names, problem):
    p = _with_rest_names(tmp_path / "bad.ply", names)
    with pytest.raises(BundleFormatError) as err:
        read_gaussian_ply(p)
    assert str(err.value).startswith(f"{p}: {problem}")


def test_non_finite_sh_coefficient_is_refused_naming_it(tmp_path):
    rest = np.zeros((4, 3, 3), np.float32)
    rest[2, 1, 2] = np.nan  # channel 2, coefficient 1: f_rest_{2 * 3 + 1}
    with pytest.raises(BundleFormatError, match="property 'f_rest_7' has NaN"):
        read_gaussian_ply(_reference_ply(tmp_path / "nan.ply", rest))


# ---- ATLASGS2 and bundles ----------------------------------------------------------------------

@pytest.mark.parametrize("degree", DEGREES)
def test_atlasgs2_round_trips_sh_bit_for_bit(tmp_path, degree):
    f = _field(64, degree, seed=degree)
    p = write_atlasgs2(f, tmp_path / "g.bin")
    data = p.read_bytes()
    assert struct.unpack("<II", data[8:16]) == (3, degree)
    assert len(data) == 24 + 64 * atlasgs2_bytes_per_gaussian(degree)
    g = read_atlasgs2(p)
    assert g.equals(f) and read_gaussian_binary(p).equals(f)
    bad = bytearray(data)
    bad[-4:] = struct.pack("<f", float("inf"))  # the last SH coefficient
    p.write_bytes(bytes(bad))
    with pytest.raises(BundleFormatError, match="NaN or infinite"):
        read_atlasgs2(p)
    p.write_bytes(data[:-12])
    with pytest.raises(BundleFormatError, match="needs .* bytes"):
        read_atlasgs2(p)
    p.write_bytes(data[:12] + struct.pack("<I", 4) + data[16:])
    with pytest.raises(BundleFormatError, match="SH degree 4"):
        read_atlasgs2(p)


def test_isotropic_field_with_sh_is_not_written_as_atlasgs1(tmp_path):
    f = _field(10, 1)
    iso = GaussianField(f.positions, np.repeat(f.scales[:, :1], 3, axis=1), np.tile([0, 0, 0, 1.0], (10, 1)),
                        f.colors, f.opacities, f.ids, f.sh_rest)
    p = write_gaussian_binary(iso, tmp_path / "g.bin")
    assert p.read_bytes()[:8] == b"ATLASGS2" and read_gaussian_binary(p).equals(iso)


def test_degree_0_atlasgs2_is_version_2_as_before(tmp_path):
    f = _field(16, 1)
    f0 = GaussianField(f.positions, f.scales, f.rotations_xyzw, f.colors, f.opacities, f.ids)
    data = write_atlasgs2(f0, tmp_path / "g.bin").read_bytes()
    assert struct.unpack("<IIQ", data[8:24]) == (2, 0, 16) and len(data) == 24 + 16 * 55
    assert read_atlasgs2(tmp_path / "g.bin").sh_degree == 0


def test_bundle_keeps_sh_in_both_copies(tmp_path):
    f = _field(40, 3, seed=5)
    d = write_world_bundle(tmp_path / "world", f, {"name": "sh"})
    for source in ("bin", "ply"):
        assert load_world_bundle(d, source=source).field.equals(f)
    sizes = bundle_disk_bytes(40, sh_degree=3)
    assert (d / "gaussians.bin").stat().st_size == sizes["gaussians.bin"]
    assert (d / "gaussians.ply").stat().st_size <= sizes["gaussians.ply"]


# ---- the fits keep them ------------------------------------------------------------------------

def test_keyframe_fit_state_carries_sh_unchanged_and_says_so(caplog):
    from atlas_pipeline.gaussian_world.fit_adam import FitState

    f = _field(20, 2, seed=6)
    with caplog.at_level(logging.WARNING):
        st = FitState(f, 1e-4, 1.0)
    assert "SH coefficients of degree 2" in caplog.text and "kept unchanged" in caplog.text
    st.append(np.array([3]), np.array([1000], np.uint64))  # a clone copies its parent's coefficients
    st.take(np.r_[np.arange(5), len(st) - 1])
    out = st.to_field(np.ones(len(st), bool))
    assert out.sh_degree == 2
    assert np.array_equal(out.sh_rest[:5], f.sh_rest[:5]) and np.array_equal(out.sh_rest[5], f.sh_rest[3])


def test_gaussian_world_npz_keeps_sh(tmp_path):
    from atlas_pipeline.gaussian_world.builder import GaussianWorld, VoxelGaussianBuilder

    f = _field(20, 3, seed=8)
    none = VoxelGaussianBuilder(0.05, np.zeros(0, np.uint64), np.zeros(0, np.int64), np.zeros((0, 3)),
                                np.zeros((0, 3)), np.zeros((0, 6)), np.zeros(0, np.int32))
    GaussianWorld(f, none, np.zeros(0, np.int64), np.zeros((0, 4, 4)), "estimated", np.zeros(0, np.int64)).save(tmp_path)
    assert GaussianWorld.load(tmp_path).field.equals(f)

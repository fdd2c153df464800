"""Voxel Gaussian merge (anisotropic), stable ids, and exact PLY / ATLASGS1 / ATLASGS2 round trips."""

import struct

import numpy as np
import pytest

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder, pack_voxel_ids, unpack_voxel_ids
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize
from atlas_pipeline.scene_memory.binary import (
    read_atlasgs1,
    read_atlasgs2,
    read_gaussian_binary,
    write_atlasgs1,
    write_atlasgs2,
    write_gaussian_binary,
)
from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply


def _points(seed=0, n=5000):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, size=(n, 3))
    c = rng.integers(0, 256, size=(n, 3))
    return p, c


def test_voxel_ids_pack_unpack():
    ijk = np.array([[0, 0, 0], [-5, 7, 1 << 19], [-(1 << 20), (1 << 20) - 1, 3]])
    assert np.array_equal(unpack_voxel_ids(pack_voxel_ids(ijk)), ijk)
    with pytest.raises(ValueError):
        pack_voxel_ids(np.array([[1 << 20, 0, 0]]))


def test_voxel_statistics_are_exact_means():
    b = VoxelGaussianBuilder(1.0)
    b.integrate(np.array([[0.1, 0.2, 0.3], [0.5, 0.6, 0.7], [1.5, 0.5, 0.5]]), np.array([[0, 0, 0], [100, 200, 50], [9, 9, 9]]))
    f = b.to_field()
    assert len(f) == 2
    i = int(np.flatnonzero(f.ids == pack_voxel_ids(np.array([[0, 0, 0]])))[0])
    assert np.allclose(f.positions[i], [0.3, 0.4, 0.5]) and f.colors[i].tolist() == [50, 100, 25]
    # Too few points for a shape of their own: a disk of half a voxel, thin along its normal.
    assert np.allclose(f.scales[:, :2], 0.5) and np.allclose(f.scales[:, 2], 0.05)


def test_incremental_merge_equals_one_batch_and_keeps_ids():
    p1, c1 = _points(1)
    p2, c2 = _points(2)
    inc = VoxelGaussianBuilder(0.1)
    inc.integrate(p1, c1)
    ids_first = inc.to_field().ids.copy()
    inc.integrate(p2, c2)
    batch = VoxelGaussianBuilder(0.1)
    batch.integrate(np.concatenate([p1, p2]), np.concatenate([c1, c2]))
    fi, fb = inc.to_field(), batch.to_field()
    assert np.array_equal(fi.ids, fb.ids) and np.array_equal(fi.colors, fb.colors)
    assert np.allclose(fi.positions, fb.positions, atol=1e-6)
    assert np.isin(ids_first, fi.ids).all()  # every earlier Gaussian keeps its id
    assert len(np.unique(fi.ids)) == len(fi)


def test_sorted_merge_of_voxel_sums_matches_a_union_of_both_id_sets():
    """``_add`` merges by search and insertion; the reference unions and re-sorts both id sets.
    New ids before, between and after the old ones; ``last_inserted_at`` rebuilds the new order."""
    rng = np.random.default_rng(5)
    b = VoxelGaussianBuilder(0.1)
    state = {"ids": np.zeros(0, np.uint64), "count": np.zeros(0, np.int64), "sum_xyz": np.zeros((0, 3))}
    for step in range(4):
        uk = np.unique(rng.choice(np.arange(1, 400, dtype=np.uint64), size=60))
        cnt = rng.integers(1, 9, len(uk)).astype(np.int64)
        sxyz = rng.normal(size=(len(uk), 3))
        old_ids = b.ids.copy()
        n_new = b._add(uk, cnt, sxyz, np.zeros((len(uk), 3)), np.zeros((len(uk), 6)), np.ones(len(uk), np.int32),
                       cnt.astype(np.float64))
        # Reference: union of the id sets, old sums scattered, new ones added.
        all_ids, inv = np.unique(np.concatenate([state["ids"], uk]), return_inverse=True)
        ref_count = np.zeros(len(all_ids), np.int64)
        ref_xyz = np.zeros((len(all_ids), 3))
        ref_count[inv[: len(state["ids"])]] = state["count"]
        ref_xyz[inv[: len(state["ids"])]] = state["sum_xyz"]
        ref_count[inv[len(state["ids"]):]] += cnt
        ref_xyz[inv[len(state["ids"]):]] += sxyz
        np.testing.assert_array_equal(b.ids, all_ids)
        np.testing.assert_array_equal(b.count, ref_count)
        np.testing.assert_array_equal(b.sum_xyz, ref_xyz)  # bit for bit: the same additions
        assert n_new == len(all_ids) - len(state["ids"])
        np.testing.assert_array_equal(np.insert(old_ids, b.last_inserted_at, b.ids[~np.isin(b.ids, old_ids)]), b.ids)
        state = {"ids": all_ids, "count": ref_count, "sum_xyz": ref_xyz}


def test_same_input_same_world_bit_for_bit():
    p, c = _points(3)
    a, b = VoxelGaussianBuilder(0.05), VoxelGaussianBuilder(0.05)
    a.integrate(p, c)
    b.integrate(p, c)
    assert a.to_field().equals(b.to_field()) and a.to_field().content_hash() == b.to_field().content_hash()


@pytest.fixture
def field():
    b = VoxelGaussianBuilder(0.02)
    b.integrate(*_points(4, 20000))
    return b.to_field()


@pytest.fixture
def iso_field(field):
    n = len(field)
    return GaussianField(field.positions, np.full((n, 3), 0.01, np.float32), np.tile([0, 0, 0, 1.0], (n, 1)),
                         field.colors, field.opacities, field.ids)


def test_ply_and_binary_roundtrip_bit_for_bit(field, iso_field, tmp_path):
    assert not field.is_isotropic
    ply = read_gaussian_ply(write_gaussian_ply(field, tmp_path / "g.ply"))
    binf = read_gaussian_binary(write_gaussian_binary(field, tmp_path / "g.bin"))
    for f in (ply, binf):
        assert np.array_equal(f.ids, field.ids)
        assert np.array_equal(f.positions, field.positions)
        assert np.array_equal(f.colors, field.colors)
        assert f.equals(field)
    assert (tmp_path / "g.bin").read_bytes()[:8] == b"ATLASGS2"
    assert (tmp_path / "g.bin").stat().st_size == 24 + 55 * len(field)
    # The paper's format still reads and writes isotropic fields, bit for bit.
    v1 = write_gaussian_binary(iso_field, tmp_path / "iso.bin")
    assert v1.read_bytes()[:8] == b"ATLASGS1" and v1.stat().st_size == 16 + 31 * len(iso_field)
    assert read_gaussian_binary(v1).equals(iso_field)


def test_anisotropic_gaussians_are_thin_along_the_surface_normal():
    rng = np.random.default_rng(3)
    # A tilted plane sampled densely, with 1 mm noise along its normal.
    normal = np.array([0.2, -0.3, 0.93])
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    ab = rng.uniform(-0.2, 0.2, (40000, 2))
    pts = ab[:, :1] * u + ab[:, 1:] * w + rng.normal(scale=0.001, size=(40000, 1)) * normal
    b = VoxelGaussianBuilder(0.02)
    b.integrate(pts, np.full((len(pts), 3), 100))
    f = b.to_field()
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    R = quat_xyzw_to_rotmat(f.rotations_xyzw.astype(np.float64))
    dense = b.count >= 20
    z_axis = R[dense, :, 2]
    assert np.median(np.abs(z_axis @ normal)) > 0.99  # local z = the normal
    assert np.median(f.scales[dense, 2]) < 0.003 < np.median(f.scales[dense, 0])  # thin along it
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-5)
    # Same input, same world, bit for bit.
    b2 = VoxelGaussianBuilder(0.02)
    b2.integrate(pts, np.full((len(pts), 3), 100))
    assert b2.to_field().equals(f)


def test_standard_3dgs_ply_with_sh_rest_imports(tmp_path):
    """A file as the reference implementation writes it: normals, DC and 45 f_rest properties."""
    props = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)] \
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    vals = np.zeros((3, len(props)), np.float32)
    vals[:, :3] = [[0, 0, 1], [1, 0, 1], [0, 1, 2]]
    vals[:, props.index("f_dc_0")] = (1.0 - 0.5) / 0.28209479  # red
    vals[:, props.index("opacity")] = 2.0
    vals[:, props.index("scale_0"):props.index("scale_2") + 1] = np.log([0.01, 0.02, 0.001])
    vals[:, props.index("rot_0")] = 1.0
    f = read_gaussian_ply(_ply_with(tmp_path, props, 3, 3, vals))
    assert len(f) == 3 and f.colors[0].tolist() == [255, 128, 128]
    assert np.allclose(f.scales[0], [0.01, 0.02, 0.001], rtol=1e-5) and np.allclose(f.opacities, 1 / (1 + np.exp(-2.0)))


def test_atlasgs2_truncated_wrong_version_or_nan(field, tmp_path):
    p = write_atlasgs2(field, tmp_path / "g2.bin")
    data = p.read_bytes()
    p.write_bytes(data[:-5])
    with pytest.raises(BundleFormatError, match="needs .* bytes"):
        read_atlasgs2(p)
    p.write_bytes(data[:8] + struct.pack("<IIQ", 4, 0, 0))
    with pytest.raises(BundleFormatError, match="version 4 is not supported"):
        read_gaussian_binary(p)
    p.write_bytes(data[:8] + struct.pack("<IIQ", 3, 0, 0))  # version 3 carries SH: degree 1-3
    with pytest.raises(BundleFormatError, match="SH degree 0"):
        read_gaussian_binary(p)
    bad = bytearray(data)
    bad[24:28] = struct.pack("<f", float("nan"))
    p.write_bytes(bytes(bad))
    with pytest.raises(BundleFormatError, match="NaN"):
        read_atlasgs2(p)


def test_canonicalize_is_idempotent_and_tiny():
    rng = np.random.default_rng(5)
    n = 1000
    f = GaussianField(rng.normal(size=(n, 3)), rng.uniform(0.001, 0.1, (n, 3)), np.tile([0, 0, 0, 1.0], (n, 1)),
                      rng.integers(0, 256, (n, 3)), rng.uniform(0.05, 0.99, n), np.arange(n, dtype=np.uint64))
    c = canonicalize(f)
    assert canonicalize(c).equals(c)
    assert np.allclose(c.opacities, f.opacities, rtol=1e-6) and np.allclose(c.scales, f.scales, rtol=1e-6)


def test_ply_header_layout_matches_3dgs(field, tmp_path):
    path = write_gaussian_ply(field, tmp_path / "g.ply")
    header = path.read_bytes()[:2000].split(b"end_header")[0].decode()
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert names[:17] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert "format binary_little_endian 1.0" in header


def _ply_with(tmp_path, props, n_declared, n_rows, values=None):
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n_declared
    header += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    data = np.zeros((n_rows, len(props)), np.float32) if values is None else values
    p = tmp_path / "x.ply"
    p.write_bytes(header.encode() + data.tobytes())
    return p


ALL = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
       "rot_0", "rot_1", "rot_2", "rot_3"]


def test_ply_missing_property_refused(tmp_path):
    with pytest.raises(BundleFormatError, match="missing Gaussian properties: opacity"):
        read_gaussian_ply(_ply_with(tmp_path, [p for p in ALL if p != "opacity"], 3, 3))


def test_ply_nan_refused(tmp_path):
    vals = np.ones((3, len(ALL)), np.float32)
    vals[1, 0] = np.nan
    with pytest.raises(BundleFormatError, match="'x' has NaN"):
        read_gaussian_ply(_ply_with(tmp_path, ALL, 3, 3, vals))


def test_ply_overflowing_log_scale_refused(tmp_path):
    vals = np.ones((3, len(ALL)), np.float32)
    vals[2, ALL.index("scale_1")] = 500.0  # exp(500) is no float32
    with pytest.raises(BundleFormatError, match="vertex 2: log scale too large"):
        read_gaussian_ply(_ply_with(tmp_path, ALL, 3, 3, vals))


def test_ply_count_larger_than_data_refused_before_allocating(tmp_path):
    with pytest.raises(BundleFormatError, match="declares 1000000000000 vertices"):
        read_gaussian_ply(_ply_with(tmp_path, ALL, 10**12, 2))


def test_foreign_ply_without_ids_gets_ids(tmp_path):
    vals = np.zeros((2, len(ALL)), np.float32)
    vals[:, ALL.index("rot_0")] = 1.0
    f = read_gaussian_ply(_ply_with(tmp_path, ALL, 2, 2, vals))
    assert f.ids.tolist() == [0, 1] and np.allclose(f.colors, 128, atol=1)


def test_atlasgs1_truncated_or_wrong_magic(iso_field, tmp_path):
    p = write_atlasgs1(iso_field, tmp_path / "g.bin")
    data = p.read_bytes()
    p.write_bytes(data[:-5])
    with pytest.raises(BundleFormatError, match="needs .* bytes"):
        read_atlasgs1(p)
    p.write_bytes(b"NOTATLAS" + struct.pack("<Q", 0))
    with pytest.raises(BundleFormatError, match="not an ATLASGS1 file"):
        read_atlasgs1(p)


def test_atlasgs1_refuses_anisotropic(field, tmp_path):
    s = field.scales.copy()
    s[:, 2] *= 0.1
    aniso = GaussianField(field.positions, s, field.rotations_xyzw, field.colors, field.opacities, field.ids)
    with pytest.raises(ValueError, match="anisotropic"):
        write_atlasgs1(aniso, tmp_path / "a.bin")

"""World bundles: the section 8.3 layout, reload bit for bit, atomic replacement."""

import json

import numpy as np
import pytest

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
from atlas_pipeline.scene_memory.bundle import load_world_bundle, update_world_bundle, write_world_bundle


@pytest.fixture
def field():
    rng = np.random.default_rng(0)
    b = VoxelGaussianBuilder(0.02)
    b.integrate(rng.uniform(-1, 1, (20000, 3)), rng.integers(0, 256, (20000, 3)))
    return b.to_field()


def test_bundle_layout_and_exact_reload(field, tmp_path):
    d = write_world_bundle(tmp_path / "world", field, {"name": "t", "partition": "t"})
    names = {p.name for p in d.iterdir()}
    assert {"metadata.json", "gaussians.ply", "gaussians.bin"} <= names
    meta = json.loads((d / "metadata.json").read_text())
    assert meta["n_gaussians"] == len(field) and meta["map_id"] == field.content_hash()[:16]
    for source in ("bin", "ply"):
        f = load_world_bundle(d, source).field
        assert np.array_equal(f.ids, field.ids) and np.array_equal(f.positions, field.positions)
        assert np.array_equal(f.colors, field.colors) and f.equals(field)


def test_edited_file_detected_by_checksum(field, tmp_path):
    d = write_world_bundle(tmp_path / "world", field, {})
    data = bytearray((d / "gaussians.bin").read_bytes())
    data[100] ^= 0xFF
    (d / "gaussians.bin").write_bytes(bytes(data))
    with pytest.raises(BundleFormatError, match="checksum does not match"):
        load_world_bundle(d, "bin")


def test_failed_rewrite_keeps_the_old_bundle(field, tmp_path, monkeypatch):
    d = write_world_bundle(tmp_path / "world", field, {"name": "old"})
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    import atlas_pipeline.scene_memory.bundle as B

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(B, "write_gaussian_binary", boom)
    with pytest.raises(RuntimeError):
        write_world_bundle(d, field, {"name": "new"})
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folder left


def test_not_a_bundle(tmp_path):
    with pytest.raises(BundleFormatError, match="metadata.json missing"):
        load_world_bundle(tmp_path)
    with pytest.raises(BundleFormatError):
        update_world_bundle(tmp_path)


def test_tracking_map_travels_with_the_bundle(tmp_path):
    """The surfels the tracker uses are saved beside the Gaussians and reloaded exactly; a bundle
    without them (an imported PLY) still gets a map from its Gaussian centres."""
    from atlas_pipeline.localization.tracker import SurfelModel

    rng = np.random.default_rng(1)
    b = VoxelGaussianBuilder(0.02)
    # a noisy plane: surfels need a neighbourhood to get a normal
    xy = rng.uniform(-0.5, 0.5, (40000, 2))
    b.integrate(np.c_[xy, 0.002 * rng.normal(size=len(xy))], rng.integers(0, 256, (len(xy), 3)))
    model = SurfelModel.from_builder(b)
    d = write_world_bundle(tmp_path / "w", b.to_field(), {}, surfels=model)
    loaded = load_world_bundle(d).tracking_model()
    assert np.allclose(loaded.centres, model.centres, atol=1e-6) and loaded.radius_m == model.radius_m
    assert np.allclose(loaded.normals, model.normals, atol=1e-6)
    # what relocalization checks a pose's appearance against: the Gaussians' colours, the same
    # from the bundle as from the world in memory
    from atlas_pipeline.localization.tracker import VoxelAppearance

    expected = VoxelAppearance.from_field(b.to_field(), 0.02)
    got = load_world_bundle(d).tracking_model(0.02).appearance()
    assert len(expected.ids) > 1000 and np.array_equal(got.ids, expected.ids)
    assert np.array_equal(got.grey, expected.grey)
    d2 = write_world_bundle(tmp_path / "w2", b.to_field(), {"gaussians": {"voxel_size_m": 0.02}})
    derived = load_world_bundle(d2).tracking_model()
    assert len(derived) > 0.9 * len(model) and np.abs(derived.normals[:, 2]).min() > 0.9
    # a tampered map is refused, naming the file
    (d / "surfels.npz").write_bytes(b"junk")
    with pytest.raises(BundleFormatError, match="surfels.npz.*(checksum|metadata.json records)"):
        load_world_bundle(d).tracking_model()


def test_malformed_surfel_file_is_refused(tmp_path):
    from atlas_pipeline.localization.tracker import SurfelModel

    p = tmp_path / "surfels.npz"
    np.savez(p, centres=np.zeros((4, 3)), normals=np.zeros((5, 3)), radius_m=0.016)
    with pytest.raises(BundleFormatError, match="must both be"):
        SurfelModel.load(p)
    np.savez(p, centres=np.full((4, 3), np.nan), normals=np.zeros((4, 3)), radius_m=0.016)
    with pytest.raises(BundleFormatError, match="non-finite"):
        SurfelModel.load(p)
    p.write_bytes(b"not a zip")
    with pytest.raises(BundleFormatError, match="not a surfel map"):
        SurfelModel.load(p)


def test_ply_normals_are_the_shortest_axis(tmp_path):
    """nx ny nz carry each flat Gaussian's normal (point-cloud viewers shade with it); the
    Gaussians still reload bit for bit."""
    from atlas_pipeline.scene_memory import ply as P

    rng = np.random.default_rng(2)
    b = VoxelGaussianBuilder(0.02)
    xz = rng.uniform(-0.5, 0.5, (40000, 2))  # a plane y = 0: normals +-y
    b.integrate(np.c_[xz[:, 0], 0.002 * rng.normal(size=len(xz)), xz[:, 1]], rng.integers(0, 256, (len(xz), 3)))
    f = b.to_field()
    path = P.write_gaussian_ply(f, tmp_path / "g.ply")
    assert P.read_gaussian_ply(path).equals(f)
    raw = path.read_bytes()
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n"):]
    dt = [(p, "<f4") for p in P._FLOAT_PROPS] + [("red", "u1"), ("green", "u1"), ("blue", "u1"),
                                                 ("id_hi", "<u4"), ("id_lo", "<u4")]
    v = np.frombuffer(body, dtype=dt)
    n = np.c_[v["nx"], v["ny"], v["nz"]]
    set_ = np.linalg.norm(n, axis=1) > 0
    assert set_.mean() > 0.9 and np.allclose(np.linalg.norm(n[set_], axis=1), 1, atol=1e-5)
    assert np.median(np.abs(n[set_, 1])) > 0.99

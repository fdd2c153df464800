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

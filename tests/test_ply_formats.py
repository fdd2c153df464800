"""Gaussian PLYs of every format and property type, written by plyfile (the 3DGS reference's own
library), read by ``read_gaussian_ply``; and what it refuses, naming the file and the header line."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement, PlyListProperty

from atlas_pipeline.errors import BundleFormatError
from atlas_pipeline.gaussian_world.field import GaussianField, canonicalize
from atlas_pipeline.scene_memory.ply import SH_C0, read_gaussian_ply, write_gaussian_ply

N = 7
FORMATS = {"ascii": dict(text=True), "binary_little_endian": dict(byte_order="<"),
           "binary_big_endian": dict(byte_order=">")}


def _values(n: int = N) -> dict[str, np.ndarray]:
    """3DGS values of ``n`` Gaussians: ``[n]`` float64 per property (exactly representable as
    float32, so every type below holds them alike)."""
    rng = np.random.default_rng(4)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    vals = {"x": rng.uniform(-2, 2, n), "y": rng.uniform(-2, 2, n), "z": rng.uniform(0, 3, n),
            "opacity": rng.uniform(-3, 3, n), **{f"rot_{k}": q[:, k] for k in range(4)},
            **{f"scale_{k}": np.log(rng.uniform(0.005, 0.05, n)) for k in range(3)},
            **{f"f_dc_{k}": rng.uniform(-1.5, 1.5, n) for k in range(3)}}
    return {k: v.astype(np.float32).astype(np.float64) for k, v in vals.items()}


def _write(path, fmt: str, types: dict[str, str], extra: list[tuple[str, str]] = (), rgb: bool = False,
           before: PlyElement | None = None, after: PlyElement | None = None):
    """A PLY written by plyfile in ``fmt``; ``types``: numpy type per 3DGS property (default f4)."""
    vals = _values()
    props = [(p, types.get(p, "f4")) for p in vals] + list(extra)
    if rgb:
        props += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.zeros(N, dtype=props)
    for p, v in vals.items():
        rows[p] = v
    for name, t in extra:
        rows[name] = np.arange(N)
    if rgb:
        rows["red"], rows["green"], rows["blue"] = 10, 20, 30
    elements = [e for e in (before, PlyElement.describe(rows, "vertex"), after) if e is not None]
    PlyData(elements, **FORMATS[fmt]).write(str(path))
    return vals


def _assert_field(f: GaussianField, vals: dict[str, np.ndarray]) -> None:
    assert len(f) == N
    assert np.array_equal(f.positions, np.stack([vals["x"], vals["y"], vals["z"]], 1).astype(np.float32))
    assert np.allclose(f.scales, np.exp(np.stack([vals[f"scale_{k}"] for k in range(3)], 1)), rtol=1e-6)
    q_xyzw = np.stack([vals["rot_1"], vals["rot_2"], vals["rot_3"], vals["rot_0"]], 1)
    assert np.array_equal(f.rotations_xyzw, q_xyzw.astype(np.float32))
    assert np.allclose(f.opacities, 1 / (1 + np.exp(-vals["opacity"])), atol=1e-6)
    assert f.ids.tolist() == list(range(N))  # a foreign file without ids


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_reads_the_same_gaussians(tmp_path, fmt):
    vals = _write(tmp_path / "g.ply", fmt, {})
    f = read_gaussian_ply(tmp_path / "g.ply")
    _assert_field(f, vals)
    dc = np.stack([vals[f"f_dc_{k}"] for k in range(3)], 1)
    assert np.array_equal(f.colors, np.clip(np.rint((dc * SH_C0 + 0.5) * 255), 0, 255).astype(np.uint8))


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_any_property_types(tmp_path, fmt):
    # doubles for positions and rotations, half a rotation in float32, uchar colours, integer extras
    types = {"x": "f8", "y": "f8", "z": "f8", "rot_0": "f8", "rot_1": "f8", "opacity": "f8"}
    extra = [("label", "i2"), ("segment", "u2"), ("flag", "i1"), ("big", "i4")]
    vals = _write(tmp_path / "g.ply", fmt, types, extra, rgb=True)
    f = read_gaussian_ply(tmp_path / "g.ply")
    _assert_field(f, vals)
    assert (f.colors == [10, 20, 30]).all()  # uchar red green blue are the colours


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_other_elements_and_list_properties_are_read_past(tmp_path, fmt):
    faces = np.zeros(2, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32), np.array([2, 3, 4, 5], np.int32)]
    cams = np.zeros(1, dtype=[("fx", "f4"), ("fy", "f4")])
    vals = _write(tmp_path / "g.ply", fmt, {}, before=PlyElement.describe(cams, "camera"),
                  after=PlyElement.describe(faces, "face"))
    _assert_field(read_gaussian_ply(tmp_path / "g.ply"), vals)
    assert isinstance(PlyData.read(str(tmp_path / "g.ply"))["face"].properties[0], PlyListProperty)


def test_our_own_ply_reads_back_bit_for_bit_through_plyfile(tmp_path):
    rng = np.random.default_rng(1)
    n = 300
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    field = canonicalize(GaussianField(rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                          rng.uniform(0.001, 0.05, (n, 3)).astype(np.float32), q,
                          rng.integers(0, 256, (n, 3)).astype(np.uint8), rng.uniform(0.05, 1, n).astype(np.float32),
                          np.arange(n, dtype=np.uint64) * np.uint64(2**33 + 5)))
    path = write_gaussian_ply(field, tmp_path / "g.ply")
    assert read_gaussian_ply(path).equals(field)
    # plyfile sees our layout as the 3DGS one: every property, binary little endian
    ply = PlyData.read(str(path))
    assert ply.byte_order == "<" and not ply.text and len(ply["vertex"].data) == n
    # and re-written by plyfile as ASCII or big endian, it is the same world
    for kw in (dict(text=True), dict(byte_order=">")):
        PlyData([PlyElement.describe(ply["vertex"].data, "vertex")], **kw).write(str(tmp_path / "re.ply"))
        assert read_gaussian_ply(tmp_path / "re.ply").equals(field)


def test_unknown_format_and_list_gaussian_property_name_the_line(tmp_path):
    p = tmp_path / "g.ply"
    props = "".join(f"property float {q}\n" for q in _values())
    p.write_bytes(b"ply\nformat binary_middle_endian 1.0\nelement vertex 1\n" + props.encode() + b"end_header\n")
    with pytest.raises(BundleFormatError, match="g.ply: header line 2: unknown PLY format 'binary_middle_endian'"):
        read_gaussian_ply(p)
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\n"
                  + props.replace("property float x\n", "").encode() + b"end_header\n1 0.5 " + b"0 " * 13 + b"\n")
    with pytest.raises(BundleFormatError, match="must be scalars, not lists: x"):
        read_gaussian_ply(p)
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list float float xs\n" + props.encode()
                  + b"end_header\n")
    with pytest.raises(BundleFormatError, match="header line 4: list length type 'float' is not an integer type"):
        read_gaussian_ply(p)


def test_ascii_counts_beyond_the_file_are_refused_before_allocating(tmp_path):
    p = tmp_path / "g.ply"
    props = "".join(f"property float {q}\n" for q in _values())
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1000000000000\n" + props.encode() + b"end_header\n"
                  + b"0 " * 14 + b"\n")
    with pytest.raises(BundleFormatError, match="declares 1000000000000 vertices"):
        read_gaussian_ply(p)
    # a face count beyond the file (after valid vertices) is refused the same way
    _write(p, "binary_little_endian", {})
    data = p.read_bytes().replace(b"end_header\n", b"element face 99999999\nproperty list uchar int vertex_indices\n"
                                                    b"end_header\n", 1)
    p.write_bytes(data)
    with pytest.raises(BundleFormatError, match="declares 7 vertex, 99999999 face"):
        read_gaussian_ply(p)


def test_garbage_in_the_ascii_data_is_a_format_error_naming_the_file(tmp_path):
    p = tmp_path / "g.ply"
    props = "".join(f"property float {q}\n" for q in _values())
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\n" + props.encode() + b"end_header\n"
                  + b"0 " * 14 + b"\n" + b"zero " * 14 + b"\n")
    with pytest.raises(BundleFormatError, match="g.ply: cannot parse the PLY data"):
        read_gaussian_ply(p)

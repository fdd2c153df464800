"""Property-based fuzzing of every file reader: never destroy, launder or mislabel data.

Each reader gets random bytes and, mostly, *mutations of valid files* written by the project
itself: bit flips, byte overwrites, truncations, insertions, integers overwritten at the offsets
that hold counts and sizes, tokens of text headers replaced (huge counts, NaN, wrong types),
lines duplicated / swapped / dropped, and for ``.npz`` archives npy members edited and re-zipped
with valid CRCs so the checks behind the CRC are reached. Two properties hold for every input:

* the reader returns or raises an :class:`AtlasError` subclass -- anything else (``KeyError``,
  ``struct.error``, ``MemoryError`` ...) fails the test with the input that caused it;
* the reader's peak traced memory (``tracemalloc``, numpy's buffers included) stays below
  ``max(64 MiB, 64 x input bytes)``: sizes claimed by a header are checked before allocating.

Tiers: the default run makes ``QUICK_EXAMPLES`` cases per reader (the file runs in well under a
minute); ``-m slow`` runs ``SLOW_EXAMPLES`` per reader, over 10,000 cases in all. Both are
derandomized, so CI sees the same cases each run. ``benchmarks/fuzz_readers.py`` uses the same
targets and strategies and prints a table.
"""

from __future__ import annotations

import io
import os
import re
import shutil
import struct
import tracemalloc
import traceback
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from atlas_pipeline.errors import AtlasError, BundleFormatError, DatasetError  # noqa: E402

# ---- limits and sizes ---------------------------------------------------------------------------

MEMORY_FLOOR_BYTES = 64 << 20  # any reader may use this much whatever its input
MEMORY_PER_INPUT_BYTE = 64  # ... and up to this many times the bytes it was given
QUICK_EXAMPLES = 50  # per reader, quick tier: a smoke test; the thorough tier (CI) looks further
SLOW_EXAMPLES = 800  # per reader with -m slow: 18 readers -> 14,400 cases
MAX_RANDOM_BYTES = 4096  # random (non-mutated) inputs
MAX_OPS = 4  # mutations applied to one valid file

FUZZ_SETTINGS = dict(deadline=None, derandomize=True, database=None, print_blob=False,
                     suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                            HealthCheck.large_base_example, HealthCheck.filter_too_much])

# Integers written over counts / sizes / offsets (little endian, in 1, 2, 4 and 8 bytes).
INTERESTING_INTS = [0, 1, 2, 3, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF,
                    10**9, 10**12, 2**63 - 1, 2**63, 2**64 - 1]
# Tokens written over words of text formats (headers, JSON, YAML, list files).
INTERESTING_TOKENS = [
    b"0", b"-1", b"1", b"2", b"nan", b"NaN", b"inf", b"-inf", b"Infinity", b"1e309", b"-1e309", b"1e-320",
    b"1000000000000", b"18446744073709551615", b"18446744073709551616", b"9" * 30, b"9" * 5000, b"1.5",
    b"0x10", b"1_0", b"true", b"false", b"null", b"[]", b"{}", b"[1, 2]", b"{\"a\": 1}", b"\"\"", b"''",
    b"'|O'", b"'<U8'", b"'>f8'", b"'<f2'", b"'|V8'", b"'<M8[s]'", b"[('a', '<f4')]", b"(1000000000000, 3)",
    b"(-1,)", b"()", b"(3, 3, 3, 3)", b"True", b"list", b"double", b"uchar", b"char", b"vertex", b"face",
    b"element", b"property", b"end_header", b"\xff\xfe", b"\x00", b"\xc3\x28", b"~", b"- a", b": :", b"&a", b"*a",
    b"!!python/object/apply:os.system", b"!!binary", b"x" * 300, b"a/../../b", b"/etc/passwd", b"~nosuchuser/x",
    b"#", b",", b"\t", b"[" * 3000, b"{\"a\": " * 3000,
]


# ---- mutation strategies ------------------------------------------------------------------------


@dataclass
class FuzzFile:
    """One file a reader opens that the fuzzer may replace.

    Attributes:
        name: path relative to the target's folder.
        seeds: valid contents written by the project (the mutation starting points).
        kind: ``binary`` (integer overwrites at ``hot``), ``text`` (token and line edits),
            ``ply`` (text header + binary body) or ``npz`` (member edits re-zipped, plus raw edits).
        hot: offsets of counts / sizes / versions in the seed (``binary``).
        magic: prefixes for random inputs, so they get past the first check.
    """

    name: str
    seeds: list[bytes]
    kind: str
    hot: Callable[[bytes], list[int]] = lambda data: []
    magic: list[bytes] = field(default_factory=lambda: [b""])


def _zip_hot_offsets(data: bytes) -> list[int]:
    """Offsets of the size / offset / method fields of every zip record (and zip64 extras)."""
    hot = []
    for m in re.finditer(rb"PK\x01\x02", data):  # central directory: method, sizes, local offset
        hot += [m.start() + k for k in (10, 20, 24, 28, 42)]
    for m in re.finditer(rb"PK\x03\x04", data):  # local header: method, sizes, name/extra lengths
        hot += [m.start() + k for k in (8, 18, 22, 26, 28)]
    for m in re.finditer(rb"PK\x05\x06", data):  # end of central directory: counts, size, offset
        hot += [m.start() + k for k in (8, 10, 12, 16)]
    for m in re.finditer(rb"\x01\x00[\x08\x10\x18\x1c]\x00", data):  # zip64 extra: sizes, offset
        hot += [m.start() + k for k in (4, 12, 20)]
    for m in re.finditer(rb"\x93NUMPY", data):  # npy version and header length
        hot += [m.start() + 6, m.start() + 8]
    return [h for h in hot if h < len(data)]


@st.composite
def _byte_ops(draw, data: bytes, hot: list[int]) -> bytes:
    """1..MAX_OPS raw byte mutations of ``data``."""
    buf = bytearray(data)
    for _ in range(draw(st.integers(1, MAX_OPS))):
        op = draw(st.sampled_from(["flip", "set", "truncate", "delete", "insert", "int", "int", "duplicate"]))
        n = len(buf)
        pos = draw(st.integers(0, max(n - 1, 0)))
        if op == "flip" and n:
            buf[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and n:
            buf[pos] = draw(st.sampled_from([0x00, 0x01, 0x7F, 0x80, 0xFF, 0x20, 0x0A, 0x2D]) | st.integers(0, 255))
        elif op == "truncate":
            del buf[pos:]
        elif op == "delete":
            del buf[pos: pos + draw(st.integers(1, 64))]
        elif op == "insert":
            buf[pos:pos] = draw(st.binary(min_size=1, max_size=32) | st.sampled_from(INTERESTING_TOKENS))
        elif op == "int":
            at = draw(st.sampled_from(hot)) if hot and draw(st.booleans()) else pos
            width = draw(st.sampled_from([1, 2, 4, 8]))
            value = draw(st.sampled_from(INTERESTING_INTS) | st.integers(0, 2**64 - 1)) % (1 << (8 * width))
            buf[at: at + width] = value.to_bytes(width, "little")
        elif op == "duplicate" and n:
            chunk = bytes(buf[pos: pos + draw(st.integers(1, 256))])
            at = draw(st.integers(0, n))
            buf[at:at] = chunk
    return bytes(buf)


@st.composite
def _text_ops(draw, data: bytes, region_end: int | None = None) -> bytes:
    """1..MAX_OPS edits of the text in ``data[:region_end]``: tokens replaced, lines duplicated,
    swapped, dropped or made huge; the rest of ``data`` is kept."""
    end = len(data) if region_end is None else region_end
    text, rest = data[:end], data[end:]
    for _ in range(draw(st.integers(1, MAX_OPS))):
        lines = text.split(b"\n")
        op = draw(st.sampled_from(["token", "token", "token", "dup-line", "swap-lines", "drop-line", "huge-line",
                                   "swap-tokens"]))
        i = draw(st.integers(0, max(len(lines) - 1, 0)))
        if op == "token":
            words = list(re.finditer(rb"[^\s,:{}\[\]()'\"]+", text))
            if words:
                w = draw(st.sampled_from(words))
                new = draw(st.sampled_from(INTERESTING_TOKENS) | st.binary(max_size=12))
                text = text[: w.start()] + new + text[w.end():]
        elif op == "swap-tokens":
            words = list(re.finditer(rb"[^\s,:{}\[\]()'\"]+", text))
            if len(words) > 1:
                a, b = sorted(draw(st.lists(st.sampled_from(words), min_size=2, max_size=2, unique_by=lambda m: m.start())),
                              key=lambda m: m.start())
                text = text[: a.start()] + b.group() + text[a.end(): b.start()] + a.group() + text[b.end():]
        elif op == "dup-line":
            lines.insert(draw(st.integers(0, len(lines))), lines[i])
            text = b"\n".join(lines)
        elif op == "swap-lines" and len(lines) > 1:
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
            text = b"\n".join(lines)
        elif op == "drop-line":
            del lines[i]
            text = b"\n".join(lines)
        elif op == "huge-line":
            lines.insert(i, draw(st.sampled_from([b"9" * 100_000, b"x" * 10_000, b"\xff" * 5000, b"1 " * 20_000])))
            text = b"\n".join(lines)
    return text + rest


def _ply_header_end(data: bytes) -> int:
    end = data.find(b"end_header\n")
    return len(data) if end < 0 else end + len(b"end_header\n")


def _npy_header_end(npy: bytes) -> int:
    end = npy.find(b"\n")
    return len(npy) if end < 0 else end + 1


def _rezip(members: list[tuple[str, bytes]], compression: int) -> bytes:
    out = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about the duplicate names we make on purpose
        with zipfile.ZipFile(out, "w", compression) as zf:
            for name, data in members:
                zf.writestr(name, data)
    return out.getvalue()


def _npz_members(data: bytes) -> list[tuple[str, bytes]]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return [(i.filename, zf.read(i)) for i in zf.infolist()]


@st.composite
def _npz_member_ops(draw, seed: bytes) -> bytes:
    """Edit the npy members of a valid archive (headers' tokens, data bytes, names, which members
    exist) and zip them again with valid CRCs, stored or deflated; sometimes edit the zip too."""
    members = _npz_members(seed)
    for _ in range(draw(st.integers(1, MAX_OPS))):
        k = draw(st.integers(0, len(members) - 1)) if members else 0
        op = draw(st.sampled_from(["header", "header", "header", "data", "drop", "rename", "duplicate", "foreign"]))
        if not members:
            break
        name, npy = members[k]
        if op == "header":
            npy = draw(_text_ops(npy, _npy_header_end(npy)))
        elif op == "data":
            npy = npy[: _npy_header_end(npy)] + draw(_byte_ops(npy[_npy_header_end(npy):], []))
        elif op == "drop":
            del members[k]
            continue
        elif op == "rename":
            name = draw(st.sampled_from(["x.npy", "centres", "../evil.npy", "/abs.npy", "a" * 300 + ".npy", " .npy"]))
        elif op == "duplicate":
            members.append((name, npy))
        elif op == "foreign":
            members.append((draw(st.sampled_from(["readme.txt", "pickle.npy"])),
                            draw(st.sampled_from([b"hello", b"\x80\x04\x95" + b"\x00" * 20, b""]))))
        members[k] = (name, npy)
    data = _rezip(members, draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED])))
    if draw(st.integers(0, 3)) == 0:
        data = draw(_byte_ops(data, _zip_hot_offsets(data)))
    return data


@st.composite
def fuzz_input(draw, f: FuzzFile) -> bytes:
    """Random bytes (behind a plausible magic) or a mutation of one of ``f.seeds``."""
    mode = draw(st.sampled_from(["random", "mutate", "mutate", "mutate", "mutate", "structure", "structure",
                                 "structure"]))
    if mode == "random":
        return draw(st.sampled_from(f.magic)) + draw(st.binary(max_size=MAX_RANDOM_BYTES))
    seed = draw(st.sampled_from(f.seeds))
    if mode == "mutate":
        hot = _zip_hot_offsets(seed) if f.kind == "npz" else f.hot(seed)
        return draw(_byte_ops(seed, hot))
    if f.kind == "npz":
        return draw(_npz_member_ops(seed))
    if f.kind == "ply":
        return draw(_text_ops(seed, _ply_header_end(seed)))
    if f.kind == "text":
        return draw(_text_ops(seed))
    return draw(_byte_ops(seed, f.hot(seed)))  # binary: one more round of raw edits


# ---- targets: a reader, the files it opens, valid seeds ----------------------------------------


@dataclass
class FuzzTarget:
    """A reader under fuzzing.

    Attributes:
        name: table / test id.
        folder: where its files live.
        files: the files that may be fuzzed (one per case); listed twice = drawn twice as often.
        call: runs the reader on ``folder``.
    """

    name: str
    folder: Path
    files: list[FuzzFile]
    call: Callable[[], object]

    def write(self, fuzz_name: str, data: bytes) -> int:
        """Write ``data`` as ``fuzz_name`` and every other file as its first seed; return the bytes
        the reader can see in all (the base of its memory allowance)."""
        total = 0
        for f in self.files:
            if f.name == fuzz_name:
                continue
            (self.folder / f.name).write_bytes(f.seeds[0])
        (self.folder / fuzz_name).write_bytes(data)
        for p in self.folder.rglob("*"):
            if p.is_file():
                total += p.stat().st_size
        return total


@dataclass
class Outcome:
    """One case: ``project_error`` / ``accepted`` / ``other``, the peak traced bytes, the bytes of
    input, and for ``other`` the exception with its traceback."""

    kind: str
    peak_bytes: int
    input_bytes: int
    error: str = ""


def memory_allowance(input_bytes: int) -> int:
    return max(MEMORY_FLOOR_BYTES, MEMORY_PER_INPUT_BYTE * input_bytes)


def run_case(target: FuzzTarget, fuzz_name: str, data: bytes) -> Outcome:
    """Write the input, run the reader under tracemalloc, classify the outcome.

    Tracing runs only around the reader (tracing Hypothesis' own generation would triple the
    run time), so the peak is the reader's alone.
    """
    input_bytes = target.write(fuzz_name, data)
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    kind, err = "accepted", ""
    try:
        target.call()
    except AtlasError:
        kind = "project_error"
    except Exception as exc:  # noqa: BLE001 - the property under test: nothing else may escape
        kind, err = "other", f"{type(exc).__module__}.{type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    finally:
        peak = tracemalloc.get_traced_memory()[1] - base
        if not was_tracing:
            tracemalloc.stop()
    return Outcome(kind, peak, input_bytes, err)


def _png(img: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", img, extension=".png")


def _small_field(n_points: int = 400, seed: int = 0):
    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder

    rng = np.random.default_rng(seed)
    b = VoxelGaussianBuilder(0.25)
    b.integrate(rng.uniform(-0.5, 0.5, (n_points, 3)), rng.integers(0, 256, (n_points, 3)))
    return b


def _seed_npz(**arrays) -> bytes:
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def _seed_npz_compressed(**arrays) -> bytes:
    out = io.BytesIO()
    np.savez_compressed(out, **arrays)
    return out.getvalue()


def _make_folder(root: Path, name: str) -> Path:
    d = root / name
    d.mkdir(parents=True, exist_ok=True)
    return d


def build_targets(root: Path) -> dict[str, FuzzTarget]:
    """Create valid seed files under ``root`` and return the fuzz targets by name (:data:`TARGET_NAMES`)."""
    from atlas_pipeline.gaussian_world.builder import GaussianWorld
    from atlas_pipeline.gaussian_world.field import GaussianField
    from atlas_pipeline.localization.places import PlaceIndex
    from atlas_pipeline.localization.tracker import SurfelModel
    from atlas_pipeline.mapping.keyframes import KeyframeSet
    from atlas_pipeline.perception.rgbd import FusedFrames
    from atlas_pipeline.safe_arrays import load_npz_checked
    from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_atlasgs1, write_atlasgs2
    from atlas_pipeline.scene_memory.bundle import load_world_bundle, read_metadata, write_world_bundle
    from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply
    from atlas_pipeline.sensors.camera import CameraIntrinsics
    from atlas_pipeline.sensors.registry import load_registry
    from atlas_pipeline.sensors.tum import load_tum_sequence, read_groundtruth, read_list_file

    builder = _small_field()
    fld = builder.to_field()
    iso = GaussianField(fld.positions, np.repeat(fld.scales[:, :1], 3, axis=1), np.tile([0, 0, 0, 1.0], (len(fld), 1)),
                        fld.colors, fld.opacities, fld.ids)
    targets: dict[str, FuzzTarget] = {}

    def add(name: str, files: list[FuzzFile], call_factory: Callable[[Path], Callable[[], object]]) -> None:
        folder = _make_folder(root, name)
        targets[name] = FuzzTarget(name, folder, files, call_factory(folder))

    # -- 3DGS PLY: ours, a reference-implementation one (f_rest, no ids / colours), one with faces
    tmp = _make_folder(root, "seeds")
    ours = write_gaussian_ply(fld, tmp / "ours.ply").read_bytes()
    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    vals = np.zeros((3, len(props)), np.float32)
    vals[:, props.index("rot_0")] = 1.0
    ref = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\n" + "".join(f"property float {p}\n" for p in props)
           + "end_header\n").encode() + vals.tobytes()
    faces = ref.replace(b"end_header\n", b"element face 1\nproperty list uchar int vertex_indices\nend_header\n") \
        + b"\x03" + struct.pack("<3i", 0, 1, 2)
    ply = FuzzFile("g.ply", [ours, ref, faces], "ply", magic=[b"", b"ply\n", b"ply\nformat binary_little_endian 1.0\n"])
    add("ply", [ply], lambda d: lambda: read_gaussian_ply(d / "g.ply"))

    # -- ATLASGS1 / ATLASGS2 (and an empty world)
    v1 = write_atlasgs1(iso, tmp / "v1.bin").read_bytes()
    v2 = write_atlasgs2(fld, tmp / "v2.bin").read_bytes()
    v1_empty = write_atlasgs1(GaussianField.empty(), tmp / "e.bin").read_bytes()
    binf = FuzzFile("g.bin", [v1, v2, v1_empty], "binary", hot=lambda data: [8, 12, 16, 20, 24, 28],
                    magic=[b"", b"ATLASGS1", b"ATLASGS2", b"ATLASGS2\x02\x00\x00\x00\x00\x00\x00\x00"])
    add("atlasgs", [binf], lambda d: lambda: read_gaussian_binary(d / "g.bin"))

    # -- TUM list files and ground truth
    t0 = 1305031102.175304
    rgb_rows = [f"{t0 + i / 30:.6f} rgb/{t0 + i / 30:.6f}.png" for i in range(3)]
    depth_rows = [f"{t0 + i / 30 + 0.004:.6f} depth/{t0 + i / 30 + 0.004:.6f}.png" for i in range(3)]
    rgb_txt = ("# color images\n# file: 'fuzz.bag'\n# timestamp filename\n" + "\n".join(rgb_rows) + "\n").encode()
    depth_txt = ("# depth maps\n# file: 'fuzz.bag'\n# timestamp filename\n" + "\n".join(depth_rows) + "\n").encode()
    gt_rows = [f"{t0 + i / 100:.4f} {0.01 * i:.4f} 1.3405 1.6102 0.6618 0.6112 -0.2951 -0.3251" for i in range(12)]
    gt_txt = ("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt_rows) + "\n").encode()
    text_magic = [b"", b"# timestamp filename\n", b"1305031102.175304 "]
    add("tum_list", [FuzzFile("rgb.txt", [rgb_txt, depth_txt], "text", magic=text_magic)],
        lambda d: lambda: read_list_file(d / "rgb.txt", 2))
    add("tum_groundtruth", [FuzzFile("groundtruth.txt", [gt_txt], "text", magic=text_magic)],
        lambda d: lambda: read_groundtruth(d / "groundtruth.txt"))

    # -- a TUM folder (3 frames of 8x6 pixels) whose rgb.txt / depth.txt are fuzzed
    camera = CameraIntrinsics(width=8, height=6, fx=10.0, fy=10.0, cx=3.5, cy=2.5)
    seq = _make_folder(root, "tum_sequence")
    rng = np.random.default_rng(1)
    for row in rgb_rows:
        (seq / row.split()[1]).parent.mkdir(exist_ok=True)
        (seq / row.split()[1]).write_bytes(_png(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)))
    for row in depth_rows:
        (seq / row.split()[1]).parent.mkdir(exist_ok=True)
        (seq / row.split()[1]).write_bytes(_png(np.full((6, 8), 5000, np.uint16)))
    (seq / "groundtruth.txt").write_bytes(gt_txt)
    add("tum_sequence", [FuzzFile("rgb.txt", [rgb_txt], "text", magic=text_magic),
                         FuzzFile("depth.txt", [depth_txt], "text", magic=text_magic)],
        lambda d: lambda: load_tum_sequence(d, camera, "fuzz"))

    # -- npz: generic arrays, and each artifact's own file
    generic = [
        _seed_npz(a=np.arange(12, dtype=np.float32).reshape(4, 3), b=np.array(True), c=np.zeros(0, np.int64),
                  d=np.asfortranarray(np.arange(6.0).reshape(2, 3)), e=np.arange(5, dtype=">u2")),
        _seed_npz_compressed(a=np.zeros((64, 3), np.float32), b=np.arange(10, dtype=np.uint64)),
    ]
    npz_magic = [b"", b"PK\x03\x04", b"PK\x05\x06"]
    add("npz", [FuzzFile("a.npz", generic, "npz", magic=npz_magic)], lambda d: lambda: load_npz_checked(d / "a.npz"))

    surfels = SurfelModel.from_builder(builder)
    surf_seed = surfels.save(tmp / "surfels.npz").read_bytes()
    add("surfels_npz", [FuzzFile("surfels.npz", [surf_seed], "npz", magic=npz_magic)],
        lambda d: lambda: SurfelModel.load(d / "surfels.npz"))
    places = PlaceIndex(None, 2, "0" * 64)
    places._codes = [np.full(192, 0.5, np.float32), np.full(192, np.nan, np.float32)]
    places._poses, places._keyframe = [np.eye(4), np.eye(4)], [0, 1]
    places_seed = places.save(tmp / "places.npz").read_bytes()
    add("places_npz", [FuzzFile("places.npz", [places_seed], "npz", magic=npz_magic)],
        lambda d: lambda: PlaceIndex.load(d / "places.npz", None))

    n_frames = 4
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, 0, 3] = np.arange(n_frames) * 0.1
    world = GaussianWorld(fld, builder, np.array([0, 2], np.int64), T[[0, 2]], "ground_truth",
                          np.array([len(builder), len(builder)], np.int64), {"steps": 0})
    world.save(_make_folder(tmp, "world"))
    keyframes = KeyframeSet(T, np.ones(n_frames, bool), np.array([0, 2], np.int64), "ground_truth")
    keyframes.save(_make_folder(tmp, "keyframes"))
    pts = rng.uniform(-1, 1, (10, 3)).astype(np.float32)
    fused = FusedFrames(pts, rng.integers(0, 256, (10, 3)).astype(np.uint8), np.array([0, 3, 3, 7, 10], np.int64),
                        np.array([0.5, 0.0, 0.4, 0.3], np.float32), 2, 0.1, 4.0)
    fused.save(_make_folder(tmp, "fused"))
    json_magic = [b"", b"{", b"{\"a\": "]
    def read_fused(d: Path):  # the index at load, then every chunk (read lazily, per frame)
        f = FusedFrames.load(d)
        return [f.frame(i) for i in range(f.n_frames)]

    for name, stem, call in (("world_npz", "world", GaussianWorld.load), ("keyframes_npz", "keyframes", KeyframeSet.load),
                             ("fused_npz", "fused", read_fused)):
        npz = FuzzFile(f"{stem}.npz", [(tmp / stem / f"{stem}.npz").read_bytes()], "npz", magic=npz_magic)
        sidecar = FuzzFile(f"{stem}.json", [(tmp / stem / f"{stem}.json").read_bytes()], "text", magic=json_magic)
        files = [npz, npz, npz, sidecar]
        if stem == "fused":  # the points chunk too
            files.append(FuzzFile("fused-00000.npz", [(tmp / stem / "fused-00000.npz").read_bytes()], "npz",
                                  magic=npz_magic))
        add(name, files, (lambda c: lambda d: lambda: c(d))(call))

    # -- world bundle: metadata.json fuzzed, the Gaussians and surfels valid
    bundle_dir = write_world_bundle(tmp / "bundle", fld, {"name": "fuzz", "dataset": {"name": "fuzz"}}, surfels=surfels)
    meta = FuzzFile("metadata.json", [(bundle_dir / "metadata.json").read_bytes()], "text", magic=json_magic)
    for name, reader in (("bundle_metadata", read_metadata), ("bundle_load", load_world_bundle)):
        d = _make_folder(root, name)
        for p in bundle_dir.iterdir():
            if p.is_file():
                (d / p.name).write_bytes(p.read_bytes())
        targets[name] = FuzzTarget(name, d, [meta], (lambda r, d: lambda: r(d))(reader, d))

    # -- dataset registry YAML
    reg = (
        "# datasets\n"
        "datasets:\n"
        "  synth-a:\n    kind: synthetic\n    path: synth/a\n    seed: 0\n    n_frames: 12\n    width: 160\n"
        "    height: 120\n"
        "  tum-b:\n    kind: tum\n    camera: freiburg1\n    path: rgbd_dataset_freiburg1_xyz\n"
        "    url: https://example.org/rgbd_dataset_freiburg1_xyz.tgz\n    sha256: '" + "0a" * 32 + "'\n"
        "  tum-c:\n    kind: tum\n    path: /tmp/fuzz/tum-c\n"
        "    camera: {width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, cy: 239.5, depth_scale: 5000}\n"
    ).encode()
    add("registry_yaml", [FuzzFile("datasets.yaml", [reg], "text", magic=[b"", b"datasets:\n  ", b"datasets:\n  a:\n    kind: "])],
        lambda d: lambda: load_registry([d / "datasets.yaml"]))

    # -- a profile (line duplication writes a key twice: refused, never the last value silently kept)
    from atlas_pipeline.config import load_profile

    profile = b"fusion:\n  stride: 2\n  min_depth_m: 0.1\nvideo:\n  fps: 15\n  orbit_frames: 30\n"
    add("profile_yaml", [FuzzFile("p.yaml", [profile], "text", magic=[b"", b"fusion:\n  ", b"<<: "])],
        lambda d: lambda: load_profile(str(d / "p.yaml")))

    # -- the other layouts' text files (poses, trajectories, intrinsics) over valid images
    from test_readers import REPLICA_CAMERA, SEVEN_SCENES_CAMERA, _replica, _scannet, _seven_scenes, _write_bag

    from atlas_pipeline.sensors.bags import load_bag_sequence
    from atlas_pipeline.sensors.layouts import load_7scenes_sequence, load_replica_sequence, load_scannet_sequence

    def layout(name: str, build, files: list[str], call) -> None:
        folder = build(_make_folder(root, name) / "rec")
        fuzz = [FuzzFile(f, [(folder / f).read_bytes()], "text", magic=[b"", b"1 0 0 0\n"]) for f in files]
        targets[name] = FuzzTarget(name, folder, fuzz, (lambda c, d: lambda: c(d))(call, folder))

    layout("7scenes_poses", lambda r: _seven_scenes(r, 2).parent, ["seq-01/frame-000000.pose.txt", "seq-01/frame-000001.pose.txt"],
           lambda d: load_7scenes_sequence(d, SEVEN_SCENES_CAMERA, "chess", sequence="seq-01"))
    layout("replica_traj", lambda r: _replica(r, 2), ["traj.txt"], lambda d: load_replica_sequence(d, REPLICA_CAMERA, "room"))
    layout("scannet_text", lambda r: _scannet(r, 2), ["intrinsic/intrinsic_depth.txt", "intrinsic/intrinsic_color.txt",
                                                      "pose/0.txt", "pose/1.txt"], lambda d: load_scannet_sequence(d, "scene"))
    bag = _make_folder(root, "bag")
    _write_bag(bag / "rec.bag", ros2=False, n=3)
    cache = _make_folder(root, "bag_cache")

    def read_bag(d: Path):
        shutil.rmtree(cache, ignore_errors=True)  # converted afresh each case
        return load_bag_sequence(d / "rec.bag", "rec", cache)

    targets["ros1_bag"] = FuzzTarget("ros1_bag", bag, [FuzzFile("rec.bag", [(bag / "rec.bag").read_bytes()], "binary",
                                                                magic=[b"", b"#ROSBAG V2.0\n"])], (lambda d: lambda: read_bag(d))(bag))
    return targets


# ---- the tests ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def targets(tmp_path_factory) -> dict[str, FuzzTarget]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return build_targets(tmp_path_factory.mktemp("fuzz"))


TARGET_NAMES = ["ply", "atlasgs", "tum_list", "tum_groundtruth", "tum_sequence", "npz", "surfels_npz", "places_npz",
                "world_npz", "keyframes_npz", "fused_npz", "bundle_metadata", "bundle_load", "registry_yaml", "profile_yaml",
                "7scenes_poses", "replica_traj", "scannet_text", "ros1_bag"]


def _check(target: FuzzTarget, fuzz_name: str, data: bytes) -> None:
    out = run_case(target, fuzz_name, data)
    assert out.kind != "other", (
        f"{target.name}: {fuzz_name} of {len(data)} bytes raised a non-project error:\n{out.error}\n"
        f"input (first 400 bytes): {data[:400]!r}")
    assert out.peak_bytes < memory_allowance(out.input_bytes), (
        f"{target.name}: {fuzz_name} of {len(data)} bytes made the reader trace {out.peak_bytes} bytes "
        f"(allowance {memory_allowance(out.input_bytes)} for {out.input_bytes} bytes of input)")


def _fuzz(targets, name: str, examples: int) -> None:
    target = targets[name]

    @settings(max_examples=examples, **FUZZ_SETTINGS)
    @given(st.data())
    def case(data):
        f = data.draw(st.sampled_from(target.files), label="file")
        _check(target, f.name, data.draw(fuzz_input(f), label="input"))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy / zipfile warnings on garbage are not failures
        case()


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_reader_fuzz_quick(targets, name):
    _fuzz(targets, name, QUICK_EXAMPLES)


@pytest.mark.slow
@pytest.mark.parametrize("name", TARGET_NAMES)
def test_reader_fuzz_thorough(targets, name):
    """14,400 cases in all (18 readers x 800): part of the full run and CI; `-m "not slow"` skips it."""
    _fuzz(targets, name, SLOW_EXAMPLES)


def test_a_bag_record_claiming_more_bytes_than_the_file_is_refused_before_it_is_read(tmp_path):
    """rosbags allocates what a record's length claims (67 MB for a 65 kB bag was seen): the
    lengths are checked against the file first, naming the byte offset."""
    from test_readers import _write_bag

    from atlas_pipeline.sensors.bags import ROS1_MAGIC, check_ros1_record_sizes, load_bag_sequence

    good = tmp_path / "good.bag"
    _write_bag(good, ros2=False, n=3)
    check_ros1_record_sizes(good)  # a real bag passes
    raw = bytearray(good.read_bytes())
    at = len(ROS1_MAGIC)
    header_len = int.from_bytes(raw[at:at + 4], "little")
    data_at = at + 4 + header_len
    raw[data_at:data_at + 4] = (64 << 20).to_bytes(4, "little")  # the first record's data: 64 MiB
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=rf"bad.bag: cannot read bag, corrupt: the data length 67108864 at byte "
                                           rf"{data_at} runs past the end of the file"):
        load_bag_sequence(bad, "bad", tmp_path / "cache")


def test_every_seed_is_accepted(targets):
    """The seeds are valid files: a reader that refuses them would make the fuzzing meaningless."""
    for target in targets.values():
        for f in target.files:
            for seed in f.seeds:
                out = run_case(target, f.name, seed)
                assert out.kind == "accepted", f"{target.name}: seed {f.name} refused ({out.kind}) {out.error}"


# ---- regressions: the specific inputs the checks were written for ------------------------------


def _tum_folder(tmp_path: Path, rgb: list[str], depth: list[str]) -> Path:
    """A TUM folder with list files only (no images: order must be refused before any image work)."""
    (tmp_path / "rgb.txt").write_text("# color images\n" + "\n".join(rgb) + "\n")
    (tmp_path / "depth.txt").write_text("# depth maps\n" + "\n".join(depth) + "\n")
    return tmp_path


def _camera():
    from atlas_pipeline.sensors.camera import CameraIntrinsics

    return CameraIntrinsics(width=8, height=6, fx=10.0, fy=10.0, cx=3.5, cy=2.5)


def test_tum_list_going_back_in_time_names_file_and_both_lines(tmp_path):
    from atlas_pipeline.sensors.tum import load_tum_sequence

    rgb = [f"1305031102.{t} rgb/{i}.png" for i, t in enumerate(["111", "175", "211", "175"])]
    depth = [f"1305031102.{t} depth/{i}.png" for i, t in enumerate(["112", "176", "212", "300"])]
    with pytest.raises(DatasetError) as exc_info:
        load_tum_sequence(_tum_folder(tmp_path, rgb, depth), _camera(), "t")
    assert str(exc_info.value) == (
        f"{tmp_path / 'rgb.txt'}:5: timestamp 1305031102.175 is not after the previous one (line 4: "
        "1305031102.211); TUM lists must be in increasing time order")
    assert exc_info.value.line == 5


def test_tum_repeated_depth_timestamp_is_an_error_not_a_dropped_frame(tmp_path):
    from atlas_pipeline.sensors.tum import load_tum_sequence

    rgb = ["1.000 rgb/0.png", "1.033 rgb/1.png", "1.066 rgb/2.png"]
    depth = ["1.001 depth/0.png", "1.034 depth/1.png", "1.034 depth/2.png"]
    with pytest.raises(DatasetError, match=r"depth.txt:4: timestamp 1.034 is not after the previous one \(line 3: 1.034\)"):
        load_tum_sequence(_tum_folder(tmp_path, rgb, depth), _camera(), "t")


@pytest.mark.parametrize("stamp", ["nan", "inf", "-Infinity", "1e400"])
def test_tum_non_finite_timestamp_names_line(tmp_path, stamp):
    from atlas_pipeline.sensors.tum import read_list_file

    p = tmp_path / "rgb.txt"
    p.write_text(f"# c\n1.0 rgb/a.png\n{stamp} rgb/b.png\n")
    with pytest.raises(DatasetError, match=f"rgb.txt:3: timestamp '{stamp}' is not a finite number"):
        read_list_file(p, 2)


def test_tum_list_garbage_is_a_dataset_error(tmp_path):
    from atlas_pipeline.sensors.tum import read_list_file

    p = tmp_path / "rgb.txt"
    p.write_bytes(b"1.0 rgb/a.png\n2.0 rgb/\xff.png\n")
    with pytest.raises(DatasetError, match="rgb.txt:2: line is not UTF-8"):
        read_list_file(p, 2)
    p.write_bytes(b"1.0 " + b"a" * 100_000)
    with pytest.raises(DatasetError, match="rgb.txt:1: line is longer than"):
        read_list_file(p, 2)


def test_groundtruth_duplicate_timestamp_names_both_lines(tmp_path):
    from atlas_pipeline.sensors.tum import read_groundtruth

    p = tmp_path / "groundtruth.txt"
    rows = ["2.0 0 0 0 0 0 0 1", "1.0 0 0 0 0 0 0 1", "2.0 1 0 0 0 0 0 1"]  # unsorted is fine, a repeat is not
    p.write_text("# gt\n" + "\n".join(rows) + "\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:4: timestamp 2.0 repeats line 2"):
        read_groundtruth(p)
    p.write_text("# gt\n" + "\n".join(rows[:2]) + "\n")
    ts, _ = read_groundtruth(p)
    assert ts.tolist() == [1.0, 2.0]


def _zip_with(name: str, npy: bytes, compression: int = zipfile.ZIP_STORED) -> bytes:
    return _rezip([(name, npy)], compression)


def _npy(descr: str, shape: tuple, data: bytes = b"") -> bytes:
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}".encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + data


def test_npz_huge_shape_is_refused_from_the_header(tmp_path):
    from atlas_pipeline.safe_arrays import load_npz_checked

    p = tmp_path / "surfels.npz"
    p.write_bytes(_zip_with("centres.npy", _npy("<f4", (10**12, 3), b"\0" * 2000)))
    tracemalloc.start()
    try:
        with pytest.raises(BundleFormatError) as exc_info:
            load_npz_checked(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert re.fullmatch(re.escape(f"{p}: member 'centres.npy' claims shape (1000000000000, 3) float32 = 12 TB "
                                  "but the archive holds ") + r"2\.\d+ kB", str(exc_info.value)), str(exc_info.value)
    assert peak < MEMORY_FLOOR_BYTES


@pytest.mark.parametrize("descr, why", [("|O", "never pickled"), ("<U4", "only plain numeric"),
                                        ("|V8", "only plain numeric")])
def test_npz_object_string_and_void_dtypes_are_refused(tmp_path, descr, why):
    from atlas_pipeline.safe_arrays import load_npz_checked

    p = tmp_path / "a.npz"
    p.write_bytes(_zip_with("a.npy", _npy(descr, (1,), b"\0" * 16)))
    with pytest.raises(BundleFormatError, match=f"member 'a.npy' has dtype .*{why}"):
        load_npz_checked(p)


def test_npz_size_mismatch_and_deflate_bomb_claims_are_refused(tmp_path):
    from atlas_pipeline.safe_arrays import load_npz_checked

    p = tmp_path / "a.npz"
    p.write_bytes(_zip_with("a.npy", _npy("<f4", (4, 3), b"\0" * 40)))  # 48 bytes claimed, 40 held
    with pytest.raises(BundleFormatError, match="claims shape \\(4, 3\\) float32 = 48 B but the member holds 40 B"):
        load_npz_checked(p)
    # a deflated member whose record claims 2000 x its compressed size
    data = bytearray(_zip_with("a.npy", _npy("<f4", (100,), b"\0" * 400), zipfile.ZIP_DEFLATED))
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as zf:
        info = zf.infolist()[0]
    cd = data.rfind(b"PK\x01\x02")
    data[cd + 24: cd + 28] = struct.pack("<I", info.compress_size * 2000)
    p.write_bytes(bytes(data))
    with pytest.raises(BundleFormatError, match="more than deflate can produce"):
        load_npz_checked(p)


def test_npz_expected_members_dtype_and_ndim(tmp_path):
    from atlas_pipeline.safe_arrays import load_npz_checked

    p = tmp_path / "a.npz"
    np.savez(p, a=np.zeros((2, 3), np.float32), b=np.arange(3))
    out = load_npz_checked(p, {"a": ("f", 2)})
    assert list(out) == ["a"] and out["a"].shape == (2, 3)
    with pytest.raises(BundleFormatError, match="missing member\\(s\\) c.npy"):
        load_npz_checked(p, {"a": ("f", 2), "c": ("f", 1)})
    with pytest.raises(BundleFormatError, match="member 'b.npy' has dtype int64, expected float"):
        load_npz_checked(p, {"b": ("f", 1)})
    with pytest.raises(BundleFormatError, match="member 'a.npy' has shape \\(2, 3\\) \\(2 dimensions\\), expected 1"):
        load_npz_checked(p, {"a": ("f", 1)})


def test_artifact_loaders_refuse_inconsistent_arrays(tmp_path):
    from atlas_pipeline.errors import ArtifactError
    from atlas_pipeline.mapping.keyframes import KeyframeSet
    from atlas_pipeline.perception.rgbd import FusedFrames

    T = np.tile(np.eye(4), (3, 1, 1))
    KeyframeSet(T, np.ones(3, bool), np.array([0, 5]), "ground_truth").save(tmp_path / "kf")
    with pytest.raises(ArtifactError, match="keyframes.npz: indices must be increasing frame indices in \\[0, 3\\)"):
        KeyframeSet.load(tmp_path / "kf")
    pts = np.zeros((4, 3), np.float32)
    FusedFrames(pts, np.zeros((4, 3), np.uint8), np.array([0, 3, 2]), np.ones(2, np.float32), 2, 0.1, 4.0) \
        .save(tmp_path / "fused")
    with pytest.raises(ArtifactError, match="fused.npz: offsets must rise from 0 to the number of points"):
        FusedFrames.load(tmp_path / "fused")
    (tmp_path / "fused" / "fused.json").write_text('{"stride": 2, "min_depth_m": ' + "9" * 5000 + "}")
    with pytest.raises(ArtifactError, match="fused.json: invalid JSON"):
        FusedFrames.load(tmp_path / "fused")


def test_ply_header_garbage_names_the_line(tmp_path):
    from atlas_pipeline.scene_memory.ply import read_gaussian_ply

    p = tmp_path / "g.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex " + b"9" * 5000 + b"\nend_header\n")
    with pytest.raises(BundleFormatError, match="g.ply: header line 3: malformed element line"):
        read_gaussian_ply(p)
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 1\n" + "property double x\n" \
        + "".join(f"property float {q}\n" for q in props[1:]) + "end_header\n"
    p.write_bytes(head.encode() + struct.pack("<d", 1e300) + np.ones(len(props) - 1, np.float32).tobytes())
    with pytest.raises(BundleFormatError, match="property 'x' has values outside the float32 range"):
        read_gaussian_ply(p)


def test_atlasgs_count_overflow_and_duplicate_ids(tmp_path):
    from atlas_pipeline.gaussian_world.field import GaussianField
    from atlas_pipeline.scene_memory.binary import read_gaussian_binary, write_atlasgs2

    p = tmp_path / "g.bin"
    p.write_bytes(b"ATLASGS2" + struct.pack("<IIQ", 2, 0, 2**64 - 1))
    with pytest.raises(BundleFormatError, match="count 18446744073709551615 needs"):
        read_gaussian_binary(p)
    f = GaussianField(np.zeros((2, 3)), np.ones((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)), np.zeros((2, 3)),
                      np.full(2, 0.5), np.array([7, 7], np.uint64))
    write_atlasgs2(f, p)
    with pytest.raises(BundleFormatError, match="ids are not unique"):
        read_gaussian_binary(p)

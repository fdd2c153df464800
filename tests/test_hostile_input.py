"""Trust under hostile input. Each bad input is an error (or a warning) that names the
file, line, field or option it is about, never a traceback, a misleading message or a silent
wrong result."""

from __future__ import annotations

import textwrap

import pytest

from atlas_pipeline.errors import ConfigError
from tests.conftest import InlinePool


# ---- a key repeated in a profile or the dataset registry ---------------------------------------

@pytest.mark.parametrize("kind, text, line, key", [
    ("profile", """\
        mapping:
          voxel_size_m: 0.02
          voxel_size_m: 0.05
        """, 3, "voxel_size_m"),
    ("profile", """\
        mapping:
          voxel_size_m: 0.02
        localization:
          finest_level: 1
        mapping:
          fit: {epochs: 0}
        """, 5, "mapping"),
    ("profile", """\
        video: {fps: 15, fps: 30}
        """, 1, "fps"),
    ("registry", """\
        datasets:
          mine:
            kind: synthetic
            n_frames: 12
          mine:
            kind: synthetic
            n_frames: 40
        """, 5, "mine"),
    ("registry", """\
        datasets:
          mine:
            kind: synthetic
            seed: 0
            seed: 1
        """, 5, "seed"),
])
def test_a_repeated_yaml_key_names_file_line_and_key(tmp_path, kind, text, line, key):
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.sensors.registry import load_registry

    path = tmp_path / f"{kind}.yaml"
    path.write_text(textwrap.dedent(text))
    with pytest.raises(ConfigError) as err:
        load_profile(path) if kind == "profile" else load_registry([path])
    msg = str(err.value)
    assert msg.startswith(f"{path}:{line}: duplicate key '{key}' (first on line "), msg


def test_merge_keys_may_still_be_overridden(tmp_path):
    from atlas_pipeline.config import parse_yaml

    data = parse_yaml("base: &b {fps: 15, scale: 1.0}\nvideo:\n  <<: *b\n  fps: 30\n")
    assert data["video"] == {"fps": 30, "scale": 1.0}


def test_a_repeated_key_in_a_set_value_is_refused():
    from atlas_pipeline.config import parse_set_overrides

    with pytest.raises(ConfigError, match=r"--set 'x=\{a: 1, a: 2\}'.*duplicate key 'a'"):
        parse_set_overrides(["x={a: 1, a: 2}"])


# ---- counts and sizes bounded at load time ---------------------------------------------------------

def _counts() -> list[tuple[str, object, object]]:
    """``(dotted name, annotation, FieldInfo of the value or of a tuple's elements)`` of every count of
    a profile (int, int | None, tuple of ints), found by reflection so a new count cannot be left
    unbounded."""
    from typing import get_args, get_origin

    from pydantic import BaseModel

    from atlas_pipeline.config import PipelineConfig

    def walk(model, prefix):
        for name, info in model.model_fields.items():
            tp = info.annotation
            if isinstance(tp, type) and issubclass(tp, BaseModel):
                yield from walk(tp, f"{prefix}{name}.")
            elif get_origin(tp) is tuple:
                yield prefix + name, tp, get_args(get_args(tp)[0])[1]  # Annotated[int, Field(...)]
            elif tp is int or int in get_args(tp):
                yield prefix + name, tp, info

    return list(walk(PipelineConfig, ""))


COUNTS = _counts()


def test_the_counts_are_found():
    names = {n for n, _, _ in COUNTS}
    assert {"video.orbit_frames", "mapping.fit.epochs", "localization.iterations",
            "dataset.max_frames", "fusion.stride", "evaluation.max_views"} <= names


def _upper_bound(info) -> float | None:
    from annotated_types import Le, Lt

    return next((m.le if isinstance(m, Le) else m.lt for m in info.metadata if isinstance(m, (Le, Lt))), None)


@pytest.mark.parametrize("name, tp, info", COUNTS + [("video.fps", float, None), ("video.scale", float, None)],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_every_count_and_size_has_a_maximum_checked_when_the_profile_is_loaded(tmp_path, name, tp, info):
    from typing import get_origin

    from atlas_pipeline.config import PipelineConfig, load_profile

    *sections, key = name.split(".")
    if info is None:
        info = PipelineConfig.model_fields[sections[0]].annotation.model_fields[key]
    top = _upper_bound(info)
    assert top is not None, f"{name} has no upper bound"
    too_many = int(top) + 1 if tp is not float else top * 2
    shown = [too_many] if get_origin(tp) is tuple else too_many
    path = tmp_path / "huge.yaml"
    indent = "\n".join(f"{'  ' * i}{s}:" for i, s in enumerate(sections))
    path.write_text(f"{indent}\n{'  ' * len(sections)}{key}: {shown}\n")
    with pytest.raises(ConfigError) as err:
        load_profile(path)
    index = "[0]" if get_origin(tp) is tuple else ""
    assert str(err.value).startswith(f"{path}: {name}{index} must be "), str(err.value)
    assert f"{top:g}" in str(err.value) or str(int(top)) in str(err.value)
    assert str(err.value).endswith(f"got {too_many!r}")


@pytest.mark.parametrize("item, message", [
    ("video.orbit_frames=1000000000", "--set: video.orbit_frames must be less than or equal to 10000, got 1000000000"),
    ("mapping.fit.epochs=1000000", "--set: mapping.fit.epochs must be less than or equal to 10000, got 1000000"),
    ("localization.iterations=[12,8,100000]", "--set: localization.iterations[2] must be less than or equal to 100, "
                                              "got 100000"),
])
def test_a_huge_count_fails_before_any_work(isolated, caplog, item, message):
    from assets.cli import main

    out = isolated / "w"
    assert main(["build", "--input", "synth-small", "--output", str(out), "--set", item]) == 2
    assert message in caplog.text
    assert not out.exists() and not (isolated / "data").exists()  # nothing generated, nothing written


# ---- timestamps that are not seconds ---------------------------------------------------------------

@pytest.fixture
def tum_copy(small_synthetic, tmp_path):
    import shutil

    dst = tmp_path / "seq"
    shutil.copytree(small_synthetic, dst)
    return dst


def _rescale(path, factor: float, offset: float = 0.0) -> None:
    """Write ``path``'s timestamps (first column) as ``t * factor + offset``, as a recorder in another unit would."""
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            out.append(line)
            continue
        t, rest = line.split(" ", 1)
        out.append(f"{float(t) * factor + offset:.3f} {rest}")
    path.write_text("\n".join(out) + "\n")


def _load_tum(root):
    from atlas_pipeline.sensors.synthetic import SyntheticSpec
    from atlas_pipeline.sensors.tum import load_tum_sequence
    from tests.conftest import SMALL_SYNTH

    return load_tum_sequence(root, SyntheticSpec(**SMALL_SYNTH).camera(), "x")


# (files rescaled, factor, offset, file named, line named or None, unit named)
UNIT_CASES = {
    "rgb_in_ns": (["rgb.txt"], 1e9, 0.0, "rgb.txt", None, "nanoseconds"),
    "depth_in_ns": (["depth.txt"], 1e9, 0.0, "depth.txt", None, "nanoseconds"),
    "groundtruth_in_ns": (["groundtruth.txt"], 1e9, 0.0, "groundtruth.txt", None, "nanoseconds"),
    # Both streams in ns: the unit is named, not "no depth frame within 20 ms".
    "rgb_and_depth_in_ns": (["rgb.txt", "depth.txt"], 1e9, 0.0, "rgb.txt", None, "nanoseconds"),
    "all_in_ns_since_the_epoch": (["rgb.txt", "depth.txt", "groundtruth.txt"], 1e9, 1.3e18, "rgb.txt", None,
                                  "nanoseconds"),
    "depth_in_us": (["depth.txt"], 1e6, 0.0, "depth.txt", None, "microseconds"),
    "rgb_in_ms": (["rgb.txt"], 1e3, 0.0, "rgb.txt", None, "milliseconds"),
    # Motion capture at 100 Hz in ms since the epoch: 10 "s" apart passes, the magnitude does not.
    "groundtruth_in_ms_since_the_epoch": (["groundtruth.txt"], 1e3, 1.3e12, "groundtruth.txt", 4, "milliseconds"),
}


@pytest.mark.parametrize("case", list(UNIT_CASES))
def test_timestamps_that_cannot_be_seconds_name_the_file_and_the_likely_unit(tum_copy, case):
    from atlas_pipeline.errors import DatasetError

    files, factor, offset, named, line, unit = UNIT_CASES[case]
    for name in files:
        _rescale(tum_copy / name, factor, offset)
    with pytest.raises(DatasetError) as err:
        _load_tum(tum_copy)
    msg = str(err.value)
    where = f"{tum_copy / named}:{line}: " if line is not None else f"{tum_copy / named}: "
    assert msg.startswith(where), msg
    assert f"look like {unit}" in msg and "TUM list files give seconds" in msg, msg
    assert "within 20 ms" not in msg
    assert err.value.path == tum_copy / named and err.value.line == line


@pytest.mark.parametrize("factor, offset", [(1.0, 0.0), (1.0, 1.3e9), (0.5, 0.0)],
                         ids=["synthetic", "seconds_since_the_epoch", "twice_the_rate"])
def test_timestamps_in_seconds_still_load(tum_copy, factor, offset):
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        _rescale(tum_copy / name, factor, offset)
    m = _load_tum(tum_copy)
    assert m.n_frames >= 2 and m.has_gt.all()


# ---- a list entry that is not a regular file ---------------------------------------------------

def _replace_entry(root, list_name: str, index: int, what: str) -> tuple[str, int]:
    """Turn the image of data row ``index`` of ``list_name`` into ``what``; ``(its name, list line)``."""
    import os

    lines = (root / list_name).read_text().splitlines()
    data = [k for k, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    lineno = data[index] + 1
    name = lines[data[index]].split()[1]
    target = root / name
    target.unlink()
    if what == "directory":
        target.mkdir()
    elif what == "fifo":
        os.mkfifo(target)
    elif what == "link_to_directory":
        (root / "elsewhere").mkdir()
        target.symlink_to(root / "elsewhere")
    elif what != "missing":
        raise AssertionError(what)
    return name, lineno


@pytest.mark.parametrize("list_name, kind, what, problem", [
    ("rgb.txt", "rgb", "directory", "is a directory"),
    ("rgb.txt", "rgb", "fifo", "is not a regular file (a FIFO)"),
    ("rgb.txt", "rgb", "link_to_directory", "is a directory"),
    ("rgb.txt", "rgb", "missing", "not found"),
    ("depth.txt", "depth", "directory", "is a directory"),
    ("depth.txt", "depth", "fifo", "is not a regular file (a FIFO)"),
])
def test_a_list_entry_that_is_not_a_file_says_what_it_is(tum_copy, list_name, kind, what, problem):
    from atlas_pipeline.errors import DatasetError

    name, lineno = _replace_entry(tum_copy, list_name, 2, what)
    with pytest.raises(DatasetError) as err:
        _load_tum(tum_copy)  # returns: a FIFO is never opened (it would block)
    assert str(err.value) == f"{tum_copy / list_name}:{lineno}: {kind} image {name!r} {problem}"


@pytest.mark.parametrize("list_name, what, problem", [
    ("rgb.txt", "directory", "list file is a directory"),
    ("depth.txt", "fifo", "list file is not a regular file (a FIFO)"),
])
def test_a_list_file_that_is_not_a_file_says_what_it_is(tum_copy, list_name, what, problem):
    import os

    from atlas_pipeline.errors import DatasetError

    (tum_copy / list_name).unlink()
    if what == "directory":
        (tum_copy / list_name).mkdir()
    else:
        os.mkfifo(tum_copy / list_name)
    with pytest.raises(DatasetError) as err:
        _load_tum(tum_copy)
    assert str(err.value) == f"{tum_copy / list_name}: {problem}"


# ---- PLY imports ---------------------------------------------------------------------------------

PLY_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
PLY_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _ply(path, n: int, n_rest: int = 0, extra_header: str = ""):
    """A 3DGS PLY of ``n`` unit Gaussians with ``n_rest`` ``f_rest_*`` properties (as the reference writes)."""
    import numpy as np

    props = PLY_BASE + [f"f_rest_{i}" for i in range(n_rest)] + PLY_TAIL
    header = ("ply\nformat binary_little_endian 1.0\n" + extra_header + f"element vertex {n}\n"
              + "".join(f"property float {p}\n" for p in props) + "end_header\n")
    vals = np.zeros((n, len(props)), np.float32)
    vals[:, 0] = np.arange(n)
    vals[:, props.index("scale_0"):props.index("scale_2") + 1] = np.log(0.01)
    vals[:, props.index("rot_0")] = 1.0
    path.write_bytes(header.encode() + vals.tobytes())
    return path


@pytest.mark.parametrize("n_rest, extra_header", [(0, ""), (45, ""), (0, "comment made by a viewer\n")],
                         ids=["plain", "with_sh", "with_comment"])
def test_importing_a_ply_of_no_vertices_names_the_file(isolated, caplog, n_rest, extra_header):
    from assets.cli import main
    from atlas_pipeline.errors import BundleFormatError
    from atlas_pipeline.scene_memory.ply import read_gaussian_ply

    src = _ply(isolated / "empty.ply", 0, n_rest, extra_header)
    with pytest.raises(BundleFormatError) as err:
        read_gaussian_ply(src)
    assert str(err.value).startswith(f"{src}: header declares 0 vertices")
    assert len(read_gaussian_ply(src, allow_empty=True)) == 0  # the round-trip check's reading
    out = isolated / "world"
    assert main(["import-ply", str(src), "--output", str(out)]) == 2
    assert f"{src}: header declares 0 vertices: the file holds no Gaussians" in caplog.text
    assert "Traceback" not in caplog.text and "TypeError" not in caplog.text
    assert not out.exists()


@pytest.mark.parametrize("n_rest, degree", [(45, 3), (24, 2), (9, 1), (0, 0)])
def test_spherical_harmonics_are_kept_on_import(isolated, capsys, n_rest, degree):
    import numpy as np

    from assets.cli import main
    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    src = _ply(isolated / "splats.ply", 5, n_rest)
    out = isolated / "world"
    assert main(["import-ply", str(src), "--output", str(out)]) == 0  # no -v
    assert "dropped" not in capsys.readouterr().err
    for source in ("bin", "ply"):  # both of the bundle's copies carry them
        field = load_world_bundle(out, source=source).field
        assert field.sh_degree == degree and field.sh_rest.shape == (5, (degree + 1) ** 2 - 1, 3)
        assert np.all(field.sh_rest == 0.0)


@pytest.mark.parametrize("n_rest, problem", [
    (10, "10 f_rest_* properties: spherical harmonics of degree 1, 2 or 3 have 9, 24 or 45"),
    (72, "72 f_rest_* properties: spherical harmonics of degree 1, 2 or 3 have 9, 24 or 45"),  # degree 4
])
def test_spherical_harmonics_of_no_supported_degree_are_refused(isolated, caplog, n_rest, problem):
    from assets.cli import main

    src = _ply(isolated / "splats.ply", 5, n_rest)
    out = isolated / "world"
    assert main(["import-ply", str(src), "--output", str(out)]) == 2
    assert f"{src}: {problem}" in caplog.text
    assert "Traceback" not in caplog.text and not out.exists()


# ---- the command line's output ---------------------------------------------------------------------

@pytest.mark.parametrize("argv, codes", [
    (["dataset", "list"], {141}),
    # every command writes through the same guard: the other printers in the full run only
    pytest.param(["dataset", "show", "synth-small"], {141}, marks=pytest.mark.slow),
    pytest.param(["dataset", "list", "-v"], {141}, marks=pytest.mark.slow),
    (["--help"], {0, 141}),  # argparse itself ignores a failed write of its help, then exits 0
], ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_a_closed_stdout_ends_the_command_quietly(isolated, argv, codes):
    """``atlas-gs dataset list | head -1``: the reader is gone before the command writes."""
    import subprocess
    import sys
    from pathlib import Path

    from assets.cli import EXIT_BROKEN_PIPE

    proc = subprocess.Popen([sys.executable, "-m", "assets.cli", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=Path(__file__).resolve().parents[1])
    proc.stdout.close()  # as `head` exits: every write of the command meets a closed pipe
    err = proc.stderr.read().decode()
    assert EXIT_BROKEN_PIPE == 141
    assert proc.wait(timeout=300) in codes, err
    assert "Broken pipe" not in err and "Traceback" not in err and "Exception ignored" not in err, err


@pytest.mark.slow
def test_head_of_dataset_list_in_a_shell(isolated):
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    reg = isolated / "datasets.local.yaml"
    # 3,000 lines (240 kB): more than a pipe holds, so the command is still writing when head leaves
    entries = {f"synth-{i}": {"kind": "synthetic", "seed": i} for i in range(3000)}
    reg.write_text(yaml.safe_dump({"datasets": entries}))
    res = subprocess.run(["bash", "-o", "pipefail", "-c", f"{sys.executable} -m assets.cli dataset list | head -1"],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert len(res.stdout.splitlines()) == 1
    assert res.stderr == ""  # was "error: (no path given by the OS): Broken pipe", exit 2
    assert res.returncode == 141  # pipefail: the command's status, as any tool's a closed pipe ended


class _FakeResult:
    """What assets.launch.run_partition reads of a Dagster run's result (the run itself is not what these tests are about)."""

    def __init__(self, partition: str):
        self.success, self.run_id, self.all_events = True, f"run-{partition}", []


@pytest.mark.parametrize("argv, failing, expected", [
    (["run", "--all", "--concurrency", "1", "--json"], None, ["par-a", "par-b", "par-c"]),
    (["run", "--all", "--concurrency", "1"], None, ["par-a", "par-b", "par-c"]),  # stdout not a terminal: JSON
    (["run", "--all", "--concurrency", "2", "--json"], None, ["par-a", "par-b", "par-c"]),  # the pool's path
    (["run", "--all", "--concurrency", "3", "--json"], "par-b", ["par-a", "par-b", "par-c"]),
    (["run", "par-b", "--json"], None, "par-b"),  # one partition: its object, as always
])
def test_run_prints_one_json_document(isolated, monkeypatch, capsys, argv, failing, expected):
    import concurrent.futures
    import json

    import assets.cli as cli
    import assets.launch as launch
    from atlas_pipeline.errors import DatasetError
    from tests.test_parallel import project_with_datasets

    names = ["par-a", "par-b", "par-c"]
    monkeypatch.setenv("ATLAS_PROJECT_ROOT", str(project_with_datasets(isolated / "project", names)))
    monkeypatch.setenv("ATLAS_LOCAL_REGISTRY", str(isolated / "none.yaml"))

    def fake_execute(run, p, *rest):
        if p == failing:
            raise DatasetError(p, "the frames are gone")
        return _FakeResult(p)

    monkeypatch.setattr(launch, "execute_partition", fake_execute)
    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", InlinePool)
    code = cli.main(argv)
    out = capsys.readouterr().out
    doc = json.loads(out)  # one document, whatever the path
    if isinstance(expected, str):
        assert code == 0 and doc["partition"] == expected and doc["run_id"] == f"run-{expected}"
        return
    assert isinstance(doc, list) and [d["partition"] for d in doc] == expected
    for d in doc:
        ok = d["partition"] != failing
        assert d["success"] is ok
        assert d.get("run_id") == (f"run-{d['partition']}" if ok else None)
    assert code == (cli.EXIT_ERROR if failing else 0)

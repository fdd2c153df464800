"""No traceback, no hang: inputs and events that ended in a Python traceback, a hang or a message
naming the wrong file end in one clear line and the documented exit status. Each test is a row of
docs/reliability.md's fault table and asserts that the line names the file, folder or option."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from assets.cli import main
from tests.conftest import SMALL_SYNTH

# no fit: what these tests check does not depend on it
FAST = ["--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0"]
CAMERA = ["--intrinsics", f"{SMALL_SYNTH['fx']} {SMALL_SYNTH['fy']} {SMALL_SYNTH['cx']} {SMALL_SYNTH['cy']}",
          "--width", str(SMALL_SYNTH["width"]), "--height", str(SMALL_SYNTH["height"])]
TUM_NO_READING_FAR = 65535  # the largest 16-bit depth: 13.1 m at TUM's 5000 units per metre, beyond the range
CLI = "import sys; from assets.cli import command; sys.exit(command())"
EXIT_ERROR = 2
EXIT_TERMINATED = 143
EXIT_INTERRUPTED = 130


def _errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error:")]


def _register(isolated: Path, small_synthetic: Path, name: str, capsys) -> Path:
    """A copy of the small synthetic recording registered as ``name`` (a TUM folder)."""
    rec = isolated / name
    shutil.copytree(small_synthetic, rec)
    assert main(["dataset", "add", name, str(rec), "--kind", "tum", *CAMERA]) == 0
    capsys.readouterr()
    return rec


def _build(isolated: Path, name: str, capsys, *extra: str) -> Path:
    world = isolated / f"world-{name}"
    assert main(["build", "--input", name, "--output", str(world), *FAST, *extra]) == 0, capsys.readouterr().err
    capsys.readouterr()
    return world


# ---- an empty field has a content hash --------------------------------------------------------


def test_the_content_hash_of_an_empty_field_is_defined_and_others_are_unchanged():
    """A field of no Gaussians hashes (a memoryview of an empty array cannot be cast); a field of
    some hashes to the sha256 of its arrays' bytes as before."""
    from atlas_pipeline.gaussian_world.field import GaussianField

    rng = np.random.default_rng(0)
    n = 5
    field = GaussianField(rng.normal(size=(n, 3)).astype(np.float32), np.full((n, 3), 0.01, np.float32),
                          np.tile(np.float32([0, 0, 0, 1]), (n, 1)), rng.integers(0, 255, (n, 3)).astype(np.uint8),
                          np.full(n, 0.5, np.float32), np.arange(n, dtype=np.uint64))
    expected = hashlib.sha256()
    for name in ("ids", "positions", "scales", "rotations_xyzw", "colors", "opacities"):
        arr = getattr(field, name)
        expected.update(name.encode() + str(arr.shape).encode() + np.ascontiguousarray(arr).tobytes())
    assert field.content_hash() == expected.hexdigest()
    empty = field.subset(np.zeros(n, bool))
    assert len(empty) == 0
    assert empty.content_hash() == empty.content_hash() != field.content_hash()


# ---- a recording with no depth in range -------------------------------------------------------


def _no_depth_in_range(isolated: Path, small_synthetic: Path, capsys) -> Path:
    """The small recording with every depth pixel at 65535 (13.1 m): readings, none in range."""
    import imageio.v3 as iio

    rec = _register(isolated, small_synthetic, "far", capsys)
    for png in (rec / "depth").iterdir():
        iio.imwrite(png, np.full((SMALL_SYNTH["height"], SMALL_SYNTH["width"]), TUM_NO_READING_FAR, np.uint16))
    return rec


@pytest.mark.parametrize("pose_source", ["ground_truth", "estimated"])
def test_a_recording_with_no_depth_in_range_is_one_line_naming_it_and_the_range(isolated, small_synthetic,
                                                                                 capsys, pose_source):
    rec = _no_depth_in_range(isolated, small_synthetic, capsys)
    out = isolated / "w"
    assert main(["build", "--input", "far", "--output", str(out), *FAST,
                 "--set", f"mapping.pose_source={pose_source}"]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(_errors(err)) == 1, err
    line = _errors(err)[0]
    for word in (str(rec), "'far'", "0.1-4 m", "fusion.max_depth_m", "13.1", "--depth-scale"):
        assert word in line, (word, line)
    assert not out.exists()


def test_extending_a_world_with_a_recording_with_no_depth_in_range_names_it(isolated, small_synthetic, capsys):
    """Tracking into a saved world reads the frames itself: the same line, not "no frame could be placed"."""
    _register(isolated, small_synthetic, "good", capsys)
    world = _build(isolated, "good", capsys)
    rec = _no_depth_in_range(isolated, small_synthetic, capsys)
    assert main(["build", "--input", "far", "--extend", str(world), "--output", str(isolated / "w2"), *FAST,
                 "--set", "mapping.pose_source=estimated"]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(_errors(err)) == 1, err
    for word in (str(rec), "none within the depth range", "0.1-4 m"):
        assert word in _errors(err)[0], (word, err)


@pytest.mark.slow
def test_a_run_of_a_recording_with_no_depth_in_range_fails_at_fusion_in_one_line(isolated, small_synthetic, capsys):
    """Through Dagster: the failed stage's line, not a TypeError from the empty world's hash, and no
    line for each later stage left out."""
    rec = _no_depth_in_range(isolated, small_synthetic, capsys)
    assert main(["run", "far", "--json", *FAST]) == 1
    captured = capsys.readouterr()
    err = captured.err
    assert "Traceback" not in err and "TypeError" not in err, err
    assert len(_errors(err)) == 1, err
    line = _errors(err)[0]
    assert line.startswith("error: fused_frames failed: ") and str(rec) in line and "0.1-4 m" in line, line
    assert "atlas_pipeline.errors" not in line, line  # the message, without the class's module path
    assert "Dependencies for step" not in err, err


# ---- build --extend at another voxel size -----------------------------------------------------


def test_extending_at_another_voxel_size_is_refused_before_any_frame_is_read(isolated, small_synthetic, capsys,
                                                                            monkeypatch):
    import atlas_pipeline.sensors.registry as registry

    _register(isolated, small_synthetic, "good", capsys)
    world = _build(isolated, "good", capsys)

    def no_frames(*_args, **_kwargs):
        raise AssertionError("the recording was read before the voxel sizes were compared")

    monkeypatch.setattr(registry, "load_dataset", no_frames)
    out = isolated / "w2"
    assert main(["build", "--input", "good", "--extend", str(world), "--output", str(out), *FAST,
                 "--set", "mapping.voxel_size_m=0.04"]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(_errors(err)) == 1, err
    for word in ("--extend", str(world), "mapping.voxel_size_m=0.02", "mapping.voxel_size_m=0.04"):
        assert word in _errors(err)[0], (word, err)
    assert not out.exists()


# ---- ATLAS_DATA_DIR / ATLAS_ARTIFACTS_DIR that are files --------------------------------------


@pytest.mark.parametrize("variable, under, argv", [
    ("ATLAS_DATA_DIR", "", ["build", "--input", "synth-small", "--output", "{root}/w"]),
    ("ATLAS_DATA_DIR", "sub", ["dataset", "fetch", "synth-small"]),
    ("ATLAS_ARTIFACTS_DIR", "", ["status", "synth-small"]),
    ("ATLAS_ARTIFACTS_DIR", "sub", ["run", "synth-small"]),
])
def test_a_data_or_artifacts_folder_that_is_a_file_names_the_variable(isolated, capsys, monkeypatch, variable,
                                                                      under, argv):
    a_file = isolated / "not-a-folder"
    a_file.write_text("mine\n")
    value = a_file / under if under else a_file
    monkeypatch.setenv(variable, str(value))
    assert main([a.format(root=isolated) for a in argv]) == EXIT_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(_errors(err)) == 1, err
    line = _errors(err)[0]
    assert f"{variable}={value}" in line, line
    assert (f"{a_file}, a part of that path, is a file" if under else f"{a_file} is a file") in line, line
    assert a_file.read_text() == "mine\n" and not (isolated / "w").exists()


# ---- a full disk during export ----------------------------------------------------------------


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("writer", ["copied colour image", "written depth image"])
def test_a_full_disk_during_export_names_the_output_file_and_leaves_nothing(isolated, small_synthetic, capsys,
                                                                            monkeypatch, writer):
    """ENOSPC part-way through a file: the line names the file being written where the user will
    look for it (not the input image, not a staging name); no staging is left, and an earlier
    export at the output path is kept as it was."""
    import imageio.v3 as iio

    rec = _register(isolated, small_synthetic, "good", capsys)
    world = _build(isolated, "good", capsys)
    out = isolated / "export"
    assert main(["export", str(world), "--format", "colmap", "--output", str(out)]) == 0
    capsys.readouterr()
    before = _snapshot(out)
    calls = []
    if writer == "copied colour image":
        real_sendfile = os.sendfile

        def full_disk(out_fd, in_fd, offset, count):  # a few bytes land, then the disk is full
            calls.append(out_fd)
            if len(calls) == 1:
                return real_sendfile(out_fd, in_fd, offset, min(count, 16))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(os, "sendfile", full_disk)
        folder = "images"
    else:
        real_imwrite = iio.imwrite

        def full_disk(path, image, **kwargs):
            calls.append(path)
            if len(calls) < 3:
                return real_imwrite(path, image, **kwargs)
            Path(path).write_bytes(b"\x89PNG half")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(iio, "imwrite", full_disk)
        folder = "depths"
    again = ["export", str(world), "--format", "colmap", "--output", str(out), "--poses", "keyframes"]
    assert main(again) == EXIT_ERROR
    err = capsys.readouterr().err
    assert calls, "the simulated full disk was never reached"
    assert "Traceback" not in err and len(_errors(err)) == 1, err
    line = _errors(err)[0]
    assert line.startswith(f"error: {out / folder}{os.sep}frame_") and "No space left on device" in line, line
    assert str(rec) not in line and ".tmp" not in line, line
    assert _snapshot(out) == before
    assert sorted(p.name for p in isolated.iterdir() if p.name.startswith(".export")) == []


# ---- SIGTERM is handled like Ctrl-C -----------------------------------------------------------

# long enough that fusing it outlasts the moment the signal is sent
SIGNAL_SYNTH = {**SMALL_SYNTH, "kind": "synthetic", "seed": 1, "n_frames": 60, "width": 320, "height": 240,
                "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}


def _signal_env(root: Path) -> dict[str, str]:
    reg = root / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {"sig": SIGNAL_SYNTH}}))
    return {**os.environ, "ATLAS_GS_HOME": str(root), "ATLAS_DATA_DIR": str(root / "data"),
            "ATLAS_ARTIFACTS_DIR": str(root / "artifacts"), "ATLAS_LOCAL_REGISTRY": str(reg),
            "DAGSTER_HOME": str(root / "dagster_home")}


def _asset_folders(artifacts: Path) -> set[str]:
    return {p.name for p in artifacts.iterdir() if p.is_dir() and not p.name.startswith(".")} if artifacts.is_dir() \
        else set()


@pytest.mark.slow
@pytest.mark.parametrize("sigint", ["default", "ignored"], ids=["terminal", "background-job"])
def test_sigterm_to_run_ends_it_in_one_line_with_status_143_and_no_later_asset(tmp_path, sigint):
    """SIGTERM (``kill``, a supervisor, a CI timeout) once the first asset is written: the run ends
    at once with one line and 143, as Ctrl-C ends it with 130; no asset after the one in progress
    appears, no staging is left. Also in a background job, whose SIGINT is ignored (where Dagster
    turned SIGTERM into its own interrupt and a traceback)."""
    env = _signal_env(tmp_path)
    (tmp_path / "dagster_home").mkdir()
    disposition = signal.SIG_DFL if sigint == "default" else signal.SIG_IGN
    p = subprocess.Popen([sys.executable, "-c", CLI, "run", "sig", *FAST], env=env, cwd=tmp_path,
                         start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, disposition))
    lines: list[str] = []
    first_asset = threading.Event()

    def read(stream) -> None:
        for line in stream:
            lines.append(line)
            if line.startswith("raw_dataset"):
                first_asset.set()

    readers = [threading.Thread(target=read, args=(s,), daemon=True) for s in (p.stdout, p.stderr)]
    for t in readers:
        t.start()
    assert first_asset.wait(300), "".join(lines)
    at_signal = _asset_folders(tmp_path / "artifacts")
    os.kill(p.pid, signal.SIGTERM)
    p.wait(60)
    for t in readers:
        t.join(30)
    time.sleep(1)  # anything still at work would write its asset now
    text = "".join(lines)
    assert p.returncode == EXIT_TERMINATED, text
    assert "Traceback" not in text and "Interrupted" not in text and "SystemError" not in text, text
    assert text.rstrip().splitlines()[-1] == "terminated (SIGTERM); nothing half-written is left", text
    assert "raw_dataset" in at_signal and _asset_folders(tmp_path / "artifacts") == at_signal
    assert not [q for q in (tmp_path / "artifacts").rglob("*") if ".tmp" in q.name]


def test_sigterm_is_passed_on_to_the_workers_of_the_commands_group():
    """A SIGTERM reaches the command's process alone (a Ctrl-C, its whole group): it passes it on to
    its children in its group (pool workers, which end themselves), leaves alone the ones that
    ignore it (multiprocessing's resource tracker) and kills those still running after the grace."""
    script = r"""
import signal, subprocess, sys
from assets import runs
runs.CHILD_GRACE_S = 2.0
code = {
    "ends": "import signal, sys, time; signal.signal(signal.SIGTERM, lambda *a: sys.exit(7))",
    "ignores": "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN)",
    "stuck": "import signal, time; signal.signal(signal.SIGTERM, lambda *a: time.sleep(60))",
}
kids = {k: subprocess.Popen([sys.executable, "-c", c + "; print('ready', flush=True); time.sleep(60)"],
                            stdout=subprocess.PIPE, text=True) for k, c in code.items()}
for k in kids.values():
    k.stdout.readline()
runs.stop_group_children(signal.SIGTERM)
print(kids["ends"].wait(10), kids["ignores"].poll(), kids["stuck"].wait(10))
kids["ignores"].kill()
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["7", "None", str(-signal.SIGKILL)], r.stdout


# ---- atlas-gs ui on a port in use -------------------------------------------------------------


def test_ui_on_a_port_in_use_is_one_line_naming_the_port_not_a_server_serving_nothing(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        env = {**os.environ, "ATLAS_GS_HOME": str(tmp_path), "DAGSTER_HOME": str(tmp_path / "dagster_home")}
        try:
            r = subprocess.run([sys.executable, "-c", CLI, "ui", "--port", str(port)], env=env, cwd=tmp_path,
                               capture_output=True, text=True, timeout=60)
        except subprocess.TimeoutExpired as exc:
            pytest.fail(f"atlas-gs ui kept running on a port in use: {exc.stderr!r}")
    assert r.returncode == EXIT_ERROR, r.stderr
    assert r.stderr.splitlines() == [r.stderr.strip()], r.stderr
    assert f"--port {port}" in r.stderr and f"127.0.0.1:{port} is already in use" in r.stderr, r.stderr
    assert not (tmp_path / "dagster_home").exists()  # nothing set up for a server that cannot start

"""User files, world bundles and transitions stay true under bad input and faults.

Each case is one row of the README's fault table (section "What can go wrong"): the bad input or
fault, what the user sees (exit code and message), and that nothing of theirs was changed.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from assets.cli import main
from atlas_pipeline.errors import BundleFormatError, OutputPolicyError, WriteError
from atlas_pipeline.io_utils import (
    MARKER_NAME,
    ProcessLock,
    LockedError,
    atomic_path,
    check_output_dir,
    check_writable,
    recover_dir,
    sha256_file,
)

FAST = ["--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0"]


def _snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` with its sha256 (what must not change)."""
    return {str(p.relative_to(folder)): sha256_file(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def _dead_pid() -> int:
    """The pid of a process that has exited (for staging names of a 'killed' writer)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.fixture
def world(isolated, capsys):
    w = isolated / "world"
    assert main(["build", "--input", "synth-small", "--output", str(w), *FAST]) == 0
    capsys.readouterr()
    return w


# ---- 1. output policy ----------------------------------------------------------------------------


def _user_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("my thesis\n")
    (path / "sub").mkdir()
    (path / "sub" / "data.csv").write_text("1,2\n")
    return path


@pytest.mark.parametrize("command", ["build", "import-ply"])
def test_output_refuses_a_users_folder(isolated, world, command, caplog):
    target = _user_folder(isolated / "mine")
    before = _snapshot(target)
    argv = (["build", "--input", "synth-small", "--output", str(target), *FAST] if command == "build"
            else ["import-ply", str(world / "gaussians.ply"), "--output", str(target)])
    assert main(argv) == 2
    assert "not written by atlas-gs" in caplog.text and str(target) in caplog.text
    assert _snapshot(target) == before


def test_output_never_replaces_an_input(isolated, small_synthetic, world, caplog):
    data = isolated / "dataset"
    shutil.copytree(small_synthetic, data)
    before = _snapshot(data)
    assert main(["build", "--input", str(data), "--output", str(data), *FAST]) == 2
    assert "input" in caplog.text
    assert main(["build", "--input", str(data / "rgb"), "--output", str(data), *FAST, "--force"]) == 2  # holds it
    assert main(["import-ply", str(world / "gaussians.ply"), "--output", str(world), "--force"]) == 2
    assert main(["build", "--input", "synth-small", "--output", str(world), "--extend", str(world), *FAST]) == 2
    assert _snapshot(data) == before


def test_force_moves_a_foreign_folder_aside_never_deletes(isolated, capsys):
    target = _user_folder(isolated / "mine")
    before = _snapshot(target)
    assert main(["build", "--input", "synth-small", "--output", str(target), *FAST, "--force"]) == 0
    backups = [p for p in isolated.iterdir() if p.name.startswith("mine.replaced-")]
    assert len(backups) == 1 and _snapshot(backups[0]) == before
    assert (target / "metadata.json").is_file()


def test_rebuild_replaces_our_bundle_but_not_one_holding_user_files(isolated, world, caplog):
    assert main(["build", "--input", "synth-small", "--output", str(world), *FAST]) == 0  # our own bundle: fine
    (world / "my_notes.txt").write_text("keep me\n")
    assert main(["build", "--input", "synth-small", "--output", str(world), *FAST]) == 2
    assert "my_notes.txt" in caplog.text and (world / "my_notes.txt").read_text() == "keep me\n"
    # ... and localize does not swap it away either (the new folder would drop the file)
    assert main(["localize", "--world", str(world), "--input", "synth-small"]) == 2
    assert (world / "my_notes.txt").is_file()


@pytest.mark.parametrize("kind", ["file", "symlink"])
def test_output_that_is_a_file_or_link_is_refused(tmp_path, kind):
    real = _user_folder(tmp_path / "real")
    target = tmp_path / "out"
    if kind == "file":
        target.write_text("x")
    else:
        target.symlink_to(real)
    with pytest.raises(OutputPolicyError):
        check_output_dir(target, "world_bundle", force=True)
    assert (real / "notes.txt").is_file()


def test_demo_video_never_overwrites_a_users_file(isolated, world, caplog):
    mine = isolated / "holiday.mp4"
    mine.write_bytes(b"\x00\x00\x00\x18ftypmp42 my own video")
    assert main(["demo-video", "--world", str(world), "--output", str(mine), "--set", "video.orbit_frames=2",
                 "--set", "video.scale=0.25"]) == 2
    assert mine.read_bytes().endswith(b"my own video")
    ours = isolated / "orbit.mp4"
    for _ in range(2):  # our own video may be rewritten
        assert main(["demo-video", "--world", str(world), "--output", str(ours), "--set", "video.orbit_frames=2",
                     "--set", "video.scale=0.25"]) == 0
    from atlas_pipeline.viz.video import is_atlas_video

    assert is_atlas_video(ours) and not is_atlas_video(mine)


# ---- 2. crash-consistent swaps -------------------------------------------------------------------


def _bundle_like(folder: Path, content: str) -> Path:
    folder.mkdir(parents=True)
    (folder / "a.txt").write_text(content)
    (folder / MARKER_NAME).write_text(json.dumps({"writer": "atlas-gs", "kind": "x", "files": ["a.txt"]}))
    return folder


@pytest.mark.parametrize("state, expect", [
    ("tmp_only", "old"),             # killed while writing: the old version stays, the scratch goes
    ("new_written", "old"),           # killed after staging, before the swap: old stays
    ("target_moved_aside", "new"),    # killed between the two renames: roll forward to the new one
    ("only_old_left", "old"),         # killed with no complete new version: roll back
    ("new_in_place_old_left", "new"),  # killed before the old one was removed
])
def test_interrupted_swap_is_repaired_on_next_open(tmp_path, state, expect):
    target = tmp_path / "world"
    pid = _dead_pid()
    tok = f"{pid}-0123abcd"
    tmp, new, old = (tmp_path / f".world.{tok}.{s}" for s in ("tmp", "new", "old"))
    if state == "tmp_only":
        _bundle_like(target, "old")
        _bundle_like(tmp, "half")
    elif state == "new_written":
        _bundle_like(target, "old")
        _bundle_like(new, "new")
    elif state == "target_moved_aside":
        _bundle_like(old, "old")
        _bundle_like(new, "new")
    elif state == "only_old_left":
        _bundle_like(old, "old")
        _bundle_like(tmp, "half")
    else:
        _bundle_like(target, "new")
        _bundle_like(old, "old")
    recover_dir(target)
    assert (target / "a.txt").read_text() == expect
    assert sorted(p.name for p in tmp_path.iterdir()) == ["world"]  # nothing hidden left


def test_staging_of_a_live_writer_is_left_alone(tmp_path):
    target = _bundle_like(tmp_path / "world", "current")
    live = _bundle_like(tmp_path / f".world.{os.getpid()}-0123abcd.tmp", "in progress")
    recover_dir(target)
    assert live.is_dir() and (target / "a.txt").read_text() == "current"


def test_a_process_killed_between_the_renames_leaves_a_whole_folder(tmp_path):
    """A real SIGKILL at the worst moment (after the old folder was moved aside)."""
    target = _bundle_like(tmp_path / "world", "old")
    script = textwrap.dedent(f"""
        import os, signal
        from pathlib import Path
        from atlas_pipeline import io_utils
        real = os.replace
        def dying(a, b):
            real(a, b)
            if str(b).endswith('.old'):
                os.kill(os.getpid(), signal.SIGKILL)
        io_utils.os.replace = dying
        with io_utils.atomic_dir(Path({str(target)!r}), kind="x") as tmp:
            (tmp / "a.txt").write_text("new")
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == -9
    assert not target.exists()  # the moment of the kill: only hidden copies
    recover_dir(target)
    assert (target / "a.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["world"]


# ---- 3. verified bundles -------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["gaussians.ply", "gaussians.bin", "surfels.npz", "places.npz", "world.npz"])
def test_a_flipped_byte_is_reported_never_laundered(isolated, world, name, caplog):
    path = world / name
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    meta_before = (world / "metadata.json").read_bytes()
    assert main(["localize", "--world", str(world), "--input", "synth-small"]) == 2
    assert name in caplog.text and "checksum" in caplog.text
    assert (world / "metadata.json").read_bytes() == meta_before  # never re-hashed into the metadata
    assert main(["log-transitions", "--world", str(world), "--input", "synth-small"]) == 2
    assert main(["build", "--input", "synth-small", "--output", str(isolated / "w2"), "--extend", str(world),
                 *FAST]) == 2
    assert not (isolated / "w2").exists()


@pytest.mark.parametrize("content, message", [
    ("[1, 2]", "JSON object"),
    ('{"format": "atlas-gs-world-bundle", "version": 1, "files": {"gaussians.bin": {"bytes": 10}}}', "sha256"),
    ('{"format": "atlas-gs-world-bundle", "version": 1, "files": {"../etc/passwd": {"bytes": 1, "sha256": "'
     + "0" * 64 + '"}}}', "plain file name"),
    ('{"format": "atlas-gs-world-bundle", "version": 99, "files": {}}', "version"),
    ('{"format": "atlas-gs-world-bundle", "version": 1, "files": {}, "gaussians": {"voxel_size_m": -1}}',
     "voxel_size_m"),
    ("{not json", "invalid JSON at line 1"),
    ("\udcff", "UTF-8"),
])
def test_metadata_is_validated_against_its_schema(tmp_path, content, message):
    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    (tmp_path / "metadata.json").write_bytes(content.encode("utf-8", "surrogateescape"))
    with pytest.raises(BundleFormatError, match=message):
        load_world_bundle(tmp_path)


# ---- 6. registry safety, bad CLI values ----------------------------------------------------------


def test_dataset_add_refuses_existing_names_unless_replace(isolated, small_synthetic, caplog):
    reg = Path(os.environ["ATLAS_LOCAL_REGISTRY"])
    before = reg.read_text()
    intr = ["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120"]
    assert main(["dataset", "add", "synthetic", str(small_synthetic), *intr]) == 2  # the built-in default
    assert "already registered" in caplog.text
    assert main(["dataset", "add", "synth-small", str(small_synthetic), *intr]) == 2  # a local entry
    assert reg.read_text() == before
    assert main(["dataset", "add", "synth-small", str(small_synthetic), *intr, "--replace"]) == 0


@pytest.mark.parametrize("argv, message", [
    (["dataset", "add", "x", "{data}", "--intrinsics", "1 2 3"], "--intrinsics needs 4 finite numbers"),
    (["dataset", "add", "x", "{data}", "--intrinsics", "1 2 3 nan"], "--intrinsics needs 4 finite numbers"),
    (["dataset", "add", "x", "{data}", "--intrinsics", "a b c d"], "--intrinsics needs 4 finite numbers"),
    (["import-ply", "x.ply", "--output", "o", "--voxel", "nan"], "--voxel must be a finite number > 0"),
    (["build", "--input", "synth-small", "--output", "o", "--set", "fusion.max_depth_m=[1"],
     "--set 'fusion.max_depth_m=[1': the value is not valid YAML"),
])
def test_bad_values_are_errors_not_tracebacks(isolated, small_synthetic, capsys, argv, message):
    """Each bad value reaches the option it is about (a real dataset folder, so layout detection
    passes) and the error names that option."""
    assert main([a.format(data=small_synthetic) for a in argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_bad_start_pose_is_an_error_naming_the_option(world, capsys):
    assert main(["localize", "--world", str(world), "--input", "synth-small", "--start-pose", "0 0 0 0 0 0"]) == 2
    err = capsys.readouterr().err
    assert "--start-pose" in err and "Traceback" not in err


# ---- 7. fail fast, name the path -----------------------------------------------------------------


def test_unwritable_output_is_found_before_the_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(WriteError, match=str(blocker)):
        check_writable(blocker / "sub")


def test_full_disk_is_found_before_the_work_and_named(tmp_path, monkeypatch):
    import atlas_pipeline.io_utils as io

    monkeypatch.setattr(io.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10, 10, 1024))
    with pytest.raises(WriteError, match=f"{tmp_path}.*MiB free"):
        check_writable(tmp_path)


def test_an_os_error_while_writing_names_the_file(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(WriteError, match=str(target)):
        with atomic_path(target):
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_run_into_an_unwritable_artifacts_folder_fails_at_once(isolated, monkeypatch, capsys):
    blocker = isolated / "blocker"
    blocker.write_text("x")
    monkeypatch.setenv("ATLAS_ARTIFACTS_DIR", str(blocker / "artifacts"))
    assert main(["run", "synth-small"]) == 2  # refused before any asset runs
    err = capsys.readouterr().err
    assert "ATLAS_ARTIFACTS_DIR" in err and str(blocker) in err and "Traceback" not in err
    assert not (isolated / "artifacts").exists()


# ---- 8. concurrency -------------------------------------------------------------------------------


def _hold_lock_in_another_process(lock: Path, what: str) -> subprocess.Popen:
    """A child process that takes ``lock`` (as ``what``) and sleeps; returns once it holds it.
    The caller kills it (the sleep bounds its life if the test dies first)."""
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import time
            from atlas_pipeline.io_utils import ProcessLock
            ProcessLock({str(lock)!r}).acquire({{"what": {what!r}}})
            print("held", flush=True)
            time.sleep(120)
        """)], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1])
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_a_lock_is_exclusive_across_processes_and_dies_with_its_holder(tmp_path):
    lock = tmp_path / "p.lock"
    holder = _hold_lock_in_another_process(lock, "test holder")
    try:
        with pytest.raises(LockedError, match="test holder"):
            ProcessLock(lock).acquire({"what": "second"})
    finally:
        holder.kill()
        holder.wait()
    assert ProcessLock(lock).acquire({"what": "after the holder died"})
    ProcessLock(lock).release()


def test_a_second_run_of_a_busy_partition_fails_clearly(isolated, capsys):
    lock = isolated / "artifacts" / ".locks" / "synth-small.lock"
    holder = _hold_lock_in_another_process(lock, "Dagster run other-run")
    try:
        assert main(["run", "synth-small"]) == 1
        out = json.loads(capsys.readouterr().out)
        assert any("being materialized by another run" in e and "other-run" in e for e in out["errors"])
        assert out["recomputed"] == []
        assert not (isolated / "artifacts" / "raw_dataset").exists()
    finally:
        holder.kill()
        holder.wait()


def test_runs_whose_process_died_are_marked_failed(isolated):
    from dagster import DagsterInstance, DagsterRun, DagsterRunStatus

    from assets.runs import HOST_TAG, PID_TAG, reap_dead_runs

    import socket

    with DagsterInstance.get() as instance:
        dead = DagsterRun(job_name="atlas_gs_all", run_id="dead0000-0000-0000-0000-000000000000",
                          status=DagsterRunStatus.STARTED,
                          tags={PID_TAG: str(_dead_pid()), HOST_TAG: socket.gethostname()})
        alive = DagsterRun(job_name="atlas_gs_all", run_id="live0000-0000-0000-0000-000000000000",
                           status=DagsterRunStatus.STARTED,
                           tags={PID_TAG: str(os.getpid()), HOST_TAG: socket.gethostname()})
        instance.add_run(dead)
        instance.add_run(alive)
        assert reap_dead_runs(instance) == [dead.run_id]
        assert instance.get_run_by_id(dead.run_id).status == DagsterRunStatus.FAILURE
        assert instance.get_run_by_id(alive.run_id).status == DagsterRunStatus.STARTED


def test_temporary_files_of_a_killed_writer_are_swept(tmp_path):
    target = tmp_path / "report.json"
    stale = tmp_path / f".report.{_dead_pid()}-0123abcd.tmp.json"
    stale.write_text("half")
    live = tmp_path / f".report.{os.getpid()}-0123abcd.tmp.json"
    live.write_text("in progress")
    from atlas_pipeline.io_utils import write_json_atomic

    write_json_atomic(target, {"ok": True})
    assert not stale.exists() and live.exists() and json.loads(target.read_text()) == {"ok": True}


def test_localize_refuses_to_rewrite_a_dagster_artifact_folder(tmp_path):
    """The world_bundle artifact belongs to the IO manager; a CLI update would drop its record."""
    import numpy as np

    from atlas_pipeline.gaussian_world.builder import VoxelGaussianBuilder
    from atlas_pipeline.io_utils import commit_dir, stage_dir
    from atlas_pipeline.scene_memory.bundle import update_world_bundle, write_world_bundle

    b = VoxelGaussianBuilder(0.05)
    rng = np.random.default_rng(0)
    b.integrate(rng.uniform(-1, 1, (2000, 3)), rng.integers(0, 255, (2000, 3)))
    src = write_world_bundle(tmp_path / "src", b.to_field(), {})
    art = tmp_path / "artifact"
    staged = stage_dir(art)
    for p in src.iterdir():
        if p.name != MARKER_NAME:
            shutil.copy2(p, staged / p.name)
    commit_dir(staged, art, "artifact")
    before = _snapshot(art)
    with pytest.raises(BundleFormatError, match="artifact of the Dagster IO manager"):
        update_world_bundle(art)
    assert _snapshot(art) == before


def test_force_on_a_foreign_file_moves_it_aside(tmp_path):
    from atlas_pipeline.io_utils import check_output_file

    mine = tmp_path / "holiday.mp4"
    mine.write_bytes(b"my own video")
    with pytest.raises(OutputPolicyError, match="not written by atlas-gs"):
        check_output_file(mine)
    backup = check_output_file(mine, force=True)
    assert not mine.exists() and backup.read_bytes() == b"my own video"
    assert backup.name.startswith("holiday.replaced-") and backup.suffix == ".mp4"
    with pytest.raises(OutputPolicyError, match="input"):
        check_output_file(tmp_path / "in.mp4", inputs=[tmp_path / "in.mp4"], force=True)

"""Faults and hostile input, second round: a bundle is one recording's truth, content changes and
corrupt caches are noticed, a lost depth frame is a lost frame, interrupts and a bad DAGSTER_HOME
end in one line. Each test is a row of docs/reliability.md's fault table and asserts that the
message names the file, field or option."""

from __future__ import annotations

import json
import os
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from assets.cli import main
from atlas_pipeline.io_utils import MARKER_NAME

# no fit, and a short orbit video: what these tests check does not depend on either
FAST = ["--set", "mapping.fit.epochs=0", "--set", "mapping.colour_refinement.iterations=0", "--set", "video.orbit_frames=8"]
SMALL = {"kind": "synthetic", "seed": 0, "n_frames": 12, "width": 160, "height": 120,
         "fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5}


def _register_other(isolated: Path) -> None:
    """A second recording, ``other`` (the same frames under another name)."""
    reg = isolated / "datasets.local.yaml"
    data = yaml.safe_load(reg.read_text())
    data["datasets"]["other"] = dict(SMALL)
    reg.write_text(yaml.safe_dump(data))


def _parts_named(world: Path) -> dict[str, tuple[str, str]]:
    """(dataset, map) each listed part names, read from the part itself (not its record)."""
    meta = json.loads((world / "metadata.json").read_text())
    named = {}
    for name in meta["files"]:
        if name == "localization.json":
            d = json.loads((world / name).read_text())
            named[name] = (d["dataset"], d["map_id"])
        elif name == "transitions.parquet":
            t = pq.read_table(world / name, columns=["partition", "map_id"])
            assert len(set(t.column("partition").to_pylist())) == 1 and len(set(t.column("map_id").to_pylist())) == 1
            named[name] = (t.column("partition")[0].as_py(), t.column("map_id")[0].as_py())
        rec = meta["files"][name]
        if "dataset" in rec:  # the record says what the part says
            assert (rec["dataset"], rec["map_id"]) == named.get(name, named.get("localization.json")), name
    return named


def _agrees(world: Path) -> None:
    """Every part the bundle lists names the same dataset, and the bundle's own map."""
    meta = json.loads((world / "metadata.json").read_text())
    named = _parts_named(world)
    assert len({d for d, _ in named.values()}) <= 1, named
    assert all(m == meta["map_id"] for _, m in named.values()), (named, meta["map_id"])


@pytest.fixture
def world(isolated, capsys):
    """A bundle of ``synth-small`` with its localization and transitions."""
    _register_other(isolated)
    w = isolated / "world"
    assert main(["build", "--input", "synth-small", "--output", str(w), *FAST]) == 0
    assert main(["localize", "--world", str(w), "--input", "synth-small"]) == 0
    assert main(["log-transitions", "--world", str(w), "--input", "synth-small"]) == 0
    capsys.readouterr()
    _agrees(w)
    return w


# ---- a bundle is one recording's truth -----------------------------------------------------------


@pytest.mark.parametrize("argv, code, says, listed", [
    # another recording's report beside the old one's transitions: refused, naming the file, both datasets, the way out
    (["localize", "--input", "other"], 2, ["transitions.parquet", "'synth-small'", "'other'", "--drop-transitions",
                                           "cp -a"], {"localization.json", "transitions.parquet"}),
    (["localize", "--input", "other", "--drop-transitions"], 0, ["transitions.parquet", "removed"],
     {"localization.json"}),
    # the same recording localized again: its old transitions are the old poses', so they leave, with the command
    (["localize", "--input", "synth-small"], 0, ["transitions.parquet", "log-transitions", "--input synth-small"],
     {"localization.json"}),
    (["log-transitions", "--input", "other"], 2, ["localization.json", "'synth-small'", "'other'"],
     {"localization.json", "transitions.parquet"}),
])
def test_a_bundle_lists_only_parts_of_one_recording(world, capsys, monkeypatch, argv, code, says, listed):
    from atlas_pipeline.localization import localizer

    if code:  # a refusal comes before any frame is localized
        monkeypatch.setattr(localizer, "localize_sequence", lambda *a, **k: pytest.fail("localized before refusing"))
    before = json.loads((world / "metadata.json").read_text())
    assert main([argv[0], "--world", str(world), *argv[1:]]) == code
    err = capsys.readouterr().err
    for word in says:
        assert word in err, (word, err)
    meta = json.loads((world / "metadata.json").read_text())
    assert {n for n in meta["files"] if n in ("localization.json", "transitions.parquet")} == listed
    if code:
        assert meta == before
    _agrees(world)


def test_parts_that_disagree_are_never_written_together(world, small_manifest):
    from atlas_pipeline.errors import BundleFormatError
    from atlas_pipeline.localization.localizer import LocalizationReport
    from atlas_pipeline.scene_memory.bundle import update_world_bundle

    report = LocalizationReport.load(world)
    table = pq.read_table(world / "transitions.parquet")
    other_map = LocalizationReport(**{**report.__dict__, "map_id": "0123456789abcdef"})
    with pytest.raises(BundleFormatError, match="holds map .* the localization to write is for map 0123456789abcdef"):
        update_world_bundle(world, localization=other_map)
    other_set = LocalizationReport(**{**report.__dict__, "dataset": "other"})
    with pytest.raises(BundleFormatError, match="localization.json: is for dataset 'other'; the transitions to write are for 'synth-small'"):
        update_world_bundle(world, localization=other_set, transitions=table)
    _agrees(world)


# ---- a copy of the Dagster artifact is the user's bundle -------------------------------------------


@pytest.fixture(scope="module")
def dagster_project(tmp_path_factory):
    """A project whose ``synth-small`` went through ``atlas-gs run`` once, shared by the tests
    below (a Dagster run is most of their time): they localize into copies of its bundle, or
    change a file and leave the partition current again by rerunning it."""
    from conftest import isolate_project

    with pytest.MonkeyPatch.context() as mp:
        root = isolate_project(tmp_path_factory.mktemp("dagster-project"), mp)
        _register_other(root)
        assert main(["run", "synth-small", *FAST]) == 0
        yield root


@pytest.fixture
def dagster_bundle(dagster_project):
    return dagster_project / "artifacts" / "world_bundle" / "synth-small"


@pytest.mark.slow
@pytest.mark.parametrize("how, code, says", [
    ("artifact", 2, ["world_bundle artifact of the Dagster IO manager", "cp -a", "--world"]),
    ("cp -a", 0, []),
    ("cp -a, marker removed", 0, []),
    ("cp -a, a file of yours added", 2, ["notes.txt", "move them out"]),
])
def test_localizing_into_a_copy_of_the_dagster_bundle(dagster_bundle, tmp_path, capsys, monkeypatch, how, code, says):
    from atlas_pipeline.localization import localizer

    target = dagster_bundle
    if how != "artifact":
        target = tmp_path / "my-world"
        shutil.copytree(dagster_bundle, target, symlinks=True, copy_function=shutil.copy2)
        if "marker" in how:
            (target / MARKER_NAME).unlink()
        if "yours" in how:
            (target / "notes.txt").write_text("mine")
    if code:  # refused before any frame is localized
        monkeypatch.setattr(localizer, "localize_sequence", lambda *a, **k: pytest.fail("localized before refusing"))
    before = sorted(p.name for p in target.iterdir())
    assert main(["localize", "--world", str(target), "--input", "other", "--drop-transitions"]) == code
    err = capsys.readouterr().err
    for word in says:
        assert word in err, (word, err)
    if code:
        assert sorted(p.name for p in target.iterdir()) == before
    else:
        assert json.loads((target / "localization.json").read_text())["dataset"] == "other"
        assert not (target / "_artifact.json").exists()  # the copy is now a bundle of its own
        _agrees(target)
    _agrees(dagster_bundle)


# ---- content changes behind restored sizes and times are noticed -----------------------------------


def _flip_keep_times(path: Path, offset: int | None = None) -> None:
    """One byte changed in place, size and modification time as before (what cp -p, rsync -t and
    tar x leave of an edit)."""
    st = path.stat()
    data = bytearray(path.read_bytes())
    i = len(data) // 2 if offset is None else offset
    data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def _replace_keep_times(path: Path, offset: int, char: str) -> None:
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[offset] = ord(char)
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def _edit(root: Path, how: str) -> None:
    frame = sorted((root / "depth").iterdir())[3]
    st = frame.stat()
    if how == "same bytes rewritten":
        frame.write_bytes(frame.read_bytes())
    elif how == "touched":
        os.utime(frame, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    elif how == "in place, mtime restored (cp -p)":
        _flip_keep_times(frame)
    elif how == "renamed into place, mtime restored (rsync -t)":
        data = bytearray(frame.read_bytes())
        data[-100] ^= 1
        tmp = frame.with_name("." + frame.name + ".rsync")
        tmp.write_bytes(bytes(data))
        os.utime(tmp, ns=(st.st_atime_ns, st.st_mtime_ns))
        os.replace(tmp, frame)
    elif how == "extracted from an archive (tar x)":
        edited = root.parent / "edited.png"
        _flip_keep_times(shutil.copy2(frame, edited))
        with tarfile.open(root.parent / "a.tar", "w") as tar:
            tar.add(edited, arcname=frame.name)
        with tarfile.open(root.parent / "a.tar") as tar:
            tar.extractall(frame.parent, filter="data")  # the test's own archive
    elif how == "a file added":
        (root / "notes.txt").write_text("x")
    else:
        raise AssertionError(how)


@pytest.mark.parametrize("how, changed", [
    ("same bytes rewritten", False), ("touched", False),
    ("in place, mtime restored (cp -p)", True), ("renamed into place, mtime restored (rsync -t)", True),
    ("extracted from an archive (tar x)", True), ("a file added", True),
])
def test_dataset_signature_notices_content_behind_restored_times(small_synthetic, tmp_path, monkeypatch, how, changed):
    from atlas_pipeline import versioning

    root = tmp_path / "rec"
    shutil.copytree(small_synthetic, root)
    cache = tmp_path / "cache"
    before = versioning.dataset_signature(root, cache)
    reads = []
    real = versioning.sha256_file
    monkeypatch.setattr(versioning, "sha256_file", lambda p, *a: reads.append(Path(p).name) or real(p, *a))
    assert versioning.dataset_signature(root, cache) == before and reads == []  # unchanged: stat only, no read
    _edit(root, how)
    assert (versioning.dataset_signature(root, cache) != before) == changed, how
    # bounded cost: only the file whose identity changed was read (none for a new file's neighbours)
    assert len(reads) <= 1, reads
    assert versioning.dataset_signature(root) == versioning.dataset_signature(root, cache)  # the cache changes nothing


def test_dataset_signature_never_opens_a_fifo(small_synthetic, tmp_path):
    from atlas_pipeline.versioning import dataset_signature

    root = tmp_path / "rec"
    shutil.copytree(small_synthetic, root)
    before = dataset_signature(root)
    os.mkfifo(root / "pipe")
    assert dataset_signature(root, tmp_path / "cache") != before  # returns: it was not opened


def _status(capsys, partition: str = "synth-small") -> tuple[int, str]:
    code = main(["status", partition, *FAST])
    out = capsys.readouterr()
    return code, out.out + out.err


# Full tier only: every case reruns part of the shared Dagster run (the dataset side's quick check
# is test_dataset_signature_notices_content_behind_restored_times).
@pytest.mark.slow
@pytest.mark.parametrize("what, path, stale, says", [
    ("a ground-truth pose, mtime restored", "data/synth-small/groundtruth.txt", "raw_dataset",
     "dataset files changed"),
    ("world.npz of the cached world, mtime restored", "artifacts/gaussian_world/synth-small/world.npz",
     "gaussian_world", "artifact files changed"),
    ("surfels.npz of the bundle, mtime restored", "artifacts/world_bundle/synth-small/surfels.npz",
     "world_bundle", "artifact files changed"),
])
def test_a_changed_byte_behind_a_restored_mtime_is_stale_and_recomputed(dagster_project, capsys, what, path, stale, says):
    from atlas_pipeline.versioning import verify_files

    code, text = _status(capsys)
    assert code == 0 and "current" in text, text
    target = dagster_project / path
    if target.suffix == ".txt":  # the last digit of the last quaternion: 1e-7 off, the file still reads
        text = target.read_text()
        i = len(text.rstrip("\n")) - 1
        _replace_keep_times(target, i, "1" if text[i] != "1" else "2")
    else:
        _flip_keep_times(target)
    code, text = _status(capsys)
    assert stale in text and says in text and "all current" not in text, text
    assert main(["run", "synth-small", *FAST]) == 0
    out = json.loads(capsys.readouterr().out)
    assert stale in out["recomputed"], out
    if "artifacts" in path:  # recomputed: the cached files are whole again
        art = target.parent
        assert verify_files(art, json.loads((art / "_artifact.json").read_text())["files"])[0]


# ---- status of a partition whose folder is gone ---------------------------------------------------


@pytest.mark.slow
def test_status_of_a_deleted_partition_folder_says_so_and_its_advice_works(isolated, small_synthetic, capsys):
    import shlex

    rec = isolated / "mine"
    shutil.copytree(small_synthetic, rec)
    camera = ["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120"]
    assert main(["dataset", "add", "mine", str(rec), "--kind", "tum", *camera]) == 0
    assert main(["run", "mine", *FAST]) == 0
    capsys.readouterr()
    moved = rec.rename(isolated / "mine-moved")
    for argv in (["status", "mine", *FAST], ["run", "mine", "--stale-only", *FAST]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        for word in (str(rec), "is missing", "atlas-gs dataset add mine PATH --replace"):
            assert word in err, (argv, word, err)
    # the advice: register where it is now; status then names the run that recomputes, and it works
    assert main(["dataset", "add", "mine", str(moved), "--kind", "tum", *camera, "--replace"]) == 0
    code, text = _status(capsys, "mine")
    assert code == 0 and "raw_dataset" in text, text
    command = text[text.index("`") + 1:text.index("`", text.index("`") + 1)]
    assert command.startswith("atlas-gs run mine --stale-only --set mapping.fit.epochs=0"), command
    assert main(shlex.split(command)[1:]) == 0
    capsys.readouterr()
    code, text = _status(capsys, "mine")
    assert code == 0 and "all 9 assets current" in text, text


# ---- Ctrl-C: one line, status 130 ------------------------------------------------------------------

SIG_SYNTH = {**SMALL, "seed": 1, "n_frames": 120, "width": 320, "height": 240,
             "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}


@pytest.fixture(scope="module")
def interrupt_env(tmp_path_factory):
    """A project of its own for the interrupted commands: a 120-frame recording (long enough to be
    interrupted mid-way) and a world of it."""
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("interrupt")
    reg = root / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {"sig": SIG_SYNTH}}))
    env = {**os.environ, "ATLAS_DATA_DIR": str(root / "data"), "ATLAS_ARTIFACTS_DIR": str(root / "artifacts"),
           "ATLAS_LOCAL_REGISTRY": str(reg), "DAGSTER_HOME": str(root / "dagster_home")}
    subprocess.run([sys.executable, "-c", CLI, "build", "--input", "sig", "--output", str(root / "world"), *FAST],
                   env=env, check=True, capture_output=True, cwd=root)
    return root, env


CLI = "import sys; from assets.cli import command; sys.exit(command())"


@pytest.mark.parametrize("argv, ready", [
    pytest.param(["-v", "build", "--input", "sig", "--output", "{root}/new-world"], "RGB-D frames",
                 marks=pytest.mark.slow),
    pytest.param(["run", "sig"], "keyframes", marks=pytest.mark.slow),
    pytest.param(["-v", "localize", "--world", "{root}/world", "--input", "sig"], "RGB-D frames", marks=pytest.mark.slow),
    pytest.param(["-v", "demo-video", "--world", "{root}/world", "--output", "{root}/orbit.mp4",
                  "--set", "video.orbit_frames=2000"], "orbit video path", marks=pytest.mark.slow),
    pytest.param(["view", "{root}/world", "--port", "0", "--no-dataset"], "open http", marks=pytest.mark.slow),
])
def test_ctrl_c_ends_with_one_line_and_status_130(interrupt_env, argv, ready):
    """SIGINT to the whole process group (what a terminal's Ctrl-C sends), once the command is at work."""
    import signal
    import subprocess
    import sys
    import threading

    root, env = interrupt_env
    before = _snapshot(root)
    argv = [a.format(root=root) for a in argv]
    # A command typed in a terminal: SIGINT at its default, even when the test runs in the
    # background (which ignores SIGINT, and a command keeps an ignored SIGINT ignored).
    p = subprocess.Popen([sys.executable, "-c", CLI, *argv], env=env, cwd=root, start_new_session=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines: list[str] = []
    at_work = threading.Event()

    def read(stream) -> None:
        for line in stream:
            lines.append(line)
            if ready in line:
                at_work.set()

    readers = [threading.Thread(target=read, args=(s,), daemon=True) for s in (p.stdout, p.stderr)]
    for t in readers:
        t.start()
    assert at_work.wait(180), "".join(lines)
    os.killpg(p.pid, signal.SIGINT)
    p.wait(60)
    for t in readers:  # until every process holding the pipes (Dagster's log mirrors too) is gone
        t.join(30)
    text = "".join(lines)
    assert p.returncode == 130, text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
    assert text.rstrip().splitlines()[-1] == "interrupted; nothing half-written is left", text
    after = _snapshot(root)
    new = sorted(set(after) - set(before))
    # nothing half-written: no staging, no new output (a Dagster run's finished stages are whole artifacts)
    assert not [n for n in new if ".tmp" in n or n.startswith(("new-world", "orbit"))], new
    assert all(after[n] == before[n] for n in before if not n.startswith(("artifacts", "dagster_home", "data"))), \
        "a file that was there changed"


@pytest.mark.slow
def test_ctrl_c_while_a_video_is_encoded_leaves_no_temporary_file_and_no_ffmpeg_lines(interrupt_env):
    """Interrupted once ffmpeg (in a process group of its own, which the Ctrl-C does not reach) is
    writing the video: it is stopped with the command, its temporary MP4 removed, no line of its own."""
    import signal
    import subprocess
    import sys
    import time

    root, env = interrupt_env
    out = root / "encoded" / "orbit.mp4"
    out.parent.mkdir()
    p = subprocess.Popen([sys.executable, "-c", CLI, "demo-video", "--world", str(root / "world"), "--output",
                          str(out), "--set", "video.orbit_frames=2000"], env=env, cwd=root, start_new_session=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 180
    while not [f for f in out.parent.iterdir() if f.name.endswith(".tmp.mp4") and f.stat().st_size > 0]:
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=60)
    time.sleep(1)  # an ffmpeg left running would finish its file (or complain) now
    assert p.returncode == 130, err
    assert err.rstrip().splitlines() == ["interrupted; nothing half-written is left"], err
    assert list(out.parent.iterdir()) == [], sorted(out.parent.iterdir())


def test_interrupt_stops_detached_children_but_the_log_mirrors():
    """What Ctrl-C stops: this process's children in process groups of their own (ffmpeg), not
    Dagster's log mirrors, which carry the command's last line to the terminal."""
    import subprocess

    from assets import runs

    ffmpeg_like = subprocess.Popen(["sleep", "60"], process_group=0)
    mirror = runs._DetachedSubprocess.Popen(["sleep", "60"])
    same_group = subprocess.Popen(["sleep", "60"])  # gets the terminal's SIGINT itself
    try:
        assert {ffmpeg_like.pid, mirror.pid} <= set(runs.detached_children())
        assert same_group.pid not in runs.detached_children()
        runs.stop_detached_children()
        assert ffmpeg_like.poll() is not None or ffmpeg_like.wait(5) is not None
        assert mirror.poll() is None and same_group.poll() is None
    finally:
        for child in (ffmpeg_like, mirror, same_group):
            child.kill()
            child.wait()
        runs._LOG_MIRRORS.discard(mirror.pid)


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_size for p in folder.rglob("*") if p.is_file()}


# ---- DAGSTER_HOME ---------------------------------------------------------------------------------


@pytest.mark.parametrize("home, says", [
    ("relative/home", ["DAGSTER_HOME=relative/home", "must be an absolute path"]),
    ("{tmp}/a-file", ["a-file is a file, not a folder"]),
    ("{tmp}/a-file/home", ["a-file", "Not a directory"]),
    ("{tmp}/full/home", ["DAGSTER_HOME={tmp}/full/home", "MiB free"]),
    ("{tmp}/damaged", ["DAGSTER_HOME={tmp}/damaged", "file is not a database", "move the folder aside"]),
])
def test_a_bad_dagster_home_is_one_line_naming_the_path(isolated, capsys, monkeypatch, home, says):
    from atlas_pipeline import io_utils

    tmp = isolated
    (tmp / "a-file").write_text("mine")
    if "full" in home:  # the disk holding it has 1 MiB left
        real = io_utils.shutil.disk_usage
        monkeypatch.setattr(io_utils.shutil, "disk_usage", lambda p: real(p)._replace(free=1 << 20))
    if "damaged" in home:
        (tmp / "damaged" / "history").mkdir(parents=True)
        (tmp / "damaged" / "history" / "runs.db").write_bytes(os.urandom(4096))
    monkeypatch.chdir(tmp)
    before = sorted(p.relative_to(tmp) for p in tmp.rglob("*"))
    monkeypatch.setenv("DAGSTER_HOME", home.format(tmp=tmp))
    assert main(["status", "synth-small"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for word in says:
        assert word.format(tmp=tmp) in err, (word, err)
    assert sorted(p.relative_to(tmp) for p in tmp.rglob("*") if "dagster" not in str(p.relative_to(tmp))) == \
        [b for b in before if "dagster" not in str(b)]  # no folder left behind


# ---- depth that drops out inside a recording ------------------------------------------------------


def _zero_depth(root: Path, frames: list[int]) -> list[Path]:
    import numpy as np
    from PIL import Image

    paths = sorted((root / "depth").iterdir())
    for i in frames:
        a = np.asarray(Image.open(paths[i]))
        Image.fromarray(np.zeros_like(a)).save(paths[i])
    return [paths[i] for i in frames]


@pytest.mark.parametrize("frames, refused", [
    ([4, 5], False),            # a few frames covered: those frames are lost, the run goes on
    ([0], False),               # the very first frame: the anchor moves on to one with depth
    ([1, 2, 3, 4, 5, 6, 7], True),  # 5 of 12 frames with depth: too few to map
])
def test_frames_without_depth_are_lost_frames(isolated, small_synthetic, capsys, caplog, frames, refused):
    import pandas as pd

    rec = isolated / "dropout"
    shutil.copytree(small_synthetic, rec)
    zeroed = _zero_depth(rec, frames)
    camera = ["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120"]
    assert main(["dataset", "add", "dropout", str(rec), "--kind", "tum", *camera]) == 0
    world = isolated / "world"
    code = main(["build", "--input", "dropout", "--output", str(world), *FAST])
    err = capsys.readouterr().err
    if refused:
        assert code == 2 and zeroed[0].name in err and "no valid pixel" in err and "too few" in err, err
        assert not world.exists()
        return
    assert code == 0, err
    assert zeroed[0].name in err and "no_depth" in err, err  # the warning names the frames and what happens
    if frames == [0]:
        return  # (a world's anchor frame is its first keyframe: localizing from frame 0 is another matter)
    assert main(["localize", "--world", str(world), "--input", "dropout"]) == 0
    assert main(["log-transitions", "--world", str(world), "--input", "dropout"]) == 0
    capsys.readouterr()
    report = json.loads((world / "localization.json").read_text())
    assert [f["frame_id"] for f in report["frames"] if f["status"] == "lost"] == frames
    assert report["summary"]["no_depth_frames"] == frames
    df = pd.read_parquet(world / "transitions.parquet")
    touched = {i for f in frames for i in (f - 1, f)}
    for _, row in df.iterrows():
        assert ("no_depth" in row["valid_reason"]) == (row["step"] in touched), row
        if row["step"] in touched:
            assert not row["valid"] and pd.isna(row["action_vx_mps"]), row
        if row["frame_id_before"] in frames:  # no pose: the pose columns of a lost frame are NaN
            assert pd.isna(row["before_x_m"]), row


# ---- the rotation error after an ill-posed alignment ----------------------------------------------


def _path(kind: str, n: int = 12):
    import numpy as np

    from atlas_pipeline.geometry import pose_from_tq

    rng = np.random.default_rng(3)
    s = np.linspace(0, 0.3, n)
    across = {"straight": 0.0, "near straight": 1e-3, "curved": 0.15}[kind]
    t = np.stack([s, across * np.sin(s * 20), across * np.cos(s * 15)], 1)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    gt = pose_from_tq(t, q)
    est = gt.copy()
    est[:, :3, 3] += 1e-3 * rng.standard_normal((n, 3))  # 1 mm of tracking noise, no rotation error
    return est, gt


@pytest.mark.parametrize("kind, reported", [("straight", False), ("near straight", False), ("curved", True)])
def test_rotation_error_is_reported_only_where_the_alignment_fixes_the_rotation(kind, reported):
    import math

    from atlas_pipeline.localization.localizer import grade
    from atlas_pipeline.localization.metrics import ate

    est, gt = _path(kind)
    a = ate(est, gt)
    summary, _, err_r = grade(np.arange(len(est)) / 30.0, est, ["tracked"] * len(est), gt)
    assert summary["rmse_rot_unaligned_deg"] < 1e-9  # the unaligned figure stays, and is right
    if reported:
        assert a["rot_note"] is None and "ate_rot_note" not in summary and summary["ate_rot_rmse_deg"] < 3.0
    else:
        assert math.isnan(a["rot_rmse_deg"]) and math.isnan(summary["ate_rot_rmse_deg"]) and np.isnan(err_r).all()
        for word in ("near straight", "uncertain by", "unaligned rotation error"):
            assert word in summary["ate_rot_note"], summary["ate_rot_note"]


@pytest.mark.slow
def test_a_revisit_with_its_fused_frames_reports_its_empty_depth_images_once(small_synthetic, tmp_path, caplog):
    """The Dagster revisit fuses the recording (which reports the frames without depth), then
    tracks it into the first world: the same frames are not reported a second time."""
    import logging

    from atlas_pipeline.config import load_profile
    from atlas_pipeline.mapping.mapper import build_gaussian_world, extend_world_with_visit, select_keyframes_stage
    from atlas_pipeline.perception.rgbd import fuse
    from atlas_pipeline.sensors.synthetic import SyntheticSpec
    from atlas_pipeline.sensors.tum import load_tum_sequence
    from tests.conftest import SMALL_SYNTH

    cfg = load_profile("default").with_overrides({"mapping.pose_source": "estimated", "mapping.fit.epochs": 0,
                                                  "mapping.colour_refinement.iterations": 0})
    camera = SyntheticSpec(**SMALL_SYNTH).camera()
    first = load_tum_sequence(small_synthetic, camera, "synth-small")
    fused_first = fuse(first, cfg)
    world = build_gaussian_world(fused_first, select_keyframes_stage(first, fused_first, cfg), cfg)
    rec = tmp_path / "again"
    shutil.copytree(small_synthetic, rec)
    zeroed = _zero_depth(rec, [3])
    again = load_tum_sequence(rec, camera, "again")
    with caplog.at_level(logging.WARNING):
        fused = fuse(again, cfg)
        extend_world_with_visit(world, again, fused, cfg)
    reports = [r for r in caplog.records if "no valid pixel" in r.getMessage()]
    assert len(reports) == 1 and zeroed[0].name in reports[0].getMessage()


def test_extending_with_a_recording_short_of_depth_names_its_images(isolated, small_synthetic, capsys):
    """``build --extend`` tracks into the saved world without a fusion pass of its own; a recording
    whose depth images are mostly empty is still refused, naming the first of them."""
    rec = isolated / "dropout"
    shutil.copytree(small_synthetic, rec)
    zeroed = _zero_depth(rec, [1, 2, 3, 4, 5, 6, 7])
    camera = ["--intrinsics", "131.25 131.25 79.5 59.5", "--width", "160", "--height", "120"]
    assert main(["dataset", "add", "dropout", str(rec), "--kind", "tum", *camera]) == 0
    world = isolated / "world"
    estimated = ["--set", "mapping.pose_source=estimated"]
    assert main(["build", "--input", "synth-small", "--output", str(world), *FAST, *estimated]) == 0
    capsys.readouterr()
    out = isolated / "extended"
    code = main(["build", "--input", "dropout", "--output", str(out), "--extend", str(world), *FAST, *estimated])
    err = capsys.readouterr().err
    assert code == 2 and zeroed[0].name in err and "no valid pixel" in err and "too few" in err, err
    assert not out.exists()

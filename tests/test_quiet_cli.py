"""A quiet, honest command line. Progress bars on a terminal (plain lines elsewhere),
Dagster's chatter only with -v, one short log format, final paths only, `status` in words, and
download presets that become partitions once fetched (tested against a server on 127.0.0.1)."""

from __future__ import annotations

import functools
import http.server
import io
import json
import logging
import threading

import pytest
import yaml

from assets.cli import ASSET_ORDER, main
from assets.cli.pipeline import run_words, status_words
from atlas_pipeline.progress import Progress, Terminal, use_terminal

QUICK = ["--set", "mapping.fit.epochs=0", "--set", "video.orbit_frames=4"]
MAX_QUIET_LINES = 30
DAGSTER_PREFIX = " - atlas_gs_all - "  # Dagster's console format: "<time> - dagster - DEBUG - atlas_gs_all - <run id> - ..."


# ---- the progress bar -----------------------------------------------------------------------------


def test_progress_not_a_terminal_gives_plain_lines_and_keeps_the_explicit_log(caplog):
    stream = io.StringIO()
    run_log: list[str] = []
    with caplog.at_level(logging.INFO, logger="atlas_pipeline"):
        with use_terminal(Terminal(stream, is_tty=False, plain_every_s=0.0)):
            p = Progress("fusing frames", 4, run_log.append, every_s=0.0)
            for _ in range(4):
                p.update(extra="0 lost")
            q = Progress("library default", 2)  # no explicit log: the terminal shows it, logging does not
            q.update()
            q.update()
    text = stream.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    assert lines[0].startswith("fusing frames: 1/4 frames (") and "frames/s" in lines[0]
    assert lines[3].startswith("fusing frames: 4/4 frames (") and "0 lost" in lines[3]
    assert any(line.startswith("library default: 2/2") for line in lines)
    # the Dagster run log keeps its plain lines (the same ones; rates read a moment apart)
    assert len(run_log) == 4 and run_log[-1].split("(")[0] == lines[3].split("(")[0]
    assert not [r for r in caplog.records if "library default" in r.getMessage()]


def test_progress_not_a_terminal_is_periodic():
    stream = io.StringIO()
    with use_terminal(Terminal(stream, is_tty=False, plain_every_s=3600.0)):
        p = Progress("short loop", 50, lambda m: None)
        for _ in range(50):
            p.update()
    assert stream.getvalue() == ""  # shorter than one period: no line at all


class _Clock:
    """A ``time`` stand-in whose ``perf_counter`` moves only when the test says so."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def perf_counter(self) -> float:
        return self.now_s


def test_progress_on_a_terminal_redraws_one_line_with_rate_and_eta(monkeypatch):
    import atlas_pipeline.progress as progress

    clock = _Clock()
    monkeypatch.setattr(progress, "time", clock)
    stream = io.StringIO()
    with use_terminal(Terminal(stream, is_tty=True, width=120)) as term:
        p = Progress("rendering orbit video", 3, lambda m: None)
        clock.now_s += 1.0
        p.update()
        clock.now_s += 1.5 * progress.BAR_REDRAW_S  # past the redraw interval
        p.update()
        assert "\n" not in stream.getvalue()  # redrawn in place, never a new line
        term.write_line("a log line")  # clears the bar first
        clock.now_s += 1.5 * progress.BAR_REDRAW_S
        p.update()
    text = stream.getvalue()
    draws = [d for d in text.split("\r") if d]
    assert "1/3 frames" in draws[0] and "frames/s" in draws[0] and "ETA" in draws[0]
    assert "2/3 frames" in draws[1] and "ETA" in draws[1]
    assert "\x1b[Ka log line\n" in text
    # finished: not drawn again, nothing left on screen (the stage's summary line follows)
    assert text.endswith("a log line\n") and "3/3" not in text


def test_progress_kept_when_finished_and_cleared_when_stopped_early():
    stream = io.StringIO()
    with use_terminal(Terminal(stream, is_tty=True, width=120, keep_finished=True)):
        with Progress("fit", 2, unit="steps") as p:
            p.update()
            p.update()
    assert stream.getvalue().endswith("\n") and "2/2 steps" in stream.getvalue() and " in " in stream.getvalue()
    stream = io.StringIO()
    with use_terminal(Terminal(stream, is_tty=True, width=120)):
        with Progress("fit", 600, unit="steps") as p:  # a plateau stop after 2 of 600
            p.update()
            p.update()
    assert stream.getvalue().endswith("\r\x1b[K")


def test_progress_counts_megabytes():
    stream = io.StringIO()
    with use_terminal(Terminal(stream, is_tty=False, plain_every_s=0.0)):
        p = Progress("downloading x.tgz", 0.3, lambda m: None, unit="MB")
        for _ in range(3):
            p.update(0.1)  # 0.1 + 0.1 + 0.1 < 0.3 in floating point: still finishes
    assert "0.3/0.3 MB" in stream.getvalue().splitlines()[-1]


# ---- words for people ------------------------------------------------------------------------------


def test_status_words():
    assert status_words("synthetic", {}) == f"synthetic: all {len(ASSET_ORDER)} assets current"
    text = status_words("synthetic", {"world_bundle": ["transitions will be recomputed (may change)"],
                                       "transitions": ["settings changed: transitions.x 1 -> 2"]})
    lines = text.splitlines()
    assert lines[0].startswith("synthetic: 2 of 9 assets would be recomputed")
    assert lines[1].split()[0] == "transitions" and "settings changed" in lines[1]  # pipeline order
    assert lines[2].split()[0] == "world_bundle"


def test_failed_run_in_words_names_only_what_exists_and_says_which_is_older(tmp_path):
    bundle = tmp_path / "world_bundle" / "p"
    summary = {"partition": "p", "success": False, "run_id": "r1", "recomputed": ["raw_dataset"], "reused": [],
               "world_bundle": str(bundle), "videos": [], "errors": ["gaussian_world: out of memory"]}
    text = run_words(summary)
    assert "run failed" in text and "gaussian_world: out of memory" in text
    assert f"{bundle}  (from an earlier run)" in text
    assert "video" not in text and "transitions" not in text


# ---- a whole run, quiet and with -v ----------------------------------------------------------------


def _seen_telemetry_notice(home) -> None:
    """Dagster prints its telemetry notice once per DAGSTER_HOME (17 lines, its own; not hidden by
    atlas-gs): mark it shown so the count below is the run's own output."""
    (home / ".telemetry").mkdir(exist_ok=True)
    (home / ".telemetry" / "id.yaml").write_text("instance_id: test\n")


@pytest.mark.slow
def test_run_is_quiet_by_default_and_says_more_with_v(isolated, capsys):
    _seen_telemetry_notice(isolated / "dagster_home")
    assert main(["run", "synth-small", *QUICK]) == 0
    cap = capsys.readouterr()
    err = cap.err.splitlines()
    assert len(err) < MAX_QUIET_LINES, cap.err
    assert "DEBUG" not in cap.err and "debug:" not in cap.err
    for noise in ("BetaWarning", "alembic", "Context impl", DAGSTER_PREFIX, "dagster.yaml", ".tmp", "staging"):
        assert noise not in cap.err, noise
    for asset in ASSET_ORDER:  # one line per stage
        assert sum(line.split()[0] == asset for line in err if line.strip()) == 1, (asset, cap.err)
    out = json.loads(cap.out)  # stdout is not a terminal: the JSON it always was
    assert out["success"] and len(out["videos"]) == 3
    from pathlib import Path

    assert all(Path(v).is_file() for v in out["videos"])

    # -v: Dagster's events, in the same short format, and warnings at most once each
    assert main(["run", "synth-small", *QUICK, "-v"]) == 0
    verbose = capsys.readouterr().err
    assert "STEP_SUCCESS" in verbose and "debug: raw_dataset: STEP_START" in verbose
    assert DAGSTER_PREFIX not in verbose
    warned = [line for line in verbose.splitlines() if "Warning:" in line]
    assert len(warned) == len(set(warned))

    assert main(["status", "synth-small", *QUICK]) == 0
    assert capsys.readouterr().out.strip() == f"synth-small: all {len(ASSET_ORDER)} assets current"
    assert main(["status", "synth-small", *QUICK, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"synth-small": {}}
    assert main(["status", "synth-small", *QUICK, "--set", "localization.photometric_weight=0.5"]) == 0
    text = capsys.readouterr().out
    assert "would be recomputed" in text and "localization_report  settings changed" in text


_LAST_LINE_SCRIPT = """
import logging, sys, tempfile
from dagster import DagsterInstance, asset, materialize
from assets.cli.output import CliOutput

@asset
def last_words():
    logging.getLogger("atlas_gs.cli").info("the step's last line")

with tempfile.TemporaryDirectory() as home, DagsterInstance.local_temp(home) as instance, CliOutput(False):
    assert materialize([last_words], instance=instance).success
"""


MIRROR_LAG_S = 5  # longer than the one-asset run takes on a loaded machine


@pytest.mark.slow
def test_a_line_logged_at_the_end_of_a_step_reaches_stderr_however_late_dagsters_log_mirror_is(tmp_path):
    """During a run Dagster points fd 2 at a compute-log file and mirrors that file back with
    ``tail -F``, stopped as the run ends: what the mirror had not read yet (a loaded machine) was
    lost, a stage's line among it. A mirror that lags behind, here by longer than the run, loses
    none of the command's lines."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    lagging_tail = bin_dir / "tail"
    # starts reading after MIRROR_LAG_S; stopped before that, it leaves no sleep behind
    lagging_tail.write_text(f"#!/bin/sh\ntrap 'kill $!; exit 0' TERM\nsleep {MIRROR_LAG_S} & wait $!\n"
                            f"exec {shutil.which('tail')} \"$@\"\n")
    lagging_tail.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    done = subprocess.run([sys.executable, "-c", _LAST_LINE_SCRIPT], capture_output=True, text=True, env=env,
                          cwd=Path(__file__).resolve().parents[1], timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stderr.splitlines().count("the step's last line") == 1, done.stderr


# ---- download presets become partitions once fetched ----------------------------------------------


@pytest.fixture
def local_server(tmp_path):
    """Static files from a temporary folder on 127.0.0.1 (no network)."""
    root = tmp_path / "www"
    root.mkdir()
    httpd = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root)))
    httpd.daemon_threads = True
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


def _register_preset(isolated, name: str, url: str) -> None:
    reg = isolated / "datasets.local.yaml"
    data = yaml.safe_load(reg.read_text())
    data["datasets"][name] = {"kind": "tum", "camera": "freiburg1", "path": name, "url": url}
    reg.write_text(yaml.safe_dump(data))


def _partitions() -> set[str]:
    """The partitions of the definitions as they load now (read from the registry)."""
    from assets.definitions import build_definitions, loaded_partitions

    return set(loaded_partitions(build_definitions()))


def test_a_preset_is_a_partition_only_once_fetched(isolated, local_server, capsys):
    from test_download import make_tgz

    root, base = local_server
    make_tgz(root / "seq.tgz")
    _register_preset(isolated, "preset-a", f"{base}/seq.tgz")

    assert main(["dataset", "sync"]) == 0  # kept for scripts: says which are partitions, changes nothing
    out = json.loads(capsys.readouterr().out)
    assert "synth-small" in out["partitions"] and "synthetic" in out["partitions"]
    assert "preset-a" not in out["partitions"] and "dataset fetch preset-a" in out["not_partitions"]["preset-a"]
    assert not {"tum-fr1-xyz", "tum-fr1-desk", "tum-fr3-teddy"} & set(out["partitions"])  # built-in presets, not fetched
    assert main(["dataset", "sync", "preset-a"]) == 0
    assert json.loads(capsys.readouterr().out)["partitions"] == []
    assert "preset-a" not in _partitions()
    assert main(["dataset", "list"]) == 0
    assert "not fetched" in next(line for line in capsys.readouterr().out.splitlines() if line.startswith("preset-a"))

    from dagster import build_sensor_context, DagsterInstance

    from assets.definitions import build_definitions

    sensor = build_definitions().resolve_sensor_def("dataset_registry_sensor")
    with DagsterInstance.get() as instance:
        assert "preset-a" not in sensor(build_sensor_context(instance=instance)).skip_message

    assert main(["dataset", "fetch", "preset-a"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["fetched"] and out["partition_added"]
    assert (isolated / "data" / "preset-a" / "rgb.txt").is_file()
    assert "preset-a" in _partitions()
    with DagsterInstance.get() as instance:  # the definitions loaded before the fetch do not have it yet
        assert "until the code location reloads: preset-a" in sensor(build_sensor_context(instance=instance)).skip_message
    assert main(["dataset", "fetch", "preset-a"]) == 0  # on disk already: nothing downloaded again
    assert json.loads(capsys.readouterr().out)["fetched"] is False


def test_a_preset_partition_of_an_older_atlas_gs_is_no_partition_before_it_is_fetched(isolated, local_server, capsys):
    from dagster import DagsterInstance

    _, base = local_server
    _register_preset(isolated, "preset-b", f"{base}/absent.tgz")
    with DagsterInstance.get() as instance:  # what an older atlas-gs did: every preset a dynamic partition
        instance.add_dynamic_partitions("datasets", ["preset-b"])
    assert "preset-b" not in _partitions()  # the instance's dynamic partitions are no longer read


def test_a_run_of_a_preset_that_cannot_be_downloaded_fails_clearly_and_adds_no_partition(isolated, local_server,
                                                                                          capsys):
    _, base = local_server
    _register_preset(isolated, "preset-c", f"{base}/absent.tgz")
    assert main(["run", "preset-c"]) == 2
    err = capsys.readouterr().err
    assert "absent.tgz" in err and "404" in err
    assert "preset-c" not in _partitions()
    assert not (isolated / "data" / "preset-c").exists()

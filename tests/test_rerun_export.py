"""``atlas-gs view WORLD --rrd FILE``: a Rerun recording of a bundle and its sequence, read back with
Rerun's own ``rerun rrd print``."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections import Counter
from pathlib import Path

import pytest

pytest.importorskip("rerun", reason="the Rerun SDK is not installed (pip install -e '.[dev]')")
pytest.importorskip("viser", reason="viser is not installed (pip install -e .)")

from assets.cli import main  # noqa: E402
from tests.test_viewer import KEYFRAMES, LOST, viewer_world  # noqa: E402,F401  (the fixture)

CHUNK_LINE = re.compile(r"with (\d+) rows .* - (/\S+) - data columns: \[(.*)\]")


def _rows(rrd: Path) -> tuple[Counter, dict[str, set[str]]]:
    """``(rows per entity path, columns per entity path)`` of a recording, from ``rerun rrd print``."""
    exe = shutil.which("rerun")
    if exe is None:
        pytest.skip("the rerun command is not on PATH")
    env = {**os.environ, "RERUN_ANALYTICS": "0"}  # no usage-data prompt in the output
    out = subprocess.run([exe, "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    rows, cols = Counter(), {}
    for m in CHUNK_LINE.finditer(out.stdout):
        rows[m.group(2)] += int(m.group(1))
        cols.setdefault(m.group(2), set()).update(m.group(3).split())
    return rows, cols


def test_recording_holds_world_trajectories_and_every_frame(viewer_world, small_manifest, tmp_path):
    (tmp_path / "rec").mkdir()
    out = tmp_path / "rec" / "seq.rrd"
    assert main(["view", str(viewer_world), "--rrd", str(out)]) == 0
    rows, cols = _rows(out)
    n = small_manifest.n_frames
    assert "GaussianSplats3D:centers" in cols["/world/gaussians"] and rows["/world/gaussians"] == 1
    assert rows["/world/trajectory/estimated"] == 1 and rows["/world/trajectory/ground_truth"] == 1
    assert rows["/world/keyframes"] == 1
    assert rows["/status"] == n and rows["/status/lost"] == n
    assert rows["/world/camera"] == n - 1  # the lost frame was never placed: no pose for it
    assert rows["/world/camera/image/rgb"] == n and rows["/world/camera/image/depth"] == n
    assert any("Pinhole" in c for c in cols["/world/camera/image"])
    assert [p.name for p in out.parent.iterdir()] == ["seq.rrd"]  # no temporary file left beside it


def test_frame_step_and_existing_files(viewer_world, tmp_path, capsys):
    from atlas_pipeline.errors import ConfigError

    out = tmp_path / "seq.rrd"
    assert main(["view", str(viewer_world), "--rrd", str(out), "--frame-step", "4", "--no-dataset"]) == 0
    rows, _ = _rows(out)
    assert rows["/status"] == 3 and "/world/camera/image/rgb" not in rows  # frames 0, 4, 8; no images
    before = out.read_bytes()
    assert main(["view", str(viewer_world), "--rrd", str(out)]) != 0  # exists: not without --force
    assert out.read_bytes() == before
    mine = tmp_path / "notes.rrd"
    mine.write_text("a user's file that happens to end in .rrd")
    assert main(["view", str(viewer_world), "--rrd", str(mine), "--force"]) != 0
    assert mine.read_text() == "a user's file that happens to end in .rrd"
    assert main(["view", str(viewer_world), "--rrd", str(out), "--force"]) == 0
    with pytest.raises(ConfigError, match="frame_step"):
        from atlas_pipeline.viz.rerun_export import export_rerun

        export_rerun(viewer_world, tmp_path / "x.rrd", frame_step=0)

"""Trust under hostile input, found by auditing the first two rounds as a new user: each bad input
is an error (or a warning) naming the file, line, field or option, never a traceback, a result
that is not JSON, or a silent loss."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from assets.cli import main

# ---- evaluate-trajectory: the files it reads, and what it prints --------------------------------

GT_LINES = [f"{1305031102.0 + i / 30:.6f} {0.01 * i:.4f} 0 0 0 0 0 1\n" for i in range(12)]


def _write(path, lines):
    path.write_text("".join(lines))
    return path


@pytest.mark.parametrize("make, says", [
    (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40)), ["est.tum:1: line is not UTF-8 text (byte 0"]),
    (lambda p: p.mkdir(), ["est.tum: trajectory file is a directory"]),
    (lambda p: os.mkfifo(p), ["est.tum: trajectory file is not a regular file (a FIFO)"]),
    (lambda p: _write(p, [f"{float(ln.split()[0]) * 1e3!r} {ln.split(' ', 1)[1]}" for ln in GT_LINES]),
     ["est.tum: timestamps are a median 33.3", "they look like milliseconds", "multiply by 0.001"]),
    (lambda p: _write(p, [f"{float(ln.split()[0]) * 1e9:.0f} {ln.split(' ', 1)[1]}" for ln in GT_LINES]),
     ["est.tum: timestamps are a median", "they look like nanoseconds", "multiply by 1e-09"]),
    (lambda p: _write(p, ["1305031102175303936 0 0 0 0 0 0 1\n"]),
     ["est.tum:1: timestamp 1305031102175303936 is too large for seconds", "nanoseconds since the epoch"]),
])
def test_evaluate_trajectory_names_a_file_it_cannot_read(tmp_path, caplog, make, says):
    est = tmp_path / "est.tum"
    make(est)
    gt = _write(tmp_path / "gt.txt", GT_LINES)
    assert main(["evaluate-trajectory", str(est), str(gt)]) == 2
    for words in says:
        assert words in caplog.text, caplog.text
    assert "Traceback" not in caplog.text


def test_evaluate_trajectory_prints_standard_json_and_the_figure_its_note_points_to(tmp_path, capsys):
    """A 12-pose straight path: RPE over 1 s has no pair and the alignment's rotation is ill-posed;
    the output is still one JSON document (null, never NaN) and holds the unaligned rotation error
    the note points to."""
    gt = _write(tmp_path / "gt.txt", GT_LINES)
    assert main(["evaluate-trajectory", str(gt), str(gt)]) == 0
    text = capsys.readouterr().out

    def refuse(constant):
        raise AssertionError(f"not JSON: {constant}")

    doc = json.loads(text, parse_constant=refuse)
    assert doc["rpe_trans_rmse_m"] is None and doc["ate_rot_rmse_deg"] is None
    assert "rmse_rot_unaligned_deg" in doc["ate_rot_note"]
    assert doc["rmse_rot_unaligned_deg"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("across_m, says", [
    (1e-3, "uncertain by about"),
    (0.0, "uncertain by any angle (the positions do not fix it)"),
])
def test_the_alignment_uncertainty_is_never_more_than_any_angle(across_m, says):
    from atlas_pipeline.geometry import pose_from_tq
    from atlas_pipeline.localization.metrics import ate

    n = 12
    t = np.stack([np.linspace(0, 0.1, n), across_m * np.sin(np.arange(n)), np.zeros(n)], axis=1)
    gt = pose_from_tq(t, np.tile([0, 0, 0, 1.0], (n, 1)))
    est = gt.copy()
    est[:, :3, 3] += np.random.default_rng(0).normal(0, 0.001, (n, 3))
    a = ate(est, gt)
    assert math.isnan(a["rot_rmse_deg"]) and says in a["rot_note"], a["rot_note"]
    if "about" in says:
        degrees = float(a["rot_note"].split("by about ")[1].split(" degrees")[0])
        assert 3 < degrees < 180, a["rot_note"]


# ---- numbers in YAML 1.2's exponent form ----------------------------------------------------------

@pytest.mark.parametrize("text, value", [
    ("1e-2", 0.01), ("1.5e-2", 0.015), ("2E-2", 0.02), ("+3e-2", 0.03), (".5e-1", 0.05), ("1_0e-3", 0.01),
])
def test_an_exponent_without_a_dot_is_a_number(tmp_path, text, value):
    """PyYAML (YAML 1.1) read ``1e-2`` as text, and the field refused it: "must be a valid number,
    got '1e-2'". In a --set value and in a profile it is the number."""
    from atlas_pipeline.config import load_profile, parse_set_overrides

    cfg = load_profile("default").with_overrides(parse_set_overrides([f"mapping.voxel_size_m={text}"]))
    assert cfg.mapping.voxel_size_m == pytest.approx(value)
    profile = tmp_path / "p.yaml"
    profile.write_text(f"mapping:\n  voxel_size_m: {text}\n")
    assert load_profile(profile).mapping.voxel_size_m == pytest.approx(value)


@pytest.mark.parametrize("text", ["1e", "e5", "1e3x", "1e-2m"])
def test_text_that_only_looks_like_an_exponent_is_still_refused_naming_the_field(text):
    from atlas_pipeline.config import load_profile, parse_set_overrides
    from atlas_pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match=rf"mapping\.voxel_size_m must be a valid number, got '{text}'"):
        load_profile("default").with_overrides(parse_set_overrides([f"mapping.voxel_size_m={text}"]), "--set")


# ---- import-ply: what the 8-bit base colour cannot keep -------------------------------------------

def _splat_ply(path, degree: int, dc: np.ndarray):
    from plyfile import PlyData, PlyElement

    n = len(dc)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *[f"f_rest_{i}" for i in range(3 * k)], "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    v = np.zeros(n, dtype=[(name, "f4") for name in names])
    v["x"] = np.arange(n) * 0.01
    for c in range(3):
        v[f"f_dc_{c}"] = dc[:, c]
        v[f"scale_{c}"] = np.log(0.01)
    for i in range(3 * k):
        v[f"f_rest_{i}"] = 0.05
    v["rot_0"] = 1.0
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


@pytest.mark.parametrize("degree, dc_values, warned", [
    (3, [0.0, 2.5, -2.5, 1.0], "2 of 4 Gaussians have a base colour (f_dc_*) outside [0, 1] (by up to 0.205)"),
    (1, [0.0, 1.77, -1.77, 1.0], None),  # within [0, 1] (up to the 8-bit rounding)
    (0, [0.0, 2.5, -2.5, 1.0], None),  # no view-dependent colour: the render clamps the base anyway
])
def test_import_ply_says_when_base_colours_of_sh_gaussians_are_clamped(tmp_path, caplog, degree, dc_values, warned):
    dc = np.repeat(np.array(dc_values, np.float32)[:, None], 3, axis=1)
    ply = _splat_ply(tmp_path / "scene.ply", degree, dc)
    assert main(["import-ply", str(ply), "--output", str(tmp_path / "w")]) == 0
    lines = [r.getMessage() for r in caplog.records if "base colour" in r.getMessage()]
    if warned is None:
        assert lines == [], lines
    else:
        assert len(lines) == 1 and lines[0].startswith(f"{ply}: {warned}"), lines


# ---- a hand-edited registry -----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../../evil", "a/b", "..", "Mine", "x y", "ünï"])
def test_a_bad_name_in_a_hand_edited_registry_names_the_registry_file(isolated, caplog, name):
    import yaml

    reg = isolated / "datasets.local.yaml"
    reg.write_text(yaml.safe_dump({"datasets": {name: {"kind": "tum", "path": str(isolated)}}}, allow_unicode=True))
    assert main(["dataset", "list"]) == 2
    assert f"{reg}: datasets: invalid dataset name {name!r}" in caplog.text, caplog.text

"""benchmarks/bench_regression.py: the comparison with the stored figures (pure, no tracking run)
and the stored block of docs/benchmarks.md."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from atlas_pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_regression", ROOT / "benchmarks" / "bench_regression.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


B = _bench()

STORED = {"seq": {"slam_ate_cm": 1.0, "own_ate_cm": 0.1, "own_placed_pct": 100.0, "psnr_db": 25.0, "slam_fps": 30.0}}


def _status(measured: dict) -> dict[str, str]:
    return {c.figure: c.status for c in B.compare({"seq": measured}, STORED)}


def test_a_figure_within_its_tolerance_passes_and_one_beyond_it_fails():
    # ATE: max(0.02 cm, 3 % of the stored) = 0.03 cm at 1 cm, 0.02 cm at 0.1 cm
    within = {"slam_ate_cm": 1.029, "own_ate_cm": 0.119, "own_placed_pct": 99.1, "psnr_db": 24.96, "slam_fps": 1.0}
    assert set(_status(within).values()) <= {"ok", "info"}
    assert B.failures(B.compare({"seq": within}, STORED)) == []
    for key, worse in (("slam_ate_cm", 1.031), ("own_ate_cm", 0.121), ("own_placed_pct", 98.9), ("psnr_db", 24.94)):
        checks = B.compare({"seq": {**within, key: worse}}, STORED)
        assert [c.figure for c in B.failures(checks)] == [key], key


def test_frames_per_second_never_fail_and_better_or_new_figures_pass():
    st = _status({"slam_ate_cm": 0.5, "own_ate_cm": 0.1, "own_placed_pct": 100.0, "psnr_db": 26.0, "slam_fps": 0.1,
                  "visit2_placed_pct": 50.0})
    assert st == {"slam_ate_cm": "better", "own_ate_cm": "ok", "own_placed_pct": "ok", "psnr_db": "better",
                  "slam_fps": "info", "visit2_placed_pct": "new"}


def test_a_stored_figure_this_run_has_no_value_for_fails():
    """No frame placed gives no ATE: that is a regression, not a pass."""
    checks = B.compare({"seq": {"slam_ate_cm": None, "own_ate_cm": float("nan"), "own_placed_pct": 100.0,
                                "psnr_db": 25.0}}, STORED)
    assert sorted(c.figure for c in B.failures(checks)) == ["own_ate_cm", "slam_ate_cm"]
    assert all(c.status == "missing" for c in B.failures(checks))


def test_a_figure_that_varied_between_the_stored_runs_gets_that_much_more_tolerance():
    """A session that relocalizes often varies from run to run (RANSAC): the stored spread, not
    the floor, bounds it."""
    spread = {"seq": {"own_ate_cm": 0.05}}  # floor 0.02 cm at 0.1 cm; SPREAD_FACTOR x 0.05 cm more
    stored = {"seq": {"own_ate_cm": 0.1}}
    tol = B.SPREAD_FACTOR * 0.05
    ok = B.compare({"seq": {"own_ate_cm": 0.1 + 0.9 * tol}}, stored, spread)
    assert [(c.status, c.tolerance) for c in ok] == [("ok", pytest.approx(tol))]
    assert B.failures(B.compare({"seq": {"own_ate_cm": 0.1 + 1.1 * tol}}, stored, spread))
    assert B.failures(B.compare({"seq": {"own_ate_cm": 0.13}}, stored))  # the floor alone: 0.02 cm
    assert (f"wider where the stored runs varied ({B.SPREAD_FACTOR:g} x their spread): seq localized ATE cm "
            f"{tol:.3f}") in B.format_table(ok)


def test_runs_are_summarized_as_their_mean_and_the_spread_of_what_moved():
    runs = [{"s": {"slam_ate_cm": 1.0, "own_ate_cm": 2.0, "slam_fps": 10.0, "psnr_db": None}},
            {"s": {"slam_ate_cm": 1.0, "own_ate_cm": 2.4, "slam_fps": 14.0, "psnr_db": 20.0}}]
    mean, spread = B.summarize_runs(runs)
    assert mean == {"s": {"slam_ate_cm": 1.0, "own_ate_cm": pytest.approx(2.2), "slam_fps": 12.0, "psnr_db": None}}
    assert spread == {"s": {"own_ate_cm": pytest.approx(0.4)}}  # frames/s vary but are never compared


def test_the_printed_table_marks_what_moved():
    measured = {"slam_ate_cm": 1.5, "own_ate_cm": 0.1, "own_placed_pct": 100.0, "psnr_db": 25.0}
    checks = B.compare({"seq": measured}, STORED)
    table = B.format_table(checks)
    assert "| seq | 1.50 (1.00) WORSE | 0.10 (0.10) |" in table
    assert "SLAM ATE cm 0.02 or 3 %" in table


def test_the_stored_block_of_the_docs_parses_and_names_known_sequences():
    stored = B.parse_stored((ROOT / "docs" / "benchmarks.md").read_text(), ROOT / "docs" / "benchmarks.md")
    names = {s.name for s in B.SEQUENCES}
    assert stored["figures"], "no figures stored: run benchmarks/bench_regression.py --update"
    assert set(stored["figures"]) <= names
    for row in stored["figures"].values():
        assert {"slam_ate_cm", "own_ate_cm", "own_placed_pct"} <= set(row)


def _doc(json_text: str) -> str:
    return f"# Title\n\ntext before\n\n{B.BLOCK_BEGIN}\n```json\n{json_text}\n```\n{B.BLOCK_END}\n\ntext after\n"


@pytest.mark.parametrize("json_text, names", [
    ('{"figures": {"seq": {"slam_ate_cm": 1.0,}}}', ["doc.md:7:", "stored block"]),
    ('{"figures": {"seq": {"ate": 1.0}}}', ["doc.md:7:", "'ate'", "slam_ate_cm"]),
    ('{"figures": {"seq": {"slam_ate_cm": "1.0"}}}', ["doc.md:7:", "seq.slam_ate_cm", "number"]),
    ('{"machine": "x"}', ["doc.md:7:", "'figures'"]),
    ('{"figures": {}, "spread": {"seq": {"slam_ate_cm": []}}}', ["doc.md:7:", "spread seq.slam_ate_cm"]),
    ('{"figures": {}, "runs": 0}', ["doc.md:7:", "'runs'"]),
])
def test_a_broken_stored_block_names_the_file_line_and_field(json_text, names):
    with pytest.raises(ConfigError) as exc:
        B.parse_stored(_doc(json_text), Path("doc.md"))
    for n in names:
        assert n in str(exc.value)


def test_a_doc_without_markers_is_an_error_naming_them():
    with pytest.raises(ConfigError, match="bench_regression: begin"):
        B.parse_stored("# nothing here\n", Path("doc.md"))


def test_update_rewrites_only_the_block_and_keeps_sequences_not_run(tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text(_doc('{"machine": "old", "figures": {"a": {"slam_ate_cm": 1.0}, "b": {"slam_ate_cm": 2.0}}}'))
    B.update_doc(doc, {"b": {"slam_ate_cm": 1.5, "own_placed_pct": 99.0, "slam_fps": 20.0}},
                 {"b": {"own_placed_pct": 0.5}}, "this machine", 2)
    text = doc.read_text()
    assert text.startswith("# Title\n\ntext before\n\n") and text.endswith("\n\ntext after\n")
    stored = B.parse_stored(text, doc)
    assert stored["machine"] == "this machine" and stored["runs"] == 2
    assert stored["spread"] == {"b": {"own_placed_pct": 0.5}}
    assert stored["figures"] == {"a": {"slam_ate_cm": 1.0},
                                 "b": {"slam_ate_cm": 1.5, "own_placed_pct": 99.0, "slam_fps": 20.0}}
    assert "| b | 1.50 | - | 99.0 |" in text  # the human-readable table beside the JSON
    assert not list(tmp_path.glob("*.tmp"))

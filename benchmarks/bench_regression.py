"""Regression guard: every sequence we have, this run's figures next to the ones stored in
``docs/benchmarks.md``; exits 1 when an accuracy figure got worse than its stored value by more than
its tolerance.

    python benchmarks/bench_regression.py                  # compare; exit 1 on a worse accuracy figure
    python benchmarks/bench_regression.py --only tum_fr3_teddy_100 synthetic-loop-far
    python benchmarks/bench_regression.py --repeat 2       # run twice, print the spread of every figure
    python benchmarks/bench_regression.py --update --repeat 3   # store the mean of 3 runs and their spread

Sequences: the real TUM frames in ``../shared/data`` when present (``tum_fr3_teddy_100``,
``tum_fr1_xyz_10``) and the synthetic presets short enough for a few minutes on 2 cores
(``synthetic``, ``synthetic-noisy``, ``synthetic-handheld``, ``synthetic-loop``,
``synthetic-loop-far``: Kinect v1 noise, the last two close a loop, the last at 3-5 m; generated
into the data folder on first use). The suite (1,500 + 900 frames) is left to
``bench_persistence.py``.

Per sequence, with the default profile as ``atlas-gs build --set mapping.pose_source=estimated
--set mapping.fit.epochs=0`` builds it (the library's build stages: one pass reads, tracks, closes
loops and fuses every frame from disk, then the world is merged; no ground truth read except to
grade):

* **SLAM**: ATE (cm) of the tracked and loop-closed poses; frames/s of that pass.
* **own frames**: the sequence localized in the world it built (``atlas-gs localize``): ATE, placed
  %, frames/s.
* **second visit** (sequences with a split): a world built from the first part, the rest localized
  in it with no start pose: placed %, ATE.
* **held-out PSNR** (sequences marked so): the world fitted to its keyframes by a short fit
  (:data:`PSNR_FIT_STEPS` steps) and rendered at the localized pose of every held-out frame
  (``render_evaluation``): mean PSNR over the whole frame.

Accuracy figures are compared with the stored ones within their tolerance: the larger of the
figure's floor (:data:`FIGURES`) and :data:`SPREAD_FACTOR` times the spread its stored runs showed
(``--update --repeat N`` stores the mean of N runs and their spread); frames/s are printed, never
compared (a shared machine's timings vary by tens of per cent). The stored figures are those of
one machine (``docs/benchmarks.md`` names it): floating point that differs in its last bits
between CPUs moves long sequences' figures, so on another machine run ``--update`` first and
compare later runs with that.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from atlas_pipeline.errors import ConfigError  # noqa: E402

DOC = ROOT / "docs" / "benchmarks.md"
BLOCK_BEGIN = "<!-- bench_regression: begin (written by benchmarks/bench_regression.py --update) -->"
BLOCK_END = "<!-- bench_regression: end -->"
# The fit of the PSNR rows: a fifth of the default profile's 300 steps (the default fit takes about
# 100 s on teddy on 2 shared cores, this one about 10 s); no minimum per keyframe, so the step count
# is the same whatever the keyframes.
PSNR_FIT_STEPS = 60


@dataclass(frozen=True)
class Figure:
    """One figure of a row: its label, how it is printed, which way is better (``lower``,
    ``higher``; None: reported, never compared) and its tolerance: a change for the worse of at
    most ``max(abs_tol, rel_tol * |stored|)`` is run-to-run noise."""

    label: str
    digits: int
    better: str | None
    abs_tol: float = 0.0
    rel_tol: float = 0.0

    def tolerance(self, stored: float) -> float:
        return max(self.abs_tol, self.rel_tol * abs(stored))

    def describe_tolerance(self) -> str:
        if self.better is None:
            return "reported only"
        parts = [f"{self.abs_tol:g}"] if self.abs_tol else []
        if self.rel_tol:
            parts.append(f"{100 * self.rel_tol:g} %")
        return " or ".join(parts) if parts else "0"


# Noise, measured by running the whole benchmark several times on one machine (``--repeat``):
# SLAM, the fit and the evaluation come out identical run after run (deterministic for a given
# machine and thread count), and so does localization where it places every frame by tracking; a
# session that relocalizes often (the far loop's own frames) varies, since the full relocalization
# search registers features by RANSAC. Such a figure's tolerance is SPREAD_FACTOR times the spread
# its stored runs showed: three runs see about 1.7 standard deviations of range, and a further run
# may land 2.5 standard deviations from their mean (1 in 100), about 1.5 times that range. The
# far loop's own-frame ATE spread 0.07 cm over its three stored runs and a fourth run landed
# 0.12 cm from their mean (three runs of an earlier world of it spread 0.2 cm): the factor is
# twice that margin. The floors below cover
# what moves between machines (floating point that differs in its last bits: docs/benchmarks.md
# saw about 0.01 cm of ATE on the TUM splits): ATE 0.02 cm or 3 % (whichever is larger), placed 1
# frame in a hundred, PSNR 0.05 dB (a ninth of the 0.45 dB a real regression on teddy lost).
SPREAD_FACTOR = 3.0
ATE_ABS_TOL_CM = 0.02
ATE_REL_TOL = 0.03
PLACED_TOL_PCT = 1.0
PSNR_TOL_DB = 0.05
FIGURES: dict[str, Figure] = {
    "slam_ate_cm": Figure("SLAM ATE cm", 2, "lower", ATE_ABS_TOL_CM, ATE_REL_TOL),
    "own_ate_cm": Figure("localized ATE cm", 2, "lower", ATE_ABS_TOL_CM, ATE_REL_TOL),
    "own_placed_pct": Figure("placed %", 1, "higher", PLACED_TOL_PCT),
    "visit2_placed_pct": Figure("visit 2 placed %", 1, "higher", PLACED_TOL_PCT),
    "visit2_ate_cm": Figure("visit 2 ATE cm", 2, "lower", ATE_ABS_TOL_CM, ATE_REL_TOL),
    "psnr_db": Figure("held-out PSNR dB", 2, "higher", PSNR_TOL_DB),
    "loops": Figure("loops kept", 0, None),
    "slam_fps": Figure("SLAM f/s", 1, None),
    "own_fps": Figure("localization f/s", 1, None),
}


@dataclass(frozen=True)
class Sequence:
    """A sequence of the benchmark: ``split`` frames make the first visit of a second-visit check
    (None: no second visit); ``psnr``: fitted and rendered at its held-out frames."""

    name: str
    split: int | None
    psnr: bool
    shared_camera: str | None = None  # a folder of ../shared/data with these TUM intrinsics; None: a registry preset


SEQUENCES = (
    Sequence("tum_fr3_teddy_100", 50, True, "freiburg3"),
    Sequence("tum_fr1_xyz_10", 5, True, "freiburg1"),
    Sequence("synthetic", 30, True),
    Sequence("synthetic-noisy", 30, False),
    Sequence("synthetic-handheld", None, False),
    Sequence("synthetic-loop", None, False),
    Sequence("synthetic-loop-far", None, False),
)


@dataclass
class Check:
    """One figure of one sequence against its stored value. ``status``: ``ok`` (within tolerance),
    ``better``, ``worse`` (fails the run), ``missing`` (stored, but this run has none: fails),
    ``new`` (nothing stored), ``info`` (reported only)."""

    sequence: str
    figure: str
    measured: float | None
    stored: float | None
    tolerance: float | None
    status: str


FAILING = ("worse", "missing")


def _number(x) -> float | None:
    return None if x is None or not np.isfinite(float(x)) else float(x)


def compare(measured: dict[str, dict[str, float | None]], stored: dict[str, dict[str, float | None]],
            spread: dict[str, dict[str, float]] | None = None) -> list[Check]:
    """Every figure of every measured sequence against ``stored`` (both ``{sequence: {figure:
    value}}``, figures keyed as :data:`FIGURES`; None: no value); ``spread``: the stored runs'
    spread of each figure (same keys), which widens its tolerance. Pure: no IO."""
    out = []
    spread = spread or {}
    for seq, row in measured.items():
        old = stored.get(seq, {})
        noise = spread.get(seq, {})
        for key, fig in FIGURES.items():
            m, s = _number(row.get(key)), _number(old.get(key))
            if key not in row and key not in old:
                continue
            if fig.better is None:
                out.append(Check(seq, key, m, s, None, "info"))
            elif s is None:
                out.append(Check(seq, key, m, None, None, "new"))
            elif m is None:
                out.append(Check(seq, key, None, s, None, "missing"))
            else:
                worse_by = (m - s) if fig.better == "lower" else (s - m)
                tol = max(fig.tolerance(s), SPREAD_FACTOR * float(noise.get(key) or 0.0))
                status = "worse" if worse_by > tol else "better" if -worse_by > tol else "ok"
                out.append(Check(seq, key, m, s, tol, status))
    return out


def failures(checks: list[Check]) -> list[Check]:
    return [c for c in checks if c.status in FAILING]


# -- the stored block ----------------------------------------------------------------------------

def _block_lines(text: str, where: Path) -> tuple[int, int]:
    """Line indices (0-based) of the begin and end markers in ``text``."""
    lines = text.splitlines()
    begin = [i for i, ln in enumerate(lines) if ln.strip() == BLOCK_BEGIN]
    end = [i for i, ln in enumerate(lines) if ln.strip() == BLOCK_END]
    if len(begin) != 1 or len(end) != 1 or end[0] < begin[0]:
        raise ConfigError(f"{where}: expected one '{BLOCK_BEGIN}' line followed by one '{BLOCK_END}' line, "
                          f"found {len(begin)} and {len(end)}")
    return begin[0], end[0]


def parse_stored(text: str, where: Path = DOC) -> dict:
    """The stored block of ``text`` (the Markdown of ``where``): ``{"machine": str, "figures":
    {sequence: {figure: value or None}}}``, from the fenced ``json`` between the markers."""
    b, e = _block_lines(text, where)
    lines = text.splitlines()
    fence = [i for i in range(b + 1, e) if lines[i].strip().startswith("```")]
    if len(fence) < 2 or lines[fence[0]].strip() != "```json":
        raise ConfigError(f"{where}:{b + 1}: the stored block holds no ```json fence")
    src = "\n".join(lines[fence[0] + 1:fence[1]])
    try:
        data = json.loads(src)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{where}:{fence[0] + 2 + exc.lineno - 1}: stored block: {exc.msg}") from exc
    where_json = f"{where}:{fence[0] + 2}"
    figures = data.get("figures") if isinstance(data, dict) else None
    if not isinstance(figures, dict):
        raise ConfigError(f"{where_json}: stored block: no 'figures' object")
    spread = data.get("spread", {})
    if not isinstance(spread, dict):
        raise ConfigError(f"{where_json}: stored block: 'spread' is not an object")
    for section, table in (("figures", figures), ("spread", spread)):
        for seq, row in table.items():
            if not isinstance(row, dict):
                raise ConfigError(f"{where_json}: stored block: {section} of {seq!r} are not an object")
            for key, v in row.items():
                if key not in FIGURES:
                    raise ConfigError(f"{where_json}: stored block: {section} of {seq!r}: unknown figure {key!r} "
                                      f"(known: {', '.join(FIGURES)})")
                if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                    raise ConfigError(f"{where_json}: stored block: {section} {seq}.{key} must be a number or null, "
                                      f"got {v!r}")
    runs = data.get("runs", 1)
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise ConfigError(f"{where_json}: stored block: 'runs' must be a positive integer, got {runs!r}")
    return {"machine": str(data.get("machine", "")), "runs": runs, "figures": figures, "spread": spread}


def _cell(fig: Figure, v: float | None) -> str:
    return "-" if v is None else f"{v:.{fig.digits}f}"


def render_stored(figures: dict[str, dict[str, float | None]], spread: dict[str, dict[str, float]], machine: str,
                  runs: int) -> str:
    """The block's text between (and with) its markers: the figures as a table, then as JSON."""
    keys = list(FIGURES)
    rows = [f"| sequence | {' | '.join(FIGURES[k].label for k in keys)} |", "|---" * (len(keys) + 1) + "|"]
    for seq, row in figures.items():
        rows.append(f"| {seq} | " + " | ".join(_cell(FIGURES[k], _number(row.get(k))) for k in keys) + " |")

    def rounded(table: dict) -> dict:
        return {seq: {k: (None if _number(row.get(k)) is None else round(float(row[k]), FIGURES[k].digits + 2))
                      for k in keys if k in row} for seq, row in table.items()}

    payload = json.dumps({"machine": machine, "runs": runs, "figures": rounded(figures),
                          "spread": {seq: row for seq, row in rounded(spread).items() if row}}, indent=2)
    return "\n".join([BLOCK_BEGIN, *rows, "", "```json", payload, "```", BLOCK_END])


def summarize_runs(runs: list[dict[str, dict[str, float | None]]]) -> tuple[dict, dict]:
    """``(mean, spread)`` of each figure over ``runs`` (each ``{sequence: {figure: value}}``): the
    spread (largest minus smallest) only where it is not 0; a figure missing from any run is None."""
    mean: dict[str, dict[str, float | None]] = {}
    spread: dict[str, dict[str, float]] = {}
    for seq in runs[-1]:
        mean[seq], spread[seq] = {}, {}
        for key in runs[-1][seq]:
            vals = [_number(r.get(seq, {}).get(key)) for r in runs]
            if any(v is None for v in vals):
                mean[seq][key] = None
                continue
            mean[seq][key] = float(np.mean(vals))
            if max(vals) > min(vals) and FIGURES[key].better is not None:
                spread[seq][key] = max(vals) - min(vals)
    return mean, spread


def update_doc(path: Path, measured: dict[str, dict[str, float | None]], spread: dict[str, dict[str, float]],
               machine: str, runs: int) -> None:
    """Store ``measured`` (and its ``spread`` over ``runs`` runs) in ``path``'s block: the measured
    sequences replace theirs, the others stay; nothing outside the markers changes (written to a
    temporary file, then renamed)."""
    text = path.read_text()
    stored = parse_stored(text, path)
    figures = {**stored["figures"], **measured}
    old_spread = {seq: row for seq, row in stored["spread"].items() if seq not in measured}
    b, e = _block_lines(text, path)
    lines = text.splitlines()
    block = render_stored(figures, {**old_spread, **spread}, machine, runs)
    new = "\n".join([*lines[:b], block, *lines[e + 1:]]) + ("\n" if text.endswith("\n") else "")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(new)
    os.replace(tmp, path)


# -- running a sequence --------------------------------------------------------------------------

def _manifest(seq: Sequence):
    """The sequence's frames (a FrameManifest), or None when its data is not here."""
    if seq.shared_camera is not None:
        from benchmarks.common import shared_tum_manifest

        return shared_tum_manifest(seq.name, seq.shared_camera)
    from atlas_pipeline.sensors.registry import load_dataset, load_registry

    from benchmarks.bench_persistence import benchmark_config

    reg = load_registry()
    if seq.name not in reg:
        raise ConfigError(f"{seq.name}: not a registered dataset (configs/datasets.yaml)")
    return load_dataset(reg[seq.name], benchmark_config())


def run_sequence(seq: Sequence, manifest) -> dict[str, float | None]:
    """This sequence's figures (keys of :data:`FIGURES`)."""
    from atlas_pipeline.gaussian_world.evaluation import evaluate_rendering
    from atlas_pipeline.localization.localizer import localize, localize_sequence, tracking_map
    from atlas_pipeline.mapping.mapper import build_gaussian_world, fuse_and_select_keyframes

    from benchmarks.bench_persistence import _placed, _slice, _stored, benchmark_config, build_first_world
    from benchmarks.common import grade

    cfg = benchmark_config()
    if seq.psnr:  # the default profile's fit, cut to PSNR_FIT_STEPS steps
        from atlas_pipeline.config import load_profile

        cfg = cfg.with_overrides({"mapping.fit.epochs": load_profile("default").mapping.fit.epochs,
                                  "mapping.fit.max_steps": PSNR_FIT_STEPS, "mapping.fit.min_steps_per_keyframe": 0})
    cm = 100.0
    # The build's stages as `atlas-gs build` runs them: one pass reads, tracks (loop closure
    # included) and fuses every frame; then the world is merged (and fitted, for a PSNR row).
    t0 = time.perf_counter()
    fused, kf = fuse_and_select_keyframes(manifest, cfg)
    pass_s = time.perf_counter() - t0
    world = build_gaussian_world(fused, kf, cfg, manifest=manifest)
    g = grade(manifest, np.where(kf.valid[:, None, None], kf.T_world_cam, np.nan))
    row: dict[str, float | None] = {
        "slam_ate_cm": _scaled(g.get("ate_rmse_m"), cm), "slam_fps": manifest.n_frames / pass_s,
        "loops": None if kf.loop_closure is None else float(kf.loop_closure["n_loops"])}
    own = localize(manifest, world, cfg)
    row.update({"own_ate_cm": _scaled(own.summary.get("ate_rmse_m"), cm),
                "own_placed_pct": 100.0 * float(_placed(own.status).mean()),
                "own_fps": _number(own.summary.get("frames_per_s"))})
    if seq.psnr:
        ev = evaluate_rendering(manifest, world, own, cfg, log=lambda _: None)
        row["psnr_db"] = _number(ev.summary.get("mean_psnr_db"))
    if seq.split is not None and 0 < seq.split < manifest.n_frames:
        # A later session: the first part's world with its stored place index, the rest localized
        # in it with no start pose (bench_persistence.py's second visit).
        base = benchmark_config()
        v1, v2 = (_slice(manifest, 0, seq.split, f"{seq.name}-1"),
                  _slice(manifest, seq.split, manifest.n_frames, f"{seq.name}-2"))
        _, world1, places1, _ = build_first_world(v1, base)
        second = localize_sequence(v2, tracking_map(world1), base.localization, None, map_id=world1.map_id,
                                   depth_range_m=(base.fusion.min_depth_m, base.fusion.max_depth_m),
                                   prior_poses=world1.T_world_cam_keyframes, places=_stored(places1, v2.camera)[0])
        row.update({"visit2_placed_pct": 100.0 * float(_placed(second.status).mean()),
                    "visit2_ate_cm": _scaled(second.summary.get("ate_rmse_m"), cm)})
    return row


def _scaled(x, scale: float) -> float | None:
    x = _number(x)
    return None if x is None else x * scale


# -- output --------------------------------------------------------------------------------------

MARKS = {"ok": "", "better": " +", "worse": " WORSE", "missing": " MISSING", "new": " (new)", "info": ""}


def format_table(checks: list[Check]) -> str:
    """Markdown: a row per sequence, each figure as ``measured (stored)`` with a mark when it moved
    beyond its tolerance (``+`` better, ``WORSE``), then the tolerances."""
    keys = [k for k in FIGURES if any(c.figure == k for c in checks)]
    by = {(c.sequence, c.figure): c for c in checks}
    seqs = list(dict.fromkeys(c.sequence for c in checks))
    lines = [f"| sequence | {' | '.join(FIGURES[k].label for k in keys)} |", "|---" * (len(keys) + 1) + "|"]
    for seq in seqs:
        cells = []
        for k in keys:
            c = by.get((seq, k))
            if c is None:
                cells.append("")
                continue
            fig = FIGURES[k]
            stored = "" if c.stored is None else f" ({_cell(fig, c.stored)})"
            cells.append(f"{_cell(fig, c.measured)}{stored}{MARKS[c.status]}")
        lines.append(f"| {seq} | " + " | ".join(cells) + " |")
    lines.append("tolerance (a change for the worse beyond it fails): " +
                 "; ".join(f"{FIGURES[k].label} {FIGURES[k].describe_tolerance()}" for k in keys))
    wider = [c for c in checks if c.tolerance is not None and c.tolerance > FIGURES[c.figure].tolerance(c.stored)]
    if wider:
        lines.append(f"wider where the stored runs varied ({SPREAD_FACTOR:g} x their spread): " + "; ".join(
            f"{c.sequence} {FIGURES[c.figure].label} {c.tolerance:.{FIGURES[c.figure].digits + 1}f}" for c in wider))
    return "\n".join(lines)


def _machine() -> str:
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"


def _warm_up(manifest) -> None:
    """The kernels loaded (or compiled) before any timing: bench_persistence's warm-up."""
    from benchmarks.bench_persistence import _warm_up as warm, benchmark_config

    warm(manifest, benchmark_config())


def run_all(sequences: list[Sequence], progress: Callable[[str], None]) -> dict[str, dict[str, float | None]]:
    measured: dict[str, dict[str, float | None]] = {}
    warmed = False
    for seq in sequences:
        manifest = _manifest(seq)
        if manifest is None:
            progress(f"{seq.name}: skipped (no frames at ../shared/data/{seq.name})")
            continue
        if not warmed:
            _warm_up(manifest)
            warmed = True
        t0 = time.perf_counter()
        measured[seq.name] = run_sequence(seq, manifest)
        progress(f"{seq.name}: {time.perf_counter() - t0:.0f} s")
    return measured


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", metavar="SEQUENCE", choices=[s.name for s in SEQUENCES],
                    help="run only these sequences")
    ap.add_argument("--repeat", type=int, default=1, metavar="N",
                    help="run N times: the mean is compared (and stored by --update), each figure's spread printed")
    ap.add_argument("--update", action="store_true", help=f"store this run's figures in {DOC.relative_to(ROOT)}")
    ap.add_argument("--doc", type=Path, default=DOC, help="the Markdown file holding the stored figures")
    ap.add_argument("--json", type=Path, help="also write this run's figures here")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error(f"--repeat must be at least 1, got {args.repeat}")
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    try:
        stored = parse_stored(args.doc.read_text(), args.doc)
    except OSError as exc:
        ap.error(f"--doc {args.doc}: {exc.strerror or exc}")
    except ConfigError as exc:
        ap.error(str(exc))
    sequences = [s for s in SEQUENCES if args.only is None or s.name in args.only]
    t0 = time.perf_counter()
    runs = []
    for k in range(args.repeat):
        if args.repeat > 1:
            print(f"run {k + 1} of {args.repeat}", file=sys.stderr, flush=True)
        try:
            runs.append(run_all(sequences, lambda msg: print(f"  {msg}", file=sys.stderr, flush=True)))
        except ConfigError as exc:
            print(f"bench_regression: {exc}", file=sys.stderr)
            return 2
    measured, spread = summarize_runs(runs)
    checks = compare(measured, stored["figures"], stored["spread"])
    print(f"\nmachine: {_machine()}; stored figures: {stored['machine'] or 'unknown machine'} "
          f"(mean of {stored['runs']} run{'s' if stored['runs'] > 1 else ''}); "
          f"profile default, mapping.pose_source=estimated; PSNR after a {PSNR_FIT_STEPS}-step fit; "
          f"{time.perf_counter() - t0:.0f} s")
    print(format_table(checks))
    if args.repeat > 1:
        print(f"\nrun-to-run spread over {args.repeat} runs (largest minus smallest; accuracy figures, "
              f"those that moved): " + ("; ".join(
                  f"{seq} " + ", ".join(f"{FIGURES[k].label} {v:.{FIGURES[k].digits + 1}f}" for k, v in row.items())
                  for seq, row in spread.items() if row) or "none"))
    if args.json:
        args.json.write_text(json.dumps(measured, indent=2) + "\n")
    bad = failures(checks)
    for c in bad:
        fig = FIGURES[c.figure]
        tol = "" if c.tolerance is None else f" (tolerance {c.tolerance:.{fig.digits + 1}f})"
        print(f"FAIL {c.sequence} {fig.label}: {_cell(fig, c.measured)} against {_cell(fig, c.stored)} stored{tol}")
    if args.update:
        update_doc(args.doc, measured, spread, _machine(), args.repeat)
        print(f"stored this run's figures in {args.doc}")
        return 0
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Fuzz every file reader and print what happened: one row per reader.

Uses the targets and Hypothesis strategies of ``tests/test_fuzz_readers.py`` (mutations of valid
files written by the project, and random bytes), derandomized, so two runs print the same counts.

Run: ``python benchmarks/fuzz_readers.py [--cases 800] [--readers ply,npz,...]``. The default
makes 800 cases for each of the 13 readers (10,400 in all).

Columns: cases run; refused with a project error (``AtlasError``); accepted; *other* exceptions
(anything else escaping a reader -- must be 0; the first reproducers are printed below the
table); the largest ``tracemalloc`` peak of one call and the largest peak / input-bytes ratio
(the tests allow ``max(64 MiB, 64 x input)``, so tiny inputs show large ratios); wall seconds.
Exit status 1 when any reader let a non-project exception escape or went over the memory allowance.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from tests.test_fuzz_readers import (  # noqa: E402
    FUZZ_SETTINGS,
    TARGET_NAMES,
    FuzzTarget,
    build_targets,
    fuzz_input,
    memory_allowance,
    run_case,
)

DEFAULT_CASES_PER_READER = 800  # x 13 readers = 10,400 cases
REPRODUCER_BYTES = 300  # of an input that escaped, printed under the table
MAX_REPRODUCERS = 3  # distinct new crashes printed per reader


def fuzz_one(target: FuzzTarget, cases: int) -> dict:
    """Run ``cases`` generated inputs against ``target``; return counts and extremes."""
    stats = {"cases": 0, "project_error": 0, "accepted": 0, "other": 0, "max_peak": 0, "max_ratio": 0.0,
             "over_allowance": 0, "reproducers": []}

    @settings(max_examples=cases, **FUZZ_SETTINGS)
    @given(st.data())
    def case(data):
        f = data.draw(st.sampled_from(target.files))
        payload = data.draw(fuzz_input(f))
        out = run_case(target, f.name, payload)
        stats["cases"] += 1
        stats[out.kind] += 1
        stats["max_peak"] = max(stats["max_peak"], out.peak_bytes)
        stats["max_ratio"] = max(stats["max_ratio"], out.peak_bytes / max(out.input_bytes, 1))
        if out.peak_bytes >= memory_allowance(out.input_bytes):
            stats["over_allowance"] += 1
        if out.kind == "other":
            if len(stats["reproducers"]) < MAX_REPRODUCERS:
                first_line = out.error.splitlines()[0]
                if all(first_line != r[1] for r in stats["reproducers"]):
                    stats["reproducers"].append((f.name, first_line, payload[:REPRODUCER_BYTES], out.error))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        case()
    return stats


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=DEFAULT_CASES_PER_READER, help="generated inputs per reader")
    ap.add_argument("--readers", default=",".join(TARGET_NAMES), help="comma-separated subset of: " + ", ".join(TARGET_NAMES))
    ap.add_argument("--tracebacks", action="store_true", help="print the full traceback of each reproducer")
    args = ap.parse_args(argv)
    names = [n for n in args.readers.split(",") if n]
    unknown = sorted(set(names) - set(TARGET_NAMES))
    if unknown:
        ap.error(f"unknown reader(s) {unknown}")
    logging.getLogger("atlas_pipeline").setLevel(logging.ERROR)  # readers warn about odd-but-valid inputs
    with tempfile.TemporaryDirectory(prefix="atlas-fuzz-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        targets = build_targets(Path(tmp))
        rows, bad = [], False
        header = f"{'reader':<16} {'cases':>6} {'project errors':>14} {'accepted':>8} {'other':>5} " \
                 f"{'max peak':>10} {'peak/input':>10} {'seconds':>8}"
        print(header)
        print("-" * len(header))
        total = {"cases": 0, "project_error": 0, "accepted": 0, "other": 0, "seconds": 0.0}
        for name in names:
            t0 = time.perf_counter()
            s = fuzz_one(targets[name], args.cases)
            dt = time.perf_counter() - t0
            rows.append((name, s))
            print(f"{name:<16} {s['cases']:>6} {s['project_error']:>14} {s['accepted']:>8} {s['other']:>5} "
                  f"{s['max_peak'] / 2**20:>7.2f} MiB {s['max_ratio']:>10.1f} {dt:>8.1f}", flush=True)
            for k in ("cases", "project_error", "accepted", "other"):
                total[k] += s[k]
            total["seconds"] += dt
            bad = bad or s["other"] > 0 or s["over_allowance"] > 0
        print("-" * len(header))
        print(f"{'total':<16} {total['cases']:>6} {total['project_error']:>14} {total['accepted']:>8} "
              f"{total['other']:>5} {'':>10} {'':>10} {total['seconds']:>8.1f}")
        for name, s in rows:
            if s["over_allowance"]:
                print(f"\n{name}: {s['over_allowance']} case(s) over the memory allowance")
            for fname, first, payload, tb in s["reproducers"]:
                print(f"\n{name}: {fname} = {payload!r}\n  -> {first}")
                if args.tracebacks:
                    print(tb)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

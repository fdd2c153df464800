"""How long an ``atlas-gs`` command takes from start to exit, with the executable's quick exit
(``assets.cli.command``: ``main``, then ``gc.freeze()`` so that the interpreter's last garbage
collection skips what the command left) against the plain ``sys.exit(main())`` as the reference,
alternating, in the same run.

    python benchmarks/bench_cli_exit.py                       # `atlas-gs status synthetic`, 5 each
    python benchmarks/bench_cli_exit.py --repeat 9 -- lineage synthetic

``status`` imports Dagster and reads the instance, as most commands do; the figure is wall time of
a fresh process each, medians.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "quick exit (atlas-gs)": "import sys; from assets.cli import command; sys.argv[0] = 'atlas-gs'; sys.exit(command())",
    "plain sys.exit(main())": "import sys; from assets.cli import main; sys.argv[0] = 'atlas-gs'; sys.exit(main())",
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("command", nargs="*", default=["status", "synthetic"], help="the atlas-gs arguments")
    args = ap.parse_args()
    times: dict[str, list[float]] = {k: [] for k in VARIANTS}
    for _ in range(args.repeat):
        for name, code in VARIANTS.items():
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-c", code, *args.command], cwd=ROOT, capture_output=True)
            times[name].append(time.perf_counter() - t0)
            if out.returncode not in (0, 1):
                sys.stderr.write(out.stderr.decode()[-2000:])
                return 1
    med = {k: statistics.median(v) for k, v in times.items()}
    ref = med["plain sys.exit(main())"]
    print(f"`atlas-gs {' '.join(args.command)}`, {args.repeat} runs each, alternating; median wall s\n")
    print("| variant | median s | min-max s | x reference |\n|---|---|---|---|")
    for k, v in times.items():
        print(f"| {k} | {med[k]:.2f} | {min(v):.2f}-{max(v):.2f} | {med[k] / ref:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""OpenMP wait policy benchmark: tracking frames/s with OpenMP threads that sleep at barriers
(``OMP_WAIT_POLICY=PASSIVE``: what ``atlas_pipeline`` sets unless the user set the variable)
against GNU OpenMP's own default (spin, then sleep), one job alone and two jobs at once on the
same cores.

    python benchmarks/bench_openmp_wait.py                 # synthetic, 60 frames
    python benchmarks/bench_openmp_wait.py --dataset synthetic-noisy --jobs 3

Each job is a fresh process (OpenMP reads the policy once, when its runtime loads) that tracks and
maps the dataset with ``slam_poses`` (default profile, no ground truth) on frames already in
memory, after a warm-up of the JIT kernels; frames/s is of that loop alone. "N at once" starts N
identical jobs together and reports their mean: what a second run, a test suite or a benchmark on
the same machine does to a tracker whose parallel kernels wait on each other's threads.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Each policy is the OpenMP environment a job starts with (these variables are removed first).
OPENMP_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
# GNU's default spins 300,000 rounds (about 3 ms) at a barrier, then sleeps. atlas_pipeline sets
# OMP_WAIT_POLICY=PASSIVE when it is unset, so the default is asked for by its spin count.
GNU_DEFAULT_SPINCOUNT = 300_000
POLICIES = {"passive": {"OMP_WAIT_POLICY": "PASSIVE"},
            "GNU default": {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": str(GNU_DEFAULT_SPINCOUNT)}}
WARMUP_FRAMES = 5


def _child(dataset: str) -> None:
    """One job: frames/s of slam_poses on ``dataset``, printed as JSON."""
    from atlas_pipeline.config import load_profile
    from atlas_pipeline.sensors.registry import ensure_dataset_files, load_registry, read_dataset_manifest
    from benchmarks.common import load_frames, run_slam

    cfg = load_profile("default")
    entry = load_registry()[dataset]
    ensure_dataset_files(entry)
    manifest = read_dataset_manifest(entry)
    frames = load_frames(manifest)
    run_slam(manifest, frames[:WARMUP_FRAMES], cfg)  # JIT warm-up
    t_cpu = time.process_time()
    out, _ = run_slam(manifest, frames, cfg)
    print(json.dumps({"frames_per_s": out["frames_per_s"], "cpu_ms_per_frame":
                      1000 * (time.process_time() - t_cpu) / len(frames), "ate_m": out["ate_rmse_m"],
                      "policy": {k: os.environ.get(k) for k in OPENMP_VARIABLES}}))


def _run_jobs(dataset: str, policy: dict[str, str], n_jobs: int) -> list[dict]:
    env = {**{k: v for k, v in os.environ.items() if k not in OPENMP_VARIABLES}, **policy}
    procs = [subprocess.Popen([sys.executable, __file__, "--child", dataset], env=env, cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) for _ in range(n_jobs)]
    results = []
    for p in procs:
        out, _ = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"a job failed (exit {p.returncode})")
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="synthetic", help="a synthetic registry entry (default: synthetic)")
    ap.add_argument("--jobs", type=int, default=2, help="jobs started together for the shared rows (default 2)")
    ap.add_argument("--spincount", type=int, action="append", default=[], metavar="N",
                    help="also a policy that spins N rounds at a barrier, then sleeps (GOMP_SPINCOUNT); repeatable")
    ap.add_argument("--child", metavar="DATASET", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    policies = {**POLICIES, **{f"spin {n:,}": {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": str(n)}
                               for n in args.spincount}}
    if args.child:
        _child(args.child)
        return 0
    print(f"# OpenMP wait policy: {args.dataset}, slam_poses frames/s, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f} at the start")
    print("| policy | jobs at once | frames/s per job | CPU ms / frame | ATE cm |")
    print("|---|---|---|---|---|")
    rows = {}
    for label, policy in policies.items():
        for n in (1, args.jobs):
            res = _run_jobs(args.dataset, policy, n)
            fps = sum(r["frames_per_s"] for r in res) / n
            cpu = sum(r["cpu_ms_per_frame"] for r in res) / n
            rows[(label, n)] = fps
            print(f"| {label} | {n} | {fps:.1f} | {cpu:.0f} | {100 * res[0]['ate_m']:.2f} |", flush=True)
    ref = "GNU default"
    for label in policies:
        if label != ref:
            print(f"{label} / {ref} frames/s: " + ", ".join(
                f"{rows[(label, n)] / rows[(ref, n)]:.2f}x with {n} job(s)" for n in (1, args.jobs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

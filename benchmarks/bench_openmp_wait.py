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

POLICIES = {"passive": "PASSIVE", "GNU default": None}
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
                      "policy": os.environ.get("OMP_WAIT_POLICY")}))


def _run_jobs(dataset: str, policy: str | None, n_jobs: int) -> list[dict]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
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
    ap.add_argument("--child", metavar="DATASET", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args.child)
        return 0
    print(f"# OpenMP wait policy: {args.dataset}, slam_poses frames/s, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f} at the start")
    print("| policy | jobs at once | frames/s per job | CPU ms / frame | ATE cm |")
    print("|---|---|---|---|---|")
    rows = {}
    for label, policy in POLICIES.items():
        for n in (1, args.jobs):
            res = _run_jobs(args.dataset, policy, n)
            fps = sum(r["frames_per_s"] for r in res) / n
            cpu = sum(r["cpu_ms_per_frame"] for r in res) / n
            rows[(label, n)] = fps
            print(f"| {label} | {n} | {fps:.1f} | {cpu:.0f} | {100 * res[0]['ate_m']:.2f} |", flush=True)
    ours, ref = list(POLICIES)
    for n in (1, args.jobs):
        print(f"{n} job(s): passive / GNU default frames/s = {rows[(ours, n)] / rows[(ref, n)]:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Many recordings at once: N small synthetic partitions through the whole graph, serial vs in
parallel (``atlas-gs run --all --concurrency 2``: a pool of worker processes, one Dagster run per
partition) vs on a local Dask cluster (a scheduler and two worker processes on 127.0.0.1; the runs
launched two at a time, their steps executed by the workers).

Every mode starts from an empty artifacts folder and Dagster instance, in a project folder whose
registry holds only the N partitions (so ``--all`` means them); the datasets are generated before
timing. Each mode is one ``atlas-gs run`` process, timed by wall clock. The Dask mode also checks
that its artifacts are byte-identical to the serial run's (run ids and times in the bundle's
lineage aside).

    python benchmarks/bench_parallel.py                 # 4 partitions, a table
    python benchmarks/bench_parallel.py --partitions 2 --json

    python benchmarks/bench_parallel.py --repeat 3      # three serial/parallel pairs, the median one

Exit status 1 when the parallel run takes more than 0.65x the serial time (the median pair's, with
``--repeat``), or a run fails.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SPEC = {"n_frames": 12, "width": 160, "height": 120, "fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5}
TARGET_RATIO = 0.65  # parallel wall time at most this fraction of serial (2 cores)
RUN_SPECIFIC = ("run_id", "created_at", "created_utc")


def make_project(base: Path, names: list[str], frames: int) -> Path:
    import yaml

    (base / "configs").mkdir(parents=True)
    for p in (ROOT / "configs").glob("*.yaml"):
        if not p.name.startswith("datasets"):
            shutil.copy(p, base / "configs" / p.name)
    entries = {n: {"kind": "synthetic", **SPEC, "n_frames": frames, "seed": i} for i, n in enumerate(names)}
    (base / "configs" / "datasets.yaml").write_text(yaml.safe_dump({"datasets": entries}))
    return base


def children_cpu_s() -> float:
    """CPU seconds (user + system) of every finished child process so far, with the processes
    they waited for (an ``atlas-gs run`` with its pool workers and their encoders)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


CPU_S: dict[str, float] = {}  # tag -> CPU seconds of that ``atlas-gs run`` command
SPAN: dict[str, tuple[float, float]] = {}  # tag -> (start, end) of that command, seconds since the epoch


def run_all(env: dict[str, str], tag: str, work: Path, extra: list[str]) -> tuple[float, list[dict]]:
    env = {**env, "ATLAS_ARTIFACTS_DIR": str(work / f"artifacts-{tag}"), "DAGSTER_HOME": str(work / f"home-{tag}")}
    Path(env["DAGSTER_HOME"]).mkdir()
    cpu0, t0, epoch0 = children_cpu_s(), time.perf_counter(), time.time()
    out = subprocess.run([sys.executable, "-m", "assets.cli", "run", "--all", "--json", *extra], env=env, cwd=ROOT,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    CPU_S[tag] = children_cpu_s() - cpu0
    SPAN[tag] = (epoch0, epoch0 + wall)
    try:
        docs = json.loads(out.stdout)  # one document: a list of the partitions' summaries
    except ValueError:
        docs = []
    if out.returncode != 0 or not docs:
        sys.stderr.write(out.stderr[-4000:])
    return wall, docs


def run_spans(work: Path, tag: str) -> list[tuple[float, float]]:
    """(start, end) of each partition's Dagster run, seconds since the epoch (the instance's run records)."""
    from dagster import DagsterInstance

    home = work / f"home-{tag}"
    with DagsterInstance.from_config(str(home)) as inst:
        return [(r.start_time, r.end_time) for r in inst.get_run_records() if r.start_time and r.end_time]


def outside_runs(tag: str, spans: list[tuple[float, float]]) -> tuple[float, float]:
    """Seconds of the command before its first run started (its start: imports, the instance, the
    pool) and after its last run ended (its shutdown); NaN when no run ended (the command failed)."""
    t0, t1 = SPAN[tag]
    if not spans:
        return float("nan"), float("nan")
    return min(s for s, _ in spans) - t0, t1 - max(e for _, e in spans)


def digest(art: Path, partition: str) -> dict:
    out = {}
    for rec_path in sorted(art.glob(f"*/{partition}/_artifact.json")):
        rec = json.loads(rec_path.read_text())
        files = {n: f["sha256"] for n, f in rec["files"].items()}
        if rec_path.parent.parent.name == "world_bundle":
            def strip(v):
                if isinstance(v, dict):
                    return {k: strip(x) for k, x in v.items() if k not in RUN_SPECIFIC}
                return [strip(x) for x in v] if isinstance(v, list) else v
            files["metadata.json"] = strip(json.loads((rec_path.parent / "metadata.json").read_text()))
        out[rec_path.parent.parent.name] = files
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--partitions", type=int, default=4)
    ap.add_argument("--frames", type=int, default=SPEC["n_frames"])
    ap.add_argument("--concurrency", type=int, default=2)
    ap.add_argument("--dask-workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1,
                    help="serial and parallel runs this many times, alternating (this VM's wall times vary by "
                         "a few seconds from run to run); the ratio is then the median of the pairs'")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    names = [f"bench-{i}" for i in range(args.partitions)]
    with tempfile.TemporaryDirectory(prefix="atlas-bench-parallel-") as tmp:
        work = Path(tmp)
        env = {**os.environ, "ATLAS_PROJECT_ROOT": str(make_project(work / "project", names, args.frames)),
               "ATLAS_LOCAL_REGISTRY": str(work / "no-local-registry.yaml"), "ATLAS_DATA_DIR": str(work / "data")}
        os.environ.update({k: env[k] for k in ("ATLAS_PROJECT_ROOT", "ATLAS_LOCAL_REGISTRY", "ATLAS_DATA_DIR")})
        from atlas_pipeline.sensors.registry import ensure_dataset_files, load_registry

        for entry in load_registry().values():  # generated before timing
            ensure_dataset_files(entry)

        pairs = []
        run_s: dict[str, list[float]] = {"serial": [], "parallel": []}
        edges: dict[str, tuple[float, float]] = {}
        for i in range(max(1, args.repeat)):
            tag = "" if i == 0 else f"-{i}"
            serial_run = run_all(env, "serial" + tag, work, ["--concurrency", "1"])
            parallel_run = run_all(env, "parallel" + tag, work, ["--concurrency", str(args.concurrency)])
            pairs.append((serial_run, parallel_run))
            for mode in ("serial", "parallel"):
                spans = run_spans(work, mode + tag)
                run_s[mode] += [e - s for s, e in spans]
                edges[mode + tag] = outside_runs(mode + tag, spans)
        # The pair whose ratio is the median (the lower middle one for an even count).
        ratios = [p[1][0] / p[0][0] for p in pairs]
        median = sorted(range(len(pairs)), key=ratios.__getitem__)[(len(pairs) - 1) // 2]
        (s_wall, s_docs), (p_wall, p_docs) = pairs[median]
        median_tag = "" if median == 0 else f"-{median}"
        cpu = {m: CPU_S[m + median_tag] for m in ("serial", "parallel")}
        start_s, end_s = edges["parallel" + median_tag]
        rows = [("serial", s_wall, s_docs), (f"parallel (concurrency {args.concurrency})", p_wall, p_docs)]

        from distributed import LocalCluster

        # Each worker's numba gets its share of the cores, as the parallel pool's workers do.
        os.environ.setdefault("NUMBA_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // args.dask_workers)))
        t0 = time.perf_counter()
        cluster = LocalCluster(n_workers=args.dask_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               scheduler_port=0, dashboard_address=None, silence_logs=logging.ERROR)
        cluster_s = time.perf_counter() - t0
        try:
            wall, docs = run_all(env, "dask", work, ["--concurrency", str(args.concurrency), "--executor", "dask",
                                                     "--dask-scheduler", cluster.scheduler_address])
        finally:
            cluster.close()
        rows.append((f"dask ({args.dask_workers} workers, {args.concurrency} runs at a time)", wall, docs))

        identical = all(digest(work / "artifacts-dask", n) == digest(work / "artifacts-serial", n)
                        and digest(work / "artifacts-dask", n) for n in names)

    serial = rows[0][1]
    med = {k: float(np.median(v)) if v else float("nan") for k, v in run_s.items()}
    cores = os.cpu_count() or 1
    # The parallel run's floor: its start and shutdown as measured (one process, one core busy),
    # every other CPU second spread over all the cores with none idle.
    floor_s = start_s + end_s + max(0.0, cpu["parallel"] - start_s - end_s) / cores
    result = {"partitions": args.partitions, "frames": args.frames, "cores": os.cpu_count(),
              "median_partition_run_s": {k: round(v, 2) for k, v in med.items()},
              "pairs": [{"serial_s": round(a[0], 2), "parallel_s": round(b[0], 2), "ratio": round(b[0] / a[0], 3),
                         "succeeded": sum(bool(d.get("success")) for d in a[1] + b[1])} for a, b in pairs],
              # the median pair's CPU seconds and the cores they kept busy on average: on C cores a
              # run cannot take less than its CPU seconds / C, and the serial run already keeps
              # more than one busy (the kernels' threads, the encoder's)
              "cpu_s": {m: round(v, 1) for m, v in cpu.items()},
              "cores_busy": {"serial": round(cpu["serial"] / s_wall, 2), "parallel": round(cpu["parallel"] / p_wall, 2)},
              "parallel_start_s": round(start_s, 2), "parallel_shutdown_s": round(end_s, 2),
              "parallel_floor_s": round(floor_s, 2), "parallel_floor_ratio": round(floor_s / s_wall, 3),
              "dask_cluster_start_s": round(cluster_s, 2), "dask_identical_to_serial": identical,
              "modes": [{"mode": m, "wall_s": round(w, 2), "ratio_to_serial": round(w / serial, 3),
                         "succeeded": sum(bool(d.get("success")) for d in docs)} for m, w, docs in rows]}
    ok = (all(r["succeeded"] == args.partitions for r in result["modes"])
          and all(p["succeeded"] == 2 * args.partitions for p in result["pairs"])
          and result["modes"][1]["ratio_to_serial"] <= TARGET_RATIO)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{args.partitions} synthetic partitions x {args.frames} frames, {os.cpu_count()} cores\n")
        if len(pairs) > 1:
            print("pairs (serial, parallel, ratio): " + "; ".join(
                f"{p['serial_s']:.1f} s, {p['parallel_s']:.1f} s, {p['ratio']:.2f}x" for p in result["pairs"])
                  + " -- the table shows the median pair\n")
        print(f"| {'mode':<40s} | wall s | x serial | ok |")
        print(f"|{'-' * 42}|--------|----------|----|")
        for r in result["modes"]:
            print(f"| {r['mode']:<40s} | {r['wall_s']:6.1f} | {r['ratio_to_serial']:8.2f} | "
                  f"{r['succeeded']}/{args.partitions} |")
        print(f"\nCPU seconds (the table's pair): serial {cpu['serial']:.1f} ({cpu['serial'] / s_wall:.2f} cores busy on "
              f"average), parallel {cpu['parallel']:.1f} ({cpu['parallel'] / p_wall:.2f}); on {os.cpu_count()} cores the "
              f"parallel run cannot take less than {cpu['parallel'] / (os.cpu_count() or 1):.1f} s "
              f"({cpu['parallel'] / (os.cpu_count() or 1) / s_wall:.2f}x serial)")
        print(f"The parallel command's start (to its first run) took {start_s:.2f} s and its shutdown (after its "
              f"last run) {end_s:.2f} s; with those on one core and every other CPU second spread over {cores} cores, "
              f"it cannot take less than {floor_s:.1f} s ({floor_s / s_wall:.2f}x serial)")
        print(f"One partition's Dagster run (median of all): {med['serial']:.2f} s in the serial runs, "
              f"{med['parallel']:.2f} s two at a time ({med['parallel'] / med['serial']:.2f}x); the rest of the wall "
              "time is the command's start and shutdown.")
        print(f"Dask cluster start (not in the time): {cluster_s:.1f} s; Dask artifacts byte-identical to the "
              f"serial run's: {identical}; target parallel <= {TARGET_RATIO}x serial: {'met' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

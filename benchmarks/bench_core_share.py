"""Recordings of different lengths at once: ``atlas-gs run --all --concurrency 2`` on a short and a
long synthetic partition, with each worker's kernels on a fixed share of the cores (the cores
divided by the concurrency, as ``$NUMBA_NUM_THREADS`` set for the whole command gives: the
reference) against the share that follows the runs still going (the default: once the short run
ends, the long one's kernels take its cores).

Every run starts from an empty artifacts folder and Dagster instance; the datasets are generated
before timing; the two settings alternate, ``--repeat`` times each, and the table gives each
one's median wall time and CPU seconds.

    python benchmarks/bench_core_share.py                       # 12 and 48 frames, 3 runs each
    python benchmarks/bench_core_share.py --frames 12 96 --repeat 5 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_parallel import make_project, run_all, CPU_S  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs=2, default=[12, 48], metavar=("SHORT", "LONG"))
    ap.add_argument("--concurrency", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import yaml

    cores = os.cpu_count() or 1
    fixed = str(max(1, cores // args.concurrency))
    with tempfile.TemporaryDirectory(prefix="atlas-bench-share-") as tmp:
        work = Path(tmp)
        project = make_project(work / "project", ["short", "long"], args.frames[0])
        reg = project / "configs" / "datasets.yaml"
        entries = yaml.safe_load(reg.read_text())
        entries["datasets"]["long"]["n_frames"] = args.frames[1]
        reg.write_text(yaml.safe_dump(entries))
        env = {**os.environ, "ATLAS_PROJECT_ROOT": str(project),
               "ATLAS_LOCAL_REGISTRY": str(work / "no-local-registry.yaml"), "ATLAS_DATA_DIR": str(work / "data")}
        env.pop("NUMBA_NUM_THREADS", None)
        os.environ.update({k: env[k] for k in ("ATLAS_PROJECT_ROOT", "ATLAS_LOCAL_REGISTRY", "ATLAS_DATA_DIR")})
        from atlas_pipeline.sensors.registry import ensure_dataset_files, load_registry

        for entry in load_registry().values():  # generated before timing
            ensure_dataset_files(entry)

        modes = {"fixed": {**env, "NUMBA_NUM_THREADS": fixed}, "following": env}
        wall: dict[str, list[float]] = {m: [] for m in modes}
        cpu: dict[str, list[float]] = {m: [] for m in modes}
        ok = True
        for i in range(max(1, args.repeat)):
            for mode, mode_env in modes.items():
                tag = f"{mode}-{i}"
                w, docs = run_all(mode_env, tag, work, ["--concurrency", str(args.concurrency)])
                ok &= len(docs) == 2 and all(d.get("success") for d in docs)
                wall[mode].append(w)
                cpu[mode].append(CPU_S[tag])

    med = {m: float(np.median(v)) for m, v in wall.items()}
    result = {"frames": args.frames, "concurrency": args.concurrency, "cores": cores, "repeat": args.repeat,
              "wall_s": {m: [round(x, 2) for x in v] for m, v in wall.items()},
              "median_wall_s": {m: round(v, 2) for m, v in med.items()},
              "median_cpu_s": {m: round(float(np.median(v)), 1) for m, v in cpu.items()},
              "ratio_following_to_fixed": round(med["following"] / med["fixed"], 3), "all_succeeded": ok}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"2 synthetic partitions ({args.frames[0]} and {args.frames[1]} frames), --concurrency "
              f"{args.concurrency}, {cores} cores, {args.repeat} runs each\n")
        print("| kernels' share of the cores | wall s (median) | runs | CPU s (median) | x fixed |")
        print("|---|---|---|---|---|")
        for m, label in (("fixed", f"fixed ({fixed} thread(s) a worker, NUMBA_NUM_THREADS)"),
                         ("following", "following the runs still going (default)")):
            print(f"| {label} | {med[m]:.1f} | {', '.join(f'{x:.1f}' for x in wall[m])} | "
                  f"{result['median_cpu_s'][m]:.1f} | {med[m] / med['fixed']:.2f} |")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Relocalization in an imported PLY world against the world it came from.

A world bundle carries its own tracking map (``surfels.npz``, from the voxel statistics); a PLY
imported with ``atlas-gs import-ply`` has only the Gaussians, so the tracker's surfels come from
their centres. This builds the dataset's world (``atlas-gs build``) with the keyframe fit on and
off, imports each world's ``gaussians.ply``, and relocalizes the given frames
(``atlas-gs relocalize``, no initial pose) in all four worlds; ground truth only grades.

    python benchmarks/bench_import_ply.py                       # the tests' small synthetic scene
    python benchmarks/bench_import_ply.py --dataset synthetic --frames 5 20 35 50

Without ``--dataset`` the scene is ``tests/conftest.py``'s ``SMALL_SYNTH`` (12 frames, 160x120),
generated into a temporary folder.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# tests/conftest.py SMALL_SYNTH (a test keeps the two equal)
SMALL_SYNTH = {"seed": 0, "n_frames": 12, "width": 160, "height": 120, "fx": 131.25, "fy": 131.25, "cx": 79.5,
               "cy": 59.5}
SMALL_NAME = "synth-small"
DEFAULT_FRAMES = (3, 5, 8, 11)


def _cli(args: list[str]) -> dict | None:
    """``atlas-gs`` in this process; its JSON output (None when it printed none)."""
    from assets.cli import main

    buf, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        code = main(args)
    if code != 0:
        sys.stderr.write(err.getvalue())
        raise SystemExit(f"atlas-gs {' '.join(args)} failed with exit code {code}")
    text = buf.getvalue().strip()
    return json.loads(text) if text.startswith("{") else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=None, help="a registered dataset (default: the tests' small synthetic scene)")
    ap.add_argument("--frames", type=int, nargs="+", default=list(DEFAULT_FRAMES), help="frames to relocalize")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for both builds (repeatable), as atlas-gs build --set")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="atlas-bench-import-ply-") as tmp:
        work = Path(tmp)
        os.environ["ATLAS_ARTIFACTS_DIR"] = str(work / "artifacts")
        dataset = args.dataset
        if dataset is None:
            import yaml

            reg = work / "datasets.local.yaml"
            reg.write_text(yaml.safe_dump({"datasets": {SMALL_NAME: {"kind": "synthetic", **SMALL_SYNTH}}}))
            os.environ["ATLAS_LOCAL_REGISTRY"] = str(reg)
            os.environ["ATLAS_DATA_DIR"] = str(work / "data")
            dataset = SMALL_NAME
        print(f"# reproduce: python benchmarks/bench_import_ply.py {' '.join(argv if argv is not None else sys.argv[1:])}")
        print(f"# dataset {dataset}, frames {args.frames}; relocalization error against ground truth, cm\n")
        print("| world | keyframe fit | " + " | ".join(f"frame {f}" for f in args.frames) + " | build s |")
        print("|---|---|" + "---|" * len(args.frames) + "---|")
        common = [a for kv in args.set for a in ("--set", kv)]
        for fit, extra in (("on", common), ("off", [*common, "--set", "mapping.fit.epochs=0"])):
            world = work / f"world-fit-{fit}"
            t0 = time.perf_counter()
            _cli(["build", "--input", dataset, "--output", str(world), *extra])
            build_s = time.perf_counter() - t0
            imported = work / f"imported-fit-{fit}"
            _cli(["import-ply", str(world / "gaussians.ply"), "--output", str(imported)])
            for label, w in (("bundle (its surfels.npz)", world), ("imported PLY", imported)):
                errs = []
                for f in args.frames:
                    out = _cli(["relocalize", "--world", str(w), "--input", dataset, "--frame", str(f)])
                    e = out["frames"][0].get("error_t_m") if out else None
                    errs.append("-" if e is None else f"{e * 100:.2f}")
                print(f"| {label} | {fit} | " + " | ".join(errs) + f" | {build_s:.1f} |")
        print(_centre_shift(work / "world-fit-on", work / "world-fit-off"))
    return 0


def _centre_shift(fitted: Path, unfitted: Path) -> str:
    """How far the keyframe fit moved the Gaussians' centres: the same voxel ids with the fit on
    and off (the fit's densified Gaussians, which have no counterpart, left out)."""
    import numpy as np

    from atlas_pipeline.scene_memory.bundle import load_world_bundle

    a = load_world_bundle(fitted, "bin").field
    b = load_world_bundle(unfitted, "bin").field
    _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    from atlas_pipeline.geometry import quat_xyzw_to_rotmat

    d = a.positions[ia] - b.positions[ib]  # [M, 3] world frame, m
    m = np.linalg.norm(d, axis=1)
    mean = d.mean(axis=0) * 100
    # Along the surface normal: the unfitted Gaussian's thinnest axis.
    R = quat_xyzw_to_rotmat(b.rotations_xyzw[ib].astype(np.float64))  # [M, 3, 3]
    normal = R[np.arange(len(ib)), :, np.argmin(b.scales[ib], axis=1)]  # [M, 3]
    along = np.abs(np.einsum("ij,ij->i", d, normal))
    return (f"\nThe fit moved the centres of {len(ia):,} Gaussians (of {len(a.ids):,} fitted, {len(b.ids):,} unfitted): "
            f"median {np.median(m) * 100:.2f} cm, 90th percentile {np.percentile(m, 90) * 100:.2f} cm; along the "
            f"surface normal median {np.median(along) * 100:.2f} cm, 90th percentile {np.percentile(along, 90) * 100:.2f} cm; "
            f"mean displacement ({mean[0]:.2f}, {mean[1]:.2f}, {mean[2]:.2f}) cm in the world frame.")


if __name__ == "__main__":
    raise SystemExit(main())

"""Our chunked 3DGS PLY writer against plyfile's, in the same run, on the same world.

Both write the same vertex layout (``scene_memory.ply._WRITE_DTYPE``: 3DGS properties, uint8
colours, id halves). plyfile's writer takes one structured array of every vertex, so its run
encodes the whole world into one array first (what a caller of plyfile must do); ours encodes and
writes ``_CHUNK`` vertices at a time. Reading is timed too: ``read_gaussian_ply`` (plyfile,
memory-mapped, decoded in chunks). Peak memory is tracemalloc's (NumPy allocations included),
beyond the world itself.

    python benchmarks/bench_ply.py                  # 2,000,000 Gaussians, best of 3
    python benchmarks/bench_ply.py --n 200000 --repeats 5
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEFAULT_N = 2_000_000
DEFAULT_REPEATS = 3
MIB = 1 << 20


def _make_field(n: int):
    """The deterministic room-surface world of ``bench_big_world.py``."""
    spec = importlib.util.spec_from_file_location("bench_big_world", ROOT / "benchmarks" / "bench_big_world.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.make_field(n)


def _plyfile_write(field, path: Path) -> None:
    from plyfile import PlyData, PlyElement

    from atlas_pipeline.scene_memory import ply as ply_mod

    rows = ply_mod._encode_vertices(field)  # [N] structured, the whole world at once
    PlyData([PlyElement.describe(rows, "vertex")], byte_order="<",
            comments=["Atlas-GS Gaussian world (3DGS layout)"]).write(str(path))


def _timed(fn, repeats: int) -> tuple[float, float]:
    """Best wall time (s) over ``repeats`` and the peak traced memory (MiB) of one run."""
    best = float("inf")
    for _ in range(repeats):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    gc.collect()
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1] / MIB
    tracemalloc.stop()
    return best, peak


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=DEFAULT_N, help="Gaussians (default 2,000,000)")
    ap.add_argument("--repeats", type=int, default=DEFAULT_REPEATS)
    args = ap.parse_args(argv)

    from atlas_pipeline.scene_memory.ply import read_gaussian_ply, write_gaussian_ply

    field = _make_field(args.n)
    with tempfile.TemporaryDirectory() as tmp:
        ours, theirs = Path(tmp) / "ours.ply", Path(tmp) / "plyfile.ply"
        t_ours, m_ours = _timed(lambda: write_gaussian_ply(field, ours), args.repeats)
        t_theirs, m_theirs = _timed(lambda: _plyfile_write(field, theirs), args.repeats)
        body_ours = ours.read_bytes().split(b"end_header\n", 1)[1]
        body_theirs = theirs.read_bytes().split(b"end_header\n", 1)[1]
        same = body_ours == body_theirs
        t_read, m_read = _timed(lambda: read_gaussian_ply(ours), args.repeats)
        assert read_gaussian_ply(theirs).equals(field)
        size = ours.stat().st_size
    print(f"{args.n:,} Gaussians, {size / MIB:.0f} MiB PLY, best of {args.repeats}; peak = traced memory beyond "
          f"the world ({len(field) * 55 / MIB:.0f} MiB)")
    print(f"{'':28s} {'seconds':>8s} {'M vertices/s':>13s} {'peak MiB':>9s}")
    for name, t, m in (("write, ours (chunked)", t_ours, m_ours), ("write, plyfile", t_theirs, m_theirs),
                       ("read_gaussian_ply (plyfile)", t_read, m_read)):
        print(f"{name:28s} {t:8.2f} {args.n / t / 1e6:13.2f} {m:9.0f}")
    print(f"vertex data identical: {same}; ours is {t_theirs / t_ours:.2f}x plyfile's speed, "
          f"{m_theirs / max(m_ours, 1e-9):.1f}x less memory")
    return 0


if __name__ == "__main__":
    sys.exit(main())

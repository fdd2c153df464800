"""Atlas-GS: RGB-D observations in, a persistent 3D Gaussian world out.

The library is orchestrator-agnostic: nothing here imports Dagster. The Dagster layer lives in the
top-level ``assets`` package and only calls into these modules.
"""

__version__ = "0.1.0"


def _default_numba_cache() -> None:
    """An installed copy keeps Numba's compiled kernels in the user's cache, never in site-packages
    (a source checkout keeps them beside the sources, as Numba does by default). Set before any
    kernel module imports Numba; ``NUMBA_CACHE_DIR`` set by the user wins."""
    import os
    from pathlib import Path

    if "NUMBA_CACHE_DIR" in os.environ:
        return
    root = Path(__file__).resolve().parents[1]
    if (root / "pyproject.toml").is_file():  # a source checkout
        return
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    os.environ["NUMBA_CACHE_DIR"] = str(Path(base) / "atlas-gs" / "numba")


# GNU OpenMP (Numba's "omp" threading layer here, and Open3D's) spins at every barrier by default.
# With any other busy process on the machine (a second run, a test, a benchmark), a kernel's
# threads then burn their time slices spinning while the thread they wait for is descheduled
# (benchmarks/bench_openmp_wait.py measures it). Waking a sleeping OpenMP thread is slow in a VM
# (~2 ms), so kernels called many times per frame on little work split their chunks over plain
# threads instead (localization/normal_equations.py); on a machine of your own,
# OMP_WAIT_POLICY=ACTIVE avoids the wake-ups.
OPENMP_WAIT_POLICY = "PASSIVE"


def _default_openmp_wait_policy() -> None:
    """Threads of parallel kernels sleep instead of spinning while they wait (see
    :data:`OPENMP_WAIT_POLICY`). OpenMP reads it once, when its runtime loads: set before Numba or
    Open3D starts any thread; ``OMP_WAIT_POLICY`` set by the user wins."""
    import os

    os.environ.setdefault("OMP_WAIT_POLICY", OPENMP_WAIT_POLICY)


_default_numba_cache()
_default_openmp_wait_policy()

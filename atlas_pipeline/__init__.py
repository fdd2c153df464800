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


_default_numba_cache()

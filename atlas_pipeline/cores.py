"""How many threads this process's compiled (Numba) kernels use, and a way for whoever runs
several processes side by side to change it while they run.

By default the kernels use Numba's own count (``$NUMBA_NUM_THREADS``, else every core). A pool of
runs (``atlas-gs run --all``) gives each process its share of the cores, and gives a process the
cores others have left once they are done: :func:`use_core_share` installs a callable that says the
share now, and :func:`kernel_threads`, called before the heavy kernels (the rasterizer's compositing,
the fit's tile streams, the tracker's alignment), applies it. Numba's count is per thread and
persists, so the kernels launched in between follow the last value set. The kernels' results do
not depend on the count (tests check renders and worlds byte for byte across thread counts).
"""

from __future__ import annotations

from typing import Callable

import numba

_share_now: Callable[[], int] | None = None  # this process's share of the cores now, when a pool set one


def use_core_share(share_now: Callable[[], int] | None) -> None:
    """From now on, :func:`kernel_threads` sets Numba's thread count to ``share_now()`` (capped at the
    threads Numba started with; ``None``: leave the count alone). ``share_now`` is called before
    each heavy kernel, so it must be cheap (a read of a shared counter)."""
    global _share_now
    _share_now = share_now


def kernel_threads() -> int:
    """Threads the next kernel launched from this thread may use: the share now, where a pool set
    one (applied to Numba's count for this thread), else Numba's count."""
    if _share_now is not None:
        wanted = max(1, min(int(_share_now()), numba.config.NUMBA_NUM_THREADS))
        if wanted != numba.get_num_threads():
            numba.set_num_threads(wanted)
    return numba.get_num_threads()

"""The tracker's Gauss-Newton normal equations on this process's share of the cores.

A call holds 2k to 40k frame points and takes 0.3 to 2.5 ms on one core, about a dozen calls a
frame. Numba's own parallel loop costs more than that to wake its OpenMP threads in a VM (see
:mod:`atlas_pipeline.localization._kernels`); a hand-off to a waiting Python thread costs about
50 microseconds. So the :data:`~atlas_pipeline.localization._kernels.N_CHUNKS` chunks of a call
are shared out: the calling thread runs its share, persistent worker threads the others (the
chunk kernel releases the GIL), and the chunks' sums are added in chunk order. The result is
the same, bit for bit, however many threads ran it.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

from atlas_pipeline.cores import kernel_threads
from atlas_pipeline.localization import _kernels as kn

__all__ = ["normal_equations", "SPLIT_MIN_POINTS"]

# Below this many points a call runs on the calling thread alone: the hand-off would cost a
# sizeable share of the work it saves (at 3-6k points a split call takes 0.27 ms against 0.39).
SPLIT_MIN_POINTS = 2000

# Chunks handed to a worker at a time: a smaller job leaves more for the calling thread to take
# back from a worker held up elsewhere, and each costs a hand-off.
JOB_CHUNKS = 2

_lock = threading.Lock()
_workers: ThreadPoolExecutor | None = None
_workers_pid = -1  # a forked child must not reuse its parent's threads (they do not exist there)
_workers_n = 0


def _pool(n: int) -> ThreadPoolExecutor:
    """This process's worker threads, ``n`` of them (made again when ``n`` grew or after a fork)."""
    global _workers, _workers_pid, _workers_n
    with _lock:
        if _workers is None or _workers_pid != os.getpid() or _workers_n < n:
            # Not shut down: another thread may still hand it work. Its idle threads end when
            # the last reference to it goes.
            _workers = ThreadPoolExecutor(n, thread_name_prefix="atlas-normal-equations")
            _workers_pid, _workers_n = os.getpid(), n
        return _workers


def normal_equations(frame: kn.FramePoints, T_world_cam, model: kn.ModelView, ref: kn.ReferenceImage,
                     params: kn.Params, threads: int | None = None) -> tuple:
    """:func:`~atlas_pipeline.localization._kernels.normal_equations` of ``frame`` at
    ``T_world_cam`` ``[4, 4]``, its chunks run on ``threads`` threads (default: this process's
    share of the cores now, :func:`~atlas_pipeline.cores.kernel_threads`; one below
    :data:`SPLIT_MIN_POINTS` points). Returns ``(H [6, 6], g [6], Stats)``, the same whatever
    the thread count."""
    n_pts = frame.points_cam.shape[0]
    if threads is None:
        threads = kernel_threads() if n_pts >= SPLIT_MIN_POINTS else 1
    threads = max(1, min(int(threads), kn.N_CHUNKS))
    if threads == 1:
        return kn.normal_equations(frame, T_world_cam, model, ref, params)
    sums = kn.chunk_sums()
    args = (frame, T_world_cam, model, ref, params, sums)
    own = kn.N_CHUNKS // threads
    pool = _pool(threads - 1)
    # The rest go to the workers a few chunks at a time: whatever a worker has not started when the
    # calling thread is done with its own (the core busy with another thread: the frame reader, a
    # second run) the calling thread takes back, from the last, instead of waiting for it.
    jobs = [(c, min(c + JOB_CHUNKS, kn.N_CHUNKS)) for c in range(own, kn.N_CHUNKS, JOB_CHUNKS)]
    futures = [pool.submit(kn.normal_equation_chunks, lo, hi, *args) for lo, hi in jobs]
    kn.normal_equation_chunks(0, own, *args)
    for (lo, hi), job in zip(reversed(jobs), reversed(futures)):
        if job.cancel():
            kn.normal_equation_chunks(lo, hi, *args)
    for job in futures:
        if not job.cancelled():
            job.result()
    return kn.add_chunks(n_pts, sums)

"""The compiled kernels' share of the cores (``atlas_pipeline.cores``) and how ``run --all``'s pool
changes it as runs end."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numba
import numpy as np
import pytest

from assets.launch import CoreShare, init_worker
from atlas_pipeline.cores import kernel_threads, use_core_share
from atlas_pipeline.gaussian_world import raster as rc
from atlas_pipeline.gaussian_world.composite import composite_tiles
from tests.test_raster import BACKGROUND, _scene, _view


@pytest.fixture
def restore_threads():
    before = numba.get_num_threads()
    yield
    use_core_share(None)
    numba.set_num_threads(before)


def test_kernels_follow_the_share_capped_at_numbas_threads(restore_threads):
    most = numba.config.NUMBA_NUM_THREADS
    assert kernel_threads() == numba.get_num_threads()  # no share: numba's own count, untouched
    share = [1]
    use_core_share(lambda: share[0])
    assert kernel_threads() == 1 and numba.get_num_threads() == 1  # applied to numba's count
    share[0] = 10 * most
    assert kernel_threads() == most  # never more than numba started with
    share[0] = 0
    assert kernel_threads() == 1  # at least one
    use_core_share(None)
    numba.set_num_threads(most)
    assert kernel_threads() == most  # an uninstalled share changes nothing


def test_a_render_does_not_depend_on_the_share(restore_threads):
    """The tiles are split among the threads the share allows; each tile is drawn alone, so the
    image is the same byte for byte."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one core: nothing to compare")
    sp = rc.prepare_splats(*_scene(800, 3), _view())
    images = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        use_core_share(lambda t=threads: t)
        images.append(composite_tiles(sp, BACKGROUND))
    for a, b in zip(*images):
        np.testing.assert_array_equal(a, b)


def test_the_share_divides_the_cores_among_the_runs_still_going():
    counter = multiprocessing.get_context("spawn").Value("i", 4)
    share = CoreShare(counter, concurrency=2, cores=2)
    assert share() == 1  # two runs at a time on two cores
    counter.value = 1
    assert share() == 2  # the last run gets the core the other left
    counter.value = 0
    assert share() == 2
    wide = CoreShare(counter, concurrency=3, cores=8)
    counter.value = 5
    assert wide() == 2  # 8 // 3
    counter.value = 2
    assert wide() == 4


def _threads_after(lower_by: int) -> tuple[int, int]:
    """In a pool worker: numba's count after the worker's start, then after ``lower_by`` runs end."""
    from assets import launch
    from atlas_pipeline.cores import kernel_threads

    first = numba.get_num_threads()
    with launch._POOL_SHARE.unfinished.get_lock():
        launch._POOL_SHARE.unfinished.value -= lower_by
    return first, kernel_threads()


def test_a_pool_worker_starts_with_its_share_and_takes_the_cores_left():
    cores = numba.config.NUMBA_NUM_THREADS
    if cores < 2:
        pytest.skip("one core: every share is one thread")
    context = multiprocessing.get_context("spawn")  # this process may have started numba's threads
    share = CoreShare(context.Value("i", 2), concurrency=2, cores=cores)
    with ProcessPoolExecutor(max_workers=1, mp_context=context, initializer=init_worker,
                             initargs=(share,)) as pool:
        first, later = pool.submit(_threads_after, 1).result()
    assert first == cores // 2  # set before any kernel ran
    assert later == cores  # the other run ended: all the cores

"""The thread-count context every parallel entry point runs under."""

from __future__ import annotations

import numba
import pytest

from noise_model.numba_config import layer_is_threadsafe, resolve_threads, threads


def test_threads_sets_the_count_inside_and_restores_it_after():
    before = numba.get_num_threads()
    other = 1 if before != 1 else numba.config.NUMBA_NUM_THREADS
    with threads(other) as n:
        assert n == other and numba.get_num_threads() == other
    assert numba.get_num_threads() == before
    with threads(before) as n:                     # the same count: nothing set, nothing restored
        assert n == before == numba.get_num_threads()
    assert numba.get_num_threads() == before


def test_threads_restores_the_count_when_the_body_raises():
    before = numba.get_num_threads()
    with pytest.raises(RuntimeError):
        with threads(1):
            raise RuntimeError("body")
    assert numba.get_num_threads() == before


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2", 10_000])
def test_a_bad_thread_count_is_refused(bad):
    with pytest.raises(ValueError, match="nthreads"):
        resolve_threads(bad)


def test_the_layer_is_known_after_a_parallel_launch_and_stays_so():
    import numpy as np

    from noise_model.valid_margin import drop_valid_margin

    drop_valid_margin(np.ones((4, 8), np.uint16), 1, nthreads=1)       # a parallel launch picks the layer
    first = layer_is_threadsafe()
    assert first in (True, False)
    assert layer_is_threadsafe() is first

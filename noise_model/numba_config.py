"""numba settings shared by every compiled kernel of ``noise_model`` and ``elevmap``.

``JIT`` is the one keyword set every ``@njit`` takes (``@njit(**JIT)``, ``@njit(parallel=True, **JIT)``):

* ``fastmath=FASTMATH``: never ``fastmath=True``, which adds ``nnan``/``ninf`` and lets LLVM fold
  ``isnan`` to False (NaN is the map's "unknown"); ``arcp`` is left out too, because a reciprocal in
  place of a division moves points across cell borders (``floor(x / res)``).
* ``error_model="numpy"``: division by zero gives inf/NaN as in NumPy instead of raising.
* ``cache=True``: compiled code is kept on disk (``NUMBA_CACHE_DIR``) so a new process starts fast.

Thread counts are passed into every parallel entry point as ``nthreads`` and applied with
:func:`threads`, which restores numba's previous setting afterwards. Parallel kernels split their work
so that every output element is written by one thread in a fixed order: results are bit-identical
whatever the thread count.
"""

from __future__ import annotations

import contextlib

import numba

__all__ = ["FASTMATH", "JIT", "resolve_threads", "threads"]

#: numba fastmath flags: no nnan/ninf (isnan must work), no arcp (exact division for binning).
FASTMATH = {"nsz", "contract", "afn", "reassoc"}

#: Keyword arguments of every ``numba.njit`` in the project.
JIT = dict(fastmath=FASTMATH, error_model="numpy", cache=True)


def resolve_threads(nthreads) -> int:
    """Validate a thread count (None = numba's current setting) against numba's maximum."""
    if nthreads is None:
        return numba.get_num_threads()
    if isinstance(nthreads, bool) or not hasattr(nthreads, "__index__"):      # int or NumPy integer
        raise ValueError(f"nthreads must be an integer in [1, {numba.config.NUMBA_NUM_THREADS}], got {nthreads!r}")
    n = int(nthreads)
    if n < 1 or n > numba.config.NUMBA_NUM_THREADS:
        raise ValueError(f"nthreads must be in [1, {numba.config.NUMBA_NUM_THREADS}], got {nthreads}")
    return n


@contextlib.contextmanager
def threads(nthreads):
    """Run the body with numba's thread count set to ``nthreads`` (validated), then restore it.

    Yields the resolved count.
    """
    n = resolve_threads(nthreads)
    previous = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        yield n
    finally:
        numba.set_num_threads(previous)

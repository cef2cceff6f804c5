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

OpenMP's threads spin only briefly before they sleep (``GOMP_SPINCOUNT=10000`` unless the user's
environment sets it or ``OMP_WAIT_POLICY``): a kernel's threads meet at a barrier after each parallel
region, and with libgomp's default spin (300,000 rounds) a thread that waits for a partner descheduled by
any other busy process burns its own time slice too, so a frame costs whole time slices per region on a
machine that also runs a robot's other software. Sleeping at once (``OMP_WAIT_POLICY=PASSIVE``) is as
robust but pays a wake-up per region on an idle machine; a short spin keeps most of the idle speed. The
variable is read when the OpenMP runtime loads (numba's first parallel launch), so it is set here, before
any kernel runs; a program that loaded OpenMP earlier keeps its own setting. docs/noise-model.md gives
the measured cost and gain.
"""

from __future__ import annotations

import contextlib
import os
import threading

#: libgomp's spin before a waiting thread sleeps, unless the user chose a wait policy or a spin count.
SPINCOUNT = "10000"
if "OMP_WAIT_POLICY" not in os.environ:
    os.environ.setdefault("GOMP_SPINCOUNT", SPINCOUNT)

import numba  # noqa: E402  (after the spin count, which OpenMP reads once when numba loads it)

__all__ = ["FASTMATH", "JIT", "SPINCOUNT", "THREADSAFE_LAYERS", "layer_is_threadsafe", "resolve_threads", "threads"]

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


#: numba threading layers that accept parallel kernels launched from several Python threads at once.
THREADSAFE_LAYERS = ("omp", "tbb")

#: Held around every parallel region while the layer is not known to be thread-safe (see :func:`threads`).
_LAYER_LOCK = threading.RLock()


#: The answer of :func:`layer_is_threadsafe` once numba has chosen its layer (it cannot change after).
_LAYER_KNOWN: list[bool] = []


def layer_is_threadsafe() -> bool | None:
    """True for the OpenMP and TBB layers, False for numba's own ``workqueue`` (which aborts the process
    when two Python threads launch parallel kernels at once), None before the first parallel launch (numba
    picks its layer then: ``workqueue`` where neither TBB nor an OpenMP runtime such as libgomp1 is found).
    The answer is kept once known: numba loads one layer per process."""
    if _LAYER_KNOWN:
        return _LAYER_KNOWN[0]
    try:
        safe = numba.threading_layer() in THREADSAFE_LAYERS
    except ValueError:
        return None
    _LAYER_KNOWN.append(safe)
    return safe


@contextlib.contextmanager
def threads(nthreads):
    """Run the body with numba's thread count set to ``nthreads`` (validated), then restore it.

    Unless numba's threading layer is known to be thread-safe (:func:`layer_is_threadsafe`), the body runs
    under one process-wide lock: mapping from several Python threads is then serialised instead of
    aborting the process. Results do not depend on it (kernels are deterministic per call).

    Yields the resolved count.
    """
    n = resolve_threads(nthreads)
    with contextlib.nullcontext() if layer_is_threadsafe() else _LAYER_LOCK:
        previous = numba.get_num_threads()
        if previous == n:                  # the common case: nothing to set or restore
            yield n
            return
        numba.set_num_threads(n)
        try:
            yield n
        finally:
            numba.set_num_threads(previous)

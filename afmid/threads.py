"""One thread for BLAS, OpenMP and numba: the one place afmid sets it up.

afmid's fit does thousands of small matrix products, which multi-threaded
OpenBLAS runs 2-4x slower, much slower on busy cores (bench/README.md,
"Threads"); one thread also makes results independent of the core count, and
keeps a batch's workers from oversubscribing the machine. The limits are
environment variables read when the libraries load, so call this before NumPy
is imported (the CLI and the tests do it first thing; batch workers are spawned
with them). This module imports nothing heavy.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable, MutableMapping

#: How many threads one fit gives the chunks of a long trace (:func:`trace_threads`; unset: up to
#: :data:`MAX_TRACE_THREADS`, as many as the process may use cores).
TRACE_THREADS_ENV = "AFMID_TRACE_THREADS"
#: At most this many threads work on one trace: each holds a chunk's temporaries (memory grows with them), and
#: the machine afmid is sized for has two cores.
MAX_TRACE_THREADS = 2

#: Environment variables that cap the thread pools of BLAS/OpenMP/numba, each at one thread, and afmid's own
#: threads over a trace's chunks (batch workers: N workers of one thread each fill N cores).
SINGLE_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
    TRACE_THREADS_ENV: "1",
}


def limit_native_threads(environ: MutableMapping[str, str] | None = None, *, override: bool = False) -> None:
    """One thread for the native thread pools, in ``environ`` (default: this process's environment).

    ``override=False`` keeps a value the user set (a person may choose more threads for one run) and leaves
    afmid's own chunk threads (:func:`trace_threads`) at their default: a single fit of a long trace uses the
    cores it has, each thread calling one-thread BLAS (no spin-waiting pool);
    ``override=True`` sets every variable (batch workers: N workers of one thread each fill N cores).
    """
    environ = os.environ if environ is None else environ
    for name, value in SINGLE_THREAD_ENV.items():
        if override:
            environ[name] = value
        elif name != TRACE_THREADS_ENV:
            environ.setdefault(name, value)


#: While set (:func:`cores_shared`): a function that says whether another process of the same job works on the
#: cores now.
_busy_elsewhere: list[Callable[[], bool] | None] = [None]


def cores_shared(busy_elsewhere: Callable[[], bool] | None) -> None:
    """Share the cores with another process of the same job (a report's forked child): while ``busy_elsewhere()``
    says it works, :func:`trace_threads` gives one thread (two processes of one thread fill two cores, without
    four threads contending); None ends the sharing. The bits do not depend on it (:func:`map_in_order`)."""
    _busy_elsewhere[0] = busy_elsewhere


def trace_threads() -> int:
    """Threads that work on the chunks of one trace: :data:`TRACE_THREADS_ENV` if set, else the cores this process
    may run on, at most :data:`MAX_TRACE_THREADS` (one while :func:`cores_shared` says another process uses them)."""
    value = os.environ.get(TRACE_THREADS_ENV, "").strip()
    if value:
        return max(1, int(value))
    busy_elsewhere = _busy_elsewhere[0]
    if busy_elsewhere is not None and busy_elsewhere():
        return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return max(1, min(MAX_TRACE_THREADS, cores))


def map_in_order(work: Callable, items: Iterable, threads: int | None = None) -> list:
    """``[work(item) for item in items]``, computed by up to ``threads`` threads (None: :func:`trace_threads`).

    For the chunks of one trace: each item's work is the same computation whichever thread runs it, so the
    results are the same bits as one thread's, in the items' order (callers reduce them in that order). The work
    must release the GIL to gain anything (NumPy's large operations and BLAS do; numba kernels with
    ``nogil=True``) and must not write where another item's work reads. The threads are kept between calls (the
    same threads, so the same malloc arenas: a new pool per call left freed chunks in fresh arenas, 0.3 GB more
    peak memory at 1e7 samples); a call from inside one of them runs its items in that thread.
    """
    items = list(items)
    threads = trace_threads() if threads is None else threads
    if threads <= 1 or len(items) <= 1 or getattr(_worker, "busy", False):
        return [work(item) for item in items]

    def run(item):
        _worker.busy = True
        try:
            return work(item)
        finally:
            _worker.busy = False

    return list(_pool(threads).map(run, items))


_worker = threading.local()  # .busy: this thread is running an item of map_in_order
_pools: dict = {}  # (process id, threads) -> ThreadPoolExecutor
_pools_lock = threading.Lock()


def _pool(threads: int):
    from concurrent.futures import ThreadPoolExecutor

    key = (os.getpid(), threads)  # a forked child makes its own (the parent's threads are not in it)
    with _pools_lock:
        pool = _pools.get(key)
        if pool is None:
            pool = _pools[key] = ThreadPoolExecutor(threads, thread_name_prefix="afmid-chunk")
        return pool

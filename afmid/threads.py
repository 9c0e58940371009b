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
from collections.abc import MutableMapping

#: Environment variables that cap the thread pools of BLAS/OpenMP/numba, each at one thread.
SINGLE_THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


def limit_native_threads(environ: MutableMapping[str, str] | None = None, *, override: bool = False) -> None:
    """One thread for the native thread pools, in ``environ`` (default: this process's environment).

    ``override=False`` keeps a value the user set (a person may choose more threads for one run);
    ``override=True`` sets every variable (batch workers: N workers of one thread each fill N cores).
    """
    environ = os.environ if environ is None else environ
    for name, value in SINGLE_THREAD_ENV.items():
        if override:
            environ[name] = value
        else:
            environ.setdefault(name, value)

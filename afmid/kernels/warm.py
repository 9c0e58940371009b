"""Compile the library-independent numba kernels ahead of the first fit: ``python -m afmid.kernels.warm``.

numba compiles a kernel on its first call and keeps it in its on-disk cache (``cache=True``; ``NUMBA_CACHE_DIR``
if set, else ``__pycache__`` beside the module or a user-wide folder). In a new install the first ``afmid fit``
therefore pays every compilation. This module calls the kernels every fit runs whatever its force law, on tiny
inputs of the exact types and layouts the fit passes (a different layout would be another compilation, and the
warm-up would miss), so that the first fit only loads them. ``make venv`` runs it; a user who installs with pip
alone does not get it unless they run the command once (the first fit then compiles them itself, as before).

What it cannot do: the kernels generated per library structure (:mod:`afmid.kernels.termgen`,
:mod:`afmid.kernels.lawgen`) exist only once a force law is known; they compile on the first fit of that
structure (~1 s each) and are cached from then on. :mod:`afmid.fit.warm` (a layer that knows the effects) runs
this module and then compiles those of the default model; ``make venv`` runs it.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _sparse() -> None:
    from afmid.kernels.sparse import (SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT, stlsq_factor, subset_lstsq,
                                      subset_rss_qr)

    T = np.ascontiguousarray(np.triu(np.arange(1.0, 17.0).reshape(4, 4)))  # 3 columns + y, as a QR factor
    protected = np.array([True, False, False])
    # the kernels themselves, not subset_rss or the fit's switching calls: those run a same-bits twin while a kernel
    # is not compiled (afmid.kernels.twin), which would leave it uncompiled here
    subset_rss_qr(T, protected, SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT)
    subset_lstsq(T, np.array([True, True, False]))
    stlsq_factor(T, np.ones(3), 0.1, protected, np.ones(3, dtype=np.bool_), 20)


def _switching() -> None:
    from afmid.kernels.switching import cell_subsamples, switching_cells

    fine = np.zeros((5, 2, 2)).transpose(1, 0, 2)  # (rows, samples, terms) sample-major, as the weak form holds it
    fine[0, 2, 0] = 1.0
    rows, cols = switching_cells(fine)
    grid = np.ascontiguousarray(np.tile(np.arange(5.0), (2, 1)))
    cell_subsamples(grid, grid, grid, rows, cols, 4)


def _periodic() -> None:
    from afmid.kernels.periodic import periodic_prediction

    # the glitch scan of every loaded trace (afmid.io.glitches): a contiguous float64 record and a float period
    periodic_prediction(np.ascontiguousarray(np.cos(np.arange(64.0))), 7.5)


#: name -> the function that compiles those kernels (in the order a fit first calls them)
KERNELS = {"periodic": _periodic, "switching": _switching, "sparse": _sparse}


def warm(names=None, stream=None, kernels=None, label: str = "afmid kernels") -> dict[str, float]:
    """Compile (or load from numba's cache) the kernels of ``names`` (default: all of ``kernels``, which defaults to
    :data:`KERNELS`; another module passes its own table of name -> compiling function); returns the seconds each
    took (a compilation ~0.5-3 s, a cache load ~10 ms). ``stream`` gets one line per group, starting with ``label``."""
    kernels = KERNELS if kernels is None else kernels
    seconds = {}
    for name in names or kernels:
        start = time.perf_counter()
        kernels[name]()
        seconds[name] = time.perf_counter() - start
        if stream is not None:
            stream.write(f"{label}: {name} ready in {seconds[name]:.2f} s\n")
    return seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afmid.kernels.warm", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", choices=[[], *KERNELS], help="kernel groups (default: all)")
    args = parser.parse_args(argv)
    warm(args.names or None, sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

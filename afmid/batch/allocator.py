"""glibc's allocator in dask worker processes: freed arrays kept for reuse, as in any other Python process.

dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536`` (``distributed.nanny.pre-spawn-environ``,
to return memory to the OS promptly). Setting any of glibc's thresholds switches off its dynamic mmap threshold:
every array above 128 kB is then mapped fresh from the OS and unmapped when freed, so each of the fit's
megabyte-sized temporaries costs page faults on every use. Measured (16x16 bench map, 9,984-sample
pixels, one process): 61 ms of CPU per pixel without the variable, 101 ms with it (sys time 2 s -> 11 s over 256
pixels); a map on the local cluster ran at the slower rate.

:func:`keep_freed_memory_for_reuse` fixes the thresholds at what glibc's dynamic rule would settle at for a
process that fits trace after trace: blocks up to 32 MiB (its largest dynamic mmap threshold on 64-bit) come
from the heap, and the heap is trimmed once 64 MiB (twice that, as the dynamic rule sets it) lie free at its top.
Left to the dynamic rule, a worker still took ~4,300 page faults per 10^4-sample pixel (1.1 M over the 16x16
bench map, sys 1.8 s), with the thresholds fixed 170 (44 k, sys 0.16 s). It is called in every engine worker
(:mod:`afmid.batch.engine_dask` before each task, so also on clusters afmid did not start; the local pool's
workers at start-up), on Linux with glibc only; a worker keeps up to 64 MiB of freed heap for reuse.
"""

from __future__ import annotations

import ctypes
import sys

#: mallopt parameters (malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: bytes: glibc's largest dynamic mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX), and twice it.
MMAP_THRESHOLD = 32 * 1024 * 1024
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD

_applied: bool | None = None  # None: not yet decided in this process


def keep_freed_memory_for_reuse() -> bool:
    """Set the thresholds described in the module docstring once per process; True when they are in effect."""
    global _applied
    if _applied is None:
        _applied = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL("libc.so.6")
                _applied = bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
                                and libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
            except (OSError, AttributeError):  # not glibc
                _applied = False
    return _applied

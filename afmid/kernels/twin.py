"""A numba kernel's same-bits twin run in its place while compiling the kernel would cost more than the twin does.

In a new install numba compiles each kernel on its first call (0.3-2 s of CPU each: most of the first-ever
``afmid fit``, bench/README.md "Cold start"). Where a kernel has a twin that gives the same bits (the same float
operations in the same order: its own Python code run by the interpreter, or NumPy array expressions shown equal by
a test) and is cheap on small inputs, :class:`KernelOrTwin` runs the twin while the kernel is compiled neither in
this process nor in numba's on-disk cache for those argument types (the cache is looked up once per argument types,
and the kernel loaded from it when there: a warm cache runs the kernel as before). In a process without a compiled
kernel the twin runs until it has taken ``compile_seconds`` of CPU, or meets an input above its size limit;
from then on the kernel is compiled and run (a ski-rental rule: a process spends at most about twice what compiling
at once would cost). ``python -m afmid.kernels.warm`` (``make venv`` runs it) compiles the kernels themselves.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np


class KernelOrTwin:
    """Call ``kernel`` (a numba dispatcher) or, while it is not compiled, ``twin`` (same arguments, same bits).

    ``small(*args)`` says whether the twin is cheap enough for these arguments; ``compile_seconds`` is the CPU time
    (s) the twin may take in a process before the kernel is compiled instead (about its compilation's cost).
    """

    def __init__(self, kernel, twin: Callable, small: Callable[..., bool], compile_seconds: float):
        self.kernel = kernel
        self.twin = twin
        self.small = small
        self.compile_seconds = compile_seconds
        self.twin_seconds = 0.0  # CPU time the twin has taken in this process
        self._looked_up: set[tuple] = set()  # argument types looked up in numba's cache
        # Arguments' kinds (:func:`argument_kinds`) for which the kernel was found compiled: it stays so, and a
        # map's pixel makes ~100 calls, where asking numba for each argument's type cost more than some calls do.
        self._compiled_kinds: set[tuple] = set()
        self._lock = threading.Lock()

    def __call__(self, *args):
        if self._kernel_runs(args):
            return self.kernel(*args)
        start = time.thread_time()  # the twin's own CPU (the caller's thread): not inflated by a loaded machine
        result = self.twin(*args)
        with self._lock:
            self.twin_seconds += time.thread_time() - start
        return result

    def _kernel_runs(self, args) -> bool:
        if self.twin_seconds >= self.compile_seconds:
            return True
        kinds = argument_kinds(args)
        if kinds is not None and kinds in self._compiled_kinds:
            return True
        if not self.small(*args):
            return True
        try:
            types = tuple(self.kernel.typeof_pyval(a) for a in args)
        except (AttributeError, ValueError, TypeError):  # not a numba dispatcher, or an argument numba cannot type
            return True
        if types in self.kernel.overloads:  # compiled or loaded in this process (also by another caller)
            return self._compiled(kinds)
        with self._lock:
            if types not in self._looked_up:  # numba's on-disk cache, once per argument types
                self._looked_up.add(types)
                return self._compiled(kinds) if _load_from_cache(self.kernel, types) else False
        return False

    def _compiled(self, kinds: tuple | None) -> bool:
        if kinds is not None:
            self._compiled_kinds.add(kinds)
        return True


def argument_kinds(args) -> tuple | None:
    """What decides numba's type of each argument, read without numba: an array's dtype, dimensions, layout flags,
    writeability and alignment; a scalar's Python or NumPy type (an int also whether it fits in int64). Equal kinds
    give equal numba types; None for an argument of another sort (then numba is asked)."""
    kinds = []
    for a in args:
        if isinstance(a, np.ndarray):
            flags = a.flags
            kinds.append((a.dtype, a.ndim, flags.c_contiguous, flags.f_contiguous, flags.writeable, flags.aligned,
                          type(a)))
        elif isinstance(a, bool | float | np.generic):
            kinds.append(type(a))
        elif type(a) is int:
            kinds.append((int, -(1 << 63) <= a < (1 << 63)))
        else:
            return None
    return tuple(kinds)


def _load_from_cache(kernel, types: tuple) -> bool:
    """Load the kernel's compiled version for these argument types from numba's on-disk cache, as the dispatcher's
    own first call does (numba.core.dispatcher.Dispatcher.compile, numba 0.68); False where it is not there. Uses
    the dispatcher's internals: a numba without them gives True, i.e. the kernel is called and numba compiles or
    loads it as before."""
    try:
        from numba.core.compiler_lock import global_compiler_lock

        cache, context = kernel._cache, kernel.targetctx
        with global_compiler_lock:
            if types in kernel.overloads:
                return True
            result = cache.load_overload(types, context)
            if result is None:
                return False
            if not result.objectmode:
                context.insert_user_function(result.entry_point, result.fndesc, [result.library])
            kernel.add_overload(result)
            kernel._cache_hits[types] += 1
            return True
    except (AttributeError, ImportError):
        return True

"""afmid.kernels.twin: a kernel's same-bits twin runs in its place while the kernel is not compiled (a new install's
first fit), and the kernel runs once it is compiled or in numba's cache; the twins the fit uses give the kernels'
bits (the interpreted subset walk here; the switching twins in test_switching.py)."""

import numpy as np
from numba import njit

from afmid.kernels import sparse
from afmid.kernels.twin import KernelOrTwin


def _factors(count: int, seed: int = 17):
    """Triangular factors of [A | y] as the subset search meets them: 1-5 free columns, columns over 12 decades,
    some nearly collinear (handed to the exact solve: NaN rss), 1-3 protected columns, square and tall."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        protected = int(rng.integers(0, 4))
        free = int(rng.integers(1, 6))
        q = protected + free + 1
        rows = q if i % 2 else q + int(rng.integers(1, 8))
        A = rng.standard_normal((rows + 20, q)) * np.logspace(0, rng.uniform(0, 12), q)
        if i % 5 == 0 and q > 2:
            A[:, 1] = 3.0 * A[:, 0] + 1e-9 * A[:, 2]
        T = np.ascontiguousarray(np.linalg.qr(A, mode="r"))[:rows] if rows <= q else np.ascontiguousarray(
            np.vstack([np.linalg.qr(A, mode="r"), np.zeros((rows - q, q))]))
        mask = np.zeros(q - 1, dtype=np.bool_)
        mask[:protected] = True
        yield np.ascontiguousarray(T), mask


def test_the_interpreted_subset_walk_is_the_kernel_bit_for_bit():
    """subset_rss_qr's own code run by the interpreter gives the compiled kernel's bits: IEEE operations in the same
    order, the same sqrt (correctly rounded), no fastmath; NaN marks the same exact subsets."""
    compared = exact = 0
    for T, protected in _factors(200):
        args = (T, protected, sparse.SUBSET_RSS_MAX_ERROR, sparse.SUBSET_RSS_MIN_PIVOT)
        rss, flags = sparse.subset_rss_qr(*args)
        rss_twin, flags_twin = sparse.subset_rss_qr_interpreted(*args)
        assert np.array_equal(rss.view(np.int64), rss_twin.view(np.int64)), (T.shape, protected)
        assert np.array_equal(flags, flags_twin)
        compared += 1
        exact += int(flags.sum())
    assert compared == 200 and exact > 0  # some subsets went to the exact solve


@njit(no_cfunc_wrapper=True)  # no cache: numba's cache never has it
def _double(a):
    out = np.empty_like(a)
    for i in range(a.size):
        out[i] = 2.0 * a[i]
    return out


def test_the_twin_runs_until_its_time_would_pay_for_compiling():
    calls = []

    def twin(a):
        calls.append(a.size)
        return 2.0 * a

    lazy = KernelOrTwin(_double, twin, lambda a: a.size <= 10, compile_seconds=3600.0)
    a = np.arange(4.0)
    assert np.array_equal(lazy(a), 2.0 * a) and calls == [4] and not _double.signatures  # not compiled
    assert np.array_equal(lazy(np.arange(20.0)), 2.0 * np.arange(20.0)) and calls == [4]  # too big: compiled
    assert len(_double.signatures) == 1
    lazy(a)  # compiled now for these argument types: the kernel runs
    assert calls == [4]
    spent = KernelOrTwin(_double, twin, lambda a: True, compile_seconds=0.0)  # no time for the twin
    spent(np.arange(3, dtype=np.int64))
    assert calls == [4] and len(_double.signatures) == 2


@njit
def _triple(a):
    return 3.0 * a


def test_a_kernel_found_compiled_is_remembered_by_its_arguments_kinds():
    """Once the kernel is compiled for some arguments, calls with arguments of the same kinds run it without asking
    numba their types again; arguments of another kind (dtype, layout, a read-only array) are still looked up, and
    the twin runs for those while they are not compiled."""
    calls = []

    def twin(a):
        calls.append(a.dtype.name)
        return 3.0 * a

    lazy = KernelOrTwin(_triple, twin, lambda a: True, compile_seconds=3600.0)
    _triple(np.arange(3.0))  # compiled for C-contiguous float64 vectors
    assert np.array_equal(lazy(np.arange(5.0)), 3.0 * np.arange(5.0)) and calls == []
    assert np.array_equal(lazy(np.arange(6.0)), 3.0 * np.arange(6.0)) and calls == []  # remembered
    lazy(np.arange(4))  # int64: not compiled
    strided = np.arange(8.0)[::2]  # layout 'A': not compiled
    lazy(strided)
    frozen = np.arange(3.0)
    frozen.flags.writeable = False  # read-only: another numba type
    lazy(frozen)
    assert calls == ["int64", "float64", "float64"] and len(_triple.signatures) == 1


def test_equal_argument_kinds_are_equal_numba_types():
    """argument_kinds may be finer than numba's types, never coarser: arguments of one kind have one numba type."""
    from numba import typeof

    from afmid.kernels.twin import argument_kinds

    base = np.arange(24.0).reshape(4, 6)
    frozen = base.copy()
    frozen.flags.writeable = False
    values = [base, base.T, base[:, ::2], base[0], base[:, 0], np.asfortranarray(base), frozen, base.astype(np.float32),
              base.astype(np.int64), base.astype(bool), np.zeros(0), np.zeros((0, 3)), np.float64(1.0), 1.0, 2, True,
              np.int32(3), np.bool_(False), 1 << 63, -(1 << 63), np.arange(3.0), np.arange(3.0)[::-1]]
    for a in values:
        for b in values:
            if argument_kinds((a,)) == argument_kinds((b,)):
                assert typeof(a) == typeof(b), (a, b)
    assert argument_kinds(("text",)) is None

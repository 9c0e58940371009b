"""Sequentially thresholded least squares on a triangular factor (numba kernel + NumPy twin).

The regression problem ``y ~ A c`` is carried as the upper-triangular factor
``T`` of the QR decomposition of ``[A | y]`` (q = p + 1 columns). Any subset
regression is then a small least-squares problem on columns of ``T`` with the
exact residual, without ever forming the ill-conditioned normal equations
(inverse powers z^-1..z^-8 make A'A singular to double precision).

:func:`subset_rss` gives the residual of every subset of the free columns in one
call (exhaustive search): a depth-first walk over the subsets that adds one column
at a time to a Householder QR of the unit-norm columns (again no normal
equations: unit-norm Gram matrices of the seed tables reach condition ~1e11-1e14),
handing the ill-conditioned and rank-deficient subsets to :func:`subset_lstsq`.
"""

from __future__ import annotations

import types as pytypes

import numpy as np
import numba.np.linalg as numba_linalg
from numba import njit, types

from afmid.kernels.twin import KernelOrTwin

# LAPACK's dgelsd (SVD least squares) through numba's own LAPACK bridge, as ``np.linalg.lstsq`` calls it inside
# numba, but without that overload's checks: their error-message formatting (strings, shape contexts) made up
# ~6 of the ~8 s it took to compile :func:`subset_rss` in a new install (the first-ever ``afmid fit``).
# The arguments are those of numba's ``lstsq`` (Fortran copy of A, lda = m, B in a max(m, n) x 1 column,
# rcond), so the solution is the same bits (tests/kernels/test_sparse_lstsq.py checks it against np.linalg.lstsq).
_LAPACK_INT = numba_linalg.F_INT_nptype
_GELSD = types.ExternalFunction("numba_ez_gelsd", types.intc(
    types.char, types.intp, types.intp, types.intp, types.CPointer(types.float64), types.intp,
    types.CPointer(types.float64), types.intp, types.CPointer(types.float64), types.float64,
    types.CPointer(numba_linalg.F_INT_nbtype)))
_DOUBLE = ord("d")  # LAPACK kind: real double precision
# BLAS dgemv through numba's bridge, as numba's ``A @ x`` calls it for a C-contiguous A (the operator's
# overload and its checks were ~0.5 s of the first-ever fit's compilation): kind, trans, m, n, alpha, a, lda, x,
# beta, y; unit strides.
_GEMV = types.ExternalFunction("numba_xxgemv", types.intc(
    types.char, types.char, types.intp, types.intp, types.CPointer(types.float64), types.CPointer(types.float64),
    types.intp, types.CPointer(types.float64), types.CPointer(types.float64), types.CPointer(types.float64)))
_TRANSPOSE = ord("t")  # a C-contiguous matrix is the transpose of BLAS's column-major one


@njit(cache=True, no_cfunc_wrapper=True)
def lstsq_solution(A, b, rcond):
    """The minimum-norm least-squares solution of ``A x ~ b`` (A m x n, b length m; any unit) by LAPACK's dgelsd
    with singular values below ``rcond`` x the largest cut (negative: machine precision): the ``x`` of
    ``np.linalg.lstsq(A, b, rcond)`` in numba, bit for bit."""
    m, n = A.shape
    if m == 0 or n == 0:
        raise np.linalg.LinAlgError("Arrays cannot be empty")
    for i in range(m):
        if not np.isfinite(b[i]):
            raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        for j in range(n):
            if not np.isfinite(A[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    big = max(m, n)
    # dgelsd overwrites A: a column-major copy, held flat (element (i, j) at i + j m, lda = m)
    a_fortran = np.empty(m * n)
    for j in range(n):
        for i in range(m):
            a_fortran[i + j * m] = A[i, j]
    b_column = np.empty(big)  # B in, the solution out (rows n..: residual components)
    for i in range(big):
        b_column[i] = b[i] if i < m else 0.0
    singular = np.empty(min(m, n))
    rank = np.empty(1, dtype=_LAPACK_INT)
    info = _GELSD(_DOUBLE, m, n, 1, a_fortran.ctypes, m, b_column.ctypes, big, singular.ctypes, rcond, rank.ctypes)
    if info != 0:
        raise ValueError("Internal algorithm failed to converge.")
    x = np.empty(n)
    for j in range(n):
        x[j] = b_column[j]
    # the work arrays stay alive until LAPACK is done with them (their last use is here)
    if a_fortran.size + singular.size + rank.size < 0:
        x[0] = np.nan
    return x


@njit(cache=True, no_cfunc_wrapper=True)
def matvec(A, x):
    """``A @ x`` (A m x n C-contiguous, x length n contiguous; any unit) by BLAS dgemv with the arguments numba's own
    ``A @ x`` passes (transposed column-major A, lda = n, alpha 1, beta 0), so the same bits without the operator's
    compilation (tests/kernels/test_sparse_lstsq.py compares them)."""
    m, n = A.shape
    y = np.empty(m)
    if n == 0:
        for i in range(m):
            y[i] = 0.0
        return y
    alpha = np.empty(1)
    alpha[0] = 1.0
    beta = np.empty(1)
    beta[0] = 0.0
    if _GEMV(_DOUBLE, _TRANSPOSE, n, m, alpha.ctypes, A.ctypes, n, x.ctypes, beta.ctypes, y.ctypes) != 0:
        raise RuntimeError("BLAS dgemv is not available")
    # the arguments stay alive until BLAS is done with them (their last use is here)
    if A.size + x.size + alpha.size + beta.size < 0:
        y[0] = np.nan
    return y


@njit(cache=True, no_cfunc_wrapper=True)
def subset_lstsq(T, active):
    """Least squares of the last column of ``T`` on its ``active`` columns (SVD, machine-precision cut-off):
    (coefficients with zeros off the subset, residual sum of squares)."""
    rows, q = T.shape
    p = q - 1
    k = 0
    for j in range(p):
        if active[j]:
            k += 1
    # Loops and np.empty only (no np.zeros, np.sum, array expressions): each NumPy call of another signature is one
    # more compilation in a new install; sums run in index order from 0, as np.sum does in numba (the same bits).
    coef = np.empty(p)
    for j in range(p):
        coef[j] = 0.0
    if k == 0:
        rss = 0.0
        for i in range(rows):
            rss += T[i, p] * T[i, p]
        return coef, rss
    # Unit-norm columns: SI columns differ by ~40 orders of magnitude, and the
    # SVD cut-off is relative to the largest singular value.
    sub = np.empty((rows, k))
    norms = np.empty(k)
    m = 0
    for j in range(p):
        if active[j]:
            squares = 0.0
            for i in range(rows):
                squares += T[i, j] * T[i, j]
            nrm = np.sqrt(squares)
            norms[m] = nrm if nrm > 0.0 else 1.0
            for i in range(rows):
                sub[i, m] = T[i, j] / norms[m]
            m += 1
    rhs = np.empty(rows)
    for i in range(rows):
        rhs[i] = T[i, p]
    sol = lstsq_solution(sub, rhs, -1.0)
    fitted = matvec(sub, sol)
    rss = 0.0
    for i in range(rows):
        resid = rhs[i] - fitted[i]
        rss += resid * resid
    m = 0
    for j in range(p):
        if active[j]:
            coef[j] = sol[m] / norms[m]
            m += 1
    return coef, rss


@njit(cache=True, no_cfunc_wrapper=True)
def stlsq_factor(T, scale, threshold, protected, initial, max_iter):
    """STLSQ on factor ``T`` (q x q) starting from the ``initial`` active set.

    A non-protected term is dropped when its contribution on unit-norm columns,
    ``|c_j| * scale_j``, falls below ``threshold``; iterate to a fixed point.
    Returns (active mask, coefficients, residual sum of squares).
    """
    p = T.shape[1] - 1
    active = initial.copy()
    coef, rss = subset_lstsq(T, active)
    for _ in range(max_iter):
        changed = False
        for j in range(p):
            if active[j] and not protected[j] and abs(coef[j]) * scale[j] < threshold:
                active[j] = False
                changed = True
        if not changed:
            break
        coef, rss = subset_lstsq(T, active)
    return active, coef, rss


def stlsq_factor_numpy(T, scale, threshold, protected, initial, max_iter):
    """Plain-NumPy twin of :func:`stlsq_factor`."""
    p = T.shape[1] - 1

    def solve(active):
        coef = np.zeros(p)
        if not active.any():
            return coef, float(np.sum(T[:, p] ** 2))
        sub = T[:, :p][:, active]
        norms = np.linalg.norm(sub, axis=0)
        norms[norms == 0] = 1.0
        sol, *_ = np.linalg.lstsq(sub / norms, T[:, p], rcond=None)
        coef[active] = sol / norms
        return coef, float(np.sum((T[:, p] - (sub / norms) @ sol) ** 2))

    active = initial.copy()
    coef, rss = solve(active)
    for _ in range(max_iter):
        drop = active & ~protected & (np.abs(coef) * scale < threshold)
        if not drop.any():
            break
        active &= ~drop
        coef, rss = solve(active)
    return active, coef, rss


# --------------------------------------------------------------------------- every subset at once
#: :func:`subset_rss` solves a subset by :func:`subset_lstsq` (SVD, as one subset fit does) when the
#: estimated relative rounding error of its QR residual exceeds ``SUBSET_RSS_MAX_ERROR``, or when a pivot of
#: its unit-norm triangular factor is below ``SUBSET_RSS_MIN_PIVOT`` (condition number >= 1e8: near
#: rank-deficient, where the SVD cut-off of the single fit decides what the residual is).
SUBSET_RSS_MAX_ERROR = 1e-10
SUBSET_RSS_MIN_PIVOT = 1e-8


@njit(cache=True, no_cfunc_wrapper=True)
def _householder(W, r, c, c_end):
    """Reflect rows r.. of ``W`` so that column ``c`` is zero below row ``r``; apply to columns c+1..c_end-1.

    Returns the new diagonal entry (0 when the column is already zero below row r, no reflection)."""
    m = W.shape[0]
    alpha = 0.0
    for i in range(r, m):
        alpha += W[i, c] * W[i, c]
    alpha = np.sqrt(alpha)
    if alpha == 0.0:
        return 0.0
    x0 = W[r, c]
    beta = -alpha if x0 >= 0.0 else alpha
    v0 = x0 - beta  # v = (v0, W[r+1:, c]), |v|^2 = 2 alpha (alpha + |x0|)
    vnorm2 = 2.0 * alpha * (alpha + abs(x0))
    for k in range(c + 1, c_end):
        s = v0 * W[r, k]
        for i in range(r + 1, m):
            s += W[i, c] * W[i, k]
        f = 2.0 * s / vnorm2
        W[r, k] -= f * v0
        for i in range(r + 1, m):
            W[i, k] -= f * W[i, c]
    W[r, c] = beta
    for i in range(r + 1, m):
        W[i, c] = 0.0
    return beta


def subset_rss(T, protected, max_error, min_pivot):
    """Residual sum of squares of every subset of the free (non-protected) columns of factor ``T``.

    ``T`` (m x q, usually the q x q factor of ``[A | y]``, C-contiguous float64); the protected columns (a
    C-contiguous bool array) are in every subset. Returns ``(rss, exact)``, arrays of length ``2**n_free``
    indexed by bitmask: bit ``i`` set = the ``i``-th free column (in column order) is active. ``exact[b]`` is
    True where subset ``b`` was solved by :func:`subset_lstsq` itself (the empty subset, near rank-deficient or
    ill-conditioned subsets, see ``SUBSET_RSS_MAX_ERROR``); elsewhere the residual comes from
    :func:`subset_rss_qr` and agrees with :func:`subset_lstsq` to rounding.

    The exact subsets are solved here, one kernel call each, not inside :func:`subset_rss_qr`: a numba kernel
    that calls another is compiled with the callee's code linked in and optimised again, and subset_lstsq (with
    LAPACK's bridge) was ~1 s of the ~2.5 s that compiling the walk cost a new install. The values
    are the same bits either way (the same kernel on the same arguments).
    """
    rss, exact = _subset_rss_walk(T, protected, max_error, min_pivot)
    if exact.any():
        free = np.flatnonzero(~protected)
        for sub in np.flatnonzero(exact):
            mask = protected.copy()
            mask[free[(int(sub) >> np.arange(free.size)) & 1 == 1]] = True
            rss[sub] = subset_lstsq_or_twin(T, mask)[1]
    return rss, exact


@njit(cache=True, no_cfunc_wrapper=True)
def subset_rss_qr(T, protected, max_error, min_pivot):
    """:func:`subset_rss`'s walk: the residual sum of squares of every subset of the free columns of ``T`` by a
    Householder QR of the unit-norm columns (as :func:`subset_lstsq` scales them) grown column by column along a
    depth-first walk over the subsets, one reflection per subset. Returns ``(rss, exact)``; where ``exact`` is
    True (the empty subset, near rank-deficient or ill-conditioned subsets) ``rss`` is NaN: the caller solves
    those by :func:`subset_lstsq`."""
    m, q = T.shape
    p = q - 1
    nf = 0
    for j in range(p):
        if not protected[j]:
            nf += 1
    npr = p - nf
    free = np.empty(nf, np.int64)
    prot = np.empty(npr, np.int64)
    a = 0
    b = 0
    for j in range(p):
        if protected[j]:
            prot[b] = j
            b += 1
        else:
            free[a] = j
            a += 1
    n_sub = 1 << nf
    # np.empty and loops, no np.zeros: each NumPy call of another signature is one more compilation in a new install
    rss = np.empty(n_sub)
    exact = np.empty(n_sub, np.bool_)
    for b in range(n_sub):
        exact[b] = False
    eps = 2.220446049250313e-16
    # unit-norm columns, protected first, then the free ones, then y
    M = np.empty((m, p + 1))
    for e in range(p):
        j = prot[e] if e < npr else free[e - npr]
        nrm = 0.0
        for i in range(m):
            nrm += T[i, j] * T[i, j]
        nrm = np.sqrt(nrm)
        if nrm == 0.0:
            nrm = 1.0
        for i in range(m):
            M[i, e] = T[i, j] / nrm
    ynorm = 0.0
    for i in range(m):
        M[i, p] = T[i, p]
        ynorm += T[i, p] * T[i, p]
    ynorm = np.sqrt(ynorm)
    # R: column e holds the triangular factor's column of the e-th active column of the current subset
    R = np.empty((max(m, p), p))
    for i in range(R.shape[0]):
        for k in range(p):
            R[i, k] = 0.0
    pivmin = np.empty(nf + 1)
    pivmin[0] = np.inf
    for e in range(npr):
        beta = _householder(M, e, e, p + 1) if e < m else 0.0
        pivmin[0] = min(pivmin[0], abs(beta))
        for i in range(min(e + 1, m)):
            R[i, e] = M[i, e]
    # W[d]: the free columns and y (last) after the reflections of the protected columns and of the
    # d free columns added on the current path
    W = np.empty((nf + 1, m, nf + 1))
    for level in range(1, nf + 1):
        for i in range(m):
            for k in range(nf + 1):
                W[level, i, k] = 0.0
    for i in range(m):
        for k in range(nf + 1):
            W[0, i, k] = M[i, npr + k]
    bits = np.empty(nf + 1, np.int64)
    nxt = np.empty(nf + 1, np.int64)
    for level in range(nf + 1):
        bits[level] = 0
        nxt[level] = 0
    coef = np.empty(p)
    d = 0
    while d >= 0:
        # ---- evaluate the subset at depth d (its reflections are done)
        r = npr + d
        sub = bits[d]
        ok = r > 0 and r < m and pivmin[d] > 0.0 and pivmin[d] >= min_pivot
        tail = 0.0
        if ok:
            for i in range(r, m):
                tail += W[d, i, nf] * W[d, i, nf]
            ok = tail > 0.0
        if ok:
            # coefficients on unit-norm columns: R c = (Q'y)[:r]
            cn2 = 0.0
            for e in range(r - 1, -1, -1):
                s = W[d, e, nf]
                for k in range(e + 1, r):
                    s -= R[e, k] * coef[k]
                coef[e] = s / R[e, e]
                cn2 += coef[e] * coef[e]
            err = 4.0 * eps * (ynorm + np.sqrt(r * cn2)) / np.sqrt(tail)
            if err <= max_error:
                rss[sub] = tail
            else:
                ok = False
        if not ok:
            rss[sub] = np.nan  # solved by subset_lstsq in subset_rss
            exact[sub] = True
        # ---- next subset: add the next free column after the last one, else backtrack
        while d >= 0 and nxt[d] >= nf:
            d -= 1
        if d < 0:
            break
        j = nxt[d]
        nxt[d] = j + 1
        rr = npr + d
        for i in range(m):
            for k in range(j, nf + 1):
                W[d + 1, i, k] = W[d, i, k]
        beta = _householder(W[d + 1], rr, j, nf + 1) if rr < m else 0.0
        for i in range(min(rr + 1, m)):
            R[i, rr] = W[d + 1, i, j]
        pivmin[d + 1] = min(pivmin[d], abs(beta))
        bits[d + 1] = bits[d] | (1 << j)
        nxt[d + 1] = j + 1
        d += 1
    return rss, exact


def _interpreted(kernel, **callees):
    """``kernel``'s own Python code, run by the interpreter, with the numba ``callees`` it calls (by global name)
    replaced by their Python code too: the same float64 operations in the same order as the compiled kernel (IEEE
    arithmetic and a correctly rounded sqrt either way, no fastmath), so the same bits, without compiling anything;
    tests/kernels/test_twin.py and test_sparse_lstsq.py compare them."""
    function = kernel.py_func
    names = dict(function.__globals__, **{name: getattr(callee, "py_func", callee) for name, callee in callees.items()})
    return pytypes.FunctionType(function.__code__, names, function.__name__, function.__defaults__,
                                function.__closure__)


#: :func:`subset_rss_qr` run by the interpreter (see :func:`_interpreted`): ~0.1 ms for 2 free columns of a 5 x 5
#: factor, ~0.4 ms for 4 free columns of 7 x 7, growing as 2^free x rows x free.
subset_rss_qr_interpreted = _interpreted(subset_rss_qr, _householder=_householder)
#: The walk's work is interpreted at most up to this many free columns and factor rows (16 subsets of <= 32 rows:
#: <= ~2 ms a call); above, the compiled kernel runs.
INTERPRETED_MAX_FREE, INTERPRETED_MAX_ROWS = 4, 32


def _few_subsets(T, protected, max_error, min_pivot) -> bool:
    free = protected.size - int(np.count_nonzero(protected))
    return T.shape[0] <= INTERPRETED_MAX_ROWS and free <= INTERPRETED_MAX_FREE


#: The walk as :func:`subset_rss` runs it: the kernel, or while it is compiled neither in this process nor in numba's
#: cache, its interpreted code on small factors, until that has taken 1 s of CPU (compiling the kernel takes ~2 s:
#: a first-ever fit of the demo runs ~120 walks of 4 or 16 subsets, ~0.05 s interpreted).
_subset_rss_walk = KernelOrTwin(subset_rss_qr, subset_rss_qr_interpreted, _few_subsets, compile_seconds=1.0)


def lstsq_solution_scipy(A, b, rcond):
    """:func:`lstsq_solution` from Python: LAPACK's dgelsd through SciPy's wrapper, the same routine of the same
    library as numba's bridge calls (both SciPy's LAPACK), with the same arguments (the workspace sizes of the same
    query, B in a max(m, n) column): the same bits (tests/kernels/test_sparse_lstsq.py)."""
    from scipy.linalg.lapack import dgelsd, dgelsd_lwork

    m, n = A.shape
    if m == 0 or n == 0:
        raise np.linalg.LinAlgError("Arrays cannot be empty")
    if not (np.isfinite(A).all() and np.isfinite(b).all()):
        raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    work, iwork, info = dgelsd_lwork(m, n, 1, rcond)
    if info != 0:
        raise ValueError("Internal algorithm failed to converge.")
    b_column = np.zeros((max(m, n), 1))
    b_column[:m, 0] = b
    x, _, _, info = dgelsd(np.asfortranarray(A), b_column, int(work), int(iwork), rcond)
    if info != 0:
        raise ValueError("Internal algorithm failed to converge.")
    return x[:n, 0].copy()


def matvec_scipy(A, x):
    """:func:`matvec` from Python: BLAS dgemv through SciPy's wrapper on the same transposed column-major view with
    the same arguments as numba's bridge passes (the same bits)."""
    from scipy.linalg.blas import dgemv

    if A.shape[1] == 0:
        return np.zeros(A.shape[0])
    return dgemv(1.0, A.T, x, 0.0, trans=1)


#: :func:`subset_lstsq` run by the interpreter with LAPACK and BLAS called through SciPy: ~0.1 ms for the factors
#: of a few columns the fit solves (compiling the kernel: ~1.1 s of CPU in a new install).
subset_lstsq_interpreted = _interpreted(subset_lstsq, lstsq_solution=lstsq_solution_scipy, matvec=matvec_scipy)


def _small_factor(T, active) -> bool:
    return T.shape[0] <= INTERPRETED_MAX_ROWS and T.shape[1] <= INTERPRETED_MAX_ROWS


#: subset_lstsq as the fit calls it from Python: the kernel, or its interpreted code while the kernel is not
#: compiled (a first-ever fit of the demo solves ~230 subsets, ~0.05 s interpreted), until that has taken 0.5 s of CPU.
subset_lstsq_or_twin = KernelOrTwin(subset_lstsq, subset_lstsq_interpreted, _small_factor, compile_seconds=0.5)


def subset_rss_numpy(T, protected, max_error=SUBSET_RSS_MAX_ERROR, min_pivot=SUBSET_RSS_MIN_PIVOT):
    """Plain-NumPy twin of :func:`subset_rss`: one QR (LAPACK) per subset, the same fallback rule."""
    T = np.asarray(T, dtype=float)
    m, q = T.shape
    p = q - 1
    free = np.flatnonzero(~protected)
    prot = np.flatnonzero(protected)
    norms = np.linalg.norm(T[:, :p], axis=0)
    norms[norms == 0] = 1.0
    X = T[:, :p] / norms
    y = T[:, p]
    ynorm = np.linalg.norm(y)
    eps = np.finfo(float).eps
    n_sub = 1 << free.size
    rss = np.empty(n_sub)
    exact = np.zeros(n_sub, dtype=bool)
    for sub in range(n_sub):
        cols = np.concatenate([prot, free[(sub >> np.arange(free.size)) & 1 == 1]])
        r = cols.size
        ok = 0 < r < m
        if ok:
            Rf = np.linalg.qr(np.column_stack([X[:, cols], y]), mode="r")
            diag = np.abs(np.diag(Rf)[:r])
            tail = float(np.sum(Rf[r:, r] ** 2))
            ok = bool(diag.min() > 0.0 and diag.min() >= min_pivot and tail > 0.0)
            if ok:
                with np.errstate(divide="ignore", invalid="ignore"):
                    c = np.linalg.solve(Rf[:r, :r], Rf[:r, r])
                    err = 4.0 * eps * (ynorm + np.sqrt(r * np.sum(c**2))) / np.sqrt(tail)
                ok = bool(err <= max_error)
        if ok:
            rss[sub] = tail
        else:  # the single subset fit (twin of subset_lstsq: SVD, machine-precision cut-off)
            mask = protected.copy()
            mask[cols] = True
            if not mask.any():
                rss[sub] = float(np.sum(y**2))
            else:
                sol, *_ = np.linalg.lstsq(X[:, mask], y, rcond=-1)
                rss[sub] = float(np.sum((y - X[:, mask] @ sol) ** 2))
            exact[sub] = True
    return rss, exact

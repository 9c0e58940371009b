"""afmid.kernels.sparse.lstsq_solution: LAPACK's dgelsd called as numba's np.linalg.lstsq calls it (issue 31: that
overload's checks cost ~6 s of compilation in a new install), so the solution must be the same bits; and
afmid.kernels.sparse.matvec: BLAS dgemv called as numba's ``A @ x`` calls it (~0.5 s of compilation less)."""

import numpy as np
import pytest
from numba import njit

from afmid.kernels.sparse import lstsq_solution, matvec, subset_lstsq


@njit(cache=True)
def numba_lstsq(A, b, rcond):
    """The reference: numba's own np.linalg.lstsq (what subset_lstsq called before)."""
    return np.linalg.lstsq(A, b, rcond)[0]


def _problems(count: int, seed: int = 31):
    """Random least-squares problems of the shapes and scales subset_lstsq meets: square and tall, triangular,
    columns over ~35 decades, exactly collinear columns (rank-deficient: the SVD cut-off decides)."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        n = int(rng.integers(1, 11))
        m = n if rng.random() < 0.5 else int(rng.integers(n, 40))
        A = rng.standard_normal((m, n)) * 10.0 ** rng.uniform(-30, 5, n)
        if rng.random() < 0.5:
            A = np.triu(A)
        if n > 1 and rng.random() < 0.3:
            A[:, n - 1] = 3.0 * A[:, 0]
        yield np.ascontiguousarray(A), rng.standard_normal(m) * 10.0 ** rng.uniform(-12, 0), rng.choice([-1.0, 1e-10])


def test_lstsq_solution_is_numbas_lstsq_bit_for_bit():
    compared = 0
    for A, b, rcond in _problems(400):
        assert np.array_equal(lstsq_solution(A, b, rcond), numba_lstsq(A, b, rcond)), (A.shape, rcond)
        compared += 1
    assert compared == 400


def test_lstsq_solution_wide_system_is_minimum_norm():
    """m < n (not met by subset_lstsq, which is handed q x k with k < q): still numba's lstsq's answer."""
    rng = np.random.default_rng(5)
    A, b = rng.standard_normal((3, 6)), rng.standard_normal(3)
    x = lstsq_solution(A, b, -1.0)
    assert np.array_equal(x, numba_lstsq(A, b, -1.0))
    assert np.allclose(A @ x, b, rtol=0, atol=1e-12 * np.abs(b).max())  # consistent system, ~10 ulp of |b|


def test_lstsq_solution_refuses_non_finite_and_empty_input():
    A = np.eye(3)
    b = np.array([1.0, np.nan, 0.0])
    with pytest.raises(np.linalg.LinAlgError, match="infs or NaNs"):
        lstsq_solution(A, b, -1.0)
    with pytest.raises(np.linalg.LinAlgError, match="empty"):
        lstsq_solution(np.empty((3, 0)), np.ones(3), -1.0)


@njit(cache=True)
def subset_lstsq_before(T, active):
    """subset_lstsq as it was before issue 31 (numba's np.linalg.lstsq, slice assignment)."""
    q = T.shape[1]
    p = q - 1
    k = 0
    for j in range(p):
        if active[j]:
            k += 1
    coef = np.zeros(p)
    if k == 0:
        return coef, np.sum(T[:, p] ** 2)
    sub = np.empty((T.shape[0], k))
    norms = np.ones(k)
    m = 0
    for j in range(p):
        if active[j]:
            nrm = np.sqrt(np.sum(T[:, j] ** 2))
            if nrm > 0.0:
                norms[m] = nrm
            sub[:, m] = T[:, j] / norms[m]
            m += 1
    rhs = T[:, p].copy()
    sol, _, _, _ = np.linalg.lstsq(sub, rhs, -1.0)
    resid = rhs - sub @ sol
    m = 0
    for j in range(p):
        if active[j]:
            coef[j] = sol[m] / norms[m]
            m += 1
    return coef, np.sum(resid**2)


def test_subset_lstsq_is_the_same_bits_as_before():
    """subset_lstsq with the new solver: coefficients and residual sum of squares equal to the code before issue
    31 bit for bit (triangular factors as the regression hands them, collinear and zero columns included)."""
    rng = np.random.default_rng(7)
    compared = 0
    for _ in range(300):
        q = int(rng.integers(2, 12))
        T = np.triu(rng.standard_normal((q, q)) * 10.0 ** rng.uniform(-30, 5, q))
        if q > 2 and rng.random() < 0.3:
            T[:, 1] = 2.0 * T[:, 0]
        if rng.random() < 0.1:
            T[:, 0] = 0.0
        T = np.ascontiguousarray(T)
        active = rng.random(q - 1) < 0.6
        coef, rss = subset_lstsq(T, active)
        coef_before, rss_before = subset_lstsq_before(T, active)
        assert np.array_equal(coef, coef_before) and rss == rss_before
        compared += 1
    assert compared == 300


@njit(cache=True)
def numba_matvec(A, x):
    """The reference: numba's own matrix-vector product (what subset_lstsq's residual used before)."""
    return A @ x


def test_matvec_is_numbas_matmul_bit_for_bit():
    """Shapes subset_lstsq meets (q x k, k <= q) and others (wide, one row, one column), magnitudes over ~35
    decades: dgemv's summation order decides the rounding, so only the same call gives the same bits."""
    rng = np.random.default_rng(17)
    compared = 0
    for _ in range(300):
        m, n = int(rng.integers(1, 40)), int(rng.integers(1, 40))
        A = np.ascontiguousarray(rng.standard_normal((m, n)) * 10.0 ** rng.uniform(-30, 5, n))
        x = rng.standard_normal(n) * 10.0 ** rng.uniform(-5, 5, n)
        assert np.array_equal(matvec(A, x), numba_matvec(A, x)), (m, n)
        compared += 1
    assert compared == 300
    assert np.array_equal(matvec(np.empty((3, 0)), np.empty(0)), np.zeros(3))  # no columns: zeros, as A @ x


def test_the_python_lapack_and_blas_calls_are_the_bridges_bit_for_bit():
    """The twins subset_lstsq runs before it is compiled: dgelsd and dgemv through SciPy's wrappers with numba's
    arguments give the bridge's bits (the same routines of the same library), and so does the interpreted
    subset_lstsq."""
    from afmid.kernels.sparse import lstsq_solution_scipy, matvec_scipy, subset_lstsq_interpreted

    compared = 0
    for A, b, rcond in _problems(400, seed=35):
        x = lstsq_solution(A, b, rcond)
        assert np.array_equal(lstsq_solution_scipy(A, b, rcond), x), (A.shape, rcond)
        assert np.array_equal(matvec_scipy(A, x), matvec(A, x)), A.shape
        if A.shape[0] >= A.shape[1]:  # a factor of [A | y]: the last column is y
            T = np.ascontiguousarray(np.column_stack([A, b]))
            for active in (np.ones(A.shape[1], np.bool_), np.arange(A.shape[1]) % 2 == 0):
                coef, rss = subset_lstsq(T, active)
                coef_twin, rss_twin = subset_lstsq_interpreted(T, active)
                assert np.array_equal(coef, coef_twin) and rss == rss_twin
        compared += 1
    assert compared == 400
    with pytest.raises(np.linalg.LinAlgError):
        lstsq_solution_scipy(np.array([[np.nan]]), np.ones(1), -1.0)

"""Sequentially thresholded least squares on a triangular factor (numba kernel + NumPy twin).

The regression problem ``y ~ A c`` is carried as the upper-triangular factor
``T`` of the QR decomposition of ``[A | y]`` (q = p + 1 columns). Any subset
regression is then a small least-squares problem on columns of ``T`` with the
exact residual, without ever forming the ill-conditioned normal equations
(inverse powers z^-1..z^-8 make A'A singular to double precision).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _subset_lstsq(T, active):
    q = T.shape[1]
    p = q - 1
    k = 0
    for j in range(p):
        if active[j]:
            k += 1
    coef = np.zeros(p)
    if k == 0:
        return coef, np.sum(T[:, p] ** 2)
    # Unit-norm columns: SI columns differ by ~40 orders of magnitude, and the
    # SVD cut-off is relative to the largest singular value.
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


@njit(cache=True)
def stlsq_factor(T, scale, threshold, protected, initial, max_iter):
    """STLSQ on factor ``T`` (q x q) starting from the ``initial`` active set.

    A non-protected term is dropped when its contribution on unit-norm columns,
    ``|c_j| * scale_j``, falls below ``threshold``; iterate to a fixed point.
    Returns (active mask, coefficients, residual sum of squares).
    """
    p = T.shape[1] - 1
    active = initial.copy()
    coef, rss = _subset_lstsq(T, active)
    for _ in range(max_iter):
        changed = False
        for j in range(p):
            if active[j] and not protected[j] and abs(coef[j]) * scale[j] < threshold:
                active[j] = False
                changed = True
        if not changed:
            break
        coef, rss = _subset_lstsq(T, active)
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

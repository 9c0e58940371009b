"""The fine-grid cells where a gated library term switches on or off, and the sub-samples inside them (the fit's
hot loop: every library evaluation of a contact model runs them).

:func:`switching_cells` finds the samples whose cell holds a switch (a term exactly zero on one sample and not on
the next) in one pass over the columns, in any layout; :func:`cell_subsamples` places sub-samples on the cubic
Hermite interpolation of (x, xdot) through those cells. Their plain-NumPy twins (the element-wise array
expressions :func:`afmid.fit.system.average_switching_cells` used before, several passes over the fine grid and
its strided views) are :func:`switching_cells_numpy` and :func:`cell_subsamples_numpy`;
tests/kernels/test_switching.py compares them bit for bit (the same operations in the same order on each element).
The fit calls :data:`switching_cells_or_twin` and :data:`cell_subsamples_or_twin`: the kernels, or their twins
while the kernels are not compiled (afmid.kernels.twin; compiling both is ~0.7 s of CPU in a new install, the
twins ~0.6 ms per library evaluation).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from afmid.kernels.twin import KernelOrTwin


@njit(cache=True, no_cfunc_wrapper=True)
def switching_cells(fine):
    """(rows, cols) int64 of the samples of ``fine`` (n, M, p: n rows of M fine-grid samples, p terms; any strides)
    next to a switch: some term is exactly zero on sample j and not on j + 1 (both samples are flagged), the first
    and last sample of each row excepted (a cell needs both neighbours). In row-major order, as ``np.nonzero``."""
    n, M, p = fine.shape
    flagged = np.empty((n, M), np.bool_)  # np.empty and a loop: np.zeros would be one more compilation in a new install
    for r in range(n):
        for j in range(M):
            flagged[r, j] = False
    for j in range(M - 1):  # the sample index outermost: the weak form keeps the columns sample-major
        for r in range(n):
            for k in range(p):
                if (fine[r, j, k] == 0.0) != (fine[r, j + 1, k] == 0.0):
                    flagged[r, j] = True
                    flagged[r, j + 1] = True
                    break
    count = 0
    for r in range(n):
        flagged[r, 0] = False
        flagged[r, M - 1] = False
        for j in range(M):
            if flagged[r, j]:
                count += 1
    rows = np.empty(count, np.int64)
    cols = np.empty(count, np.int64)
    i = 0
    for r in range(n):
        for j in range(M):
            if flagged[r, j]:
                rows[i] = r
                cols[i] = j
                i += 1
    return rows, cols


@njit(cache=True, no_cfunc_wrapper=True)
def cell_subsamples(x, v, t, rows, cols, subsamples):
    """Positions, velocities and times (cells, subsamples) of ``subsamples`` points evenly spread over the cell of
    each sample (``rows``, ``cols``) of the fine-grid rows ``x`` (m), ``v`` (m/s), ``t`` (s) (n, M each, uniform
    time step), from the cubic Hermite interpolation of (x, v) between the samples around each point. The point
    at offset u (in cells, -0.5 .. 0.5) lies between samples j - 1 and j when u < 0 (at s = 1 + u from j - 1),
    else between j and j + 1 (at s = u)."""
    h = t[0, 1] - t[0, 0]
    cells = rows.size
    xs = np.empty((cells, subsamples))
    vs = np.empty((cells, subsamples))
    ts = np.empty((cells, subsamples))
    for c in range(cells):
        r, j = rows[c], cols[c]
        t_cell = t[r, j]
        for k in range(subsamples):
            u = (k + 0.5) / subsamples - 0.5
            if u < 0:
                a, s = j - 1, 1.0 + u
            else:
                a, s = j, u
            xa, xb, va, vb = x[r, a], x[r, a + 1], v[r, a], v[r, a + 1]
            s2 = s * s
            s3 = s * s * s
            xs[c, k] = ((2 * s3 - 3 * s2 + 1) * xa + (s3 - 2 * s2 + s) * h * va + (3 * s2 - 2 * s3) * xb
                        + (s3 - s2) * h * vb)
            vs[c, k] = (6 * s2 - 6 * s) * (xa - xb) / h + (3 * s2 - 4 * s + 1) * va + (3 * s2 - 2 * s) * vb
            ts[c, k] = t_cell + u * h
    return xs, vs, ts


def switching_cells_numpy(fine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain-NumPy twin of :func:`switching_cells`: the samples next to a zero / non-zero change of any term."""
    zero = fine == 0.0
    switch = np.any(zero[:, 1:] != zero[:, :-1], axis=2)  # between samples j and j + 1
    flagged = np.zeros(fine.shape[:2], dtype=bool)
    flagged[:, :-1] |= switch
    flagged[:, 1:] |= switch
    flagged[:, 0] = flagged[:, -1] = False  # the cell needs both neighbours
    return np.nonzero(flagged)


def cell_subsamples_numpy(x, v, t, rows, cols, subsamples):
    """The plain-NumPy twin of :func:`cell_subsamples` (the cubic Hermite interpolation as array expressions)."""
    h = float(t[0, 1] - t[0, 0])
    u = (np.arange(subsamples) + 0.5) / subsamples - 0.5  # offsets within the cell, in cells
    left = u < 0  # the left half of the cell lies between samples j - 1 and j
    a = cols[:, None] - left[None, :].astype(int)
    s = np.where(left, 1.0 + u, u)[None, :]
    r = rows[:, None]
    xa, xb, va, vb = x[r, a], x[r, a + 1], v[r, a], v[r, a + 1]
    s2, s3 = s * s, s * s * s
    xs = (2 * s3 - 3 * s2 + 1) * xa + (s3 - 2 * s2 + s) * h * va + (3 * s2 - 2 * s3) * xb + (s3 - s2) * h * vb
    vs = (6 * s2 - 6 * s) * (xa - xb) / h + (3 * s2 - 4 * s + 1) * va + (3 * s2 - 2 * s) * vb
    ts = t[rows, cols][:, None] + u[None, :] * h
    return xs, vs, ts


#: The twins run on fine grids of at most this many values (the demo's 50 x 2200 x 4: 0.44 million); a larger
#: record compiles the kernels at once (the twins' passes grow with the grid, the compilation does not).
TWIN_MAX_VALUES = 1 << 22


def _small_grid(fine) -> bool:
    return fine.size <= TWIN_MAX_VALUES


def _few_cells(x, v, t, rows, cols, subsamples) -> bool:
    return rows.size * subsamples <= TWIN_MAX_VALUES


#: The fit's calls: the kernels, or while they are compiled neither in this process nor in numba's cache, their
#: twins until those have taken about what compiling the kernel costs (0.4 and 0.3 s of CPU).
switching_cells_or_twin = KernelOrTwin(switching_cells, switching_cells_numpy, _small_grid, compile_seconds=0.4)
cell_subsamples_or_twin = KernelOrTwin(cell_subsamples, cell_subsamples_numpy, _few_cells, compile_seconds=0.3)

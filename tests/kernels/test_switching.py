"""The switching-cell kernels (afmid.kernels.switching) against their NumPy twins, bit for bit.

The twins are the array expressions afmid.fit.system.average_switching_cells used before the kernels: the same
comparisons (integer results) and the same floating-point operations in the same order on each element (the
Hermite sub-samples), so the same bits are required, in both layouts the fit passes (the weak form's transposed
sample-major view, and a C-contiguous array).
"""

from __future__ import annotations

import numpy as np
import pytest

from afmid.kernels.switching import cell_subsamples, cell_subsamples_numpy, switching_cells, switching_cells_numpy

SUBSAMPLES = 32


def _tapping_rows(n_rows=6, samples=512, seed=3):
    """Fine-grid rows of a tapping trajectory (m, m/s, s) and a gated contact term and an always-on term on them."""
    rng = np.random.default_rng(seed)
    h = 1.0 / (300e3 * samples)
    t = np.arange(n_rows * samples).reshape(n_rows, samples) * h + 1e-3
    w = 2 * np.pi * 300e3
    x = 10e-9 * np.cos(w * t) + 0.3e-9 * np.cos(2 * w * t + 0.4) + 1e-12 * rng.standard_normal(t.shape)
    v = -10e-9 * w * np.sin(w * t) - 0.6e-9 * w * np.sin(2 * w * t + 0.4)
    depth = x - 9.6e-9  # in contact near the lowest point of each period
    columns = np.stack([np.where(depth > 0, np.abs(depth) ** 1.5, 0.0), 1.0 / (1e-9 + np.abs(x))], axis=2)
    columns[2, 5, 1] = np.nan  # NaN counts as non-zero, as == 0.0 says
    columns[4, 100:103, 1] = 0.0  # a second term switching too
    return x, v, t, columns


@pytest.mark.parametrize("layout", ["sample-major view", "C-contiguous"])
def test_switching_cells_are_the_numpy_twins(layout):
    x, v, t, columns = _tapping_rows()
    fine = (np.ascontiguousarray(columns.transpose(1, 0, 2)).transpose(1, 0, 2) if layout == "sample-major view"
            else np.ascontiguousarray(columns))
    rows, cols = switching_cells(fine)
    rows_np, cols_np = switching_cells_numpy(fine)
    assert rows.size > 20  # the contact switches twice a period in every row
    np.testing.assert_array_equal(rows, rows_np)
    np.testing.assert_array_equal(cols, cols_np)
    xs, vs, ts = cell_subsamples(x, v, t, rows, cols, SUBSAMPLES)
    for kernel, twin in zip((xs, vs, ts), cell_subsamples_numpy(x, v, t, rows_np, cols_np, SUBSAMPLES)):
        assert np.array_equal(kernel, twin)  # the same operations in the same order: the same bits


def test_no_switch_gives_no_cell():
    fine = np.ones((3, 50, 2))
    fine[1, :, 0] = 0.0  # zero on the whole row: no change, no cell
    rows, cols = switching_cells(fine)
    assert rows.size == cols.size == 0
    fine[1, 0, 0] = 1.0  # a change between samples 0 and 1: only sample 1 has both neighbours
    rows, cols = switching_cells(fine)
    assert rows.tolist() == [1] and cols.tolist() == [1]

"""The periodic-prediction kernel (afmid.kernels.periodic) against its NumPy twin, bit for bit.

The twin is the array expression the glitch scan used before the kernel (afmid.io.glitches): the same cubic
Lagrange weights and products in the same order, and the median of the four chosen neighbours as the mean of the
middle two sorted values, so the same bits are required: on whole and fractional periods, the shortest records
(6 periods: near the ends the neighbours +-3 and +-4 periods away are taken), samples of very different scales,
and NaN samples (a NaN neighbour keeps its place among the four and is left out of the median).
"""

from __future__ import annotations

import numpy as np
import pytest

from afmid.kernels.periodic import median_of_rows, periodic_prediction, periodic_prediction_numpy


def _bits(values: np.ndarray) -> list[int]:
    return values.view(np.int64).tolist()


@pytest.mark.parametrize("period, periods, scale", [(128.0, 78, 1e-9), (128.00384, 78, 1e-9), (200.0, 50, 1.0),
                                                    (37.3, 6.01, 1e3), (1000.0 / 7, 9.5, 1e-9), (6.5, 6.2, 1.0)])
def test_the_kernel_gives_its_twins_bits(period, periods, scale):
    rng = np.random.default_rng(int(period * 100))
    n = int(periods * period)
    t = np.arange(n)
    x = scale * (np.sin(2 * np.pi * t / period) + 0.2 * np.cos(6 * np.pi * t / period) ** 7
                 + 1e-3 * rng.standard_normal(n))
    x[rng.integers(0, n, 5)] += 0.3 * scale  # glitches: outliers among the four neighbours of other samples
    kernel, twin = periodic_prediction(x, period), periodic_prediction_numpy(x, period)
    assert not np.isnan(twin).any()
    assert _bits(kernel) == _bits(twin)


def test_a_nan_sample_keeps_its_place_among_the_four_neighbours():
    """A NaN neighbour is one of the four chosen (the next valid shift does not replace it) and is left out of the
    median, which is then that of three: the kernel must choose as the twin does, not skip to a fifth."""
    rng = np.random.default_rng(5)
    period = 50.5
    x = np.sin(2 * np.pi * np.arange(int(12 * period)) / period) + 0.01 * rng.standard_normal(int(12 * period))
    x[[3, 200, 201, 400]] = np.nan
    x[300] = np.inf
    with np.errstate(invalid="ignore"):  # the twin's weights times inf: 0 * inf
        twin = periodic_prediction_numpy(x, period)
    kernel = periodic_prediction(x, period)
    assert _bits(kernel) == _bits(twin)
    # the sample one period after a NaN one: a median of three, not of four
    i = 200 + int(round(period)) + 20
    assert np.isfinite(kernel[i])


def test_no_neighbour_on_the_record_gives_nan():
    """A record shorter than two periods and a half: some samples have no neighbour whose stencil lies on it."""
    x = np.cos(np.arange(20) * 0.9)
    kernel, twin = periodic_prediction(x, 15.0), periodic_prediction_numpy(x, 15.0)
    assert np.isnan(twin).any() and _bits(kernel) == _bits(twin)


def test_the_row_median_is_nanmedians_with_nan_rows():
    """Rows of 0 to 8 values among NaN: the same bits as np.nanmedian (NaN where a row has none)."""
    rng = np.random.default_rng(3)
    values = rng.standard_normal((400, 8))
    values[rng.random(values.shape) < np.linspace(0, 1, 400)[:, None]] = np.nan
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):  # nanmedian warns of the all-NaN rows
        expected = np.nanmedian(values, axis=1)
    assert np.isnan(values).all(axis=1).any()
    assert np.array_equal(median_of_rows(values), expected, equal_nan=True)

"""Each sample of a record predicted from the same phase of its neighbouring periods (the glitch scan's prediction,
:mod:`afmid.io.glitches`, which runs on every trace loaded and on every pixel of a map).

A sample's prediction is the median of the record one and two periods before and after it (the nearest four
periods on the record near its ends: the shifts +-1, +-2, +-3, +-4 periods in that order, the first four whose
interpolation stencil lies on the record), each read by cubic Lagrange interpolation between samples (the period
is not a whole number of them). :func:`periodic_prediction` is the numba kernel, one pass over the samples with no
temporaries; :func:`periodic_prediction_numpy` its twin, the array expressions the glitch scan used before (a
median as ``np.nanmedian`` takes it: the middle two sorted values added and halved). They give the same bits: the
same float operations in the same order on each sample (tests/kernels/test_periodic.py). The scan calls
:data:`periodic_prediction_or_twin` (afmid.kernels.twin: the twin while the kernel is compiled neither in this process
nor in numba's cache, about 2.5 ms of CPU on a 10^4-sample record against ~0.3 ms for the kernel).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afmid.kernels.twin import KernelOrTwin

#: Periods before and after a sample whose values at the same phase may predict it, nearest first.
SHIFTS = np.array([-1, 1, -2, 2, -3, 3, -4, 4])
#: Neighbouring periods whose values predict a sample.
CHOSEN = 4
#: Samples per chunk of the twin (bounds its (chunk, 8) temporaries).
TWIN_CHUNK = 1 << 18


@njit(cache=True, no_cfunc_wrapper=True)
def periodic_prediction(x, period):
    """The prediction of every sample of ``x`` (float64, contiguous; any units) from its neighbouring periods,
    ``period`` samples long (> 0, fractional); NaN where no neighbour's stencil lies on the record. Same units as
    ``x``. See the module docstring."""
    n = x.size
    out = np.empty(n)
    chosen = np.empty(CHOSEN)
    for i in range(n):
        t = float(i)
        taken = 0  # neighbours chosen (a NaN one included: it takes its place among the four)
        count = 0  # of them, values not NaN
        for s in range(SHIFTS.size):
            if taken == CHOSEN:
                break
            where = t + SHIFTS[s] * period
            base = int(math.floor(where))
            if base < 1 or base > n - 3:
                continue
            taken += 1
            u = where - base
            # cubic Lagrange weights on samples base-1 .. base+2 at u in [0, 1), each product in the twin's order
            w0 = -u * (u - 1) * (u - 2) / 6
            w1 = (u + 1) * (u - 1) * (u - 2) / 2
            w2 = -(u + 1) * u * (u - 2) / 2
            w3 = (u + 1) * u * (u - 1) / 6
            value = 0.0 + w0 * x[base - 1]
            value = value + w1 * x[base]
            value = value + w2 * x[base + 1]
            value = value + w3 * x[base + 2]
            if value != value:  # NaN: left out of the median, as the twin's nanmedian leaves it
                continue
            k = count  # insertion into the sorted ones so far
            while k > 0 and chosen[k - 1] > value:
                chosen[k] = chosen[k - 1]
                k -= 1
            chosen[k] = value
            count += 1
        if count == 0:
            out[i] = np.nan
        else:
            half = count // 2
            low = half if count % 2 == 1 else half - 1
            out[i] = (chosen[low] + chosen[half]) / 2.0
    return out


def periodic_prediction_numpy(x: np.ndarray, period: float) -> np.ndarray:
    """:func:`periodic_prediction`'s twin: the same bits from array expressions, in chunks of :data:`TWIN_CHUNK`
    samples (its temporaries are (chunk, 8))."""
    n = x.size
    out = np.empty(n)
    for lo in range(0, n, TWIN_CHUNK):
        t = np.arange(lo, min(lo + TWIN_CHUNK, n), dtype=float)
        # the first four valid shifts, nearest first: +-1 and +-2 periods away from the ends
        where = t[:, None] + SHIFTS[:CHOSEN] * period  # (m, 4) fractional sample positions
        base = np.floor(where).astype(np.int64)
        valid = (base >= 1) & (base <= n - 3)
        near_end = ~valid.all(axis=1)
        if near_end.any():  # the nearest valid ones among all eight (invalid ones after them when fewer)
            wide = t[near_end][:, None] + SHIFTS * period
            wide_base = np.floor(wide).astype(np.int64)
            wide_valid = (wide_base >= 1) & (wide_base <= n - 3)
            columns = np.argsort(~wide_valid, axis=1, kind="stable")[:, :CHOSEN]
            where[near_end] = np.take_along_axis(wide, columns, axis=1)
            base[near_end] = np.take_along_axis(wide_base, columns, axis=1)
            valid[near_end] = np.take_along_axis(wide_valid, columns, axis=1)
        u = where - base
        weights = (-u * (u - 1) * (u - 2) / 6, (u + 1) * (u - 1) * (u - 2) / 2, -(u + 1) * u * (u - 2) / 2,
                   (u + 1) * u * (u - 1) / 6)
        index = np.clip(base, 1, n - 3)
        values = sum(w * x[index + j - 1] for j, w in enumerate(weights))
        chosen = np.where(valid, values, np.nan)
        out[lo:lo + t.size] = median_of_rows(chosen)
    return out


def median_of_rows(values: np.ndarray) -> np.ndarray:
    """The median of each row of ``values`` (m, k) over its values that are not NaN, as ``np.nanmedian(values,
    axis=1)`` computes it for short rows (sorted, the two middle values added and halved; the middle one twice for
    an odd count): the same bits, without the masked arrays that cost most of its time. NaN for a row of NaN."""
    ordered = np.sort(values, axis=1)  # NaN last
    counts = np.count_nonzero(~np.isnan(values), axis=1)
    half = counts // 2
    low = np.where(counts % 2 == 1, half, half - 1)
    rows = np.arange(values.shape[0])
    middle = (ordered[rows, np.maximum(low, 0)] + ordered[rows, half.clip(max=values.shape[1] - 1)]) / 2.0
    return np.where(counts > 0, middle, np.nan)


#: The twin runs on records of at most this many samples; a longer one compiles the kernel at once (the twin's
#: cost grows with the record, the compilation's does not).
TWIN_MAX_SAMPLES = 1 << 20


def _short_record(x, period) -> bool:
    return x.size <= TWIN_MAX_SAMPLES


#: The glitch scan's call: the kernel, or while it is compiled neither in this process nor in numba's cache, its twin
#: until that has taken about what compiling the kernel costs.
periodic_prediction_or_twin = KernelOrTwin(periodic_prediction, periodic_prediction_numpy, _short_record,
                                           compile_seconds=0.5)

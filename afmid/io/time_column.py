"""Checks of a time column (``data.time_column``): NaN, resolution, order, gaps, duplicates, jitter.

Every problem is an error naming ``data.time_column``: the fit needs uniformly spaced samples. Split from
:mod:`afmid.io.defects` (which re-exports :func:`check_time`), whose other checks look at the deflection.
"""

from __future__ import annotations

import math

import numpy as np

from afmid.io.findings import Finding

#: Time steps may jitter by this fraction of the mean step (as afmid.fit.pipeline requires).
TIME_JITTER = 1e-3


#: Time values whose float64 spacing exceeds this fraction of the sampling step cannot be uniform to the 0.1 % the
#: jitter check asks: the step itself is rounded to the spacing.
_TIME_RESOLUTION_FRACTION = TIME_JITTER


def _time_resolution(time: np.ndarray) -> Finding | None:
    """The finding for a time column float64 cannot resolve: absolute (Unix-epoch) seconds, ~1.7e9 s, are spaced
    2^-22 s = 2.4e-7 s apart there, coarser than a 17 ns step, so the steps come out 0 or 2.4e-7 s (before, this
    read 'duplicated or reordered samples', which named no cause). None when the values resolve the step."""
    largest = float(np.max(np.abs(time)))
    step = float(time[-1] - time[0]) / (time.size - 1)
    resolution = float(np.spacing(largest))
    if not (math.isfinite(step) and step > 0) or resolution <= _TIME_RESOLUTION_FRACTION * step:
        return None
    return Finding("time_resolution", "error",
                   f"the time column's values reach {largest:.3g} s, where float64 resolves only {resolution:.3g} s, "
                   f"coarser than a thousandth of the sampling step {step:.3g} s (the steps must be uniform to 0.1 %): "
                   "absolute (e.g. Unix-epoch) times? subtract the start time (a relative time column) or remove "
                   "data.time_column and give data.sample_rate", "data.time_column",
                   {"largest": largest, "resolution": resolution, "step": step})


def check_time(time: np.ndarray) -> list[Finding]:
    """Gaps (dropped samples), short steps (duplicated samples) and jitter in a time column.

    Every problem is an error: the fit needs uniformly spaced samples.
    """
    key = "data.time_column"
    if not np.all(np.isfinite(time)):
        return [Finding("time_nan", "error", "the time column has NaN/inf values", key)]
    steps = np.diff(time)
    if steps.size == 0:
        return []
    if (resolution := _time_resolution(time)) is not None:
        return [resolution]
    if np.any(steps <= 0):
        first = int(np.argmax(steps <= 0)) + 1
        return [Finding("time_order", "error",
                        f"time is not strictly increasing (sample {first}); duplicated or reordered samples", key,
                        {"first": first})]
    step = float(np.median(steps))
    long_ = steps > 1.5 * step
    short = steps < 0.5 * step
    findings = []
    # Regular parts: split between the samples around each irregular step.
    breaks = np.flatnonzero(long_ | short)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks + 1, [time.size]])
    best = int(np.argmax(ends - starts))
    clean_start, clean_len = int(starts[best]), int(ends[best] - starts[best])
    crop = f"crop the trace to a regular part (the longest is samples {clean_start}-{clean_start + clean_len - 1})"
    if long_.any():
        first = int(np.argmax(long_))
        largest = float(steps.max() / step)
        findings.append(Finding(
            "time_gaps", "error",
            f"the time column has {int(long_.sum())} gap{'s' if long_.sum() > 1 else ''} (the largest "
            f"{largest:.3g} sampling steps, the first after sample {first} at t = {time[first]:.6g} s): samples "
            f"were dropped; {crop} or resample it onto a uniform grid",
            key, {"n_gaps": int(long_.sum()), "first": first, "largest_steps": largest, "step": step,
                  "clean_start": clean_start, "clean_length": clean_len}))
    if short.any():
        first = int(np.argmax(short))
        findings.append(Finding(
            "time_duplicates", "error",
            f"the time column has {int(short.sum())} step{'s' if short.sum() > 1 else ''} shorter than half the "
            f"sampling step (the first after sample {first}): duplicated or inserted samples; remove them or {crop}",
            key, {"n_short": int(short.sum()), "first": first, "step": step,
                  "clean_start": clean_start, "clean_length": clean_len}))
    if findings:
        return findings
    mean = float((time[-1] - time[0]) / steps.size)
    jitter = float(np.max(np.abs(steps - mean)) / mean)
    if jitter > TIME_JITTER:
        findings.append(Finding(
            "time_jitter", "error",
            f"the time steps vary by up to {100 * jitter:.2g} % of the step (rounded time values or an irregular "
            f"clock), the fit needs them uniform to {100 * TIME_JITTER:.1g} %: remove data.time_column and give "
            f"data.sample_rate ({1 / mean:.6g} Hz on average)",
            key, {"jitter": jitter, "mean_rate": 1 / mean}))
    return findings

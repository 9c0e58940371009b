"""History-dependent states along a measured trajectory: gates (meniscus, JKR neck) and relaxing states (the
standard linear solid's lagging indentation)."""

from __future__ import annotations

import numpy as np
from numba import njit

from afmid.kernels.integrate import next_gate_state_at, next_relaxation_state_at
from afmid.terms.kinematics import relaxation_weights


@njit(cache=True)
def scan_hysteresis(on: np.ndarray, off: np.ndarray, initial: float, out: np.ndarray) -> float:
    """Fill ``out`` with the gate state (0/1) sample by sample; returns the final state.

    The state switches on where ``on`` is true (non-zero) while off, and off where
    ``off`` is true while on. ``initial`` is the state before the first sample,
    so chunks of a long trace can be scanned in sequence.
    """
    state = initial
    for i in range(on.size):
        state = next_gate_state_at(state, on[i], off[i])
        out[i] = state
    return state


def scan_hysteresis_numpy(on: np.ndarray, off: np.ndarray, initial: float = 0.0) -> np.ndarray:
    """Plain-NumPy twin of :func:`scan_hysteresis`, vectorised over switching events.

    The state after sample i equals the most recent decisive event: an 'on'
    sample seen while off or an 'off' sample seen while on. Because on and off
    regions of a physical gate do not overlap, the state is the last of the
    samples where exactly one of on/off holds (on -> 1, off -> 0).
    """
    on_b = on != 0
    off_b = off != 0
    decisive = on_b ^ off_b
    value = np.where(on_b, 1.0, 0.0)
    idx = np.where(decisive, np.arange(on.size), -1)
    last = np.maximum.accumulate(idx)
    return np.where(last >= 0, value[np.maximum(last, 0)], initial)


@njit(cache=True)
def scan_relaxation(source: np.ndarray, t: np.ndarray, time: float, initial: float, out: np.ndarray) -> float:
    """Fill ``out`` with a relaxing state, d(state)/dt = (source - state) / time (s), along samples at times ``t``
    (s), from ``initial`` at the first sample, the source linear between samples; returns the last value."""
    state = initial
    if source.size > 0:
        out[0] = state
    for i in range(1, source.size):
        state = next_relaxation_state_at(state, source[i - 1], source[i], t[i] - t[i - 1], time)
        out[i] = state
    return state


def scan_relaxation_numpy(source: np.ndarray, t: np.ndarray, time: float, initial: float) -> np.ndarray:
    """Plain-NumPy twin of :func:`scan_relaxation`, vectorised: the exact steps (decay_i, drive_i) compose as
    state_n = P_n (initial + sum_{i<=n} drive_i / P_i), P_n = prod_{i<=n} decay_i, summed in blocks short enough
    that 1 / P_i stays finite (each block restarts from the state at its start)."""
    decay, w_start, w_end = relaxation_weights(np.diff(t), time)
    drive = w_start * source[:-1] + w_end * source[1:]
    out = np.empty(source.size)
    if source.size == 0:
        return out
    out[0] = initial
    state = float(initial)
    log_decay = np.log(decay)
    start = 0
    while start < decay.size:
        # The longest block over which the product falls by at most e^-300 (one step at least).
        fall = np.cumsum(log_decay[start:])
        stop = start + max(1, int(np.searchsorted(-fall, 300.0)))
        product = np.exp(fall[:stop - start])
        values = product * (state + np.cumsum(drive[start:stop] / product))
        out[start + 1:stop + 1] = values
        state = float(values[-1])
        start = stop
    return out

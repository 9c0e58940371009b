"""History-dependent state gates (meniscus, JKR neck) along a measured trajectory."""

from __future__ import annotations

import numpy as np
from numba import njit

from afmid.kernels.integrate import next_gate_state_at


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

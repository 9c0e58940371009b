"""The kinematics of the tip and the rule of a history gate: the one NumPy definition of each.

The term language (:mod:`afmid.terms.expr`) sees the deflection x (m, towards the
sample positive) and its velocity xdot (m/s) through the separation
``z = d - x`` (d: the rest separation, m), ``zdot = -xdot``, the indentation
``delta = a0 - z`` in contact (``z <= a0``) and 0 outside, and
``deltadot = -zdot`` in contact and 0 outside.

A history gate (meniscus, JKR neck) switches on where its ``on`` condition holds
while it is off, and off where its ``off`` condition holds while it is on.

The compiled kernels use numba twins of both
(:func:`afmid.kernels.integrate.contact_kinematics_at`,
:func:`afmid.kernels.integrate.next_gate_state_at`); tests/terms/test_kinematics.py
holds them equal bit for bit. No numba here: the fit's and the CLI's start-up
import this module.
"""

from __future__ import annotations

import numpy as np


def contact_kinematics(x, xdot, d: float, a0: float):
    """(z, zdot, delta, deltadot), in m and m/s, for deflections ``x`` (m) and velocities ``xdot`` (m/s) (arrays
    of one shape) at rest separation ``d`` (m) and contact distance ``a0`` (m)."""
    z = d - x
    contact = z <= a0
    return z, -xdot, np.where(contact, a0 - z, 0.0), np.where(contact, xdot, 0.0)  # deltadot = -zdot = xdot


def next_gate_state(state, on, off):
    """The gate (0.0 off, 1.0 on) after a sample where the conditions ``on``/``off`` (non-zero: true) hold, from
    ``state`` before it (a gate that is on stays as it is until ``off``); arrays broadcast (one gate per
    trajectory, e.g.)."""
    return np.where(state == 0.0, np.where(on != 0, 1.0, 0.0), np.where(off != 0, 0.0, state))


#: Below this step / time constant the lag's weights come from their series (1 - (1 - e^-u) / u loses digits).
RELAXATION_SERIES_BELOW = 1e-4


def relaxation_weights(dt, time):
    """(decay, w_start, w_end) of the exact step of d(state)/dt = (source - state) / time over dt (s, > 0),
    the source linear in time from its value at the start to its value at the end::

        state_end = decay * state_start + w_start * source_start + w_end * source_end

    decay = e^-u, w_end = 1 - (1 - e^-u) / u, w_start = 1 - e^-u - w_end, u = dt / time. Arrays broadcast."""
    u = np.asarray(dt, float) / time
    decay = np.exp(-u)
    gain = -np.expm1(-u)
    small = u < RELAXATION_SERIES_BELOW
    with np.errstate(divide="ignore", invalid="ignore"):
        w_end = np.where(small, u / 2.0 - u * u / 6.0, 1.0 - gain / np.where(small, 1.0, u))
    return decay, gain - w_end, w_end


def next_relaxation_state(state, source_start, source_end, dt, time):
    """A relaxing state after dt (s) (:func:`relaxation_weights`), from ``state`` where the source went from
    ``source_start`` to ``source_end``; arrays broadcast (one state per trajectory, e.g.)."""
    decay, w_start, w_end = relaxation_weights(dt, time)
    return decay * state + w_start * source_start + w_end * source_end

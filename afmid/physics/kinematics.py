"""The kinematics of the tip and the rule of a history gate: the one NumPy definition of each.

The term language (:mod:`afmid.physics.expr`) sees the deflection x (m, towards the
sample positive) and its velocity xdot (m/s) through the separation
``z = d - x`` (d: the rest separation, m), ``zdot = -xdot``, the indentation
``delta = a0 - z`` in contact (``z <= a0``) and 0 outside, and
``deltadot = -zdot`` in contact and 0 outside.

A history gate (meniscus, JKR neck) switches on where its ``on`` condition holds
while it is off, and off where its ``off`` condition holds while it is on.

The compiled kernels use numba twins of both
(:func:`afmid.kernels.integrate.contact_kinematics_at`,
:func:`afmid.kernels.integrate.next_gate_state_at`); tests/physics/test_kinematics.py
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

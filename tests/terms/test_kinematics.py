"""The kinematics and the gate rule (afmid.terms.kinematics) equal their numba twins bit for bit."""

from __future__ import annotations

import numpy as np
from numba import njit

from afmid.kernels.hysteresis import scan_hysteresis, scan_hysteresis_numpy
from afmid.kernels.integrate import contact_kinematics_at, next_gate_state_at
from afmid.terms.kinematics import contact_kinematics, next_gate_state


@njit(cache=False)
def _kinematics_along(x, v, separation, a0, out):
    for i in range(x.size):
        out[0, i], out[1, i], out[2, i], out[3, i] = contact_kinematics_at(x[i], v[i], separation, a0)


@njit(cache=False)
def _gates_along(state, on, off, out):
    for i in range(state.size):
        out[i] = next_gate_state_at(state[i], on[i], off[i])


def _same_bits(a, b) -> bool:
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def test_contact_kinematics_equals_its_numba_twin_bit_for_bit():
    rng = np.random.default_rng(7)
    a0, separation = 0.165e-9, 1.2e-9
    x = np.concatenate([rng.normal(0.0, 2e-9, 2000), [separation - a0, separation - a0 + 1e-25, 0.0, -0.0]])
    v = np.concatenate([rng.normal(0.0, 1e-3, 2000), [0.0, -0.0, 1e-3, -1e-3]])
    z, zdot, delta, deltadot = contact_kinematics(x, v, separation, a0)
    twin = np.empty((4, x.size))
    _kinematics_along(x, v, separation, a0, twin)
    for row, mine in zip(twin, (z, zdot, delta, deltadot)):
        assert _same_bits(row, mine)
    contact = z <= a0
    assert contact.any() and (~contact).any()
    assert np.all(delta[contact] > -1e-30) and np.all(delta[~contact] == 0.0)
    np.testing.assert_array_equal(deltadot[contact], -zdot[contact])


def test_gate_rule_equals_its_numba_twin_and_the_scans():
    grid = np.array([(s, on, off) for s in (0.0, 1.0, 0.5) for on in (0.0, 1.0, -2.0) for off in (0.0, 1.0, 3.0)])
    state, on, off = grid.T.copy()
    twin = np.empty(state.size)
    _gates_along(state, on, off, twin)
    assert _same_bits(twin, next_gate_state(state, on, off))
    # off: switches on only where on holds; on: switches off only where off holds, else stays as it is
    np.testing.assert_array_equal(next_gate_state(0.0, np.array([0.0, 1.0]), 1.0), [0.0, 1.0])
    np.testing.assert_array_equal(next_gate_state(1.0, 1.0, np.array([0.0, 1.0])), [1.0, 0.0])
    # the scans over a trajectory are the rule applied sample by sample
    rng = np.random.default_rng(3)
    z = np.cumsum(rng.normal(0.0, 1.0, 3000))
    on, off = (z < -2.0).astype(float), (z > 4.0).astype(float)
    for initial in (0.0, 1.0):
        expected, state = np.empty(z.size), initial
        for i in range(z.size):
            state = float(next_gate_state(state, on[i], off[i]))
            expected[i] = state
        out = np.empty(z.size)
        scan_hysteresis(on, off, initial, out)
        np.testing.assert_array_equal(out, expected)
        np.testing.assert_array_equal(scan_hysteresis_numpy(on, off, initial), expected)

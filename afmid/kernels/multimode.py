"""Fixed-step RK4 for a cantilever with several flexural modes, non-smooth events located exactly.

Each mode i is an oscillator driven by the same tip force (SI, x positive toward the sample)::

    m_i x_i'' + c_i x_i' + k_i x_i = F0 cos(w t) - F_ts(z, zdot, states) + F_th,i,   x = sum_i x_i,  z = d - x

(mode 0 is the first mode; ``F_th`` acts on the first mode only). The force law is the generic VM law of
:mod:`afmid.kernels.integrate` (``law_force``/``law_full``/``law_conditions`` at the tip's x = sum x_i,
v = sum v_i), with its ``dyn`` layout for d and a0. Events (contact, gate flips) are handled as in
:mod:`afmid.kernels.integrate`: after a step over which a relevant switching function changed sign, the first
crossing is located by Illinois regula falsi on RK4 sub-steps from the step start, the state advanced to just
past it, the gates updated, and the rest of the step integrated. With one mode this is the same algorithm as
the single-mode kernel (a test compares the two).

``modes`` is (M, 3): [m_i (kg), c_i (kg/s), k_i (N/m)] per mode. The plain-Python twin of :func:`integrate_modes`
is its ``py_func`` (the same text run by the interpreter); the single-mode kernel is the independent check.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afmid.kernels.integrate import (
    EVENT_TOLERANCE,
    MAX_EVENTS_PER_STEP,
    MAX_ROOT_ITERATIONS,
    NOT_FINITE,
    OK,
    law_conditions,
    law_force,
    law_full,
    law_work,
    start_relaxation_clocks,
    update_gates,
)

_jit = njit(cache=True, error_model="numpy")


@_jit
def switch_matters(owner, gates):
    """Whether a switching function (owner -1: a term's; 2 g / 2 g + 1: gate g's on / off) can change anything."""
    if owner < 0:
        return True
    if owner % 2 == 0:
        return gates[owner // 2] == 0.0
    return gates[owner // 2] != 0.0


@_jit
def _accelerations(x, v, tip_force, f_thermal, modes, out):
    """x_i'' (m/s^2) of every mode for the tip force (drive - F_ts, N); the thermal force on mode 0."""
    for i in range(x.size):
        extra = f_thermal if i == 0 else 0.0
        out[i] = (tip_force + extra - modes[i, 1] * v[i] - modes[i, 2] * x[i]) / modes[i, 0]


@_jit
def rk4_modes(x, v, t, h, f_start, f_thermal, dyn, modes, gates, law, work, tmp, x_out, v_out):
    """One RK4 step of h (s) of all modes from (x, v) at t (F_ts = f_start there); result into x_out, v_out."""
    half = 0.5 * h
    F0, w = dyn[3], dyn[4]
    a1, a2, a3, a4 = tmp[0], tmp[1], tmp[2], tmp[3]
    xs, v2, v3, v4 = tmp[4], tmp[5], tmp[6], tmp[7]
    _accelerations(x, v, F0 * math.cos(w * t) - f_start, f_thermal, modes, a1)
    for i in range(x.size):
        xs[i] = x[i] + half * v[i]
        v2[i] = v[i] + half * a1[i]
    f = law_force(xs.sum(), v2.sum(), t + half, dyn, gates, law, work)
    _accelerations(xs, v2, F0 * math.cos(w * (t + half)) - f, f_thermal, modes, a2)
    for i in range(x.size):
        xs[i] = x[i] + half * v2[i]
        v3[i] = v[i] + half * a2[i]
    f = law_force(xs.sum(), v3.sum(), t + half, dyn, gates, law, work)
    _accelerations(xs, v3, F0 * math.cos(w * (t + half)) - f, f_thermal, modes, a3)
    for i in range(x.size):
        xs[i] = x[i] + h * v3[i]
        v4[i] = v[i] + h * a3[i]
    f = law_force(xs.sum(), v4.sum(), t + h, dyn, gates, law, work)
    _accelerations(xs, v4, F0 * math.cos(w * (t + h)) - f, f_thermal, modes, a4)
    for i in range(x.size):
        x_out[i] = x[i] + h / 6.0 * (v[i] + 2.0 * v2[i] + 2.0 * v3[i] + v4[i])
        v_out[i] = v[i] + h / 6.0 * (a1[i] + 2.0 * a2[i] + 2.0 * a3[i] + a4[i])


@_jit
def _update_gates(x, v, t, dyn, gates, law, work, cond_values):
    """The single-mode kernel's gate update (flips, relaxing states) at the tip's (x, v, t)."""
    return update_gates(x, v, t, dyn, gates, law, work, cond_values)


@_jit
def _first_crossing(x, v, t, h, f_start, f_thermal, dyn, modes, gates, law, work, tmp, owners, state, s_end, s_tmp,
                    xt, vt):
    """Time in (0, h] just past the first sign change of a relevant switching function, or -1 if none."""
    hi = -1.0
    for j in range(owners.size):
        if not switch_matters(owners[j], gates) or (s_end[j] > 0.0) == (state[1 + j] > 0.0):
            continue
        top = h if hi < 0.0 else hi
        if hi >= 0.0:  # an earlier crossing is known: is j's before it?
            rk4_modes(x, v, t, top, f_start, f_thermal, dyn, modes, gates, law, work, tmp, xt, vt)
            law_full(xt.sum(), vt.sum(), t + top, dyn, gates, law, work, s_tmp)
            s_hi = s_tmp[j]
            if (s_hi > 0.0) == (state[1 + j] > 0.0):
                continue
        else:
            s_hi = s_end[j]
        s_lo = state[1 + j]
        side = s_lo > 0.0
        lo = 0.0
        last = 0
        tol = EVENT_TOLERANCE * h
        for _ in range(MAX_ROOT_ITERATIONS):
            if top - lo <= tol:
                break
            theta = top - s_hi * (top - lo) / (s_hi - s_lo)
            if not (lo < theta < top):
                theta = 0.5 * (lo + top)
            rk4_modes(x, v, t, theta, f_start, f_thermal, dyn, modes, gates, law, work, tmp, xt, vt)
            law_full(xt.sum(), vt.sum(), t + theta, dyn, gates, law, work, s_tmp)
            s_mid = s_tmp[j]
            if (s_mid > 0.0) == side:
                lo, s_lo = theta, s_mid
                if last == -1:
                    s_hi *= 0.5
                last = -1
            else:
                top, s_hi = theta, s_mid
                if last == 1:
                    s_lo *= 0.5
                last = 1
        hi = top
    return hi


@_jit
def integrate_modes(x, v, t0, h, n_steps, n_sub, dyn, modes, gates, law, owners, thermal, out_x, out_v, out_f,
                    out_g):
    """Integrate n_steps RK4 steps of h (s) of the modes' states x, v (M,) (updated in place) from t0 (s).

    Records the tip (sum of the modes) at t0 and after every n_sub-th step into out_x (m), out_v (m/s),
    out_f (F_ts, N) and out_g (gates). ``thermal``: force (N) on the first mode per step (or length 0).
    Returns (status, events).
    """
    M = x.size
    n_gates = gates.size
    n_switch = owners.size
    work = law_work(law, n_gates)
    tmp = np.empty((8, M))
    x1, v1, xt, vt = np.empty(M), np.empty(M), np.empty(M), np.empty(M)
    state = np.empty(1 + n_switch)
    s_end, s_tmp = np.empty(n_switch), np.empty(n_switch)
    cond_values = np.empty(2 * n_gates)
    has_thermal = thermal.size > 0
    if n_gates > 0:
        law_conditions(x.sum(), v.sum(), t0, dyn, gates, law, work, cond_values)
        start_relaxation_clocks(t0, gates, cond_values)
    state[0] = law_full(x.sum(), v.sum(), t0, dyn, gates, law, work, s_tmp)
    for j in range(n_switch):
        state[1 + j] = s_tmp[j]
    out_x[0], out_v[0], out_f[0] = x.sum(), v.sum(), state[0]
    for g in range(n_gates):
        out_g[0, g] = gates[g]
    events = 0
    record = 1
    for i in range(n_steps):
        f_thermal = thermal[i] if has_thermal else 0.0
        t = t0 + i * h
        remaining = h
        n_events = 0
        while True:
            rk4_modes(x, v, t, remaining, state[0], f_thermal, dyn, modes, gates, law, work, tmp, x1, v1)
            if not (math.isfinite(x1.sum()) and math.isfinite(v1.sum())):
                return NOT_FINITE, events
            f_end = law_full(x1.sum(), v1.sum(), t + remaining, dyn, gates, law, work, s_end)
            hi = -1.0
            if n_events < MAX_EVENTS_PER_STEP:
                hi = _first_crossing(x, v, t, remaining, state[0], f_thermal, dyn, modes, gates, law, work, tmp,
                                     owners, state, s_end, s_tmp, xt, vt)
            if hi < 0.0:
                x[:] = x1
                v[:] = v1
                state[0] = f_end
                for j in range(n_switch):
                    state[1 + j] = s_end[j]
                if _update_gates(x.sum(), v.sum(), t + remaining, dyn, gates, law, work, cond_values):
                    state[0] = law_force(x.sum(), v.sum(), t + remaining, dyn, gates, law, work)
                break
            # Advance to just past the crossing, flip gates there, integrate the rest of the step.
            rk4_modes(x, v, t, hi, state[0], f_thermal, dyn, modes, gates, law, work, tmp, xt, vt)
            x[:] = xt
            v[:] = vt
            t += hi
            remaining -= hi
            n_events += 1
            _update_gates(x.sum(), v.sum(), t, dyn, gates, law, work, cond_values)
            state[0] = law_full(x.sum(), v.sum(), t, dyn, gates, law, work, s_tmp)
            for j in range(n_switch):
                state[1 + j] = s_tmp[j]
            if remaining <= EVENT_TOLERANCE * h:
                break
        events += n_events
        if (i + 1) % n_sub == 0:
            out_x[record] = x.sum()
            out_v[record] = v.sum()
            out_f[record] = state[0]
            for g in range(n_gates):
                out_g[record, g] = gates[g]
            record += 1
    return OK, events

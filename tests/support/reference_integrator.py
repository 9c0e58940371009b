"""Plain-Python twin of the integration kernel (slow; for the tests that check the kernels). Test code: it lives
in tests/support (issue 30: no test-only code in the shipped package), imported by plain name.

:func:`reference_integrate` runs the same RK4 + event algorithm as
:func:`afmid.kernels.integrate.integrate` without numba, evaluating the force
with :func:`afmid.terms.expr.evaluate_numpy`; :func:`reference_drive` reproduces the
kernel's drive. It uses :mod:`afmid.simulate.model`'s public names only.
"""

from __future__ import annotations

import math

import numpy as np

import afmid.terms.expr as expr
from afmid.terms.kinematics import next_gate_state
from afmid.simulate.model import CompiledForceLaw, Oscillator, force_numpy, initial_gates, program_variables


def reference_drive(oscillator: Oscillator, t0: float, h: float, n_steps: int) -> np.ndarray:
    """Plain-Python twin of the kernel's drive: F0 cos(w t) (N) at t = t0 + (i + m/2) h.

    Shape (n_steps, 3), columns m = 0, 1, 2 (the RK4 stage times of step i).
    Exact (``math.cos``) at every DRIVE_ANCHOR_STEPS-th step start, by the
    angle-addition formula with the table of :func:`afmid.kernels.integrate.drive_table`
    in between, as :func:`afmid.kernels.integrate.integrate` computes it.
    """
    from afmid.kernels.integrate import DRIVE_ANCHOR_STEPS as K

    w, F0 = oscillator.omega, oscillator.drive_force
    angles = [w * (0.5 * h * m) for m in range(2 * K + 1)]
    cos_table, sin_table = [math.cos(a) for a in angles], [math.sin(a) for a in angles]
    out = np.empty((n_steps, 3))
    c = s = 0.0
    for i in range(n_steps):
        k = i % K
        if k == 0:
            phase = w * (t0 + i * h)
            c, s = math.cos(phase), math.sin(phase)
        for j in range(3):
            out[i, j] = F0 * (c * cos_table[2 * k + j] - s * sin_table[2 * k + j])
    return out


def reference_integrate(compiled: CompiledForceLaw, oscillator: Oscillator, separation: float,
                        x: float, v: float, t0: float, h: float, n_steps: int, gates=None, thermal=None):
    """Plain NumPy/Python twin of the kernel's RK4 + event logic (slow; for tests).

    Same algorithm as :func:`afmid.kernels.integrate.integrate` and
    :func:`~afmid.kernels.integrate.event_step` (drive included, see
    :func:`reference_drive`), written without numba and evaluating the force
    with :func:`afmid.terms.expr.evaluate_numpy`. Returns arrays x (m), v (m/s) and
    gates at t0 + i h, i = 0..n_steps, and the number of events.
    """
    from afmid.kernels.integrate import EVENT_TOLERANCE, MAX_EVENTS_PER_STEP, MAX_ROOT_ITERATIONS

    o = oscillator
    a0 = compiled.law.parameters["a0"]
    owners = compiled.owners
    gates = initial_gates(compiled, x, v, t0, separation) if gates is None else np.array(gates, float)
    drives = reference_drive(o, t0, h, n_steps)

    def drive(t):
        return o.drive_force * math.cos(o.omega * t)

    inverse_mass = 1.0 / o.mass

    def accel(x, v, t, g, f_th, d):
        f_ts = float(force_numpy(compiled, x, v, t, separation, g)[0])
        return (d + f_th - o.damping * v - o.spring_constant * x - f_ts) * inverse_mass

    def rk4(x, v, t, dt, g, f_th, d1, d2=None, d4=None):
        """One RK4 step; the drive at t + dt/2 and t + dt is evaluated directly unless given."""
        d2 = drive(t + 0.5 * dt) if d2 is None else d2
        d4 = drive(t + dt) if d4 is None else d4
        a1 = accel(x, v, t, g, f_th, d1)
        x2, v2 = x + 0.5 * dt * v, v + 0.5 * dt * a1
        a2 = accel(x2, v2, t + 0.5 * dt, g, f_th, d2)
        x3, v3 = x + 0.5 * dt * v2, v + 0.5 * dt * a2
        a3 = accel(x3, v3, t + 0.5 * dt, g, f_th, d2)
        x4, v4 = x + dt * v3, v + dt * a3
        a4 = accel(x4, v4, t + dt, g, f_th, d4)
        return x + dt / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4), v + dt / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)

    def switching(x, v, t, g):
        variables = program_variables(x, v, t, separation, a0, g)
        return np.array([expr.evaluate_numpy(p, variables)[0] for p in compiled.switching])

    def relevant(owner, g):
        return owner < 0 or (g[owner // 2] == 0.0) == (owner % 2 == 0)

    def flip(x, v, t, g):
        variables = program_variables(x, v, t, separation, a0, g)
        values = [expr.evaluate_numpy(p, variables)[0] for p in compiled.conditions]
        for i in range(g.size):
            g[i] = next_gate_state(g[i], values[2 * i], values[2 * i + 1])

    def crossing(x, v, t, g, f_th, d1, j, s0, s_hi, hi):
        side = s0 > 0.0
        lo, f_lo, f_hi, last = 0.0, s0, s_hi, 0
        for _ in range(MAX_ROOT_ITERATIONS):
            if hi - lo <= EVENT_TOLERANCE * h:
                break
            theta = hi - f_hi * (hi - lo) / (f_hi - f_lo)
            if not (lo < theta < hi):
                theta = 0.5 * (lo + hi)
            f_mid = switching(*rk4(x, v, t, theta, g, f_th, d1), t + theta, g)[j]
            if (f_mid > 0.0) == side:
                lo, f_lo = theta, f_mid
                f_hi = f_hi * 0.5 if last == -1 else f_hi
                last = -1
            else:
                hi, f_hi = theta, f_mid
                f_lo = f_lo * 0.5 if last == 1 else f_lo
                last = 1
        return hi

    xs, vs, gs = [x], [v], [gates.copy()]
    s_now = switching(x, v, t0, gates)
    events = 0
    for i in range(n_steps):
        f_th = 0.0 if thermal is None else float(thermal[i])
        t_now, remaining, n_ev = t0 + i * h, h, 0
        d1 = drives[i, 0]
        x1, v1 = rk4(x, v, t_now, remaining, gates, f_th, d1, drives[i, 1], drives[i, 2])
        while True:
            s_end = switching(x1, v1, t_now + remaining, gates)
            hi, crossed = remaining, False
            if n_ev < MAX_EVENTS_PER_STEP:
                for j in range(len(s_now)):
                    if not relevant(owners[j], gates) or (s_end[j] > 0.0) == (s_now[j] > 0.0):
                        continue
                    if crossed:
                        s_hi = switching(*rk4(x, v, t_now, hi, gates, f_th, d1), t_now + hi, gates)[j]
                        if (s_hi > 0.0) == (s_now[j] > 0.0):
                            continue
                    else:
                        s_hi = s_end[j]
                    hi = crossing(x, v, t_now, gates, f_th, d1, j, s_now[j], s_hi, hi)
                    crossed = True
            if not crossed:
                x, v, s_now = x1, v1, s_end
                flip(x, v, t_now + remaining, gates)
                break
            x, v = rk4(x, v, t_now, hi, gates, f_th, d1)
            t_now += hi
            remaining -= hi
            n_ev += 1
            flip(x, v, t_now, gates)
            s_now = switching(x, v, t_now, gates)
            if remaining <= EVENT_TOLERANCE * h:
                break
            d1 = drive(t_now)
            x1, v1 = rk4(x, v, t_now, remaining, gates, f_th, d1)
        events += n_ev
        xs.append(x)
        vs.append(v)
        gs.append(gates.copy())
    return np.array(xs), np.array(vs), np.array(gs), events

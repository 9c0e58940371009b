"""Benchmark: afmid's simulator against scipy's solve_ivp (DOP853) at matched accuracy.

Workload: 50 steady tapping periods of the DMT model of configs/dmt.yaml (noise
off), integrated by afmid at 2,000 RK4 steps per period with contact events
located exactly, recorded at 200 samples per period.

Matching the accuracy: a tight reference (DOP853, rtol 1e-13, terminal events
at the contact surface z = a0) gives x at the sample times. afmid's error is its
max |x - x_ref| over the run. solve_ivp (same events, a plain-Python right-hand
side written out by hand, dense output at the sample times) is then timed at
the loosest rtol on a quarter-decade grid from 1e-5 to 1e-13 whose error does not exceed
afmid's. JIT compilation is excluded (a warm-up run first; numba caches).

afmid runs its default kernel, generated from the force law (afmid.kernels.lawgen);
the generic VM kernel's time is given in the notes for comparison. Timings are the
best of several runs, wall and CPU (process time) separately: the machine may be
shared, and the ratio is given for both.

Run: python bench/bench_simulate.py [--quick]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from afmid.config import load_config  # noqa: E402
from afmid.simulate.driver import Integrator, compile_force_law, resolve_setup, settle  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "dmt.yaml"
STEPS_PER_PERIOD = 2000
SAMPLES_PER_PERIOD = 200
RTOL_GRID = [10.0**-e for e in np.arange(5.0, 13.25, 0.25)]


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.platform()}; {cpu}; {os.cpu_count()} cores; Python {platform.python_version()}"


def _dmt_solver(setup, d):
    """solve_ivp over [t0, t1] with the DMT force written out by hand, regime frozen between contact events."""
    p = setup.force_law.parameters
    osc = setup.oscillator
    a0, R, H, E = p["a0"], p["R"], p["hamaker"], p["E_star"]
    m, c, k, F0, w = osc.mass, osc.damping, osc.spring_constant, osc.drive_force, osc.omega
    hertz, adhesion, vdw = 4.0 / 3.0 * E * math.sqrt(R), H * R / (6.0 * a0**2), H * R / 6.0

    def rhs(t, y, contact):
        z = d - y[0]
        f = hertz * max(a0 - z, 0.0) ** 1.5 - adhesion if contact else -vdw / (z * z)
        return [y[1], (-f + F0 * math.cos(w * t) - c * y[1] - k * y[0]) / m]

    def at_contact(t, y, contact):
        return d - y[0] - a0

    at_contact.terminal = True

    def solve(x0, v0, t_eval, rtol):
        out = np.empty(t_eval.size)
        t, y = t_eval[0], np.array([x0, v0])
        contact = d - x0 <= a0
        while True:
            at_contact.direction = 1.0 if contact else -1.0
            sol = solve_ivp(rhs, (t, t_eval[-1]), y, method="DOP853", rtol=rtol, atol=[rtol * 1e-8, rtol * 1e-2],
                            events=[at_contact], dense_output=True, args=(contact,))
            inside = (t_eval >= t) & (t_eval <= sol.t[-1])
            out[inside] = sol.sol(t_eval[inside])[0]
            if sol.status != 1:
                return out
            t, y, contact = sol.t[-1], sol.y[:, -1], not contact

    return solve


def run(quick: bool = False) -> list[dict]:
    """Time both integrators on the same steady trajectory; returns one table row."""
    periods = 10 if quick else 50
    config = load_config(CONFIG, [f"simulate.steps_per_period={STEPS_PER_PERIOD}", "simulate.noise.thermal=false"])
    setup = resolve_setup(config)
    compiled = compile_force_law(setup.force_law)
    d = setup.separation
    osc = setup.oscillator
    integrator = Integrator(osc, compiled, d)
    integrator.start(*osc.free_state(0.0))
    settle(integrator, STEPS_PER_PERIOD, 1e-9, 20000)  # not timed: the steady state to start from
    x0, v0, gates0 = integrator.x, integrator.v, integrator.gates.copy()

    h = osc.period / STEPS_PER_PERIOD
    n_steps = periods * STEPS_PER_PERIOD
    n_sub = STEPS_PER_PERIOD // SAMPLES_PER_PERIOD

    def time_kernel(kind: str, repeat: int):
        kernel = Integrator(osc, compiled, d, kernel=kind)
        kernel.run(0.0, h, 10, 1)  # warm the JIT (numba's on-disk cache makes this a load)

        def once():
            kernel.start(x0, v0, gates=gates0)
            return kernel.run(0.0, h, n_steps, n_sub)

        return best_of(once, repeat)

    (afmid_wall, afmid_cpu), seg = time_kernel("generated", 5 if quick else 15)
    (vm_wall, vm_cpu), vm_seg = time_kernel("vm", 1 if quick else 3)
    t = np.arange(seg.x.size) * (n_sub * h)
    amplitude = setup.free_amplitude

    solve = _dmt_solver(setup, d)
    reference = solve(x0, v0, t, 1e-13)
    afmid_error = np.max(np.abs(seg.x - reference)) / amplitude
    vm_error = np.max(np.abs(vm_seg.x - reference)) / amplitude
    chosen, chosen_error = None, None
    for rtol in RTOL_GRID:
        error = np.max(np.abs(solve(x0, v0, t, rtol) - reference)) / amplitude
        if error <= afmid_error:
            chosen, chosen_error = rtol, error
            break
    if chosen is None:
        chosen, chosen_error = RTOL_GRID[-1], np.max(np.abs(solve(x0, v0, t, RTOL_GRID[-1]) - reference)) / amplitude
    (reference_wall, reference_cpu), _ = best_of(lambda: solve(x0, v0, t, chosen), 1 if quick else 3)
    ratio = reference_wall / afmid_wall
    return [{
        "name": f"simulate: {periods} steady DMT periods, {STEPS_PER_PERIOD} RK4 steps/period",
        "afmid_s": afmid_wall,
        "reference_s": reference_wall,
        "ratio": ratio,
        "target": ">= 100x at matched accuracy",
        "met": bool(ratio >= 100.0 and reference_cpu / afmid_cpu >= 100.0),
        "notes": (f"solve_ivp DOP853 rtol={chosen:.0e} (max error {chosen_error:.1e} A0) vs afmid "
                  f"(max error {afmid_error:.1e} A0); {seg.events} contact events; CPU time afmid "
                  f"{1e3 * afmid_cpu:.2f} ms, solve_ivp {1e3 * reference_cpu:.0f} ms, ratio "
                  f"{reference_cpu / afmid_cpu:.0f}x; generic VM kernel {1e3 * vm_wall:.1f} ms wall, "
                  f"{1e3 * vm_cpu:.1f} ms CPU (max error {vm_error:.1e} A0); load average {load_average()}"),
    }]


def best_of(fn, repeat: int):
    """((best wall time, best CPU time) in s, result of the last call) over ``repeat`` calls."""
    wall = cpu = math.inf
    result = None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        wall, cpu = min(wall, time.perf_counter() - w0), min(cpu, time.process_time() - c0)
    return (wall, cpu), result


def load_average() -> str:
    try:
        return " ".join(f"{v:.1f}" for v in os.getloadavg())
    except OSError:  # pragma: no cover
        return "n/a"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10 periods instead of 50")
    args = parser.parse_args()
    rows = run(args.quick)
    print(f"machine: {machine()}")
    print(f"{'benchmark':58s} {'afmid (s)':>10s} {'reference (s)':>14s} {'ratio':>8s}  target")
    for r in rows:
        print(f"{r['name']:58s} {r['afmid_s']:10.4f} {r['reference_s']:14.3f} {r['ratio']:7.0f}x  "
              f"{r['target']}: {'met' if r['met'] else 'not met'}")
        print(f"  {r['notes']}")


if __name__ == "__main__":
    main()

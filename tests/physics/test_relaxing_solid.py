"""Issue 16, part 3: a relaxing solid, the ``standard_linear_solid`` (Zener) contact.

Unit tests (fast): the relaxing state's exact step against its closed form and the numba kernels against their
NumPy twins; the effect's force against the Lee-Radok hereditary integral written out here; the simulator's
recorded force against the fit's library along the same trajectory (one declaration, one law); the generated and
the VM integration kernels bit for bit; the declaration checks; ``afmid effects`` listing it.

Accuracy and diagnosis (``slow``): tests/physics/test_relaxing_solid_accuracy.py.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytestmark = pytest.mark.numerics

R, A0 = 10e-9, 0.165e-9


def test_relaxation_step_is_exact_for_a_linear_source():
    """d q/dt = (g - q) / tau with g = c t from q(0) = 0: q = c (t - tau (1 - e^(-t/tau))), for any step size
    (also below the series threshold): the step is exact for a source linear over it."""
    from afmid.terms.kinematics import next_relaxation_state

    tau, c = 2e-7, 3.0e6
    for steps in (np.full(50, 1e-9), np.full(50, 1e-13), np.geomspace(1e-12, 1e-7, 40)):
        t = np.concatenate([[0.0], np.cumsum(steps)])
        q = 0.0
        for i in range(1, t.size):
            q = next_relaxation_state(q, c * t[i - 1], c * t[i], t[i] - t[i - 1], tau)
        exact = c * (t[-1] - tau * -math.expm1(-t[-1] / tau))
        assert float(q) == pytest.approx(exact, rel=1e-11, abs=1e-15 * c * t[-1])


def test_relaxation_kernels_match_their_numpy_twins():
    """The simulator's step (integrate.next_relaxation_state_at), the fit's scan (hysteresis.scan_relaxation) and
    their twins: the same recursion (the twin's product form rounds differently: a few 1e-13 relative)."""
    from afmid.kernels.hysteresis import scan_relaxation, scan_relaxation_numpy
    from afmid.kernels.integrate import next_relaxation_state_at
    from afmid.terms.kinematics import next_relaxation_state

    rng = np.random.default_rng(5)
    for u in (1e-7, 5e-5, 1e-4, 2e-4, 0.01, 0.5, 3.0, 40.0):
        args = (0.7, 0.2, 1.3, u * 1e-6, 1e-6)
        assert next_relaxation_state_at(*args) == pytest.approx(float(next_relaxation_state(*args)), rel=1e-14)
    t = np.cumsum(rng.uniform(1e-10, 3e-9, 4000))
    source = np.maximum(np.sin(2e7 * t), 0.0) ** 1.5 * 40.0
    for tau in (1e-8, 3e-7, 1e-4):
        out = np.empty_like(source)
        last = scan_relaxation(source, t, tau, 5.0, out)
        twin = scan_relaxation_numpy(source, t, tau, 5.0)
        assert last == out[-1]
        np.testing.assert_allclose(out, twin, rtol=1e-10, atol=1e-12 * source.max())
    # A long scan whose decay underflows a single product: the twin works in blocks.
    t = np.arange(5000) * 1e-8
    out = np.empty(t.size)
    scan_relaxation(np.ones(t.size), t, 1e-9, 0.0, out)
    np.testing.assert_allclose(out, scan_relaxation_numpy(np.ones(t.size), t, 1e-9, 0.0), rtol=1e-12)


def _law(tau=3e-7, E_inf=1e9, dE=1.5e9):
    from afmid.physics.effects import build_force_law

    return build_force_law(["dmt", "standard_linear_solid"],
                           {"E_star": E_inf, "hamaker": 1e-19, "relaxing_modulus": dE, "relaxation_time": tau},
                           {"R": R, "a0": A0})


def test_force_is_the_lee_radok_integral_for_a_ramp():
    """Indentation with delta^1.5 = c t (from contact at t = 0): Lee-Radok with E(t) = E_inf + dE e^(-t/tau) gives
    F = 4/3 sqrt(R) c [E_inf t + dE tau (1 - e^(-t/tau))] (plus DMT's adhesion); the library column of the effect
    (its state scanned along the samples) times its declared coefficient, plus DMT's columns, gives it."""
    from afmid.config import ModelConfig
    from afmid.physics.library import build_library

    tau, E_inf, dE = 3e-7, 1e9, 1.5e9
    law = _law(tau, E_inf, dE)
    library = build_library(ModelConfig(effects=["dmt", "standard_linear_solid"]))
    c = 2e-8  # m^1.5 / s
    t = np.linspace(0.0, 1.5e-6, 3001)
    delta = (c * t) ** (2.0 / 3.0)
    d = 5e-9
    x = d - A0 + delta  # z = d - x = a0 - delta
    xdot = np.gradient(x, t)
    columns = library.evaluate(x, xdot, t, {"d": d, "a0": A0, "R": R, "relaxation_time": tau})
    coefficients = {label: value for _, label, _, value in law.terms}
    force = columns @ np.array([coefficients[term.label] for term in library.terms])
    adhesion = -1e-19 * R / (6 * A0**2)
    expected = 4 / 3 * math.sqrt(R) * c * (E_inf * t + dE * tau * -np.expm1(-t / tau)) + adhesion
    np.testing.assert_allclose(force, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("kernel", ["generated", "vm"])
def test_simulated_force_is_the_fitted_law_along_the_trajectory(kernel):
    """The simulator's recorded F_ts (its state advanced exactly at every step end, the source linear over the
    step) equals the fit's library (its state scanned along the same samples, the same exact step) times the
    declared coefficients, to O(h^2) from steps split at contact (there the source is taken linear over each
    piece): bounded by 1e-5 of the peak force at 2000 steps a period. The generated and the VM kernels agree bit
    for bit."""
    from afmid.config import ModelConfig
    from afmid.physics.library import build_library
    from afmid.simulate.integrator import Integrator
    from afmid.simulate.model import Oscillator, compile_force_law

    tau = 2e-7
    law = _law(tau)
    compiled = compile_force_law(law)
    assert compiled.n_gates == 3
    oscillator = Oscillator(40.0, 300e3, 250.0, 300e3, 40.0 * 15e-9 / 250.0)
    d = 12e-9
    steps = 2000
    runs = {}
    for kind in ("generated", "vm"):
        integrator = Integrator(oscillator, compiled, d, kernel=kind)
        integrator.start(*oscillator.free_state(0.0), 0.0)
        integrator.run(0.0, oscillator.period / steps, 40 * steps, steps)  # settle roughly
        runs[kind] = integrator.run(0.0, oscillator.period / steps, 3 * steps, 1)
    seg = runs[kernel]
    other = runs["vm" if kernel == "generated" else "generated"]
    assert np.array_equal(seg.force, other.force) and np.array_equal(seg.gates, other.gates)
    t = np.arange(seg.x.size) * oscillator.period / steps
    library = build_library(ModelConfig(effects=["dmt", "standard_linear_solid"]))
    params = {"d": d, "a0": A0, "R": R, "relaxation_time": tau}
    lag = seg.gates[0, 0]  # the fit's scan starts relaxed; start it where the simulator's state is
    states = library.states_along(seg.x, seg.v, t, params, initial=np.array([lag]))
    np.testing.assert_allclose(states[0], seg.gates[:, 0], rtol=0, atol=1e-5 * np.abs(seg.gates[:, 0]).max())
    columns = library.evaluate(seg.x, seg.v, t, params, state_values=states)
    coefficients = {label: value for _, label, _, value in law.terms}
    fitted = columns @ np.array([coefficients[term.label] for term in library.terms])
    assert np.abs(seg.force).max() > 1e-9  # it taps
    np.testing.assert_allclose(fitted, seg.force, rtol=0, atol=1e-5 * np.abs(seg.force).max())


def test_relaxing_state_declaration_is_checked():
    """A relaxing state's source must be dimensionless and its time a nonlinear parameter in s."""
    import dataclasses

    from afmid.errors import DefinitionError
    from afmid.physics.effect_types import RelaxingState, validate_effect
    from afmid.physics.effects import EFFECTS

    effect = EFFECTS.get("standard_linear_solid")
    validate_effect(effect)
    with pytest.raises(DefinitionError, match="not dimensionless"):
        validate_effect(dataclasses.replace(effect, states=(RelaxingState("sls_lag", "delta^1.5", "relaxation_time"),)))
    with pytest.raises(DefinitionError, match="nonlinear parameter in s"):
        validate_effect(dataclasses.replace(effect, states=(RelaxingState("sls_lag", "delta * R^-1",
                                                                          "relaxing_modulus"),)))


def test_afmid_effects_lists_the_standard_linear_solid(run_cli):
    code, out, _ = run_cli("effects", "standard_linear_solid")
    assert code == 0
    assert "Lee, Radok" in out and "Ting" in out and "relaxation_time" in out and "sls_lag" in out
    code, out, _ = run_cli("effects", "--json")
    record = next(e for e in json.loads(out) if e["name"] == "standard_linear_solid")
    assert record["states"] == [{"name": "sls_lag", "source": "delta^1.5 * R^-1.5", "time": "relaxation_time"}]
    assert "integral" in record["formula"] and len(record["references"]) >= 3
    tau = next(p for p in record["parameters"] if p["name"] == "relaxation_time")
    assert tau["unit"] == "s" and tau["nonlinear"] is True


def test_relaxation_time_is_searched_over_its_range():
    """A time is not capped like the decay lengths (20 nm)."""
    from afmid.config import ModelConfig
    from afmid.fit.search import search_range
    from afmid.physics.library import build_library

    library = build_library(ModelConfig(effects=["dmt", "standard_linear_solid"]))
    assert library.nonlinear == {"relaxation_time": 1e-6}
    span = search_range(library, "relaxation_time")
    assert (span.low, span.high, span.unit) == (1e-9, 1e-3, "s")


def test_simulated_relaxing_solid_converges_at_second_order():
    """The kernel reads a relaxing state inside a step by linear extrapolation from its exact value at the last
    step end: the trajectory's error is O(h^2). Halving the step from 1000 to 2000 and to 4000 steps a period
    (30 periods from the free state, noise-free): the differences to 8000 steps fall by ~4 per halving (at least
    3; a first-order scheme gives 2)."""
    from afmid.simulate.integrator import Integrator
    from afmid.simulate.model import Oscillator, compile_force_law

    compiled = compile_force_law(_law(tau=1.6e-7, dE=1e9))
    oscillator = Oscillator(40.0, 300e3, 250.0, 300e3, 40.0 * 15e-9 / 250.0)
    ends = {}
    for steps in (1000, 2000, 4000, 8000):
        integrator = Integrator(oscillator, compiled, 11e-9)
        integrator.start(*oscillator.free_state(0.0), 0.0)
        seg = integrator.run(0.0, oscillator.period / steps, 30 * steps, steps // 100)
        ends[steps] = seg.x[-100:]
    errors = [np.abs(ends[s] - ends[8000]).max() for s in (1000, 2000, 4000)]
    assert errors[0] / errors[1] > 3.0 and errors[1] / errors[2] > 3.0, errors

"""Tests of the simulator: force laws, accuracy against solve_ivp, energy balance, noise, files.

Runs are short (few periods, low Q where settling is needed) so the file stays
well under a minute once numba's cache is warm.
"""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from afmid.config import build_config
from afmid.errors import AfmidError, ConfigError
from afmid.io.trace import write_trace_file
from afmid.physics.effects import BOLTZMANN, EFFECTS, EPSILON_0, MODELS, ForceLaw, StateGate, build_force_law
from afmid.simulate.driver import Integrator, Oscillator, compile_force_law, resolve_setup, simulate
from afmid.simulate.model import NondimensionalForm, drive_force_for_amplitude, force_numpy
from reference_integrator import reference_drive, reference_integrate

pytestmark = pytest.mark.numerics  # floating-point results compared (blas_sensitive ones: make test-kernels runs them again)

K, F0_HZ, R, A0_CONTACT = 40.0, 300e3, 10e-9, 0.165e-9
A_FREE = 10e-9  # m, free amplitude of the test runs
D_TAP = 8.5e-9  # m, rest separation of the test runs: tapping with ~1 nm indentation
H, E_STAR = 5e-20, 2e9

MODEL_PARAMETERS = {
    "dmt": {"E_star": E_STAR, "hamaker": H},
    "lennard_jones": {"hamaker": H},
    "dmt_viscoelastic": {"E_star": E_STAR, "hamaker": H, "viscosity": 150.0},
    "dmt_exponential_damping": {"E_star": E_STAR, "hamaker": H, "damping_coefficient": 1e-7, "damping_length": 1e-9},
    "jkr": {"E_star": E_STAR, "hamaker": H, "surface_energy": 0.03},
    "jkr_hysteretic": {"E_star": E_STAR, "hamaker": H, "surface_energy": 0.03},
}


def make_config(model="dmt", parameters=None, effects=(), Q=250.0, d=D_TAP, A0=A_FREE, noise=None, **simulate_keys):
    sim = {
        "model": model,
        "effects": list(effects),
        "parameters": MODEL_PARAMETERS.get(model, {}) if parameters is None else parameters,
        "noise": {"thermal": False} if noise is None else noise,
        **simulate_keys,
    }
    raw = {
        "cantilever": {"spring_constant": K, "resonance_frequency": F0_HZ, "quality_factor": Q, "tip_radius": R},
        "drive": {"frequency": F0_HZ, "free_amplitude": A0},
        "sample": {"separation": d},
        "simulate": sim,
    }
    return build_config(raw)


# =========================================================================== (1) force laws
def _law(effects, params):
    return compile_force_law(build_force_law(effects, params, {"R": R, "a0": A0_CONTACT}))


def _kernel_force(compiled, z, zdot, gates=()):
    """F_ts through the numba kernel (a zero-step run records the force at the start)."""
    osc = Oscillator(K, F0_HZ, 100.0, F0_HZ, 1e-9)
    d = 20e-9
    integrator = Integrator(osc, compiled, d)
    integrator.start(d - z, -zdot, gates=np.array(gates, float))
    return integrator.run(0.0, 1e-9, 0, 1).force[0]


def _check_force(compiled, z, zdot, expected, gates=()):
    numpy_value = force_numpy(compiled, 20e-9 - z, -zdot, 0.0, 20e-9, np.array(gates, float))[0]
    kernel_value = _kernel_force(compiled, z, zdot, gates)
    assert numpy_value == pytest.approx(expected, rel=1e-12, abs=1e-30)
    assert kernel_value == pytest.approx(expected, rel=1e-12, abs=1e-30)


@pytest.mark.parametrize("z", [0.1e-9, 0.165e-9, 0.3e-9, 2e-9])
def test_dmt_force(z):
    law = _law(["dmt"], {"hamaker": H, "E_star": E_STAR})
    if z > A0_CONTACT:
        expected = -H * R / (6 * z**2)
    else:
        expected = 4 / 3 * E_STAR * math.sqrt(R) * (A0_CONTACT - z) ** 1.5 - H * R / (6 * A0_CONTACT**2)
    _check_force(law, z, 0.0, expected)


@pytest.mark.parametrize("z", [0.15e-9, 0.3e-9, 1e-9])
def test_lennard_jones_force(z):
    sigma = 0.3e-9
    law = _law(["lennard_jones"], {"hamaker": H, "sigma": sigma})
    _check_force(law, z, 0.0, -H * R / (6 * z**2) + H * R * sigma**6 / (180 * z**8))


@pytest.mark.parametrize("z, zdot", [(0.1e-9, -0.01), (0.1e-9, 0.02), (0.3e-9, -0.01)])
def test_viscoelastic_force(z, zdot):
    eta = 150.0
    law = _law(["viscoelastic"], {"viscosity": eta})
    delta = max(A0_CONTACT - z, 0.0)
    deltadot = -zdot if z <= A0_CONTACT else 0.0
    _check_force(law, z, zdot, eta * math.sqrt(R * delta) * deltadot)


@pytest.mark.parametrize("z, zdot", [(0.1e-9, -0.01), (2e-9, 0.02)])
def test_exponential_damping_force(z, zdot):
    law = _law(["exponential_damping"], {"damping_coefficient": 1e-7, "damping_length": 1e-9})
    _check_force(law, z, zdot, -1e-7 * math.exp(-z / 1e-9) * zdot)


@pytest.mark.parametrize("z", [0.1e-9, 5e-9])
def test_electrostatic_force(z):
    law = _law(["electrostatic"], {"voltage": 2.0})
    _check_force(law, z, 0.0, -math.pi * EPSILON_0 * R * 4.0 / max(z, A0_CONTACT))


@pytest.mark.parametrize("z", [0.1e-9, 0.5e-9])
def test_hydration_force(z):
    law = _law(["hydration"], {"hydration_force": 2e-9, "hydration_length": 0.3e-9})
    _check_force(law, z, 0.0, 2e-9 * math.exp(-(z - A0_CONTACT) / 0.3e-9))


@pytest.mark.parametrize("z, zdot", [(0.1e-9, -0.01), (3e-9, 0.02)])
def test_squeeze_film_force(z, zdot):
    law = _law(["squeeze_film"], {"fluid_viscosity": 1e-3})
    _check_force(law, z, zdot, -6 * math.pi * 1e-3 * R**2 * zdot / max(z, A0_CONTACT))


def test_capillary_force_depends_on_the_meniscus_state():
    law = _law(["capillary"], {"surface_tension": 0.072, "contact_angle": 0.5, "rupture_distance": 1e-9})
    meniscus = -4 * math.pi * R * 0.072 * math.cos(0.5)
    z = 0.6e-9  # between a0 and a0 + rupture distance: approach (off) and retraction (on) differ
    _check_force(law, z, -0.01, 0.0, gates=(0.0,))
    _check_force(law, z, 0.01, meniscus, gates=(1.0,))


def test_jkr_force_and_neck():
    gamma = 0.03
    law = _law(["jkr"], {"hamaker": H, "E_star": E_STAR, "surface_energy": gamma, "neck_length": 0.5e-9})
    adhesion = -3 * math.pi * R * gamma
    _check_force(law, 0.1e-9, 0.0, 4 / 3 * E_STAR * math.sqrt(R) * (A0_CONTACT - 0.1e-9) ** 1.5 + adhesion, (1.0,))
    _check_force(law, 0.4e-9, 0.0, adhesion, (1.0,))  # neck still attached on retraction
    _check_force(law, 0.4e-9, 0.0, -H * R / (6 * (0.4e-9) ** 2), (0.0,))  # approach: not yet in contact


def test_capillary_hysteresis_along_a_trajectory():
    """The meniscus forms at z = a0 on approach and ruptures at a0 + rupture distance on retraction."""
    rupture = 1e-9
    config = make_config("dmt", effects=["capillary"],
                         parameters={**MODEL_PARAMETERS["dmt"], "rupture_distance": rupture})
    setup = resolve_setup(config)
    compiled = compile_force_law(setup.force_law)
    integrator = Integrator(setup.oscillator, compiled, D_TAP)
    integrator.start(*setup.oscillator.free_state(0.0))
    h = setup.oscillator.period / 2000
    seg = integrator.run(0.0, h, 6 * 2000, 1)
    z = D_TAP - seg.x
    gate = seg.gates[:, 0]
    expected = np.empty_like(gate)
    state = 0.0
    for i, zi in enumerate(z):
        if zi <= A0_CONTACT:
            state = 1.0
        elif zi > A0_CONTACT + rupture:
            state = 0.0
        expected[i] = state
    np.testing.assert_array_equal(gate, expected)
    window = (z > A0_CONTACT) & (z <= A0_CONTACT + rupture)
    approaching, retracting = seg.v > 0, seg.v < 0
    assert np.all(gate[window & approaching & (np.cumsum(gate) == 0)] == 0.0)
    assert np.any(gate[window & retracting] == 1.0)
    # The recorded force includes the meniscus exactly while it exists.
    meniscus = -4 * math.pi * R * 0.072 * math.cos(0.5)
    dmt = np.where(z > A0_CONTACT, -H * R / (6 * z**2),
                   4 / 3 * E_STAR * math.sqrt(R) * np.maximum(A0_CONTACT - z, 0) ** 1.5 - H * R / (6 * A0_CONTACT**2))
    np.testing.assert_allclose(seg.force, dmt + gate * meniscus, rtol=1e-10, atol=1e-22)


# =========================================================================== (2) accuracy vs solve_ivp
def _hand_force(model, p, z, zdot, contact, gate):
    """Tip-sample force (N, repulsive positive) written out by hand, in a frozen regime."""
    a0, Rt = p["a0"], p["R"]
    delta = max(a0 - z, 0.0) if contact else 0.0
    deltadot = -zdot if contact else 0.0
    if model == "lennard_jones":
        return -p["hamaker"] * Rt / (6 * z**2) + p["hamaker"] * Rt * p["sigma"] ** 6 / (180 * z**8)
    if model in ("jkr", "jkr_hysteretic"):
        if gate:
            return 4 / 3 * p["E_star"] * math.sqrt(Rt) * delta**1.5 - 3 * math.pi * Rt * p["surface_energy"]
        return -p["hamaker"] * Rt / (6 * z**2)
    if contact:
        f = 4 / 3 * p["E_star"] * math.sqrt(Rt) * delta**1.5 - p["hamaker"] * Rt / (6 * a0**2)
    else:
        f = -p["hamaker"] * Rt / (6 * z**2)
    if model == "dmt_viscoelastic":
        f += p["viscosity"] * math.sqrt(Rt * delta) * deltadot
    if model == "dmt_exponential_damping":
        f += -p["damping_coefficient"] * math.exp(-z / p["damping_length"]) * zdot
    if model == "capillary" and gate:
        f += -4 * math.pi * Rt * p["surface_tension"] * math.cos(p["contact_angle"])
    return f


def reference_solution(model, params, osc, d, x0, v0, t_eval):
    """DOP853 (rtol 1e-12) with terminal events at z = a0 and at the gate's release distance."""
    a0 = params["a0"]
    release = params.get("neck_length", params.get("rupture_distance", 0.0))
    gated = model in ("jkr", "jkr_hysteretic", "capillary")
    m, c, k, F0, w = osc.mass, osc.damping, osc.spring_constant, osc.drive_force, osc.omega

    def rhs(t, y, contact, gate):
        f = _hand_force(model, params, d - y[0], -y[1], contact, gate)
        return [y[1], (-f + F0 * math.cos(w * t) - c * y[1] - k * y[0]) / m]

    def at_contact(t, y, contact, gate):
        return d - y[0] - a0

    def at_release(t, y, contact, gate):
        return d - y[0] - a0 - release

    t, y = t_eval[0], np.array([x0, v0])
    contact = d - x0 <= a0
    gate = gated and contact
    out = np.empty(t_eval.size)
    while True:
        at_contact.terminal = at_release.terminal = True
        at_contact.direction = 1.0 if contact else -1.0  # leaving / entering contact
        at_release.direction = 1.0
        events = [at_contact] + ([at_release] if gated and gate and release > 0 else [])
        sol = solve_ivp(rhs, (t, t_eval[-1]), y, method="DOP853", rtol=1e-12, atol=[1e-24, 1e-18],
                        events=events, dense_output=True, args=(contact, gate))
        end = sol.t[-1]
        inside = (t_eval >= t) & (t_eval <= end)
        out[inside] = sol.sol(t_eval[inside])[0]
        if sol.status != 1:
            return out
        t, y = end, sol.y[:, -1]
        if sol.t_events[0].size:
            contact = not contact
            if gated and (contact or release == 0):
                gate = contact  # the gate forms at contact; without a release distance it also breaks there
        else:
            gate = False


ACCURACY_CASES = [
    # Steady tapping, Q = 50 to settle quickly; 6 recorded periods from the first sample.
    ("dmt", "steady"),
    ("lennard_jones", "steady"),
    ("dmt_viscoelastic", "steady"),
    ("dmt_exponential_damping", "steady"),
    ("jkr", "steady"),
    # Transient: the free oscillation placed at the tapping separation at t = 0 crashes
    # into the sample (the gates start open, so the reference knows their state).
    ("dmt", "transient"),
    ("dmt_viscoelastic", "transient"),
    ("jkr_hysteretic", "transient"),
    ("capillary", "transient"),
]


@pytest.mark.parametrize("model, mode", ACCURACY_CASES)
def test_agrees_with_solve_ivp(model, mode):
    """max |x_afmid - x_ref| < 1e-4 A0 over 6 periods in interaction, at the default 2000 steps per period."""
    kw = {"mode": mode, "periods": 6, "Q": 50.0 if mode == "steady" else 250.0, "settle_tolerance": 1e-6}
    if model == "capillary":
        config = make_config("dmt", effects=["capillary"], **kw)
    else:
        # The LJ wall is far stiffer than Hertz: tap it lightly (a crash would need finer steps).
        config = make_config(model, d=9.5e-9 if model == "lennard_jones" else D_TAP, **kw)
    trace = simulate(config)
    setup = resolve_setup(config)
    params = dict(setup.force_law.parameters)
    t = np.arange(trace.n_samples) / trace.sample_rate
    d = config.sample.separation
    reference = reference_solution(model, params, setup.oscillator, d, trace.deflection[0], trace.truth.velocity[0], t)
    assert trace.truth.separation.min() < A0_CONTACT + 0.05e-9  # it does interact
    deviation = np.max(np.abs(trace.deflection - reference)) / A_FREE
    assert deviation < 1e-4, deviation


@pytest.mark.parametrize("kernel", ["generated", "vm"])
def test_kernel_matches_its_python_twin(kernel):
    for model in ("dmt_viscoelastic", "jkr_hysteretic"):
        config = make_config(model, Q=250.0)
        setup = resolve_setup(config)
        compiled = compile_force_law(setup.force_law)
        x0, v0 = setup.oscillator.free_state(0.0)
        h = setup.oscillator.period / 200
        n = 300  # 1.5 periods: in and out of contact
        rng = np.random.default_rng(0)
        thermal = rng.standard_normal(n) * 1e-11
        integrator = Integrator(setup.oscillator, compiled, D_TAP, kernel=kernel)
        assert integrator.kernel == kernel
        integrator.start(x0, v0)
        seg = integrator.run(0.0, h, n, 1, thermal)
        x, v, gates, events = reference_integrate(compiled, setup.oscillator, D_TAP, x0, v0, 0.0, h, n, thermal=thermal)
        assert events == seg.events >= 2
        assert np.max(np.abs(seg.x - x)) < 1e-12 * A_FREE
        assert np.max(np.abs(seg.v - v)) < 1e-12 * A_FREE * setup.oscillator.omega
        np.testing.assert_array_equal(seg.gates, gates)


# =========================================================================== generated kernels
# A law whose terms, switching functions and gate conditions use every opcode of the VM, with
# values that reach inf, nan and -0.0 at some of the points below (z = 0, z < 0, z = a0, ...).
ALL_OPCODE_TERMS = (
    "exp(-z / lam) * zdot", "log(z + 1e-9)", "sqrt(abs(x)) * sin(t * w) + cos(xdot)", "pos(a0 - z) ^ 2.5",
    "max(z, a0)^-3", "z ^ -1.5", "min(z, 2 * a0) ^ 1.7", "[z <= a0 and not meniscus] * delta^1.5",
    "[z > a0 or deltadot > 0] * [meniscus] * z^-2", "[meniscus]", "-(x * 2)", "z ^ zdot", "deltadot * delta^0.5",
    "x / (z - a0)", "[z >= a0] * [z < 3 * a0] * (z - a0) ^ 0.5", "[not (z < a0)] * z^0 + z^1 - z^-1 + z^2",
)


def _all_opcode_law():
    params = {"a0": A0_CONTACT, "R": R, "lam": 1e-9, "w": 2e6, "rup": 1e-9}
    terms = tuple(("custom", f"t{i}", text, 1.0 + i) for i, text in enumerate(ALL_OPCODE_TERMS))
    return compile_force_law(ForceLaw(("custom",), params, terms, (StateGate("meniscus", "z <= a0", "z > a0 + rup"),)))


def _laws_under_test():
    context = {"R": R, "a0": A0_CONTACT, "eps_r": 78.3}  # every context quantity (CONTEXT_UNITS): water's eps_r
    laws = {f"effect {name}": compile_force_law(build_force_law([name], {}, context)) for name in EFFECTS.names()}
    for name in MODELS.names():
        model = MODELS.get(name)
        laws[f"model {name}"] = compile_force_law(
            build_force_law(model.effects, dict(model.defaults), context, model.derived_defaults))
    laws["all opcodes"] = _all_opcode_law()
    return laws


def _points(n_gates, d):
    """Points (x, v, t, gate rows) across the contact, at its edge, at z = 0, beyond, and non-finite ones."""
    z = np.concatenate([np.linspace(-0.5e-9, 3e-9, 41), [A0_CONTACT, 0.0, -0.0, 1e-6, np.inf, -np.inf, np.nan]])
    v = np.resize([0.0, -0.0, 0.3, -0.7, 2e-3, np.nan, np.inf], z.size)
    t = np.resize([0.0, 1e-7, 3.3e-6, -2e-6], z.size)
    x = d - z
    rows = [np.zeros(n_gates), np.ones(n_gates)]
    x, v, t = (np.repeat(a, len(rows)) for a in (x, v, t))
    gates = np.tile(np.array(rows).reshape(len(rows), n_gates), (z.size, 1))
    return x, v, t, gates


def _evaluate(module, law, compiled, x, v, t, dyn, gates):
    n, n_switch = x.size, compiled.owners.size
    out = (np.empty(n), np.empty(n), np.empty((n, n_switch)), np.empty((n, 2 * compiled.n_gates)))
    module.evaluate_law(x, v, t, dyn, np.ascontiguousarray(gates), law, n_switch, *out)
    return out


def test_generated_law_is_the_vm_law_bit_for_bit():
    """Every effect, every model and a law using every opcode: generated code == VM == NumPy twin."""
    from afmid.terms.expr import evaluate_numpy
    from afmid.kernels import integrate as vm_kernel

    d = 20e-9
    for name, compiled in _laws_under_test().items():
        dyn = np.array([1.0, 1.0, 1.0, 1.0, 1.0, d, compiled.law.parameters["a0"], 1.0])
        x, v, t, gates = _points(compiled.n_gates, d)
        generated = compiled.generated_kernel()
        ours = _evaluate(generated.module, generated.law, compiled, x, v, t, dyn, gates)
        vm = _evaluate(vm_kernel, compiled.vm_law(), compiled, x, v, t, dyn, gates)
        for a, b in zip(ours, vm):
            np.testing.assert_array_equal(a, b, err_msg=name)  # NaN == NaN here; -0.0 == 0.0
            numbers = ~np.isnan(a)  # (the sign of a NaN is not specified by IEEE 754)
            assert np.array_equal(np.signbit(a[numbers]), np.signbit(b[numbers])), name
        np.testing.assert_array_equal(ours[0], ours[1], err_msg=name)  # law_force == law_full's force
        # The NumPy twin (evaluates the parsed text, without the compiler's constant folding).
        finite = np.isfinite(x) & np.isfinite(v)
        with np.errstate(all="ignore"):  # inf - inf in the sum of terms
            numpy_force = np.array([force_numpy(compiled, x[i], v[i], t[i], d, gates[i])[0] if finite[i] else np.nan
                                    for i in range(x.size)])
        ok = np.isfinite(numpy_force) & finite
        np.testing.assert_allclose(ours[0][ok], numpy_force[ok], rtol=1e-12, atol=0, err_msg=name)
        np.testing.assert_array_equal(np.isfinite(ours[0][finite]), np.isfinite(numpy_force[finite]), err_msg=name)
        from afmid.simulate.model import program_variables

        variables = program_variables(x[finite], v[finite], t[finite], d, dyn[6], gates[finite])
        for j, p in enumerate(compiled.switching):
            np.testing.assert_allclose(ours[2][finite, j], evaluate_numpy(p, variables), rtol=1e-12, err_msg=name)
        for j, p in enumerate(compiled.conditions):
            # Not bit for bit: NumPy's exp and pow take its AVX-512 code where the CPU has it (a few ulp from the
            # C library's, which numba calls): on a Zen 5 the standard linear solid's conditions differed by one
            # ulp (session 11). rtol << 1 with atol 0 keeps what a condition decides: its sign and its zeros.
            np.testing.assert_allclose(ours[3][finite, j], evaluate_numpy(p, variables), rtol=1e-12, atol=0,
                                       err_msg=name)


@pytest.mark.parametrize("model, mode", [("dmt", "steady"), ("dmt_exponential_damping", "steady"),
                                         ("jkr_hysteretic", "transient"), ("capillary", "transient")])
def test_generated_kernel_runs_as_the_vm_kernel(model, mode):
    """Same trajectory, events, gates and forces from both kernels (thermal force on)."""
    kw = {"mode": mode, "Q": 50.0, "settle_tolerance": 1e-6}
    config = make_config("dmt", effects=["capillary"], **kw) if model == "capillary" else make_config(model, **kw)
    setup = resolve_setup(config)
    compiled = compile_force_law(setup.force_law)
    h = setup.oscillator.period / 2000
    n = 4 * 2000
    thermal = np.random.default_rng(1).standard_normal(n) * 3e-11
    segments = []
    for kernel in ("generated", "vm"):
        integrator = Integrator(setup.oscillator, compiled, D_TAP, kernel=kernel)
        assert integrator.kernel == kernel
        integrator.start(*setup.oscillator.free_state(0.0))
        segments.append(integrator.run(0.1e-6, h, n, 10, thermal))
    a, b = segments
    assert a.events == b.events > 0
    np.testing.assert_array_equal(a.gates, b.gates)
    assert np.max(np.abs(a.x - b.x)) <= 1e-13 * A_FREE
    assert np.max(np.abs(a.force - b.force)) <= 1e-11 * np.max(np.abs(b.force))


def test_drive_table_and_its_twin():
    """The drive by angle addition stays within rounding of F0 cos(w t), over a long run, and the twin agrees."""
    from afmid.kernels.integrate import DRIVE_ANCHOR_STEPS, drive_table

    osc = Oscillator(K, F0_HZ, 250.0, F0_HZ, 2e-9)
    h = osc.period / 2000
    table = drive_table(osc.omega, h, DRIVE_ANCHOR_STEPS)
    angles = osc.omega * (0.5 * h * np.arange(2 * DRIVE_ANCHOR_STEPS + 1))
    np.testing.assert_allclose(table[0], np.cos(angles), rtol=0, atol=2e-16)
    np.testing.assert_allclose(table[1], np.sin(angles), rtol=0, atol=2e-16)
    n = 100_000  # 50 periods
    t0 = 1.2345e-6
    drive = reference_drive(osc, t0, h, n)
    i = np.arange(n)[:, None]
    exact = osc.drive_force * np.cos(osc.omega * t0 + osc.omega * h * (i + np.array([0.0, 0.5, 1.0])))
    # |error| is a few ulp of F0, as for cos(w t) evaluated at each t (no error accumulates).
    assert np.max(np.abs(drive - exact)) < 2e-13 * osc.drive_force
    np.testing.assert_array_equal(drive[::DRIVE_ANCHOR_STEPS, 0],
                                  osc.drive_force * np.cos(osc.omega * (t0 + i[::DRIVE_ANCHOR_STEPS, 0] * h)))


def test_generated_modules_are_files_written_once(tmp_path, monkeypatch):
    from afmid.kernels import lawgen

    monkeypatch.setenv("AFMID_KERNEL_DIR", str(tmp_path))
    assert lawgen.kernel_directory() == tmp_path
    text = '"""test module"""\nVALUE = 42\n'
    module = lawgen.load_module(text)
    assert module.VALUE == 42 and lawgen.load_module(text) is module
    (path,) = tmp_path.glob("afmid_law_*.py")
    assert path.read_text() == text and module.SOURCE_PATH == path
    mtime = path.stat().st_mtime_ns
    lawgen._write_once(path, text)  # unchanged text: the file (and numba's cache of it) is left alone
    assert path.stat().st_mtime_ns == mtime
    # The source of a real kernel: the algorithm section verbatim, then the generated law.
    compiled = compile_force_law(build_force_law(["dmt"], {}, {"R": R, "a0": A0_CONTACT}))
    source = lawgen.module_source(compiled.terms, compiled.switching, compiled.conditions, compiled.n_gates)
    assert lawgen.algorithm_source() in source
    assert "def law_force(" in source and "max(z, a0)^-2" in source
    # a law without gates switches the algorithm's gate handling off; a law with gates keeps it
    assert compiled.n_gates == 0 and "\nHAS_GATES = False\n" in source
    gated = compile_force_law(build_force_law(["jkr"], {}, {"R": R, "a0": A0_CONTACT}))
    assert gated.n_gates > 0
    assert "\nHAS_GATES = False\n" not in lawgen.module_source(gated.terms, gated.switching, gated.conditions,
                                                              gated.n_gates)


#: Run in a fresh process: in the suite's own process another test may have called a module's law_conditions.
_GATE_FREE_CHECK = """
from afmid.physics.effects import build_force_law
from afmid.simulate.driver import Integrator, Oscillator, compile_force_law
compiled = compile_force_law(build_force_law(["dmt"], {{}}, {{"R": {R!r}, "a0": {a0!r}}}))
osc = Oscillator({k!r}, {f0!r}, 50.0, {f0!r}, 8e-9)
integrator = Integrator(osc, compiled, {d!r}, kernel="generated")
integrator.start(*osc.free_state(0.0))
integrator.run(0.0, osc.period / 2000, 4000, 10)
module = compiled.generated_kernel().module
print(module.HAS_GATES, bool(module.integrate.signatures), bool(module.law_conditions.signatures))
"""


def test_a_gate_free_generated_kernel_does_not_compile_the_gate_handling():
    """HAS_GATES = False prunes the gate handling before numba types it: running a gate-free law's generated kernel
    (in a new process, from the on-disk cache or compiled) loads no version of its law_conditions (the code before
    compiled it, unused, into integrate and event_step: ~1 s of CPU of the first-ever fit). The trajectory is the
    VM kernel's (which keeps the gate handling)."""
    import subprocess
    import sys

    code = _GATE_FREE_CHECK.format(R=R, a0=A0_CONTACT, k=K, f0=F0_HZ, d=D_TAP)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "True", "False"], out.stdout
    compiled = compile_force_law(build_force_law(["dmt"], {}, {"R": R, "a0": A0_CONTACT}))
    osc = Oscillator(K, F0_HZ, 50.0, F0_HZ, 8e-9)  # drive 8 nN at Q 50: a free amplitude of 10 nm, tapping at D_TAP
    h = osc.period / 2000
    ends = []
    for kernel in ("generated", "vm"):
        integrator = Integrator(osc, compiled, D_TAP, kernel=kernel)
        integrator.start(*osc.free_state(0.0))
        segment = integrator.run(0.0, h, 4000, 10)
        ends.append((segment.x, segment.events))
    assert ends[0][1] == ends[1][1] > 0
    np.testing.assert_array_equal(ends[0][0], ends[1][0])  # the same operations in the same order


def test_integrator_falls_back_to_the_vm_kernel(monkeypatch):
    from afmid.kernels import lawgen
    from afmid.simulate.driver import CompiledForceLaw

    def fail(self):
        raise lawgen.GenerationError("no place to write")

    monkeypatch.setattr(CompiledForceLaw, "generated_kernel", fail)
    compiled = _law(["dmt"], {"hamaker": H, "E_star": E_STAR})
    osc = Oscillator(K, F0_HZ, 100.0, F0_HZ, 1e-9)
    assert Integrator(osc, compiled, D_TAP).kernel == "vm"
    with pytest.raises(lawgen.GenerationError):
        Integrator(osc, compiled, D_TAP, kernel="generated")
    with pytest.raises(ValueError):
        Integrator(osc, compiled, D_TAP, kernel="fast")


# =========================================================================== (3) energy balance
def _energy_terms(trace, Q):
    """Per-period drive work, viscous loss, tip-sample dissipation and stored-energy change (J)."""
    osc = Oscillator(K, F0_HZ, Q, F0_HZ, trace.drive_force_amplitude)
    x, v, f = trace.deflection, trace.truth.velocity, trace.truth.force
    n = round(trace.samples_per_period)
    t = np.arange(x.size) / trace.sample_rate
    rows = []
    for p in range(trace.n_samples // n):
        s = slice(p * n, (p + 1) * n + 1)
        drive = np.trapezoid(osc.drive_force * np.cos(osc.omega * t[s]) * v[s], t[s])
        viscous = np.trapezoid(osc.damping * v[s] ** 2, t[s])
        # Multiply the EOM by xdot: F0 cos(wt) xdot = c xdot^2 + F_ts xdot + d/dt(m xdot^2/2 + k x^2/2).
        # The sample takes E_ts = integral F_ts xdot dt = -(closed integral of F_ts dz) per period.
        tip_sample = np.trapezoid(f[s] * v[s], t[s])
        energy = 0.5 * osc.mass * v[s] ** 2 + 0.5 * K * x[s] ** 2
        rows.append((drive, viscous, tip_sample, energy[-1] - energy[0]))
    return np.array(rows)


@pytest.mark.parametrize("model, dissipative", [("dmt_viscoelastic", True), ("dmt_exponential_damping", True),
                                                ("dmt", False), ("lennard_jones", False)])
def test_energy_balance_per_period(model, dissipative):
    Q = 50.0
    config = make_config(model, Q=Q, periods=3, samples_per_period=2000, settle_tolerance=1e-6,
                         d=9.5e-9 if model == "lennard_jones" else D_TAP)
    trace = simulate(config)
    assert trace.truth.separation.min() < A0_CONTACT + 0.05e-9
    for drive, viscous, tip_sample, stored in _energy_terms(trace, Q):
        assert abs(drive - viscous - tip_sample - stored) < 1e-3 * drive
        if dissipative:
            assert tip_sample > 0.01 * drive
        else:
            assert abs(tip_sample) < 1e-4 * drive


# =========================================================================== (4, 5) noise
NOISY = {"thermal": True, "temperature": 300.0, "detector_rms": 1e-12, "adc_step": 1e-13}


def test_same_seed_same_trace_and_different_seed_differs():
    kw = {"Q": 20.0, "periods": 3, "noise": NOISY, "settle_tolerance": 1e-5, "steps_per_period": 400}
    a = simulate(make_config(seed=7, **kw))
    b = simulate(make_config(seed=7, **kw))
    c = simulate(make_config(seed=8, **kw))
    assert np.array_equal(a.deflection, b.deflection) and np.array_equal(a.truth.force, b.truth.force)
    assert not np.array_equal(a.deflection, c.deflection)
    quiet = simulate(make_config(Q=20.0, periods=3, settle_tolerance=1e-5, steps_per_period=400))
    assert np.array_equal(quiet.deflection, simulate(make_config(Q=20.0, periods=3, settle_tolerance=1e-5,
                                                                 steps_per_period=400)).deflection)
    assert np.allclose(np.round(a.deflection / 1e-13) * 1e-13, a.deflection, rtol=0, atol=1e-25)  # ADC rounding


def test_thermal_variance_is_kT_over_k_far_from_the_sample():
    """Equipartition: <x^2> = k_B T / k for the undriven lever (Q = 2: short correlation time)."""
    config = build_config({
        "cantilever": {"spring_constant": K, "resonance_frequency": F0_HZ, "quality_factor": 2.0, "tip_radius": R},
        "drive": {"frequency": F0_HZ, "force_amplitude": 1e-30},
        "sample": {"separation": 1e-6},
        "simulate": {"model": "dmt", "periods": 10000, "samples_per_period": 20, "steps_per_period": 100,
                     "noise": {"thermal": True, "temperature": 300.0}, "seed": 3},
    })
    trace = simulate(config)
    variance = np.var(trace.deflection)
    expected = BOLTZMANN * 300.0 / K
    # ~1 % statistical error (10,000 periods, correlation time Q / pi periods).
    assert variance == pytest.approx(expected, rel=0.05)


# =========================================================================== (6) files
def test_trace_file_layout(tmp_path):
    trace = simulate(make_config(Q=20.0, periods=3, settle_tolerance=1e-5, noise=NOISY))
    path = write_trace_file(tmp_path / "t.h5", trace, "simulate: {}\n")
    with h5py.File(path, "r") as h5:
        assert h5.attrs["format"] == "afmid-trace"
        for key in ("afmid_version", "format_version", "created", "config", "sample_rate"):
            assert key in h5.attrs
        assert h5["deflection"].attrs["units"] == "m"
        assert h5["truth/force"].attrs["units"] == "N"
        assert h5["truth/separation"].attrs["units"] == "m"
        assert h5["truth/velocity"].attrs["units"] == "m/s"

        def check_units(name, obj):
            if isinstance(obj, h5py.Dataset):
                assert "units" in obj.attrs, name

        h5.visititems(check_units)
        truth = h5["truth"]
        assert truth.attrs["model"] == "dmt"
        assert truth.attrs["drive_force_amplitude"] == pytest.approx(
            drive_force_for_amplitude(K, F0_HZ, 20.0, F0_HZ, A_FREE))
        assert truth.attrs["separation"] == D_TAP
        assert truth["parameters"].attrs["E_star"] == E_STAR
        assert "E_star: Pa" in truth["parameters"].attrs["units"]
        assert h5["deflection"].shape == (600,)


# =========================================================================== (7) setpoint, free response
def test_setpoint_search_hits_the_requested_amplitude():
    config = make_config(Q=50.0, periods=3, settle_tolerance=1e-6, setpoint=0.8)
    config.sample.separation = None
    trace = simulate(config)
    extra = trace.truth.extra
    assert extra["setpoint"] == pytest.approx(0.8, abs=1e-3)
    # The recorded trace has that amplitude too.
    n = round(trace.samples_per_period)
    phase = 2 * np.pi * np.arange(n) / n
    x = trace.deflection[:n]
    amplitude = 2 / n * abs(np.dot(x, np.exp(1j * phase)))
    assert amplitude / A_FREE == pytest.approx(0.8, abs=1e-3)


def test_far_from_the_sample_the_amplitude_is_the_free_amplitude():
    trace = simulate(make_config("lennard_jones", Q=100.0, d=1e-6, periods=3))
    assert trace.truth.extra["steady_amplitude"] == pytest.approx(A_FREE, rel=1e-6)
    assert trace.truth.extra["settle_periods"] < 50


# =========================================================================== (8) nondimensional form
def test_nondimensional_form_maps_onto_the_si_simulation():
    """A steady LJ tapping run, converted to (tau, xi), solves the paper's equation."""
    config = make_config("lennard_jones", Q=50.0, periods=4, d=9.5e-9, settle_tolerance=1e-6)
    trace = simulate(config)
    setup = resolve_setup(config)
    osc, p = setup.oscillator, dict(setup.force_law.parameters)
    form = NondimensionalForm.from_oscillator(osc)
    assert form.length == pytest.approx(A_FREE)
    assert form.damping == 1 / 50.0 and form.stiffness == 1.0 and form.drive_frequency == 1.0
    assert form.drive == pytest.approx(1 / 50.0)  # B = F0 / (k A0) = 1/Q at resonance

    t = np.arange(trace.n_samples) / trace.sample_rate
    tau, xi, xi_prime, f = form.to_nondimensional(t, trace.deflection, trace.truth.velocity, trace.truth.force)
    back = form.to_si(tau, xi, xi_prime, f)
    np.testing.assert_allclose(back[1], trace.deflection, rtol=1e-15)
    np.testing.assert_allclose(back[3], trace.truth.force, rtol=1e-15)

    def f_ts(xi_value):  # the paper's f_ts: force toward the sample in units of k L
        z = config.sample.separation - xi_value * form.length
        return -_hand_force("lennard_jones", p, z, 0.0, False, False) / (K * form.length)

    def rhs(s, y):
        return [y[1], form.acceleration(s, y[0], y[1], f_ts(y[0]))]

    sol = solve_ivp(rhs, (tau[0], tau[-1]), [xi[0], xi_prime[0]], method="DOP853", rtol=1e-12, atol=1e-14,
                    t_eval=tau)
    assert np.max(np.abs(sol.y[0] - xi)) < 1e-4  # xi is in units of A0: the same bound as the SI check
    np.testing.assert_allclose(-f_ts(xi) * K * form.length, trace.truth.force, rtol=1e-9)


# =========================================================================== configuration errors
def test_config_errors_name_the_key():
    config = make_config()
    config.cantilever.tip_radius = None
    with pytest.raises(ConfigError) as err:
        simulate(config)
    assert err.value.key == "cantilever.tip_radius"

    config = make_config("dmtt")
    with pytest.raises(ConfigError) as err:
        simulate(config)
    assert err.value.key == "simulate.model" and "did you mean 'dmt'" in err.value.message

    config = make_config(parameters={"E_star": -1.0})
    with pytest.raises(ConfigError) as err:
        simulate(config)
    assert err.value.key == "simulate.parameters" and "E_star" in err.value.message

    config = make_config()
    config.sample.separation = None
    with pytest.raises(ConfigError) as err:
        simulate(config)
    assert err.value.key == "sample.separation"


def test_a_run_that_does_not_settle_says_so():
    config = make_config(max_settle_periods=3)
    with pytest.raises(AfmidError) as err:
        simulate(config)
    assert err.value.key == "simulate.max_settle_periods" and "did not settle" in err.value.message
    assert "simulate.unsettled: record" in err.value.message


def test_an_unsettled_run_is_recorded_as_it_is_when_asked():
    """simulate.unsettled: record keeps the state after max_settle_periods and records from it; the truth says
    it did not settle and how much of the start is left (exp(-pi N / Q) after N periods)."""
    Q, periods = 250.0, 5
    trace = simulate(make_config(Q=Q, max_settle_periods=3, unsettled="record", periods=periods))
    extra = trace.truth.extra
    assert extra["settled"] is False and extra["settle_periods"] == 3
    assert extra["start_decay"] == pytest.approx(math.exp(-math.pi * 3 / Q), rel=1e-12)
    assert 0 < extra["unsettled_amplitude_low"] <= extra["unsettled_amplitude_high"] < 1.1 * A_FREE
    assert trace.deflection.size == round(periods * 200)  # the recording itself as in a settled run
    assert simulate(make_config(Q=2.0, unsettled="record", periods=3)).truth.extra["settled"] is True


def test_orbit_period_finds_the_repeat_and_none_in_a_beat():
    from afmid.simulate.integrator import orbit_period

    n = np.arange(128)
    period_3 = 6.7e-9 * (1 + 1e-3 * np.array([0.0, 1.0, -0.5])[n % 3])
    assert orbit_period(period_3, np.full(128, 2.3), 1e-7) == 3
    beat = 6.7e-9 * (1 + 1e-3 * np.sin(2 * np.pi * n / (3 + math.sqrt(2))))  # incommensurate: never repeats
    assert orbit_period(beat, np.full(128, 2.3), 1e-7) == 0
    assert orbit_period(np.full(128, 6.7e-9), 2.3 + 1e-3 * (n % 2), 1e-7) == 2  # a repeat in the phase alone


def test_a_capillary_neck_formed_on_some_taps_only_is_a_period_8_orbit():
    """Draw 13 of configs/coverage/loop_air.yaml (seed 2805): a meniscus that forms on 5 taps of every 8 never
    settles to one period; the orbit is reached well within 2000 periods at Q 200 (the start decays to
    exp(-pi 2000 / 200) ~ 2e-14) and repeats after exactly 8 periods."""
    config = make_config(effects=["capillary"], Q=199.96188082020134, d=7.142663936778473e-09,
                         A0=9.951341595965224e-09,
                         parameters={"E_star": 3178269521.180495, "hamaker": 3.551827748040398e-20,
                                     "contact_angle": 0.6207703356041621, "rupture_distance": 1.1448647850999555e-09},
                         max_settle_periods=2000, unsettled="record", periods=16, samples_per_period=100)
    extra = simulate(config).truth.extra
    assert extra["settled"] is False and extra["orbit_periods"] == 8
    assert 6.9e-9 < extra["unsettled_amplitude_low"] < extra["unsettled_amplitude_high"] < 7.0e-9

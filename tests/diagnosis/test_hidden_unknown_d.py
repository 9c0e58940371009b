"""Issue 13's Done-when, with the separation NOT given: every hidden catalog effect named first on three variants.

Each case simulates a sample with one effect a ``[dmt]`` fit lacks (50 steady periods, thermal noise at 300 K),
fits it with ``sample.separation`` absent, writes and reads the run file and diagnoses it
(tests/support/unknown_separation.py). Required: the hidden effect is named first (``suggestions[0]``; "the
data cannot decide" fails), the catalog explains the data, and the error with the named effect falls within
1.5x its noise floor (the issue's number).

Variants (seeds and parameters fixed before any of these runs was made):
- viscoelastic, exponential damping, electrostatic, capillary, hydration: tests/diagnosis/test_diagnose.py's
  VARIANTS a-c (there with the separation given);
- electrostatic at 3 V and 50 samples per period: scripts/experiment_table.py's three (seeds 45, 47, 48);
- contact damping: tests/configs/hidden_contact_damping.yaml (c_d 3e-7 kg/s) and two new ones (1.5e-7 and
  6e-7 kg/s, other moduli, Hamaker constants and separation);
- the relaxing solid: tests/configs/hidden_standard_linear_solid.yaml (w tau 0.3) and two new ones (w tau 1;
  a stronger relaxation on a stiffer relaxed modulus);
- the double layer in liquid (Q 4 lever): tests/physics/test_liquid_physics.py's DOUBLE_LAYER_SETS a-c at 50 periods.
  Variant b (a Q 2, 0.3 N/m lever, lambda_D 5 nm) puts the [dmt] fit's surface at -0.86 nm (truth 5 nm; the run is
  flagged implausible): the candidates then search the separation over the fit's whole window
  (afmid.diagnosis.candidate_refit.separation_starts) and are judged by their error over their own noise floor
  (1.47 -> 1.15 floors; the raw errors, normalised differently at the two separations, rose 0.187 -> 0.228).

Cost: ~20-30 s CPU per case. By default one variant per effect runs (``b``, the one no other d-unknown test
covers); ``AFMID_HIDDEN_FULL=1`` runs all three (the table of docs/diagnosis.md, "Separation unknown").
``AFMID_HIDDEN_RECORD=path`` appends one JSON line per case. Each case's answer (named effect, flags, every
ΔBIC) is also compared with the one stored in tests/diagnosis/verdict_reference.json (tests/support/
verdict_reference.py: a faster diagnosis must say the same).
"""

from __future__ import annotations

import json
import os

import pytest

from afmid.config import apply_overrides, parse_override, read_yaml
from repo_paths import TEST_CONFIGS
from tests.diagnosis.test_diagnose import VARIANTS
from tests.physics.test_liquid_physics import DOUBLE_LAYER_SETS
from unknown_separation import diagnose_without_separation
from verdict_reference import check_answer

pytestmark = [pytest.mark.numerics, pytest.mark.slow]

FULL = os.environ.get("AFMID_HIDDEN_FULL", "") not in ("", "0")
RECORD = os.environ.get("AFMID_HIDDEN_RECORD")
DEFAULT_VARIANT = "b"
WITHIN_FLOOR = 1.5  # the "errors fall to within 1.5x the floor"

_THREE_VOLTS = ["simulate.parameters.voltage=3.0", "simulate.samples_per_period=50"]
#: effect -> (config under tests/configs, {variant: overrides}); the config's simulate section hides the effect.
CASES: dict[str, tuple[str, dict[str, list[str]]]] = {
    **{effect: (f"hidden_{effect}", {v: VARIANTS[effect][v] for v in "abc"})
       for effect in ("viscoelastic", "exponential_damping", "electrostatic", "capillary", "hydration")},
    "electrostatic-3V-50": ("hidden_electrostatic", {
        "a": _THREE_VOLTS + ["simulate.seed=45"],
        "b": _THREE_VOLTS + ["simulate.seed=47", "simulate.parameters.E_star=2.0e9", "simulate.parameters.hamaker=5.0e-20"],
        "c": _THREE_VOLTS + ["simulate.seed=48", "sample.separation=8.0e-9", "simulate.parameters.E_star=1.5e9"]}),
    "contact_damping": ("hidden_contact_damping", {
        "a": [],
        "b": ["simulate.parameters.contact_damping=1.5e-7", "simulate.parameters.E_star=2.0e9",
              "simulate.parameters.hamaker=5.0e-20", "simulate.seed=302"],
        "c": ["simulate.parameters.contact_damping=6.0e-7", "simulate.parameters.E_star=1.5e9",
              "simulate.parameters.hamaker=6.0e-20", "sample.separation=8.0e-9", "simulate.seed=303"]}),
    "standard_linear_solid": ("hidden_standard_linear_solid", {
        "a": [],
        "b": ["simulate.parameters.relaxation_time=5.305e-7", "simulate.parameters.relaxing_modulus=1.5e9",
              "simulate.seed=702"],
        "c": ["simulate.parameters.E_star=1.5e9", "simulate.parameters.relaxing_modulus=2.0e9", "simulate.seed=703"]}),
    "double_layer": ("liquid_double_layer", {
        v: DOUBLE_LAYER_SETS[v] + ["model.effects=[dmt]", "simulate.periods=50"] for v in "abc"}),
}


def _expected(case: str) -> str:
    return case.split("-")[0]


#: Cases the data cannot decide at 50 periods, with the measured numbers (not strict, as every measured xfail in
#: the suite: a change that names the effect shows as XPASS; these sit near a decision threshold, and another
#: CPU's BLAS rounding must not fail the suite by deciding one of them).
UNDECIDED_AT_50 = {
    ("capillary", "b"): "a 3.3 nN meniscus rupturing 0.5 nm out: capillary vs exponential damping χ² 6.8 apart "
    "(Vuong 0.5 σ); taken as the truth each predicts the other's fit worse by χ² 37 (spread 15): exponential "
    "damping is refuted at 2.8 σ and capillary meets its own prediction within 1.9 σ, so capillary is named (since "
    "session 13, when the candidates' separation search started also from the middle of the fit's window; before: "
    "2.2 σ, 'cannot decide'): on the 2 σ threshold; at 200 periods capillary is named (ΔBIC -5316 vs -5179, "
    "exponential damping leaves a residual 1.8x the floor: test_capillary_b_is_decided_by_a_longer_record)",
    ("double_layer", "c"): "lambda_D 2 nm: double_layer vs hydration χ² 8.8 apart (Vuong 1.0 σ), ΔBIC -570 vs -558; "
    "linearised, each is within χ² 0.7-2.2 of the other's model, so neither taken as the truth is refuted "
    "(1.1 σ): 'cannot decide: double_layer, hydration' (a 2 nm Debye length and a hydration length searched up "
    "to 1.5 nm overlap in shape over the 3.5 nm the tip samples)",
}
PARAMS = [pytest.param(case, variant, id=f"{case}-{variant}",
                       marks=[pytest.mark.xfail(reason=UNDECIDED_AT_50[case, variant], strict=False)]
                       if (case, variant) in UNDECIDED_AT_50 else [])
          for case, (_, variants) in CASES.items() for variant in variants if FULL or variant == DEFAULT_VARIANT]


@pytest.mark.parametrize("case, variant", PARAMS)
def test_hidden_effect_is_named_first_with_the_separation_unknown(tmp_path, case, variant):
    config, variants = CASES[case]
    raw = apply_overrides(read_yaml(TEST_CONFIGS / f"{config}.yaml"), [parse_override(o) for o in variants[variant]])
    summary, result = diagnose_without_separation(tmp_path, raw)
    verdict = summary["diagnosis"]["verdict"]
    top = summary["suggestions"][0] if summary["suggestions"] else None
    if RECORD:
        with open(RECORD, "a", encoding="utf-8") as out:
            out.write(json.dumps({
                "case": f"{case}-{variant}", "top": top["effect"] if top else None, "verdict": verdict,
                "error_before": result.cv_error, "floor_before": result.cv_error_noise_floor,
                "error_after": top["error_after"] if top else None,
                "floor_after": top["noise_floor_after"] if top else None,
                "tried": {t["effect"]: t["delta_bic"] for t in summary["tried"]},
                "compared": summary.get("compared_with_best")}, default=float) + "\n")
    check_answer("hidden", f"{case}-{variant}", summary)
    assert top is not None and top["effect"] == _expected(case), verdict
    assert summary["diagnosis"]["explained_by_catalog"] is True, verdict
    assert top["error_after"] <= WITHIN_FLOOR * top["noise_floor_after"], verdict


def test_capillary_b_is_decided_by_a_longer_record(tmp_path):
    """The case the data cannot decide at 50 periods (UNDECIDED_AT_50), recorded for 200: capillary is named
    first and explains the data (~70 s CPU: the one slow case, it shows the limit is the record length)."""
    config, variants = CASES["capillary"]
    raw = apply_overrides(read_yaml(TEST_CONFIGS / f"{config}.yaml"),
                          [parse_override(o) for o in variants["b"] + ["simulate.periods=200"]])
    summary, _ = diagnose_without_separation(tmp_path, raw)
    verdict = summary["diagnosis"]["verdict"]
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == "capillary", verdict
    assert summary["diagnosis"]["explained_by_catalog"] is True, verdict
    top = summary["suggestions"][0]
    assert top["error_after"] <= WITHIN_FLOOR * top["noise_floor_after"], verdict

"""The diagnosis with the rest separation NOT given (the normal experimental case).

The run estimates the separation with the wrong model ([dmt] on a trace with a hidden effect); the candidate
refits re-search it (afmid.diagnosis.candidate_refit). A representative subset of scripts/hidden_effects_unknown_d.py
(the full table is in docs/diagnosis.md, "Separation unknown"), cases fixed before they were run: the
electrostatic variant "a" of tests/diagnosis/test_diagnose.py (before: no effect named), the `make demo` trace (LDPE-like,
hidden viscoelasticity; before: "exponential_damping explains part") and a clean trace (variant "c").
Required: the hidden effect is named first and explains the data, the error with it falls within 1.5x its
noise floor; no suggestion and no alarm on the clean trace. The clean trace failed that until issue 13's
audit: its [dmt] error is 0.0907 against a floor of 0.0694, 1.31x, just above the old FLOOR_FACTOR 1.3 (the
99 % point of a right model's error / floor at its degrees of freedom); FLOOR_FACTOR is now 1.45
(docs/diagnosis.md, "The noise floor and its threshold").
"""

from __future__ import annotations


import pytest

from afmid.config import apply_overrides, parse_override, read_yaml
from repo_paths import REPO_ROOT
from unknown_separation import diagnose_without_separation

pytestmark = [pytest.mark.numerics, pytest.mark.slow]

ROOT = REPO_ROOT
CASES = {
    "electrostatic-a": (ROOT / "tests" / "configs" / "hidden_electrostatic.yaml", [], "electrostatic"),
    "demo": (ROOT / "afmid" / "templates" / "demo_ldpe.yaml", [], "viscoelastic"),
    "clean-c": (ROOT / "tests" / "configs" / "hidden_clean.yaml",
                ["simulate.parameters.E_star=1.5e9", "simulate.parameters.hamaker=6.0e-20", "sample.separation=8.0e-9",
                 "simulate.seed=63"], None),
}


@pytest.mark.parametrize("case", CASES)
def test_hidden_effect_is_named_with_the_separation_unknown(tmp_path, case):
    path, overrides, effect = CASES[case]
    raw = apply_overrides(read_yaml(path), [parse_override(o) for o in overrides])
    summary, _ = diagnose_without_separation(tmp_path, raw)
    verdict = summary["diagnosis"]["verdict"]
    if effect is None:
        assert summary["suggestions"] == [], verdict
        assert summary["missing_effect"] is False, verdict
        return
    assert summary["suggestions"] and summary["suggestions"][0]["effect"] == effect, verdict
    assert summary["diagnosis"]["explained_by_catalog"] is True, verdict
    top = summary["suggestions"][0]
    assert top["error_after"] <= 1.5 * top["noise_floor_after"], verdict

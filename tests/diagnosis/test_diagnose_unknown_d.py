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

"viscoelastic-far" is the trace that showed the candidates' separation search too narrow (session 13, the
issue's table re-measured on new seeds): a strong Kelvin-Voigt sample (eta 400 Pa s) puts the [dmt] fit 3.4 nm
above the truth with no contact term selected; the viscoelastic candidate, searched only within 2.5 nm of that,
never reached a contact and exponential damping was named ("explains part").
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
    "viscoelastic-far": (ROOT / "tests" / "configs" / "hidden_viscoelastic.yaml",
                         ["simulate.parameters.viscosity=400.0", "simulate.parameters.E_star=1.5e9",
                          "simulate.parameters.hamaker=6.0e-20", "sample.separation=8.0e-9", "simulate.seed=513"],
                         "viscoelastic"),
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


def _clean_prepared(tmp_path):
    """(config, prepared trace, first contact in m) of hidden_clean.yaml simulated for 20 periods."""
    from afmid.config import build_config
    from afmid.fit.pipeline import first_contact
    from afmid.fit.prepare import prepare
    from afmid.simulate.driver import simulate

    source = REPO_ROOT / "tests" / "configs" / "hidden_clean.yaml"
    raw = read_yaml(source)
    raw["simulate"]["periods"] = 20
    config = build_config(raw, source=source, base_dir=tmp_path)
    prepared = prepare(simulate(config), config.fit)
    return config, prepared, first_contact(prepared, config.sample.a0)


@pytest.mark.parametrize("below_beyond_touch", [-2e-9, 0.5e-9, 5e-9])
def test_a_candidate_with_an_implausible_separation_starts_inside_the_window_above_a0(tmp_path, below_beyond_touch):
    """A run whose separation is not above zero restarts each candidate on fit.separation_window around first
    contact, its part above sample.a0 only: a window reaching below a0 (first contact closer than the window's
    lower reach) must not centre the candidate at a separation <= 0 (it then failed and dropped out)."""
    from types import SimpleNamespace

    from afmid.diagnosis.candidate_refit import separation_starts

    config, prepared, touch = _clean_prepared(tmp_path)
    a0 = config.sample.a0
    above = 3e-9
    config.fit.separation_window = [touch + below_beyond_touch, above]
    starts, low, high = separation_starts(SimpleNamespace(separation=-0.5e-9), prepared, config)
    assert low == pytest.approx(max(touch - config.fit.separation_window[0], a0), rel=1e-12)
    assert high == pytest.approx(touch + above, rel=1e-12)
    assert starts == [pytest.approx(0.5 * (low + high), rel=1e-12)] and starts[0] > a0 and high > low


def test_a_candidates_separation_search_reaches_the_fits_window_and_starts_twice(tmp_path):
    """A run whose estimate lies far from first contact (a missing effect moved it): a candidate searches the
    window a fit with it would search (fit.separation_window around first contact) joined to the run's estimate
    +- SEPARATION_WINDOW, and starts its shape search from the run's estimate and from the middle of that span."""
    from types import SimpleNamespace

    from afmid.diagnosis.candidate_refit import SEPARATION_WINDOW, separation_starts

    config, prepared, touch = _clean_prepared(tmp_path)
    below, above = config.fit.separation_window
    far = touch + above + 1e-9  # beyond the fit's own window
    starts, low, high = separation_starts(SimpleNamespace(separation=far), prepared, config)
    assert low == pytest.approx(touch - below, rel=1e-12)
    assert high == pytest.approx(far + SEPARATION_WINDOW, rel=1e-12)
    assert starts == [far, pytest.approx(0.5 * (low + high), rel=1e-12)]
    near = touch - 1e-9  # inside: the span is the fit's window, the middle a second start
    starts, low, high = separation_starts(SimpleNamespace(separation=near), prepared, config)
    assert (low, high) == (pytest.approx(touch - below, rel=1e-12), pytest.approx(touch + above, rel=1e-12))
    assert starts[0] == near and len(starts) == 2

"""The estimated separation's share of the force's uncertainty (afmid.fit.separation_share; issue 13).

With the separation NOT given, the force curve's largest uncertainty on short or noisy records is the
separation's (a deeper indentation of a softer sample imitates the data: scripts/separation_budget.py
--information measures that the records hold no more). What is tested (operating points, seeds and
tolerances fixed before the results were looked at):

- the arithmetic: the record length that brings the share to a target (1 / sqrt(periods)), the warning's
  text, nothing computed without a sigma;
- the poor instrument (10 pm detector noise, 50 samples per period, 50 periods; seeds 231-233): the fit
  warns "separation-limited" with a share >= 1 %, and the share accounts for the force error: error <=
  3 x share on every seed (the separation's part is |d - d_true| / sigma x share, < 2 share within 2 sigma,
  the part left with d known was measured at <= 1.3 share);
- the share is what a full refit says: fits with the separation GIVEN at d_est +- sigma (selection, row
  weights and read-out re-run) move the force curve by the share within a factor 1.5 (poor instrument and
  the liquid lever of scripts/experiment_table.py);
- a separation given: nothing computed, no warning; the ideal instrument on a 150-period record: share
  < 1 %, no warning (the share at 50 periods was measured 1.1 %; 1.1 / sqrt(3) = 0.64 %);
- the separation is profiled with whole effects (afmid.fit.undetermined.whole_effects).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from repo_paths import TEST_CONFIGS

from afmid.fit.separation_share import NOT_COMPUTED, WARN_FRACTION, SeparationShare, is_separation_limited

pytestmark = pytest.mark.numerics

CONFIGS = TEST_CONFIGS
POOR = ["simulate.noise.detector_rms=1.0e-11", "simulate.samples_per_period=50", "fit.bootstrap=0"]
LIQUID = {  # scripts/experiment_table.py's _liquid at d 4 nm: k 0.8 N/m, f0 25 kHz, Q 4, 5 pm detector
    "cantilever": {"spring_constant": 0.8, "resonance_frequency": 25e3, "quality_factor": 4.0, "tip_radius": 10e-9},
    "drive": {"frequency": 25e3, "free_amplitude": 5e-9},
    "sample": {"separation": 4.0e-9, "a0": 0.165e-9},
    "model": {"effects": ["dmt"]},
    "fit": {"bootstrap": 0},
    "simulate": {"model": "dmt", "effects": [], "parameters": {"E_star": 50e6, "hamaker": 1e-20},
                 "mode": "steady", "periods": 50, "samples_per_period": 200, "steps_per_period": 2000,
                 "seed": 234, "noise": {"thermal": True, "temperature": 300.0, "detector_rms": 5e-12}},
}


def test_periods_for_a_target_scale_as_the_square_of_the_share():
    share = SeparationShare(0.05, 3e-10, 50)
    assert share.periods_for(0.01) == 1250  # (5 %)^2 / (1 %)^2 x 50
    assert share.periods_for(0.1) == 50  # already below: the record as it is
    text = share.warning()
    assert text.startswith("separation-limited:") and "+-0.3 nm" in text and "5 % of its peak" in text
    assert "about 1,250 periods (now 50)" in text
    # recognised with and without the fit's "warning: " (a map pixel is not made suspect by it)
    assert is_separation_limited(text) and is_separation_limited("warning: " + text)
    assert not is_separation_limited("warning: model-limited: the cross-validated error 0.3 stands above ...")


def test_below_the_threshold_or_not_computed_there_is_no_warning():
    assert SeparationShare(0.5 * WARN_FRACTION, 1e-11, 50).warning() is None
    assert NOT_COMPUTED.warning() is None and NOT_COMPUTED.periods_for() is None
    assert math.isnan(NOT_COMPUTED.relative)


def _raw(name_or_raw, overrides: list[str]) -> dict:
    from afmid.config import apply_overrides, parse_override, read_yaml

    base = read_yaml(CONFIGS / f"{name_or_raw}.yaml") if isinstance(name_or_raw, str) else copy.deepcopy(name_or_raw)
    return apply_overrides(base, [parse_override(o) for o in overrides])


def _fit(raw: dict, separation=None, uncertainty=True):
    """Simulate ``raw`` and fit it with the separation given (a value) or not (None): (trace, result)."""
    from afmid.config import build_config
    from afmid.simulate.driver import simulate

    trace = simulate(build_config(raw, source=CONFIGS / "x.yaml", base_dir=CONFIGS))
    return trace, _refit(raw, trace, separation, uncertainty)


def _refit(raw: dict, trace, separation, uncertainty=True):
    from afmid.config import build_config
    from afmid.fit.pipeline import run_fit

    fit_raw = copy.deepcopy(raw)
    fit_raw["simulate"]["parameters"] = {}
    fit_raw["sample"]["separation"] = separation
    return run_fit(build_config(fit_raw, source=CONFIGS / "x.yaml", base_dir=CONFIGS), trace=trace,
                   uncertainty=uncertainty)


def _force_error(force, trace) -> float:
    truth = trace.truth.force
    used = np.isfinite(force)
    return float(np.sqrt(np.mean((force[used] - truth[used]) ** 2)) / np.abs(truth[used]).max())


@pytest.mark.slow
def test_poor_instrument_is_flagged_separation_limited_and_the_share_accounts_for_the_force_error():
    seen = []
    for seed in (231, 232, 233):
        trace, result = _fit(_raw("hidden_clean", POOR + [f"simulate.seed={seed}"]))
        share = result.separation_share
        error = _force_error(result.force_estimate, trace)
        seen.append(f"seed {seed}: share {100 * share.relative:.2f} %, force error {100 * error:.2f} %")
        assert share.relative >= WARN_FRACTION, seen[-1]
        assert any(w.startswith("warning: separation-limited:") for w in result.warnings), result.warnings
        assert error <= 3 * share.relative, "; ".join(seen)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["poor", "liquid"])
def test_the_share_is_what_full_refits_at_d_plus_minus_sigma_give(case):
    raw = _raw("hidden_clean", POOR + ["simulate.seed=235"]) if case == "poor" else _raw(LIQUID, [])
    trace, result = _fit(raw)
    d, sigma = result.nonlinear["d"].value, result.nonlinear["d"].sigma
    share = result.separation_share
    used = np.isfinite(result.force_estimate)
    changes = [(_refit(raw, trace, d + s * sigma, uncertainty=False).force_estimate - result.force_estimate)[used]
               for s in (1, -1)]
    refit = max(float(np.sqrt(np.mean(c**2))) for c in changes) / np.abs(result.force_estimate[used]).max()
    assert share.sigma == sigma
    assert refit / 1.5 <= share.relative <= 1.5 * refit, (share.relative, refit)


@pytest.mark.slow
def test_given_separation_and_a_long_ideal_record_raise_no_warning(tmp_path):
    from afmid.runfile import run_data, write_run
    from afmid.runfile import load_run

    raw = _raw("hidden_clean", ["simulate.periods=150", "simulate.seed=236", "fit.bootstrap=0"])
    trace, result = _fit(raw)
    assert result.separation_share.relative < WARN_FRACTION, result.separation_share
    assert not any("separation-limited" in w for w in result.warnings), result.warnings
    write_run(tmp_path / "run.h5", run_data(result, result.config))
    assert load_run(tmp_path / "run.h5").force_separation_uncertainty == result.separation_share.relative
    given = _refit(raw, trace, raw["sample"]["separation"])
    assert math.isnan(given.force_separation_uncertainty)
    assert not any("separation-limited" in w for w in given.warnings)


def test_the_separation_is_profiled_with_whole_effects():
    """A term the selection dropped stays in the profile when its effect has another selected term (DMT's tail
    beside Hertz); an effect with no selected term stays out; the nuisance columns are as given."""
    from afmid.config import ModelConfig
    from afmid.fit.undetermined import whole_effects
    from afmid.physics.library import build_library

    library = build_library(ModelConfig(effects=["dmt", "viscoelastic", "capillary"]), None)
    assert library.names == ["dmt.vdw", "dmt.hertz", "viscoelastic.kelvin_voigt", "capillary.meniscus"]
    mask = np.array([False, True, True, False, True, False])  # hertz, Kelvin-Voigt; drive cos in, drive sin out
    assert whole_effects(library, mask).tolist() == [True, True, True, False, True, False]
    assert mask.tolist() == [False, True, True, False, True, False]  # not modified
    nothing = np.zeros(6, dtype=bool)
    assert whole_effects(library, nothing).tolist() == nothing.tolist()

"""Model selection that converges (issue 17): more periods must mean the right law, not more distractors.

For each of the five seed models, fitted with its seed table (tests/configs/<model>.yaml, separation
known), and for the issue's own case (configs/lennard_jones.yaml, Q 250, table I), at 50 and 500 drive
periods and over ten noise draws:

- the selected terms are exactly the true ones in at least 9 of the 10 draws;
- the law error (the identified force law on the true trajectory minus the true force, RMS over the
  samples / peak true force) is no worse at 500 periods than at 50 (median over the draws).

The seeds (101-110) were fixed when this file was written, before any of these fits was run; they are
not among the seeds the selection strategy was chosen on (configs/lennard_jones.yaml seeds 2-11,
tests/configs dmt and jkr seeds 1-6; docs/accuracy.md, "Selection as the record grows").

Cost: 120 simulations and fits (60 of 500 periods) with the cheapest settings that still test the claim:
no bootstrap and no error bars (``run_fit(..., uncertainty=False)``: the support and the coefficients are
those of the full fit; only the intervals are skipped). Each (case, periods, seed) is fitted once per
session and shared by both tests. Marked ``slow`` (``make test`` runs it).
"""

from __future__ import annotations


import numpy as np
import pytest
from repo_paths import REPO_ROOT

# blas_sensitive: make test-kernels runs these again (selection accuracy: subset criteria from LAPACK least squares)
pytestmark = [pytest.mark.slow, pytest.mark.numerics, pytest.mark.blas_sensitive]

ROOT = REPO_ROOT
SEEDS = tuple(range(101, 111))  # fixed before any result was seen
PERIODS = (50, 500)
MIN_RIGHT = 9  # of the 10 draws

#: case -> (config, overrides, true terms by their seed-table names)
CASES = {
    "dmt": (ROOT / "tests/configs/dmt.yaml", [], {"z^-2", "delta^1.5", "[z<=a0] (bridging)"}),
    "lennard_jones": (ROOT / "tests/configs/lennard_jones.yaml", [], {"z^-2", "z^-8"}),
    "dmt_viscoelastic": (ROOT / "tests/configs/dmt_viscoelastic.yaml", [],
                         {"z^-2", "delta^0.5*deltadot", "delta^1.5", "[z<=a0] (bridging)"}),
    "dmt_exponential_damping": (ROOT / "tests/configs/dmt_exponential_damping.yaml", [],
                                {"z^-2", "exp(-z/lambda)*zdot", "delta^1.5", "[z<=a0] (bridging)"}),
    "jkr": (ROOT / "tests/configs/jkr.yaml", [], {"z^-2", "delta^1.5", "[z<=a0] (bridging)"}),
    # the case: configs/ operating point (Q 250), table I instead of the config's catalog effect
    "lennard_jones_q250": (ROOT / "configs/lennard_jones.yaml", ["model.effects=[]", "model.library=lj_table1"],
                           {"z^-2", "z^-8"}),
}


def law_error(result, trace) -> float:
    """RMS of (identified force law - true force) along the true trajectory (true separation and velocity),
    over the samples, divided by the peak true force."""
    library = result.library
    p = len(library)
    d_true = float(trace.truth.extra["separation"])
    params = dict(result.system.params, d=d_true)
    columns = library.evaluate(d_true - trace.truth.separation, trace.truth.velocity, trace.times, params)
    force = columns @ np.where(result.selected[:p], result.coef[:p], 0.0)
    truth = trace.truth.force
    return float(np.sqrt(np.mean((force - truth) ** 2)) / np.max(np.abs(truth)))


@pytest.fixture(scope="session")
def selection_outcomes():
    """``get(case, periods, seed)`` -> (selected terms, law error), simulated and fitted once per session."""
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    cache: dict[tuple, tuple[set, float]] = {}

    def get(case: str, periods: int, seed: int):
        key = (case, periods, seed)
        if key not in cache:
            path, overrides, _ = CASES[case]
            config = load_config(path, overrides + [f"simulate.periods={periods}", f"simulate.seed={seed}",
                                                    "fit.bootstrap=0"])
            trace = simulate(config)
            result = run_fit(config, trace=trace, uncertainty=False)
            cache[key] = (set(result.selected_terms()), law_error(result, trace))
        return cache[key]

    return get


#: Measured failures, kept at the requirement (xfail, not strict: a fix shows up as XPASS). The issue's Q 250 case at
#: 50 periods (8/10 with 10-period vote groups) passes with 6-period groups (docs/accuracy.md): none left.
KNOWN_FAILURES: dict[tuple[str, int], str] = {}


def _support_cases():
    return [pytest.param(case, periods, id=f"{case}-{periods}",
                         marks=[pytest.mark.xfail(reason=KNOWN_FAILURES[case, periods], strict=False)]
                         if (case, periods) in KNOWN_FAILURES else [])
            for case in CASES for periods in PERIODS]


@pytest.mark.parametrize("case, periods", _support_cases())
def test_right_support_in_most_draws(selection_outcomes, case, periods):
    """Exactly the true terms in at least 9 of 10 noise draws, at 50 and at 500 periods."""
    truth = CASES[case][2]
    outcomes = {seed: selection_outcomes(case, periods, seed)[0] for seed in SEEDS}
    wrong = {seed: f"+{sorted(s - truth)} -{sorted(truth - s)}" for seed, s in outcomes.items() if s != truth}
    assert len(SEEDS) - len(wrong) >= MIN_RIGHT, f"{case}, {periods} periods: wrong support in seeds {wrong}"


@pytest.mark.parametrize("case", list(CASES))
def test_law_error_does_not_grow_with_the_record(selection_outcomes, case):
    """The median law error over the draws at 500 periods is no larger than at 50."""
    medians = {P: float(np.median([selection_outcomes(case, P, seed)[1] for seed in SEEDS])) for P in PERIODS}
    assert medians[500] <= medians[50], f"{case}: median law error {medians} (fraction of the peak force)"

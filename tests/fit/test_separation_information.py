"""afmid's sigma of the rest separation against the record's information about it (the Cramér-Rao bound).

Issue 13: clean ideal-instrument records with d unknown at 50 periods miss the 1 % force target by the
separation's share. Is that the record's information, or does afmid's weak-form estimator throw some away? The
bound (tests/support/cramer_rao.py: the Fisher information of the record's harmonics, the force law's
parameters and the drive fitted alongside, no afmid code in the loop) answers it: measured on seeds 101-143
(docs/accuracy.md, "Is it the record or the estimator?"), afmid's sigma lies at 0.83-1.41x the bound
at 1 and 5 pm of detector noise; ``fit.max_harmonic`` 95, ``fit.smooth_periods`` 1 and
``fit.periods_per_block`` 2 change it by < 15 %.

Held here on seeds not used there (fixed before they were run), hidden_clean.yaml (DMT 2 GPa, 50 periods,
200 samples per period) at 1 pm and 5 pm of detector noise, where the bound (37 and 152 pm) is small against
the indentation (~0.5 nm), so the linear bound applies:

- no fit claims a sigma below half the bound (no unbiased estimator gets far under it: the bound ignores only
  the thermal wander of the amplitude between periods, which probes the law at slightly different
  indentations) or above twice it (an estimator that wastes 3/4 of the information);
- over the six fits the geometric mean of sigma / bound lies within 0.75-1.35: afmid's sigma is the larger of
  the chi-square width and a 12-group block jackknife (~20 % spread each, the max biased up by ~10 %), so the
  mean of six is ~1.1 +- 0.1 when the estimator is efficient and its sigma honest.
"""

from __future__ import annotations

import math

import pytest

from afmid.config import apply_overrides, build_config, parse_override, read_yaml
from cramer_rao import separation_bound
from repo_paths import REPO_ROOT, TEST_CONFIGS

pytestmark = [pytest.mark.numerics, pytest.mark.slow]

#: (detector noise m, seeds): fixed before the runs.
CASES = [(1e-12, (171, 172, 173)), (5e-12, (174, 175, 176))]
PER_FIT = (0.5, 2.0)
MEAN = (0.75, 1.35)


def _raw(noise: float, seed: int) -> dict:
    return apply_overrides(read_yaml(TEST_CONFIGS / "hidden_clean.yaml"),
                           [parse_override(o) for o in (f"simulate.noise.detector_rms={noise:.3g}",
                                                         f"simulate.seed={seed}", "fit.bootstrap=0")])


def test_the_bound_does_not_depend_on_the_seed_and_the_drive_costs_little():
    """The bound is a property of the operating point (the noise-free response and the noise levels), not of
    one realisation; fitting the drive's amplitude and phase (as afmid does) widens it, never narrows it."""
    first = separation_bound(_raw(1e-12, 1), REPO_ROOT)
    second = separation_bound(_raw(1e-12, 2), REPO_ROOT)
    assert first.sigma == pytest.approx(second.sigma, rel=1e-12)
    assert first.sigma_drive_known <= first.sigma <= 1.5 * first.sigma_drive_known
    assert 10e-12 < first.sigma < 100e-12  # tens of pm at 1 pm over 50 periods (measured 37 pm)


def test_the_separation_sigma_is_at_the_records_information():
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    rows = []
    for noise, seeds in CASES:
        bound = separation_bound(_raw(noise, seeds[0]), REPO_ROOT).sigma
        for seed in seeds:
            raw = _raw(noise, seed)
            trace = simulate(build_config(raw, source=REPO_ROOT / "x.yaml", base_dir=REPO_ROOT))
            fit_raw = dict(raw, sample=dict(raw["sample"], separation=None))
            est = run_fit(build_config(fit_raw, source=REPO_ROOT / "x.yaml", base_dir=REPO_ROOT),
                          trace=trace).nonlinear["d"]
            rows.append((noise, seed, est.sigma / bound, est.value - float(trace.truth.extra["separation"]), bound))
    detail = "\n".join(f"{1e12 * n:.0f} pm seed {s}: sigma / bound {r:.2f}, d error {1e12 * e:+.0f} pm, "
                       f"bound {1e12 * b:.0f} pm" for n, s, r, e, b in rows)
    ratios = [r for _, _, r, _, _ in rows]
    assert all(PER_FIT[0] <= r <= PER_FIT[1] for r in ratios), detail
    mean = math.exp(sum(math.log(r) for r in ratios) / len(ratios))
    assert MEAN[0] <= mean <= MEAN[1], detail

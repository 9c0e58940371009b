"""The rest separation with a decay length free (afmid.fit.joint_profile): a second valley found, d's interval
honest.

Unit: a residual with two valleys in (d, length), the fit's point in the higher one: the joint profile finds
the lower valley, and the half span of d's near-equal values covers both valleys when they are equal.

Accuracy (``slow``): the hidden-hydration samples of tests/diagnosis/test_diagnose.py (variants a-d: F_h 0.7-3
nN, lambda_h 0.6-1.5 nm, d 8-8.5 nm) fitted with ``[dmt, hydration]`` and the separation absent. Before: d
7.40 +- 0.22, 6.53 +- 0.22, 7.63 +- 0.24, 8.80 +- 0.024 nm on the variants' own seeds (4.9, 9.0, 3.6, 33 sigma
off: the one-at-a-time search ended in the valley of a short hydration length, and d's profile held it);
after: 1.8, 0.5, 0.3, 0.9 sigma (docs/accuracy.md). Held here on other seeds (151-154, fixed before they were
run): |d - d_true| < 2 sigma in at least 3 of 4 fits (0.99 when the sigma is honest) and < 3 sigma in all. Its
first run (the joint grid, d's sigma still the conditional one) failed with 2 of 4; with the profiled sigma
(afmid.fit.joint_profile.profiled_sigma) it passes. ~40 s CPU.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.fit.joint_profile import joint_separation_profile

pytestmark = [pytest.mark.numerics]


D_LOW = 6.5e-9 + 6 * 2.5e-9 / 8


def _two_valleys(depth_low: float):
    """rss(d, lam): a bowl at (6.5 nm, 0.3 nm) at 0 and one at (D_LOW, 1.0 nm) at -depth_low (s2 = 1): 10 units
    per 0.2 nm in d squared, 100 per 20 % in lam squared (narrow in the length at a given d, as measured on
    hydration b). D_LOW lies on the d grid from 6.5 nm (6 steps of 0.3125 nm), so both floors are sampled."""
    def rss(p):
        def bowl(d0, lam0, level):
            return level + 10 * ((p["d"] - d0) / 0.2e-9) ** 2 + 100 * (math.log(p["lam"] / lam0) / 0.2) ** 2
        return 1000.0 + min(bowl(6.5e-9, 0.3e-9, 0.0), bowl(D_LOW, 1.0e-9, -depth_low))
    return rss


def test_the_lower_valley_is_found_from_the_higher_one():
    rss = _two_valleys(5.0)
    start = {"d": 6.5e-9, "lam": 0.3e-9}
    found = joint_separation_profile(rss, start, {"d": (2e-9, 11e-9), "lam": (0.1e-9, 3e-9)})
    assert found.best["d"] == pytest.approx(D_LOW, abs=1e-15)
    assert found.best["lam"] == pytest.approx(1.0e-9, rel=0.2)
    assert found.best_rss < rss(start) - 1.0
    # the d grid's profile: each valley's floor reached at its own d (the length minimised there)
    i_low, i_high = np.argmin(np.abs(found.d - D_LOW)), np.argmin(np.abs(found.d - 6.5e-9))
    assert found.rss[i_low] < found.rss[i_high]


def test_equal_valleys_widen_the_interval_to_cover_both():
    rss = _two_valleys(0.0)
    start = {"d": 6.5e-9, "lam": 0.3e-9}
    found = joint_separation_profile(rss, start, {"d": (2e-9, 11e-9), "lam": (0.1e-9, 3e-9)})
    # both floors lie within one unit: the half span reaches from one valley to the other
    assert found.half_span(1.0, 6.5e-9, rss(start)) == pytest.approx(0.5 * (D_LOW - 6.5e-9), rel=1e-9)
    # one valley alone: nothing to widen beyond its own grid step
    alone = joint_separation_profile(_two_valleys(50.0), {"d": D_LOW, "lam": 1.0e-9}, {"d": (2e-9, 11e-9), "lam": (0.1e-9, 3e-9)})
    assert alone.half_span(1.0, D_LOW, alone.best_rss) == 0.0  # neighbours 0.31 nm away: 2.4 units up


HYDRATION_SEEDS = {"a": 151, "b": 152, "c": 153, "d": 154}


@pytest.mark.slow
def test_hydration_with_the_separation_unknown_is_covered_by_its_interval():
    from afmid.config import apply_overrides, build_config, parse_override, read_yaml
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate
    from repo_paths import REPO_ROOT, TEST_CONFIGS
    from tests.diagnosis.test_diagnose import VARIANTS

    rows = []
    for variant, seed in HYDRATION_SEEDS.items():
        raw = apply_overrides(read_yaml(TEST_CONFIGS / "hidden_hydration.yaml"),
                              [parse_override(o) for o in VARIANTS["hydration"][variant] + [f"simulate.seed={seed}"]])
        trace = simulate(build_config(raw, source=REPO_ROOT / "x.yaml", base_dir=REPO_ROOT))
        fit_raw = dict(raw, sample=dict(raw["sample"], separation=None),
                       model=dict(raw["model"], effects=["dmt", "hydration"]))
        est = run_fit(build_config(fit_raw, source=REPO_ROOT / "x.yaml", base_dir=REPO_ROOT),
                      trace=trace).nonlinear["d"]
        rows.append((variant, est.value - float(trace.truth.extra["separation"]), est.sigma))
    detail = "\n".join(f"{v}: d error {1e12 * e:+.0f} pm, sigma {1e12 * s:.0f} pm" for v, e, s in rows)
    ratios = [abs(e) / s if math.isfinite(s) and s > 0 else math.inf for _, e, s in rows]
    assert sum(r < 2 for r in ratios) >= 3, detail
    assert all(r < 3 for r in ratios), detail

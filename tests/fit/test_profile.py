"""The robust profile of a nonlinear parameter (afmid.fit.profile) and the coverage of the separation's sigma.

Unit tests: the minimum of a V-shaped profile (a kink, where a parabola through many points misplaces its
vertex), the chi-square interval of a parabolic profile, and the block jackknife on a synthetic nonlinear
regression with correlated noise (where the chi-square width is overconfident and the jackknife is not).

Coverage (``slow``): short simulated traces at three operating points (DMT 2 GPa, a stiff 50 GPa sample whose
profile is V-shaped, DMT + viscoelastic), 7 seeds each, fitted with the separation absent:
|d - d_true| < 2 sigma in at least 90 % of the 21 fits (19). Seeds and the threshold were fixed before these
seeds were run (scripts/separation_coverage.py measured other seeds; docs/accuracy.md, "Separation unknown").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.fit.profile import GroupedProfile, chi2_interval, local_minimum, robust_profile
from repo_paths import REPO_ROOT

# floating-point results compared; blas_sensitive: make test-kernels runs these again (BLAS/LAPACK on the path)
pytestmark = [pytest.mark.numerics, pytest.mark.blas_sensitive]


class _Curve:
    """A profile given as a function (no blocks: no jackknife), with GroupedProfile's protocol."""

    def __init__(self, f):
        self.f, self.full = f, {}

    def __call__(self, v):
        v = float(v)
        if v not in self.full:
            self.full[v] = self.f(v)
        return self.full[v]

    def points(self):
        x = np.array(sorted(self.full))
        return x, np.array([self.full[v] for v in x])

    def jackknife_groups(self):
        return 0


def test_minimum_of_a_v_shaped_profile_is_at_the_kink():
    """rss = 100 + 40 (x0 - x) / s below x0, 100 + 4 (x - x0) / s above (s2 = 1): an asymmetric V (the contact
    point of a stiff sample). A parabola through its points within 9 chi-square units puts the vertex ~0.5 s
    above the kink; the profile must find the kink, and its interval where the chi-square rises by 1."""
    x0, s = 8.4817e-9, 50e-12
    curve = _Curve(lambda x: 100.0 + (40.0 * (x0 - x) if x < x0 else 4.0 * (x - x0)) / s)
    found = robust_profile(curve, 8.43e-9, 0.3e-9, 1.0, jackknife=False)
    half = 0.5 * (s / 40 + s / 4)  # half the interval where the chi-square has risen by 1
    assert found.sigma_width == pytest.approx(half, rel=0.05)
    assert abs(found.value - x0) <= 0.2 * half  # the resolution is a tenth of the half-width
    assert found.sigma >= found.sigma_width


def test_symmetric_v_gets_a_sigma_at_least_its_chi2_width():
    x0, s = 8.4817e-9, 50e-12
    curve = _Curve(lambda x: 100.0 + 40.0 * abs(x - x0) / s)
    found = robust_profile(curve, 8.43e-9, 0.3e-9, 1.0, jackknife=False)
    assert found.sigma >= s / 40
    assert abs(found.value - x0) <= 0.1 * found.sigma


def test_interval_of_a_parabolic_profile_is_its_sigma():
    x0, sigma = 2.0e-9, 7e-12
    s2 = 3.0
    curve = _Curve(lambda x: 500.0 + s2 * ((x - x0) / sigma) ** 2)
    found = robust_profile(curve, 1.8e-9, 0.3e-9, s2, jackknife=False)
    assert found.sigma_width == pytest.approx(sigma, rel=0.02)
    assert found.value == pytest.approx(x0, abs=0.05 * sigma)


def test_profile_falling_to_a_bound_gets_a_one_sided_sigma_reaching_it():
    """The minimum on the lower bound: the chi-square (s2 = 1) rises by one unit at 1e-3 above it and never
    closes below it. The interval is [0, 1e-3], one-sided: sigma 1e-3 (was NaN: nothing was flagged)."""
    curve = _Curve(lambda x: 1e3 * x)  # falls towards the lower bound
    found = robust_profile(curve, 0.5, 0.1, 1.0, lo=0.0, hi=1.0, jackknife=False)
    assert found.value == pytest.approx(0.0, abs=1e-9)
    assert found.open_side == "below"
    assert found.sigma_width == pytest.approx(1e-3, rel=0.02)  # the closed side's crossing, linear interpolation
    assert found.sigma >= found.sigma_width


def test_a_profile_flat_down_to_the_window_edge_gets_a_sigma_reaching_the_edge():
    """The poor instrument's d profile (draw 31 of configs/coverage/poor.yaml): within 0.04 chi-square units of
    its minimum down to the searched window's lower edge, rising steeply above it. Here: minimum at 0.3, one
    unit reached 0.1 above it, and only 0.42 units at the bound -1.0 (1.3 below). The closed side alone (0.1)
    would be a tight wrong interval; the 1-sigma must reach the bound: 1.3 (+ the grid's resolution, at most a
    tenth of the 0.1-wide closed side, in quadrature: < 0.4 % of 1.3)."""
    curve = _Curve(lambda x: ((x - 0.3) / 0.1) ** 2 if x > 0.3 else ((x - 0.3) / 2.0) ** 2)
    found = robust_profile(curve, 0.35, 0.1, 1.0, lo=-1.0, hi=3.0, jackknife=False)
    assert found.open_side == "below"
    assert found.value == pytest.approx(0.3, abs=0.01)
    assert found.sigma == pytest.approx(1.3, rel=0.01)


def test_a_profile_flatter_than_one_unit_over_the_window_is_not_located():
    """0.1 x^2 on [-1, 2] with s2 = 1 stays below one unit everywhere: the data do not locate the parameter, and
    its 1-sigma is the larger distance from the estimate (0) to an edge of the window: 2."""
    curve = _Curve(lambda x: 0.1 * x * x)
    found = robust_profile(curve, 0.5, 0.1, 1.0, lo=-1.0, hi=2.0, jackknife=False)
    assert found.open_side == "both"
    assert found.sigma == pytest.approx(2.0 - found.value, abs=1e-9)
    assert abs(found.value) < 0.1


def test_a_profile_falling_without_a_bound_has_no_sigma():
    """No finite bound on the open side: no interval can be given, the sigma stays NaN."""
    curve = _Curve(lambda x: 1e3 * x)
    found = robust_profile(curve, 0.5, 0.1, 1.0, jackknife=False)
    assert math.isnan(found.sigma)


def test_the_open_side_is_warned_naming_the_edge():
    from afmid.fit.profile import open_side_warning

    curve = _Curve(lambda x: ((x - 0.3e-9) / 0.1e-9) ** 2 if x > 0.3e-9 else ((x - 0.3e-9) / 2e-9) ** 2)
    found = robust_profile(curve, 0.35e-9, 0.1e-9, 1.0, lo=-1e-9, hi=3e-9, jackknife=False)
    text = open_side_warning("d", "m", found, (-1e-9, 3e-9))
    assert "lower edge -1 nm" in text and "d undetermined on one side" in text
    closed = robust_profile(_Curve(lambda x: ((x - 1e-9) / 0.1e-9) ** 2), 0.9e-9, 0.3e-9, 1.0, lo=-1e-9, hi=3e-9,
                            jackknife=False)
    assert closed.open_side == "" and open_side_warning("d", "m", closed, (-1e-9, 3e-9)) is None


def test_local_minimum_stays_between_the_neighbours():
    x = np.array([0.0, 1.0, 2.0, 3.0])
    assert local_minimum(x, np.array([3.0, 1.0, 1.0, 3.0])) == pytest.approx(1.5)
    assert 1.0 <= local_minimum(x, np.array([5.0, 0.0, 4.0, 9.0])) <= 2.0
    lo, hi = chi2_interval(x, np.array([3.0, 1.0, 1.0, 3.0]), 1.0)
    assert lo == pytest.approx(0.5) and hi == pytest.approx(2.5)


def _synthetic_fit(theta_true: float, rho: float, seed: int, n_blocks: int = 24, rows: int = 25):
    """y = a g(t; theta) + b + AR(1) noise (coefficient rho) over n_blocks blocks of rows; returns the
    GroupedProfile over theta with (a, b) linear, and the white-noise residual variance at theta_true."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n_blocks * rows)
    e = np.empty_like(t)
    e[0] = rng.normal()
    for i in range(1, t.size):
        e[i] = rho * e[i - 1] + math.sqrt(1 - rho**2) * rng.normal()
    y = 2.0 * np.exp(-((np.mod(7 * t, 1.0) - theta_true) ** 2) / 0.02) + 0.3 + 0.05 * e

    def factors_at(theta):
        g = np.exp(-((np.mod(7 * t, 1.0) - theta) ** 2) / 0.02)
        A = np.column_stack([g, np.ones_like(t), y]).reshape(n_blocks, rows, 3)
        return A, t.size

    profile = GroupedProfile(factors_at, None)
    rss = profile(theta_true)
    return profile, rss / (t.size - 2)


@pytest.mark.parametrize("rho", [0.0, 0.95])
def test_block_jackknife_covers_the_truth_with_correlated_noise(rho):
    """Over 20 seeds: with white noise the chi-square width alone is right; with strongly correlated noise
    (rho 0.95: neighbouring rows nearly repeat, the white-noise width is several times too small) it is not,
    and the reported sigma (the larger of width and jackknife) still gives |error| < 2 sigma in >= 80 % (a
    jackknife of 12 groups is itself uncertain by ~20 %)."""
    inside_reported = inside_width = 0
    n = 20
    for seed in range(n):
        profile, s2 = _synthetic_fit(0.5, rho, seed)
        found = robust_profile(profile, 0.48, 0.05, s2, lo=0.3, hi=0.7)
        inside_reported += abs(found.value - 0.5) < 2 * found.sigma
        inside_width += abs(found.value - 0.5) < 2 * found.sigma_width
    assert inside_reported >= 0.8 * n
    if rho == 0.0:
        assert inside_width >= 0.8 * n
    else:
        assert inside_width < inside_reported  # the white-noise width alone is overconfident here


# --------------------------------------------------------------------------- coverage on simulated traces
COVERAGE_POINTS = [
    ("tests/configs/hidden_clean.yaml", "[dmt]", []),
    ("tests/configs/hidden_clean.yaml", "[dmt]", ["simulate.parameters.E_star=50e9"]),
    ("tests/configs/hidden_viscoelastic.yaml", "[dmt,viscoelastic]", []),
]
COVERAGE_SEEDS = (11, 12, 13, 14, 15, 16, 17)


@pytest.mark.slow
def test_separation_sigma_covers_the_truth():

    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    root = REPO_ROOT
    rows = []
    for path, effects, overrides in COVERAGE_POINTS:
        for seed in COVERAGE_SEEDS:
            common = [f"simulate.seed={seed}", "simulate.periods=20", "fit.bootstrap=0", "data.path=null"] + overrides
            trace = simulate(load_config(root / path, common))
            config = load_config(root / path, common + [f"model.effects={effects}", "sample.separation=null"])
            result = run_fit(config, trace=trace)
            est = result.nonlinear["d"]
            error = est.value - float(trace.truth.extra["separation"])
            rows.append((path, overrides, seed, error, est.sigma))
    covered = sum(abs(e) < 2 * s for *_, e, s in rows if math.isfinite(s))
    detail = "\n".join(f"{p} {o} seed {s}: d error {1e12 * e:+.1f} pm, sigma {1e12 * sg:.1f} pm"
                       for p, o, s, e, sg in rows)
    assert covered >= math.ceil(0.9 * len(rows)), detail


#: Issue 13's weaker cases, 50 periods each: the soft lever in liquid (Q 4; tests/configs/liquid.yaml, d 4 nm)
#: and the clean sample behind a declared 2-pole detector at 10 f0. Seeds and thresholds fixed before these
#: seeds were run (scripts/separation_coverage.py measured seeds 1-12: liquid 8/12 within 1 sigma, 12/12
#: within 2; detector 7/12 and 11/12). With an honest sigma, 12 fits fall within 2 sigma 10 or more times with
#: probability 0.98 (0.95 per fit, a little less with the jackknife's 11 degrees of freedom) and within
#: 1 sigma 5 or more times with probability 0.99 (0.68 per fit): a sigma 1.3x too small would give 0.84 and
#: 0.56 per fit (8.5 % and 30 % chances to pass both).
HARD_POINTS = [
    ("tests/configs/liquid.yaml", []),
    ("tests/configs/hidden_clean.yaml", ["data.detector={bandwidth: 3.0e6, filter: butterworth, order: 2}"]),
]
HARD_SEEDS = (21, 22, 23, 24, 25, 26)


@pytest.mark.slow
def test_separation_sigma_covers_the_truth_in_liquid_and_behind_a_declared_detector():
    from afmid.config import load_config
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    rows = []
    for path, overrides in HARD_POINTS:
        for seed in HARD_SEEDS:
            common = [f"simulate.seed={seed}", "simulate.periods=50", "fit.bootstrap=0", "data.path=null"] + overrides
            trace = simulate(load_config(REPO_ROOT / path, common))
            config = load_config(REPO_ROOT / path, common + ["model.effects=[dmt]", "sample.separation=null"])
            est = run_fit(config, trace=trace).nonlinear["d"]
            rows.append((path, seed, est.value - float(trace.truth.extra["separation"]), est.sigma))
    ratios = [abs(e) / s if math.isfinite(s) and s > 0 else math.inf for *_, e, s in rows]
    detail = "\n".join(f"{p} seed {s}: d error {1e12 * e:+.1f} pm, sigma {1e12 * sg:.1f} pm"
                       for p, s, e, sg in rows)
    assert sum(r < 2 for r in ratios) >= 10, detail
    assert sum(r < 1 for r in ratios) >= 5, detail

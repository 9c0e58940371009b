"""A nonlinear parameter's other valleys (afmid.fit.valleys): the interval covers what the data cannot rule out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.fit.profile import ProfileResult
from afmid.fit.search import NonlinearEstimate
from afmid.fit.valleys import (chi2_inflation, cover_other_valleys, covering_sigma, near_valleys, other_valleys,
                               separated_minima, Valley)

S2 = 1.0  # one chi-square unit of the residual
WIDTH = 0.02e-9  # each valley's 1-sigma half-width, m
HOME, AWAY = 0.08e-9, 0.5e-9  # the fit's valley and the other one, m
BASE = 4800.0


def double_well(rise: float):
    """A residual with valleys at HOME (BASE) and AWAY (BASE + rise chi-square units), a barrier between."""
    def rss(value: float) -> float:
        home = ((value - HOME) / WIDTH) ** 2
        away = ((value - AWAY) / WIDTH) ** 2 + rise
        return BASE + S2 * min(home, away, 40.0)
    return rss


def fake_profile(rss):
    """``profile(name, est)`` of the fit: the minimum of the valley holding params[name], its chi-square width."""
    def profile_at(params: dict, name: str) -> ProfileResult:
        centre = HOME if abs(params[name] - HOME) < abs(params[name] - AWAY) else AWAY
        grid = np.linspace(centre - 3 * WIDTH, centre + 3 * WIDTH, 61)
        values = np.array([rss(g) for g in grid])
        return ProfileResult(centre, WIDTH, WIDTH, math.nan, grid[1] - grid[0], grid, values, grid.size, S2)
    return profile_at


def estimate(rss) -> NonlinearEstimate:
    grid = np.geomspace(0.02e-9, 1.5e-9, 25)
    return NonlinearEstimate("hydration_length", HOME, WIDTH, "m", True, grid, np.array([rss(g) for g in grid]),
                             (0.02e-9, 1.5e-9), WIDTH, math.nan)


def run(rise: float):
    rss = double_well(rise)
    est, params, warnings = estimate(rss), {"hydration_length": HOME}, []
    profile_at = fake_profile(rss)
    found = profile_at(params, "hydration_length")
    moved = cover_other_valleys("hydration_length", est, found, params,
                                lambda name, est: profile_at(params, name), warnings)
    return est, params, warnings, moved


def test_an_equally_good_valley_is_covered_at_one_sigma():
    est, params, warnings, moved = run(rise=0.5)
    assert not moved and params["hydration_length"] == HOME
    # sqrt(0.5) < 1: the other valley sits at one sigma
    assert est.sigma == pytest.approx(AWAY - HOME)
    assert len(warnings) == 1 and "0.5 nm" in warnings[0] and "hydration_length" in warnings[0]


def test_a_valley_four_units_higher_sits_at_two_sigmas():
    est, _, warnings, moved = run(rise=4.0)
    assert not moved
    assert est.sigma == pytest.approx((AWAY - HOME) / 2.0)
    assert warnings


def test_a_valley_beyond_the_reach_changes_nothing():
    est, _, warnings, moved = run(rise=12.0)
    assert not moved and est.sigma == WIDTH and not warnings


def test_a_lower_valley_moves_the_fit_and_covers_the_first():
    est, params, warnings, moved = run(rise=-3.0)
    assert moved and params["hydration_length"] == AWAY and est.value == AWAY
    # the fit's first valley is now 3 units higher: at sqrt(3) sigmas
    assert est.sigma == pytest.approx((AWAY - HOME) / math.sqrt(3.0))
    assert warnings and "0.08 nm" in warnings[0]


def test_a_shoulder_without_a_barrier_is_no_second_valley():
    grid = np.linspace(0.0, 1.0, 21)
    values = np.where(grid < 0.5, 0.0, 0.3)  # flat within one unit: one wide valley, the profile's interval
    values = values + 0.01 * grid
    assert separated_minima(grid, values, 0.0, 9.0, 1.0) == []


def test_separated_minima_lowest_first_and_ends_count():
    grid = np.linspace(0.0, 10.0, 11)
    values = np.array([2.0, 5.0, 0.0, 5.0, 5.0, 1.0, 5.0, 5.0, 5.0, 5.0, 3.0])
    assert separated_minima(grid, values, 2.0, 9.0, 1.0) == [5.0, 0.0, 10.0]
    assert separated_minima(grid, values, 2.0, 2.5, 1.0) == [5.0, 0.0]


def test_inflation_from_the_jackknife():
    found = ProfileResult(1.0, 0.3, 0.1, 0.3, 0.0, np.zeros(1), np.zeros(1), 1, 1.0)
    assert chi2_inflation(found) == pytest.approx(9.0)
    found = ProfileResult(1.0, 0.1, 0.2, math.nan, 0.0, np.zeros(1), np.zeros(1), 1, 1.0)
    assert chi2_inflation(found) == 1.0  # never below one


def test_the_inflation_scales_the_rise():
    """With correlated rows (jackknife sigma 2x the chi-square width) a valley 4 raw units higher is 1 unit."""
    rss = double_well(4.0)
    profile_at = fake_profile(rss)
    params = {"x": HOME}
    found = profile_at(params, "x")
    found = ProfileResult(found.value, 2 * WIDTH, WIDTH, 2 * WIDTH, found.resolution, found.grid, found.values,
                          found.evaluations, S2)
    est = estimate(rss)

    def refine(start):
        return profile_at({"x": start}, "x")

    valleys = other_valleys(found, est.grid, est.objective, S2, refine)
    assert len(valleys) == 1 and valleys[0].rise == pytest.approx(1.0, rel=1e-6)
    assert covering_sigma(HOME, 2 * WIDTH, valleys) == pytest.approx(AWAY - HOME)


def test_covering_sigma_never_shrinks():
    assert covering_sigma(0.0, 5.0, [Valley(1.0, 0.0, 0.0)]) == 5.0
    assert covering_sigma(0.0, math.nan, [Valley(1.0, 0.0, 9.0)]) == pytest.approx(1.0 / 3.0)


def near_double_well(rise: float, barrier: float):
    """The fit's own profile points (as robust_profile leaves them, a grid step of WIDTH / 2): a valley at HOME
    and, 6 widths away, one ``rise`` units higher behind a barrier ``barrier`` units above the lowest."""
    away = HOME + 6 * WIDTH
    grid = np.linspace(HOME - 4 * WIDTH, away + 4 * WIDTH, 29)
    home = ((grid - HOME) / WIDTH) ** 2
    other = ((grid - away) / WIDTH) ** 2 + rise
    values = BASE + S2 * np.minimum(np.minimum(home, other), barrier)
    return ProfileResult(HOME, WIDTH, WIDTH, math.nan, WIDTH / 2, grid, values, grid.size, S2), away


def test_a_valley_among_the_profiles_own_points_is_covered():
    """The outer grid steps over a valley a few widths away (draw 9 of instrument.yaml): the profile's points
    show it; 3 units higher, it sits at sqrt(3) sigmas."""
    found, away = near_double_well(rise=3.0, barrier=6.0)
    valleys = other_valleys(found, np.linspace(0.02e-9, 1.5e-9, 3), np.full(3, BASE + 20.0), S2, lambda s: None)
    assert len(valleys) == 1
    assert valleys[0].value == pytest.approx(away, abs=1e-15) and valleys[0].rise == pytest.approx(3.0, rel=1e-9)
    assert covering_sigma(HOME, WIDTH, valleys) == pytest.approx((away - HOME) / math.sqrt(3.0))


def test_a_dip_on_the_flank_is_no_valley():
    """A point below its neighbours by less than one unit (the quadrature's small steps) is no second valley;
    nor is a valley more than REACH units up."""
    found, _ = near_double_well(rise=3.0, barrier=3.8)  # the barrier 0.8 units above the other minimum
    assert near_valleys(found, S2) == []
    found, _ = near_double_well(rise=10.0, barrier=20.0)
    assert near_valleys(found, S2) == []


def test_the_near_valley_follows_the_effective_unit():
    found, away = near_double_well(rise=4.0, barrier=12.0)
    valleys = near_valleys(found, 4.0 * S2)  # correlated rows: one effective unit is 4 raw ones
    assert len(valleys) == 1 and valleys[0].rise == pytest.approx(1.0, rel=1e-9)


# --------------------------------------------------------------------------- a model-limited fit
def model_limited(rise: float, misfit):
    """The fit's profile and estimate of a double well ``rise`` units apart, widened as a model-limited fit's."""
    from afmid.fit.valleys import cover_model_limited

    rss = double_well(rise)
    profile_at = fake_profile(rss)
    est, warnings = estimate(rss), []
    found = profile_at({"x": HOME}, "x")
    before = cover_model_limited("hydration_length", est, found, misfit, lambda start: profile_at({"x": start}, "x"),
                                 warnings)
    return est, before, warnings


def test_a_model_limited_fit_covers_the_valley_its_unphysical_law_cannot_rule_out():
    """The old behaviour: a valley 37.5 units higher is beyond the reach, the curvature sigma stays (draw 48 of
    instrument.yaml, seed 2804: 49 pm, d 1.7 nm off). A law with physical parameters loses 2339 units at the
    fit's minimum, so the other valley is one such a law prefers: it sits at one sigma."""
    from afmid.fit.valleys import Misfit

    est, params, warnings, moved = run(rise=37.5)
    assert not moved and est.sigma == WIDTH and not warnings  # what the fit reported before
    est, before, warnings = model_limited(37.5, Misfit(ratio=0.97, allowance=2339.0))
    assert before == WIDTH
    assert est.sigma == pytest.approx(AWAY - HOME)
    assert len(warnings) == 1 and "model-limited" in warnings[0] and "0.5 nm" in warnings[0]
    assert "2.34e+03 chi-square units" in warnings[0]


def test_a_model_limited_fit_scales_its_chi_square_by_the_misfit():
    """Error 2x the floor: the unit is 4x, so a valley 12 raw units higher (beyond the reach of 9) is 3 units
    higher and sits at sqrt(3) sigmas; the fit's own valley's sigma doubles."""
    from afmid.fit.valleys import Misfit

    est, _, warnings, _ = run(rise=12.0)
    assert est.sigma == WIDTH and not warnings
    est, before, warnings = model_limited(12.0, Misfit(ratio=2.0))
    assert before == WIDTH
    assert est.sigma == pytest.approx(max(2 * WIDTH, (AWAY - HOME) / math.sqrt(3.0)), rel=1e-9)
    assert warnings and "scaled by (error / floor)^2 = 4" in warnings[0]


def test_a_model_limited_fit_with_nothing_to_weigh_is_unchanged():
    """Error at its floor and no unphysical read-out (a contact-law probe's flag): a valley beyond the reach
    changes nothing, no warning."""
    from afmid.fit.valleys import Misfit

    est, before, warnings = model_limited(12.0, Misfit(ratio=0.9, allowance=0.0))
    assert est.sigma == before == WIDTH and not warnings


def test_the_allowance_is_the_residual_of_the_law_held_physical():
    """afmid.fit.pipeline.physical_allowance: the rise of the weighted residual when the unphysical read-out's
    source term is dropped, against the same least-squares fits done directly."""
    from types import SimpleNamespace

    import afmid.fit.regression as regression
    from afmid.fit.pipeline import physical_allowance

    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 40, 3))
    b = A @ np.array([1.0, -0.5, 0.2]) + 0.1 * rng.normal(size=(6, 40))
    system = SimpleNamespace(names=["dmt.vdw", "dmt.hertz", "drive_cos"],
                             T_blocks=regression.factor_blocks(A, b))
    hamaker = {"value": -1e-18, "error": 1e-19, "ci_low": -1.2e-18, "ci_high": -0.8e-18, "unit": "J",
               "effect": "dmt", "sources": ("vdw",), "determined": True}
    mask = np.ones(3, dtype=bool)
    state = SimpleNamespace(system=system, mask=mask, quantities={"hamaker": hamaker})
    flat_A, flat_b = A.reshape(-1, 3), b.ravel()
    full = np.sum((flat_b - flat_A @ np.linalg.lstsq(flat_A, flat_b, rcond=None)[0]) ** 2)
    kept = flat_A[:, 1:]
    without = np.sum((flat_b - kept @ np.linalg.lstsq(kept, flat_b, rcond=None)[0]) ** 2)
    assert physical_allowance(state) == pytest.approx(without - full, rel=1e-8)
    hamaker.update(value=5e-20, ci_low=3e-20, ci_high=7e-20)  # physical: nothing to allow
    assert physical_allowance(state) == 0.0

"""The model-limited threshold is the fit's own: the one-sided 99 % point of a right model's error / floor at the
floor's effective degrees of freedom (afmid.fit.forces.FoldErrors.floor_dof, afmid.fit.uncertainty.floor_threshold),
never above FLOOR_FACTOR."""

import math

import numpy as np
import pytest

from afmid.fit.forces import FoldErrors
from afmid.fit.uncertainty import FLOOR_FACTOR, FLOOR_QUANTILE, floor_threshold, model_limited


def test_the_threshold_is_the_chi_square_point_and_never_above_the_one_factor():
    assert floor_threshold(math.nan) == FLOOR_FACTOR and floor_threshold(0.5) == FLOOR_FACTOR
    # FLOOR_FACTOR is the 99 % point at nu = 13.5 (its own comment): the two agree to its two decimals
    assert floor_threshold(13.5) == pytest.approx(FLOOR_FACTOR, abs=0.006)
    assert floor_threshold(5.0) == FLOOR_FACTOR  # fewer degrees of freedom: capped
    # a different computation: the Wilson-Hilferty cube-root normal approximation of chi2's quantile, good to
    # ~0.1 % at nu >= 20 (z_0.99 = 2.3263)
    for nu in (20.0, 32.0, 80.0, 300.0):
        a = 2.0 / (9.0 * nu)
        wilson = nu * (1.0 - a + 2.326348 * math.sqrt(a)) ** 3
        assert floor_threshold(nu) == pytest.approx(math.sqrt(wilson / nu), rel=2e-3)
    assert floor_threshold(32.0) < floor_threshold(20.0) < FLOOR_FACTOR
    # the threshold decides, not the factor
    assert model_limited(1.35, 1.0, 32.0) and not model_limited(1.35, 1.0) and not model_limited(1.25, 1.0, 32.0)


def _fold_errors(sigmas: np.ndarray, harmonics: np.ndarray, residuals: np.ndarray) -> FoldErrors:
    errors = FoldErrors(harmonics)
    free = np.full(harmonics.size, 1e3)  # every row far above 3 sigma: all kept
    errors.add(free, free - residuals, sigmas, sigmas, np.ones(harmonics.size, dtype=bool))
    return errors


def test_equal_noise_rows_give_one_degree_of_freedom_each():
    harmonics = np.repeat(np.arange(1, 11), 2)  # cos and sin of 10 harmonics: 20 real rows
    errors = _fold_errors(np.full(20, 2.0), harmonics, np.zeros(20))
    assert errors.floor_dof == pytest.approx(20.0, rel=1e-12)


def test_a_right_models_error_over_floor_exceeds_the_threshold_about_once_in_a_hundred():
    """Residuals drawn with the rows' own noise (unequal, as the harmonics of a real record): the fraction of
    draws above the threshold is the threshold's tail probability. 20000 draws: the binomial sd of 1 % is 0.07 %;
    the Satterthwaite approximation moves the tail by a few tenths of a percent at these weights, so 0.5-1.6 %."""
    rng = np.random.default_rng(20261129)
    harmonics = np.repeat(np.arange(1, 16), 2)
    sigmas = np.repeat(np.geomspace(1.0, 0.3, 15), 2)  # noise falling with the harmonic, as through the operator
    nu = _fold_errors(sigmas, harmonics, np.zeros(30)).floor_dof
    assert 8.0 < nu < 30.0
    limit = floor_threshold(nu)
    assert limit < FLOOR_FACTOR - 0.05  # the fit's own threshold, not the cap
    ratios = []
    for _ in range(20000):
        errors = _fold_errors(sigmas, harmonics, rng.normal(0.0, sigmas))
        ratios.append(math.sqrt(errors.misfit / errors.noise))
    tail = float(np.mean(np.asarray(ratios) > limit))
    assert 0.005 < tail < 0.016, (tail, nu, limit)
    assert 1.0 - FLOOR_QUANTILE == pytest.approx(0.01)

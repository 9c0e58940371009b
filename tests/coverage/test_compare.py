"""z against the truth and the coverage counts (afmid.coverage.compare, afmid.coverage.summary) on hand-made cases:
the true read-outs are the DMT formulas at the simulated parameters, z is (estimate - truth) / the reported 1
sigma, the force curve's z is its RMS error over the reported band, the flags come from the fit's own marks,
and every fraction in the table is its count over n with Wilson's interval."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from afmid.coverage.compare import FORCE_CURVE, SEPARATION, compare, z_score
from afmid.coverage.summary import EXPECTED_1, EXPECTED_2, binomial_interval, summarize, table_text
from afmid.fit.separation_share import SEPARATION_LIMITED_TEXT
from afmid.io.trace import Truth
from afmid.physics.tips import SPHERE

H, E, R, A0 = 6.0e-20, 1.5e9, 10e-9, 0.165e-9
D_TRUE = 8.0e-9


def _quantity(value, error, effect="dmt", unit="", **extra):
    return {"value": value, "error": error, "ci_low": value - 2.5 * error, "ci_high": value + 2.5 * error,
            "unit": unit, "effect": effect, "model_limited": False, "determined": True, "plausible": True,
            "plausibility": "", **extra}


def _case(warnings=(), model_limited=False):
    adhesion = H * R / (6 * A0**2)
    truth_force = 1e-9 * np.sin(np.linspace(0, 6 * np.pi, 600))
    estimate = truth_force + 3e-11  # an RMS error of 3e-11 N everywhere
    estimate[:50] = np.nan  # samples the fit did not estimate
    quantities = {
        "hamaker": _quantity(H * 1.1, H * 0.05, unit="J"),  # z = +2
        "E_star": _quantity(E * 0.97, E * 0.03, unit="Pa"),  # z = -1
        "adhesion_force": _quantity(adhesion, adhesion * 0.1, unit="N"),  # z = 0
        "surface_energy": _quantity(math.nan, math.nan, unit="J/m^2", determined=False),
    }
    # the fit's run record (afmid.runfile.RunData), the fields compare reads
    result = SimpleNamespace(
        quantities=quantities, warnings=list(warnings), model_limited=model_limited, effects=["dmt"],
        nonlinear={"d": {"value": D_TRUE + 3e-11, "error": 2e-11, "unit": "m", "estimated": True}},
        force={"estimate": estimate}, force_total_uncertainty=0.02)
    truth = Truth(force=truth_force, separation=np.zeros(600), velocity=np.zeros(600), model="dmt",
                  effects=["dmt"], parameters={"hamaker": H, "E_star": E, "R": R, "a0": A0, "eps_r": 1.0},
                  units={}, extra={"separation": D_TRUE})
    return result, SimpleNamespace(truth=truth)


def test_z_of_every_number_against_the_hand_computed_truth():
    result, trace = _case()
    numbers = compare(result, trace, SPHERE, separation_given=False)
    adhesion = H * R / (6 * A0**2)
    truths = {"hamaker": H, "E_star": E, "adhesion_force": adhesion, "surface_energy": adhesion / (4 * math.pi * R)}
    for name, value in truths.items():
        assert numbers[name]["truth"] == pytest.approx(value, rel=1e-12), name
    assert numbers["hamaker"]["z"] == pytest.approx(2.0, rel=1e-9)
    assert numbers["E_star"]["z"] == pytest.approx(-1.0, rel=1e-9)
    assert numbers["adhesion_force"]["z"] == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(numbers["surface_energy"]["z"]) and "undetermined" in numbers["surface_energy"]["flags"]
    assert numbers["hamaker"]["in_ci95"] is True and numbers["hamaker"]["flags"] == []
    # the separation: (d - d_true) / sigma = 3e-11 / 2e-11
    assert numbers[SEPARATION]["z"] == pytest.approx(1.5, rel=1e-9)
    # the force curve: RMS error 3e-11 N over the estimated samples, band 2 % of the estimate's peak
    curve = numbers[FORCE_CURVE]
    peak = float(np.nanmax(np.abs(result.force["estimate"])))
    assert curve["estimate"] == pytest.approx(3e-11, rel=1e-9)
    assert curve["sigma"] == pytest.approx(0.02 * peak, rel=1e-12)
    assert curve["z"] == pytest.approx(3e-11 / (0.02 * peak), rel=1e-9)
    # told the separation, it is not a number of the draw
    assert SEPARATION not in compare(result, trace, SPHERE, separation_given=True)


def test_the_fits_own_marks_flag_every_number_of_the_draw():
    warning = "warning: " + SEPARATION_LIMITED_TEXT.format(sigma_nm=0.05, share=2.0, periods="80", now="20",
                                                           target=1.0)
    result, trace = _case(warnings=[warning], model_limited=True)
    numbers = compare(result, trace, SPHERE, separation_given=False)
    for name, record in numbers.items():
        assert {"model_limited", "separation_limited"} <= set(record["flags"]), name


def test_an_effect_the_simulation_did_not_have_reads_out_zero():
    result, trace = _case()
    result.quantities["viscosity"] = _quantity(5.0, 2.0, effect="viscoelastic", unit="Pa*s")
    numbers = compare(result, trace, SPHERE, separation_given=False)
    assert numbers["viscosity"]["truth"] == 0.0 and numbers["viscosity"]["z"] == pytest.approx(2.5)


def test_z_score_needs_a_positive_finite_sigma():
    assert z_score(3.0, 1.0, 0.5) == 4.0
    assert all(math.isnan(z_score(*args)) for args in [(1, 0, 0), (1, 0, -1), (math.nan, 0, 1), (1, 0, math.inf)])


def _draws(zs, flagged=()):
    return [{"index": i, "seed": 100 + i, "status": "ok",
             "numbers": {"E_star": {"z": z, "unit": "Pa", "flags": ["model_limited"] if i in flagged else [],
                                    "in_ci95": abs(z) < 1.96 if math.isfinite(z) else None}}}
            for i, z in enumerate(zs)] + [{"index": len(zs), "seed": 0, "status": "failed", "numbers": {}}]


def test_the_summary_counts_and_the_table_shows_count_over_n():
    zs = [0.5, -1.5, 2.5, 0.9, -0.2, 6.0, -7.0, math.nan]
    summary = summarize(_draws(zs, flagged={6}))[0]
    finite = np.array([z for z in zs if math.isfinite(z)])
    assert (summary.n, summary.missing, summary.flagged) == (7, 1, 1)
    assert (summary.within_1, summary.within_2) == (3, 4)
    assert summary.beyond_5_unflagged == 1  # 6.0; the -7.0 was flagged
    assert summary.rms_z == pytest.approx(math.sqrt(np.mean(finite**2)), rel=1e-12)
    assert summary.median_abs_z == pytest.approx(np.median(np.abs(finite)), rel=1e-12)
    assert [(d, s) for d, s, _ in summary.worst] == [(6, 106), (5, 105), (2, 102)]
    assert summary.in_ci95 == 4 and summary.n_ci95 == 7
    unflagged = summarize(_draws(zs, flagged={6}), unflagged_only=True)[0]
    assert (unflagged.n, unflagged.flagged, unflagged.within_2) == (6, 0, 4)
    row = table_text([summary], "title").splitlines()[2]
    low, high = binomial_interval(3, 7)
    assert f"{3 / 7:.2f} [{low:.2f}, {high:.2f}]" in row and f"{4 / 7:.2f} [" in row


@pytest.mark.parametrize("k, n", [(0, 10), (7, 10), (10, 10), (45, 50), (190, 200)])
def test_wilson_interval_is_the_score_formula(k, n):
    z = 1.959963984540054
    centre = (k + z * z / 2) / (n + z * z)
    half = z / (n + z * z) * math.sqrt(k * (n - k) / n + z * z / 4)
    low, high = binomial_interval(k, n)
    assert low == pytest.approx(max(0.0, centre - half), abs=1e-12)
    assert high == pytest.approx(min(1.0, centre + half), abs=1e-12)


def test_expected_fractions_are_the_normal_ones():
    assert EXPECTED_1 == pytest.approx(0.682689492, abs=1e-9) and EXPECTED_2 == pytest.approx(0.954499736, abs=1e-9)

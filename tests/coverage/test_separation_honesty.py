"""The estimated separation on the poor instrument and on a barely touching liquid record (issue 28): no
confident wrong d.

Draws 31 and 132 of configs/coverage/poor.yaml (seed 2803; 18-20 pm of detector noise, 50 samples per period, 50
periods). Before: draw 31's d profile stayed within 0.04 chi-square units of its minimum down to the searched
window's lower edge, so its chi-square interval did not close and its sigma was NaN: d 8.56 nm for a truth of
12.09, no separation share, no flag, and E* 0.11 GPa +- 11 MPa against 0.88 GPa (z -72), the force curve z +12.9.
Draw 132's d was 8.2 +- 1.8 nm (truth 11.2) and E*, which grows ever faster as d nears contact, was widened by its
change at d +- 1 sigma only: z -4.1. Now the one-sided interval reaches the window's edge
(afmid.fit.profile.robust_profile, ``open_side``). Each draw must come out with a finite d sigma and flagged
separation-limited (the record cannot locate d); draw 31's d, E* and force curve within 2 reported sigma of the truth
(it was |z| 72). Draw 132's E* stays at z -4.1: a read-out that bends with d is understated by the 1-sigma sides, and
counting the 2-sigma sides widened the accuracy suite's poor rows past their seed spread (docs/coverage.md); it is
flagged, and within the issue's |z| <= 5 for flagged numbers, which is what is asserted for it.

Draw 9 of configs/coverage/liquid.yaml (seed 2802; Q 7.4, d 4.05 nm at A0 4.65 nm, 0.5 nm indentation of a 53 MPa
sample, reported "the tip never touches"): the d profile has a broad valley at 3.1 nm (E* and H < 0) and the
truth's, 6.6 pm wide and ~650 chi-square units lower, which the outer search's 0.375 nm grid stepped over. The
fit refined the broad one and reported its local width: d 3.15 +- 0.039 nm, z -23, unflagged. afmid.fit.valleys
(the other minima of the outer grid refined, a lower one moves the fit) finds the truth's valley: z +0.14.
"""

from __future__ import annotations

import math

import pytest
import yaml
from repo_paths import REPO_ROOT

from afmid.config import build_config
from afmid.coverage.run import run_coverage

pytestmark = [pytest.mark.numerics, pytest.mark.slow]

POOR = REPO_ROOT / "configs" / "coverage" / "poor.yaml"
LIQUID = REPO_ROOT / "configs" / "coverage" / "liquid.yaml"


@pytest.fixture(scope="module")
def draws():
    config = build_config(yaml.safe_load(POOR.read_text()), source=POOR)
    return {d["index"]: d for d in run_coverage(config, only=[31, 132]).draws}


@pytest.mark.parametrize("index", [31, 132])
def test_a_separation_the_record_does_not_locate_gets_an_interval_and_a_flag(draws, index):
    draw = draws[index]
    assert draw["status"] == "ok", draw["error"]
    numbers = draw["numbers"]
    separation = numbers["separation"]
    assert math.isfinite(separation["sigma"]) and separation["sigma"] > 0
    for name in ("separation", "E_star", "force_curve"):
        assert abs(numbers[name]["z"]) <= (2.0 if index == 31 or name != "E_star" else 5.0), (name, numbers[name])
        assert "separation_limited" in numbers[name]["flags"], (name, numbers[name])


def test_the_open_side_of_the_separation_is_named(draws):
    warnings = draws[31]["warnings"]
    assert any("d undetermined on one side" in w and "lower edge" in w for w in warnings), warnings


def test_a_barely_touching_liquid_record_is_fitted_in_the_truths_valley():
    config = build_config(yaml.safe_load(LIQUID.read_text()), source=LIQUID)
    draw = run_coverage(config, only=[9]).draws[0]
    assert draw["status"] == "ok", draw["error"]
    for name in ("separation", "E_star", "hamaker", "force_curve"):
        number = draw["numbers"][name]
        assert abs(number["z"]) <= 2.0, (name, number)

"""A force map's values per group and "not selected" (afmid.report.map_values, issue 33) on a small hand-made
result file: which pixels selected a term of a parameter's effect (from /maps/selected and /model/terms), and the
cells the page shows."""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest

from afmid.report.map_values import group_values, selected_maps, stats_text, term_belongs_to, value_stats


@pytest.fixture()
def result(tmp_path):
    path = tmp_path / "result.h5"
    with h5py.File(path, "w") as h5:
        h5.create_dataset("model/terms", data=np.array([b"dmt.vdw", b"dmt.hertz", b"viscoelastic.kelvin_voigt"]))
        # bit 2 (the viscous term) selected at the right column only; dmt's terms everywhere.
        selected = np.array([[3, 3, 7], [3, 3, 7]])
        h5.create_dataset("maps/selected", data=selected).attrs["units"] = "1"
        for name, effect, unit in (("E_star", "dmt", "Pa"), ("viscosity", "viscoelastic", "Pa*s")):
            ds = h5.create_dataset(f"maps/{name}", data=np.zeros((2, 3)))
            ds.attrs["units"], ds.attrs["effect"] = unit, effect
    return path


def test_a_parameter_is_selected_where_a_term_of_its_effect_is(result):
    chosen = selected_maps(result, ["E_star", "viscosity"])
    assert chosen["E_star"].all()
    np.testing.assert_array_equal(chosen["viscosity"], [[False, False, True], [False, False, True]])
    assert term_belongs_to("dmt.hertz", "dmt") and not term_belongs_to("dmt_viscoelastic.x", "dmt")


def test_an_unselected_term_reads_not_selected_and_a_partly_selected_one_says_where():
    values = np.array([[0.0, 0.0, 40.0], [0.0, 0.0, 42.0]])  # read_out gives 0 where the term is not selected
    sigma = np.full((2, 3), 1.0)
    everywhere = np.ones((2, 3), bool)
    right = np.array([[False, False, True], [False, False, True]])
    none = value_stats(values, sigma, everywhere, np.zeros((2, 3), bool), "Pa*s")
    assert none["selected_pixels"] == 0 and math.isnan(none["median"]) and stats_text(none) == "not selected"
    part = value_stats(values, sigma, everywhere, right, "Pa*s")
    assert part["median"] == pytest.approx(41.0, rel=1e-12)  # of 40 and 42 only: the zeros are not values
    assert stats_text(part).endswith("selected at 2 of 6 pixels") and "median 0" not in stats_text(part)
    one = value_stats(values, sigma, everywhere, right & np.array([[True], [False]]), "Pa*s")
    # one pixel is no group: its value is said to be that pixel's, without a median or a 16-84 % spread
    assert stats_text(one) == "40 Pa s ± 1 (1 sigma) at that one pixel only, not a group value; selected at 1 of 6 pixels"


def test_values_per_group_are_each_groups_own():
    """A bimodal map: the whole-map median lies between the phases, each group's is its phase's."""
    e_star = np.array([[2.0e9, 2.0e9, 0.35e9], [2.0e9, 0.35e9, 0.35e9]])
    maps = {"E_star": (e_star, "Pa", ""), "E_star_sigma": (np.full((2, 3), 1e7), "Pa", "1 sigma")}
    labels = (e_star < 1e9).astype(int)
    groups = {"labels": labels, "groups": [{"group": 1}, {"group": 2}]}
    out = group_values(maps, ["E_star"], groups, {"E_star": np.ones((2, 3), bool)}, np.ones((2, 3), bool))
    assert [g["values"]["E_star"]["median"] for g in out] == pytest.approx([2000.0, 350.0], rel=1e-12)
    assert [g["values"]["E_star"]["pixels"] for g in out] == [3, 3]
    assert group_values(maps, ["E_star"], None, {}, np.ones((2, 3), bool)) == []

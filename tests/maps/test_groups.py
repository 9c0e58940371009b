"""The grouping of a map's pixels (afmid.maps.groups) and the group verdicts' wording
(afmid.maps.group_diagnosis) on constructed inputs: no fit. Seeds and thresholds fixed before the first run."""

from __future__ import annotations

import math

import numpy as np
import pytest

import afmid.maps.groups as groups
from afmid.maps.group_diagnosis import NOTHING, UNEXPLAINED, GroupVerdict, pixel_verdict, summary_sentence


def constructed_maps(rng: np.random.Generator, shape=(6, 6), hidden: bool = True) -> tuple[dict, np.ndarray]:
    """Flat maps of a matrix at its noise floor and a square domain (rows 1-3, cols 1-3) with another E* and,
    when ``hidden``, a dissipative residual 6x its floor; the domain's mask."""
    n = shape[0] * shape[1]
    domain = np.zeros(shape, bool)
    domain[1:4, 1:4] = True
    domain = domain.ravel()
    ratio = rng.normal(1.0, 0.05, n)
    snr = np.exp(rng.normal(0.0, 0.3, n))
    character = np.zeros(n, int)
    share = rng.uniform(0, 1, n)
    if hidden:
        ratio[domain] = rng.normal(6.0, 0.5, domain.sum())
        snr[domain] = rng.normal(12.0, 1.0, domain.sum())
        character[domain] = 2
        share[domain] = rng.normal(0.8, 0.03, domain.sum())
    e_star = np.where(domain, 0.35e9, 2.0e9) * rng.normal(1.0, 0.04, n)
    hamaker = rng.normal(5e-20, 0.3e-20, n)
    maps = {"cv_error": 0.05 * ratio, "cv_error_noise_floor": np.full(n, 0.05), "residual_snr": snr,
            "residual_character": character, "residual_dissipative_share": share, "E_star": e_star,
            "hamaker": hamaker, "adhesion_force": 2.5e10 * hamaker, "residual_region": np.zeros(n, int),
            "E_star_sigma": 0.04 * e_star, "hamaker_sigma": np.full(n, 0.3e-20), "adhesion_force_sigma": np.full(n, 0.75e-10)}
    return maps, domain


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("hidden", [True, False])
def test_two_phases_make_two_groups_matching_the_phases(seed, hidden):
    maps, domain = constructed_maps(np.random.default_rng(seed), hidden=hidden)
    fitted = np.ones(domain.size, bool)
    grouping = groups.group_pixels(maps, ["E_star", "hamaker", "adhesion_force"], fitted, (6, 6), seed=seed)
    assert grouping.n_groups == 2 and grouping.silhouette >= groups.MIN_SILHOUETTE
    labels = grouping.labels.ravel()
    assert len(set(labels[domain])) == 1 and len(set(labels[~domain])) == 1 and labels[domain][0] != labels[~domain][0]
    assert labels[~domain][0] == 0  # numbered by size: the matrix (27 pixels) first
    # the adhesion force is a fixed multiple of the Hamaker constant: counted once
    assert "hamaker" in grouping.feature_names and "adhesion_force" not in grouping.feature_names


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_phase_at_its_noise_floor_is_one_group(seed):
    rng = np.random.default_rng(seed)
    maps, domain = constructed_maps(rng, hidden=False)
    maps["E_star"] = 2.0e9 * rng.normal(1.0, 0.04, domain.size)  # no domain: every pixel alike
    grouping = groups.group_pixels(maps, ["E_star", "hamaker"], np.ones(domain.size, bool), (6, 6), seed=seed)
    assert grouping.n_groups == 1 and math.isnan(grouping.silhouette)


def test_unfitted_pixels_have_no_group_and_representatives_are_nearest_the_centre():
    maps, domain = constructed_maps(np.random.default_rng(4))
    fitted = np.ones(domain.size, bool)
    fitted[[0, 7]] = False  # pixel 7 lies in the domain
    grouping = groups.group_pixels(maps, ["E_star"], fitted, (6, 6))
    assert grouping.labels.ravel()[0] == -1 and grouping.labels.ravel()[7] == -1
    g = int(grouping.labels.ravel()[8])
    chosen = groups.representatives(grouping, g, 3)
    members = np.flatnonzero(grouping.labels.ravel() == g)
    assert len(chosen) == 3 and set(chosen) <= set(members)
    rows = {p: i for i, p in enumerate(grouping.pixels)}
    distance = {p: float(((grouping.features[rows[p]] - grouping.centres[g]) ** 2).sum()) for p in members}
    assert max(distance[p] for p in chosen) <= min(distance[p] for p in members if p not in chosen)


def test_no_fitted_pixel_gives_no_group():
    maps, domain = constructed_maps(np.random.default_rng(5))
    grouping = groups.group_pixels(maps, ["E_star"], np.zeros(domain.size, bool), (6, 6))
    assert grouping.n_groups == 0 and np.all(grouping.labels == -1)


def test_silhouette_of_two_pairs_by_hand():
    # 1-D points 0, 1 | 10, 12: point 0: a = 1, b = (10 + 12) / 2 = 11 -> 10/11; point 1: a = 1, b = 10 -> 9/10;
    # point 10: a = 2, b = (10 + 9) / 2 = 9.5 -> 7.5/9.5; point 12: a = 2, b = (12 + 11) / 2 = 11.5 -> 9.5/11.5
    x = np.array([[0.0], [1.0], [10.0], [12.0]])
    want = np.mean([10 / 11, 9 / 10, 7.5 / 9.5, 9.5 / 11.5])
    assert groups.silhouette(x, np.array([0, 0, 1, 1])) == pytest.approx(want, rel=1e-12)


def test_pixel_verdicts_from_diagnosis_summaries():
    assert pixel_verdict({"missing_effect": False}) == (NOTHING, [])
    named = {"missing_effect": True, "diagnosis": {"explained_by_catalog": True},
             "suggestions": [{"effect": "viscoelastic"}]}
    assert pixel_verdict(named) == ("missing: viscoelastic", ["viscoelastic"])
    partial = {"missing_effect": True, "diagnosis": {"explained_by_catalog": False},
               "suggestions": [{"effect": "viscoelastic"}]}
    assert pixel_verdict(partial) == (UNEXPLAINED, [])
    undecided = {"missing_effect": True, "diagnosis": {"explained_by_catalog": False}, "suggestions": [],
                 "undecided": [{"effect": "viscoelastic"}, {"effect": "exponential_damping"}]}
    assert pixel_verdict(undecided) == ("cannot decide: viscoelastic or exponential_damping", [])
    instrument = {"missing_effect": True, "suggestions": [],
                  "diagnosis": {"explained_by_catalog": False, "instrument": {"kind": "detector_lowpass"}}}
    assert pixel_verdict(instrument) == ("instrument: detector_lowpass", [])


def test_the_map_sentence_names_the_effect_and_where():
    verdicts = [GroupVerdict(0, 24, 24 / 36, 1.0, [], NOTHING, False),
                GroupVerdict(1, 12, 12 / 36, 6.4, ["viscoelastic"], "missing: viscoelastic", True,
                             [3, 4, 5], ["missing: viscoelastic"] * 3, [-4600.0, -4400.0, -4500.0], [0.06] * 3,
                             [0.05] * 3, region="contact", character="dissipative")]
    assert summary_sentence(verdicts) == ("viscoelastic missing in group 2 (33 % of the pixels); "
                                          "nothing missing elsewhere")
    sentence = verdicts[1].sentence()
    assert "viscoelastic missing (3 of 3 representative pixels; ΔBIC -4600 .. -4400" in sentence
    assert "1.20x the floor" in sentence and "dissipative" in sentence
    assert summary_sentence(verdicts[:1]) == "nothing missing anywhere on the map"


def test_the_leading_candidate_when_no_verdict_has_a_majority():
    from afmid.maps.group_diagnosis import LEADING, leading_candidate

    assert leading_candidate({"suggestions": [], "undecided": [{"effect": "viscoelastic", "delta_bic": -4400.0}]}) == {
        "effect": "viscoelastic", "delta_bic": -4400.0}
    assert leading_candidate({"missing_effect": False}) is None
    v = GroupVerdict(1, 12, 12 / 36, 6.4, ["viscoelastic"], LEADING + "viscoelastic", True, [13, 19, 8],
                     ["cannot decide: viscoelastic or contact_damping", UNEXPLAINED, "missing: viscoelastic"],
                     [-4380.0, -4375.0, -4391.0], [0.055, 0.065, 0.077], [0.059, 0.056, 0.063],
                     leading=["viscoelastic"] * 3)
    sentence = v.sentence()
    assert "viscoelastic the leading candidate (3 of 3 representative pixels rank it first" in sentence
    assert "cannot decide: viscoelastic or contact_damping" in sentence and UNEXPLAINED in sentence
    assert summary_sentence([v]).startswith("viscoelastic the leading candidate in group 2 (33 % of the pixels)")


def test_a_settled_group_verdict_is_the_verdict_of_all_three_representatives():
    """issue 31: the third representative is skipped when the first two settle the verdict. Over every outcome of
    three representatives (verdicts and leading candidates from the kinds a diagnosis gives), wherever
    verdict_settled says the first two settle it, majority() of the two equals majority() of the three."""
    import itertools

    from afmid.maps.group_diagnosis import NOTHING, UNEXPLAINED, majority, verdict_settled

    outcomes = [("missing: viscoelastic", "viscoelastic"), ("missing: capillary", "capillary"),
                ("missing: viscoelastic + capillary", "viscoelastic"), (NOTHING, ""), (UNEXPLAINED, ""),
                (UNEXPLAINED, "viscoelastic"), ("cannot decide: viscoelastic or contact_damping", "viscoelastic"),
                ("cannot decide: viscoelastic or contact_damping", "contact_damping"), ("instrument: filter", "")]
    settled = 0
    for a, b, c in itertools.product(outcomes, repeat=3):
        if verdict_settled([a[0], b[0]], [a[1], b[1]], 3):
            settled += 1
            assert majority([a[0], b[0]], [a[1], b[1]]) == majority([a[0], b[0], c[0]], [a[1], b[1], c[1]]), (a, b, c)
        else:
            assert not (a == b), "two identical outcomes settle a group of three"
    assert settled == len(outcomes) * len(outcomes)  # exactly the 9 pairs a == b, each with any of the 9 thirds
    assert not verdict_settled(["missing: viscoelastic"], ["viscoelastic"], 3)  # one of three is no majority
    assert verdict_settled(["missing: viscoelastic"], ["viscoelastic"], 1)

"""The pixel fits of ``afmid map`` (afmid.maps.pixel_fit), in-process (no dask): the default ``shared`` fit against the
``full`` fit (every pixel as ``afmid fit``) and against the simulator's truth per phase, its covariance intervals
and separation search on their own, and a pixel that the shared support does not fit flagged suspect.

Maps: tests/configs/map_small.yaml (3x3, a glassy matrix and a soft domain 1 nm higher) for two simulator seeds.
Tolerances were fixed before the first run.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from afmid.fit.orchestration import covariance_draws
from afmid.maps.pixel_fit import (ROUTE_ANCHOR, ROUTE_FULL, ROUTE_RESEARCHED, ROUTES,
                                parabolic_minimum)
from afmid.maps.task import STATUS_SUSPECT, fit_chunk
from repo_paths import REPO_ROOT

REPO = REPO_ROOT
CONFIG = REPO / "tests" / "configs" / "map_small.yaml"
SEEDS = (7, 8)
#: Per pixel: shared vs full separation within this many of the full fit's sigma, E* within this many sigma.
SEPARATION_AGREEMENT = 1.0
E_STAR_AGREEMENT = 1.0
#: Median over a map of the shared fit's E* sigma / the full fit's bootstrap sigma (5 resamples: a noisy spread).
SIGMA_RATIO = (0.5, 2.0)
#: Per phase: the shared fit's median E* error may exceed the full fit's by at most this (relative).
NOT_WORSE = 0.02
#: Mean library evaluations of a carried (not anchor) pixel; the full fit needs ~90.
MAX_EVALUATIONS = 20


def simulate_map(folder: Path, seed: int, changes: dict | None = None) -> tuple[Path, Path]:
    from afmid.config import build_config, dump_config
    from afmid.maps.simulate import simulate_map as simulate, write_map_file

    raw = yaml.safe_load(CONFIG.read_text())
    raw["simulate"]["seed"] = seed
    for key, value in (changes or {}).items():
        section, name = key.split(".", 1)
        raw[section][name] = value
    config = build_config(raw, source=folder / "run.yaml")
    (folder / "run.yaml").write_text(dump_config(config))
    path = folder / f"map_{seed}.h5"
    write_map_file(path, simulate(config), dump_config(config))
    return folder / "run.yaml", path


def fit_map(config: Path, path: Path, pixel_fit: str, chunk: int = 9) -> dict:
    import h5py

    with h5py.File(path, "r") as h5:
        n = h5["deflection"].shape[0] * h5["deflection"].shape[1]
    parts = [fit_chunk({"input": str(path), "config": config.read_text(), "source": str(config), "first": lo,
                        "stop": min(n, lo + chunk), "pixel_fit": pixel_fit}) for lo in range(0, n, chunk)]
    out = {k: np.concatenate([p[k] for p in parts]) for k in ("separation", "separation_sigma", "status", "route",
                                                              "evaluations", "cv_error", "cv_error_noise_floor")}
    out["message"] = sum((p["message"] for p in parts), [])
    for name in ("E_star", "hamaker"):
        if name not in parts[0]["names"]:
            continue
        out[name] = np.concatenate([p["values"][p["names"].index(name)] for p in parts])
        out[name + "_sigma"] = np.concatenate([p["sigmas"][p["names"].index(name)] for p in parts])
    return out


def truth_of(path: Path) -> dict:
    import h5py

    with h5py.File(path, "r") as h5:
        return {name: h5["truth"][name][()].ravel() for name in ("phase", "E_star", "hamaker", "separation")}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    runs = []
    for seed in SEEDS:
        folder = tmp_path_factory.mktemp(f"pixels{seed}")
        config, path = simulate_map(folder, seed)
        runs.append((truth_of(path), fit_map(config, path, "shared"), fit_map(config, path, "full")))
    return runs


@pytest.mark.slow
def test_shared_pixels_agree_with_full_fits(fitted):
    for _, shared, full in fitted:
        assert np.all(shared["status"] < 2) and np.all(full["status"] < 2), (shared["message"], full["message"])
        assert np.all(full["route"] == ROUTE_FULL)
        assert shared["route"][0] == ROUTE_ANCHOR
        d_sigma = np.maximum(full["separation_sigma"], shared["separation_sigma"])
        assert np.all(np.abs(shared["separation"] - full["separation"]) < SEPARATION_AGREEMENT * d_sigma)
        diff = np.abs(shared["E_star"] - full["E_star"])
        assert np.all(diff < E_STAR_AGREEMENT * full["E_star_sigma"]), diff / full["E_star_sigma"]
        ratio = np.median(shared["E_star_sigma"] / full["E_star_sigma"])
        assert SIGMA_RATIO[0] < ratio < SIGMA_RATIO[1], ratio
        carried = shared["route"] != ROUTE_ANCHOR
        assert shared["evaluations"][carried].mean() < MAX_EVALUATIONS, shared["evaluations"]


@pytest.mark.slow
def test_shared_pixels_are_as_accurate_as_full_fits_per_phase(fitted):
    for truth, shared, full in fitted:
        for phase in np.unique(truth["phase"]):
            px = truth["phase"] == phase
            want = truth["E_star"][px][0]
            err_shared = abs(np.median(shared["E_star"][px]) / want - 1)
            err_full = abs(np.median(full["E_star"][px]) / want - 1)
            assert err_shared <= err_full + NOT_WORSE, (phase, err_shared, err_full)


def test_a_chunk_of_one_pixel_is_its_own_anchor_and_agrees_with_a_carried_chunk(fitted, tmp_path):
    config, path = simulate_map(tmp_path, SEEDS[0])
    one = fit_map(config, path, "shared", chunk=1)
    assert np.all(one["route"] == ROUTE_ANCHOR)
    _, carried, _ = fitted[0]
    d_sigma = np.maximum(one["separation_sigma"], carried["separation_sigma"])
    assert np.all(np.abs(one["separation"] - carried["separation"]) < SEPARATION_AGREEMENT * d_sigma)


@pytest.mark.slow
def test_pixels_the_shared_support_does_not_fit_are_researched_and_flagged(tmp_path):
    """A model without contact mechanics (lennard_jones) on the blend: the soft domain's pixels, indented deepest,
    stand above their noise floor; every such pixel is searched again and reported suspect (model-limited), and
    no pixel at its floor is called model-limited."""
    from afmid.fit.uncertainty import FLOOR_FACTOR

    config, path = simulate_map(tmp_path, SEEDS[0], {"model.effects": ["lennard_jones"]})
    out = fit_map(config, path, "shared")
    limited = out["cv_error"] > FLOOR_FACTOR * out["cv_error_noise_floor"]
    soft = truth_of(path)["phase"] == 1
    assert limited[soft].all(), out["message"]
    for i in range(limited.size):
        assert ("model-limited" in out["message"][i]) == bool(limited[i]), (i, out["message"][i])
        if limited[i]:
            assert out["status"][i] == STATUS_SUSPECT
            assert out["route"][i] in (ROUTE_RESEARCHED, ROUTE_ANCHOR), out["route"]
    assert ROUTES[ROUTE_RESEARCHED].startswith("shared")


def test_covariance_draws_follow_the_least_squares_covariance():
    """Columns of very different scales (as SI library columns are); 4,000 draws: the spread's relative
    sampling error is 1/sqrt(2 n) = 1.1 %, so 5 % is four of those."""
    rng = np.random.default_rng(3)
    n_rows, scales = 400, np.array([1e-20, 1.0, 1e5])
    A = rng.standard_normal((n_rows, 3)) * scales
    y = A @ (1 / scales) + rng.standard_normal(n_rows)
    T = np.linalg.qr(np.column_stack([A, y]), mode="r")
    mask = np.array([True, True, True])
    coef = np.linalg.lstsq(A / scales, y, rcond=None)[0] / scales
    rss = float(np.sum((y - A @ coef) ** 2))
    s2 = rss / (n_rows - 3)
    want = np.sqrt(np.diag(s2 * np.linalg.inv((A / scales).T @ (A / scales)))) / scales
    draws = covariance_draws(T, coef, mask, rss, n_rows, 4000, np.random.default_rng(4))
    np.testing.assert_allclose(draws.std(axis=0, ddof=1), want, rtol=0.05)
    assert np.all(np.abs(draws.mean(axis=0) - coef) < 4 * want / math.sqrt(4000))
    # a column outside the support gets no spread
    partial = covariance_draws(T, coef, np.array([True, False, True]), rss, n_rows, 10, rng)
    assert np.all(partial[:, 1] == coef[1])


class _Profile:
    """A GroupedProfile over a synthetic problem: y = 2 g(t; d0) + noise, one column g(t; d) = 1 / (1 + (t - d)^2)."""

    def __init__(self):
        from afmid.fit.profile import GroupedProfile

        rng = np.random.default_rng(5)
        self.t = np.linspace(-5, 5, 2400).reshape(24, 100)
        self.y = 2 / (1 + (self.t - 0.3) ** 2) + 0.05 * rng.standard_normal(self.t.shape)
        self.calls = 0

        def factors_at(d):
            self.calls += 1
            g = 1 / (1 + (self.t - d) ** 2)
            from afmid.fit.regression import factor_blocks

            return factor_blocks(g[..., None], self.y), self.t.size

        self.profile = GroupedProfile(factors_at, None)


def test_parabolic_minimum_agrees_with_the_robust_profile():
    from afmid.fit.profile import robust_profile

    fast = _Profile()
    found = parabolic_minimum(fast.profile, 0.25, 0.01, -2.0, 2.0, 1)
    slow = _Profile()
    s2 = slow.profile(0.25) / (slow.t.size - 1)
    ref = robust_profile(slow.profile, 0.25, 0.3, s2, -2.0, 2.0, jackknife=True)
    assert found is not None
    assert abs(found.value - ref.value) < 0.1 * ref.sigma, (found, ref)
    assert abs(found.sigma / ref.sigma - 1) < 0.25, (found, ref)
    assert fast.calls < slow.calls


def test_parabolic_minimum_from_a_neighbours_curvature():
    """Started with the profile curvature of a neighbour (afmid.maps.pixel_fit.predicted_third_point): the same
    minimum and sigma as the robust profile (tolerances of the test above), within four evaluations when the
    neighbour's curvature is within 25 % of the pixel's own and its start within 2.5 sigma (two points, the predicted
    vertex, at most one correction), fewer in all than the plain bracket from the same starts; a curvature far off
    or a start far away (another phase) falls back to the bracket and still finds the minimum."""
    from afmid.fit.profile import robust_profile

    slow = _Profile()
    s2 = slow.profile(0.25) / (slow.t.size - 1)
    ref = robust_profile(slow.profile, 0.25, 0.3, s2, -2.0, 2.0, jackknife=True)
    own = parabolic_minimum(_Profile().profile, 0.25, 0.01, -2.0, 2.0, 1).curvature
    assert own > 0
    near = [(offset, scale) for offset in (-2.5, -1.5, -1.0, 0.7, 1.5, 2.5) for scale in (0.8, 1.0, 1.25)]
    calls = {"curvature": 0, "bracket": 0}
    for offset, scale in near + [(1.5, 10.0), (1.5, 0.1), (20.0, 1.0)]:
        for way, curvature in (("curvature", scale * own), ("bracket", None)):
            fast = _Profile()
            found = parabolic_minimum(fast.profile, ref.value + offset * ref.sigma, ref.sigma, -2.0, 2.0, 1,
                                      curvature=curvature)
            assert found is not None, (offset, scale, way)
            assert abs(found.value - ref.value) < 0.1 * ref.sigma, (offset, scale, way, found, ref)
            assert abs(found.sigma / ref.sigma - 1) < 0.25, (offset, scale, way, found, ref)
            if (offset, scale) in near:
                calls[way] += fast.calls
                assert way == "bracket" or fast.calls <= 4, (offset, scale, fast.calls)
    assert calls["curvature"] < calls["bracket"], calls


def _search_over(points):
    """A finished search whose systems (one block [A | y] of a one-column fit each) sit at ``points`` (m)."""
    from types import SimpleNamespace

    from afmid.maps.pixel_fit import SeparationSearch

    block = np.array([[[1.0, 2.0], [0.0, 0.5]]])  # coefficient 2 at every point: the read-out reads d alone
    return SeparationSearch(None, {float(v): SimpleNamespace(T_blocks=block) for v in points})


def test_the_separations_sigma_reaches_a_read_out_by_its_larger_side():
    """The map pixel adds d's sigma to a read-out as the single-trace fit does (the larger change at d +- sigma,
    afmid.fit.uncertainty.add_largest_shift), from the search's points without a library evaluation: a read-out
    linear in d gains |slope| sigma; one with its extremum at the minimum (a slope of zero through symmetric
    points) gains its change at +- sigma, which a slope misses."""
    from afmid.maps.pixel_fit import SeparationFound

    d0, sigma = 5e-9, 0.2e-9
    points = d0 + sigma * np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    search = _search_over(points)
    support = np.array([True])

    def read(coef, d):
        assert coef[0] == pytest.approx(2.0)
        u = (d - d0) / sigma
        return {"linear": {"value": 3.0 + 0.5 * u}, "valley": {"value": 3.0 - 0.8 * u * u},
                "lopsided": {"value": 3.0 + 0.1 * u + 0.4 * u * u}}

    quantities = {k: {"value": q["value"], "error": 0.1, "ci_low": q["value"] - 0.196, "ci_high": q["value"] + 0.196}
                  for k, q in read(np.array([2.0]), d0).items()}
    assert search.propagate(quantities, SeparationFound(d0, sigma), read, support)
    expected = {"linear": 0.5, "valley": 0.8, "lopsided": 0.5}  # the larger side: 0.1 + 0.4 at +1 sigma
    for k, shift in expected.items():
        assert quantities[k]["error"] == pytest.approx(math.hypot(0.1, shift), rel=1e-9), k
        assert quantities[k]["ci_high"] - 3.0 == pytest.approx(math.hypot(0.196, 1.96 * shift), rel=1e-9), k


def test_the_map_pixel_refits_when_its_search_has_too_few_points_near_the_minimum():
    from afmid.maps.pixel_fit import SeparationFound

    search = _search_over([5e-9, 5.1e-9, 9e-9])  # one point more than 3 sigma away
    assert not search.propagate({}, SeparationFound(5e-9, 0.1e-9), lambda c, d: {}, np.array([True]))

"""The cheaper per-pixel work of ``afmid map`` (issue 14) against the slower computations it replaces, pixel by pixel.

- The trajectory's fine grid kept across a fit's library evaluations (afmid.fit.prepare.with_fine_grid) and the
  library's programs compiled once per separation search (afmid.physics.library.Library.compile): the same code
  path on the same numbers, so the same bits.
- The carried pixel's separation search (afmid.maps.pixel_fit.parabolic_minimum: only its own bracket's points,
  the other phases' starts tried only when the first bracket's minimum lies outside it, an edge's parabola followed
  to its vertex) against the single-trace robust profile (afmid.fit.profile.robust_profile) on the same pixel's
  residual profile, started as a carried pixel of another phase would be (first from the other phase's offset,
  1.5 nm away). Tolerances fixed before the first run: the minimum within 0.2 of the robust profile's sigma (the
  search stops when its vertex moves by less than 0.1 sigma), the sigma within 25 % (as the synthetic test in
  test_map_pixel.py), fewer library evaluations.

Maps: tests/configs/map_small.yaml (3x3, a glassy matrix and a soft domain 1 nm higher), simulator seeds 7 and 8.
"""

from __future__ import annotations

import numpy as np
import pytest

from small_map import simulated_pixels
SEEDS = (7, 8)
#: |search minimum - robust minimum| / robust sigma, per pixel.
SEPARATION_AGREEMENT = 0.2
#: |search sigma / robust sigma - 1|, per pixel.
SIGMA_AGREEMENT = 0.25
#: m, how far the other phase's start lies (the domain stands 1 nm higher: its offset from first contact differs).
OTHER_PHASE = 1.5e-9


def _pixels(folder, seed):
    """(config, library, [prepared pixel]) of the small map simulated with ``seed``."""
    from afmid.fit.prepare import prepare
    from afmid.preprocess.instrument import from_config

    config, library, traces = simulated_pixels(folder, seed)
    return config, library, [prepare(trace, config.fit, from_config(config)) for trace in traces]


@pytest.fixture(scope="module", params=SEEDS)
def small_map(request, tmp_path_factory):
    return _pixels(tmp_path_factory.mktemp(f"speed{request.param}"), request.param)


def _profile(prep, library, params, counter):
    from afmid.fit.system import build_system
    from afmid.fit.profile import GroupedProfile

    def factors_at(value):
        counter[0] += 1
        system = build_system(prep, library, dict(params, d=value))
        return system.T_blocks, system.n_rows

    return GroupedProfile(factors_at, None)


def test_kept_fine_grid_and_compiled_programs_give_the_same_bits(small_map):
    from afmid.fit.pipeline import first_contact, library_parameters
    from afmid.fit.system import build_system
    from afmid.fit.prepare import with_fine_grid

    config, library, preps = small_map
    for prep in preps[:3]:
        params = library_parameters(prep, config, library)
        kept = with_fine_grid(prep)
        assert kept.fine_grid is not None
        for offset in (-0.3e-9, 0.0, 0.2e-9):  # in and out of contact: the switching cells are averaged
            params["d"] = first_contact(prep, config.sample.a0) + offset
            fresh = build_system(prep, library, params)
            again = build_system(kept, library, params)
            assert np.array_equal(fresh.T_blocks, again.T_blocks)
            assert np.array_equal(fresh.theta, again.theta)
        # one program set for every d (the programs do not hold it); a grid too big to keep is not kept
        assert library.compile(dict(params, d=1e-9)) is library.compile(dict(params, d=2e-9))
        assert with_fine_grid(prep, max_bytes=1).fine_grid is None
        assert with_fine_grid(kept) is kept  # kept once, with the chunks made so far


def test_a_fit_keeps_the_fine_grid_only_while_it_runs(small_map):
    """afmid fit keeps the grid for its own evaluations; its result does not hold it (callers keep many results)."""
    from afmid.fit.pipeline import fit_prepared

    config, library, preps = small_map
    result = fit_prepared(preps[0], library, config, uncertainty=False)
    assert preps[0].fine_grid is None and result.prep.fine_grid is None


def test_carried_separation_search_agrees_with_the_robust_profile_pixel_by_pixel(small_map):
    from afmid.fit.pipeline import first_contact, library_parameters
    from afmid.fit.profile import robust_profile
    from afmid.maps.pixel_fit import parabolic_minimum

    config, library, preps = small_map
    below, above = config.fit.separation_window
    fast_calls = slow_calls = 0
    for i, prep in enumerate(preps):
        params = library_parameters(prep, config, library)
        touch = first_contact(prep, config.sample.a0)
        lo, hi = touch - below, touch + above
        k = len(library) + len(prep.nuisance_names)
        slow_counter, fast_counter = [0], [0]
        slow = _profile(prep, library, params, slow_counter)
        # s2 read at the minimum (as both searches read it there): located first, then the profile from it
        located = robust_profile(slow, touch, 0.3e-9, slow(touch) / (slow.n_rows - k), lo, hi, min_step=1e-14)
        s2 = slow(located.value) / (slow.n_rows - k)
        ref = robust_profile(slow, located.value, 0.3e-9, s2, lo, hi, min_step=1e-14, jackknife=True)
        fast = _profile(prep, library, params, fast_counter)
        # a carried pixel after a pixel of the other phase: that phase's offset first, its own phase's second
        # (0.8 sigma off its minimum, as a neighbour's offset typically is)
        other = min(max(ref.value + OTHER_PHASE, lo), hi)
        found = parabolic_minimum(fast, other, ref.sigma, lo, hi, k, alternatives=[ref.value + 0.8 * ref.sigma])
        assert found is not None, i
        assert abs(found.value - ref.value) < SEPARATION_AGREEMENT * ref.sigma, (i, found, ref)
        assert abs(found.sigma / ref.sigma - 1) < SIGMA_AGREEMENT, (i, found, ref)
        fast_calls += fast_counter[0]
        slow_calls += slow_counter[0]
    assert fast_calls < slow_calls, (fast_calls, slow_calls)

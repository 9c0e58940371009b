"""Issue 28: a low-Q record from rest builds up over a few periods with a settling phase (physics, not a defect).

Before, ``check_trace`` refused 35 of 112 such liquid records (Q 2-8) as "the oscillation phase jumps by -5 .. -25 deg
near period 2-4: samples were repeated". Now the phase-jump check starts after the build-up
(:func:`afmid.io.onset.find_build_up`), one warning says so, and the whole record is fitted; a real jump in a
steady record, or after the build-up, is still refused.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.config import build_config
from afmid.errors import InputError
from afmid.io import defects
from afmid.io.onset import FOLLOWED_RING_DOWN, find_build_up
from afmid.io.trace import check_trace
from afmid.simulate.driver import simulate

SPP = 200
PERIODS = 50
#: An honest 1-sigma bar leaves the truth beyond 4 sigma with probability 6e-5 (two-sided Gauss).
Z_MAX = 4.0


def _raw(Q: float, mode: str, seed: int, separation: float | None = 3.6e-9) -> dict:
    """The liquid coverage distribution's setup (configs/coverage/liquid.yaml): k 0.8 N/m, 25 kHz, A0 5 nm, DMT
    at E* 50 MPa, H 1e-20 J, thermal noise and 5 pm of detector noise; ``mode`` steady or transient from rest."""
    return {
        "cantilever": {"spring_constant": 0.8, "resonance_frequency": 25e3, "quality_factor": Q, "tip_radius": 10e-9},
        "drive": {"frequency": 25e3, "free_amplitude": 5e-9},
        "sample": {"separation": separation, "a0": 0.165e-9, "medium": "liquid"},
        "model": {"effects": ["dmt"]},
        "fit": {"bootstrap": 30, "seed": 0},
        "simulate": {"model": "dmt", "parameters": {"E_star": 5e7, "hamaker": 1e-20}, "mode": mode,
                     "transient_start": "rest", "periods": PERIODS, "samples_per_period": SPP,
                     "steps_per_period": 2000, "seed": seed,
                     "noise": {"thermal": True, "temperature": 300.0, "detector_rms": 5e-12}},
    }


def _fit_config(Q: float, mode: str, seed: int):
    raw = _raw(Q, mode, seed, separation=None)  # the separation estimated, as afmid coverage does
    raw.pop("simulate")
    return build_config(raw)


@pytest.fixture(scope="module")
def records():
    """``get(Q, mode, seed)`` -> the simulated trace (simulated once per module)."""
    cache = {}

    def get(Q, mode, seed):
        if (Q, mode, seed) not in cache:
            cache[Q, mode, seed] = simulate(build_config(_raw(Q, mode, seed)))
        return cache[Q, mode, seed]

    return get


@pytest.mark.parametrize("Q", [2.0, 4.0, 8.0])
@pytest.mark.parametrize("seed", [31, 32, 33])
def test_a_low_q_record_from_rest_is_accepted_with_one_line_saying_what_was_done(records, Q, seed):
    trace = records(Q, "transient", seed)
    checked = check_trace(trace, _fit_config(Q, "transient", seed))
    assert not any(f.severity == "error" for f in checked.findings)
    [build_up] = [f for f in checked.findings if f.name == "build_up"]
    assert build_up.severity == "warning" and "\n" not in build_up.message
    assert build_up.message.startswith(f"the oscillation builds up from rest over the first {build_up.numbers['periods']} "
                                       f"periods (Q {Q:.3g}:")
    assert "the fit uses the whole record" in build_up.message
    # The build-up's free response starts at the settled amplitude's size (deficit <= 1) and the check's smallest
    # step is at least half a sample's phase (pi / SPP rad): at most Q/pi ln(SPP/pi) periods + 1, at least 1.
    assert 1 <= build_up.numbers["periods"] <= math.ceil(Q / math.pi * math.log(SPP / math.pi)) + 1
    assert checked.first_sample == trace.first_sample, "nothing cut: the transient is fitted"


@pytest.mark.parametrize("Q", [2.0, 4.0, 8.0])
def test_a_low_q_record_from_rest_is_fitted(records, Q):
    """The whole transient is fitted with the separation estimated: the separation, E* and the force curve lie
    within Z_MAX of their reported 1 sigma (z as afmid coverage computes it)."""
    from afmid.coverage.compare import compare
    from afmid.fit.pipeline import run_fit
    from afmid.physics.tips import tip_geometry
    from afmid.runfile import run_data

    seed = 41
    config = _fit_config(Q, "transient", seed)
    trace = check_trace(records(Q, "transient", seed), config)
    result = run_fit(config, trace=trace)
    assert "dmt.hertz" in result.selected_terms()
    numbers = compare(run_data(result, config), trace, tip_geometry(config.cantilever), False)
    for name in ("separation", "E_star", "force_curve"):
        assert abs(numbers[name]["z"]) <= Z_MAX, (name, numbers[name])


@pytest.mark.parametrize("period", [4, 25])
def test_a_steady_record_with_a_phase_jump_is_still_refused(records, period):
    """An acquisition glitch: 10 samples (18 deg) lost in a steady liquid record (the thermal phase noise of this
    lever, 5 sigma ~ 7 deg, hides a single sample), early where a build-up would be skipped and in the middle."""
    trace = records(4.0, "steady", 51)
    cut = period * SPP + 77
    broken = _with_deflection(trace, np.delete(trace.deflection, np.arange(cut, cut + 10)))
    with pytest.raises(InputError, match=r"phase jumps by \+1\d\.\d* deg .* samples were dropped") as info:
        check_trace(broken, _fit_config(4.0, "steady", 51))
    assert info.value.key == "data.path"
    assert abs(int(info.value.message.split("near sample ")[1].split()[0]) - cut) <= 1.5 * SPP
    assert check_trace(trace, _fit_config(4.0, "steady", 51)) is not None, "the record without the glitch passes"


def test_a_phase_jump_after_the_build_up_is_still_refused(records):
    trace = records(8.0, "transient", 31)
    cut = 30 * SPP + 77
    broken = _with_deflection(trace, np.delete(trace.deflection, np.arange(cut, cut + 10)))
    with pytest.raises(InputError, match=r"phase jumps by .* samples were dropped"):
        check_trace(broken, _fit_config(8.0, "transient", 31))


def test_a_slow_build_up_is_left_to_the_check_s_models_of_smooth_motion(records):
    """A lever ringing down in more than FOLLOWED_RING_DOWN periods (Q > 5 pi: air) gets no build-up window: the
    check's smooth-motion models follow it (tests/preprocess/test_transient.py: a Q 250 record from rest)."""
    trace = records(8.0, "transient", 31)
    settings = defects.settings_for(trace, _fit_config(8.0, "transient", 31))
    analysis = defects.analyse_with(np.asarray(trace.deflection), settings)
    smallest = defects.smallest_jump(analysis, settings)
    assert find_build_up(analysis, 8.0, smallest) is not None
    assert find_build_up(analysis, math.pi * FOLLOWED_RING_DOWN * 1.01, smallest) is None
    assert find_build_up(analysis, None, smallest) is None, "no lever known: no window"


def _with_deflection(trace, deflection):
    """``trace`` with other samples (no truth: the edit breaks it)."""
    import dataclasses

    return dataclasses.replace(trace, deflection=deflection, truth=None, time=None, findings=[], drive=None)

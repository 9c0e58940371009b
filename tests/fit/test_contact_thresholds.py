"""Each tap's contact threshold (afmid.fit.contact_thresholds): where a gate that forms at contact switches a tap on.

On a grazing meniscus orbit the taps' peaks differ by picometres (the neck forms on some taps only and the
amplitude recovers in between); the set of taps whose neck forms changes at each threshold a0 + (a tap's
largest deflection), on the trajectory the library's gates are scanned on.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmid.config import read_yaml
from repo_paths import REPO_ROOT

pytestmark = [pytest.mark.numerics]

#: The grazing record: hidden_capillary.yaml (theta 1.0 rad, rupture 1 nm) at a rest separation where the tip
#: just reaches a0 at A0 10 nm; the orbit does not settle (the neck forms on some taps only).
GRAZING_SEPARATION = 8.5e-9
GRAZING_RUPTURE = 1.0e-9


def grazing_meniscus_record(base_dir):
    """(config with d to be estimated and the model [dmt, capillary] at the true rupture distance, prepared trace
    with its fine grid kept) of a grazing meniscus orbit: 30 periods at 100 samples per period, recorded as it is
    after 2000 periods (~1 s of CPU)."""
    from afmid.config import build_config
    from afmid.fit.prepare import prepare
    from afmid.fit.prepare import with_fine_grid
    from afmid.simulate.driver import simulate

    source = REPO_ROOT / "tests" / "configs" / "hidden_capillary.yaml"
    raw = read_yaml(source)
    raw["sample"]["separation"] = GRAZING_SEPARATION
    raw["simulate"].update(periods=30, samples_per_period=100, max_settle_periods=2000, unsettled="record")
    config = build_config(raw, source=source, base_dir=base_dir)
    prepared = with_fine_grid(prepare(simulate(config), config.fit))
    config.sample.separation = None
    config.model.effects = ["dmt", "capillary"]
    config.model.parameters = {"rupture_distance": GRAZING_RUPTURE}
    return config, prepared


@pytest.fixture(scope="module")
def grazing(tmp_path_factory):
    return grazing_meniscus_record(tmp_path_factory.mktemp("grazing"))


def test_the_taps_differ_on_a_grazing_orbit(grazing):
    """The premise: one tap per period, their peaks picometres apart, the truth among their thresholds."""
    from afmid.fit.contact_thresholds import contact_thresholds, tap_peaks

    config, prepared = grazing
    peaks = tap_peaks(prepared)
    assert peaks.size == prepared.blocks.n_blocks
    thresholds = contact_thresholds(prepared, config.sample.a0)
    assert 5e-12 < thresholds[-1] - thresholds[0] < 100e-12
    assert thresholds[0] < GRAZING_SEPARATION < thresholds[-1]


def test_a_gate_that_forms_at_contact_switches_each_tap_at_its_threshold(grazing):
    """Just below a tap's threshold its meniscus gate switches on somewhere in the tap, just above it does not,
    for every tap and every threshold: the thresholds are the library's (the smoothed trajectory on the fine grid),
    not the raw record's. Either side by 1e-16 m: far above the rounding of d - x (~1e-24 m), far below the
    picometre gaps between the taps."""
    from afmid.fit.contact_thresholds import contact_thresholds, tap_peaks
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.prepare import fine_chunks
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry

    config, prepared = grazing
    library = build_library(config.model, config.source, tip_geometry(config.cantilever))
    gate = [s.name for s in library.states].index("meniscus")
    params = library_parameters(prepared, config, library)
    a0 = config.sample.a0
    peaks = tap_peaks(prepared)
    rows = [(x[i], v[i], t[i]) for _, x, v, t in fine_chunks(prepared) for i in range(x.shape[0])]
    for threshold in contact_thresholds(prepared, a0):
        for d in (threshold - 1e-16, threshold + 1e-16):
            necked = np.array([library.states_along(x, v, t, dict(params, d=d))[gate].any() for x, v, t in rows])
            np.testing.assert_array_equal(necked, a0 + peaks >= d)


def test_one_trial_between_each_two_thresholds():
    from afmid.fit.contact_thresholds import contact_trial_separations

    pm = 1e-12
    trials = contact_trial_separations(np.array([4, 1, 2, 2]) * pm, 0.0, 1.0, 0.1 * pm)
    np.testing.assert_allclose(trials, np.array([0.5, 1.5, 3.0, 5.0]) * pm, rtol=1e-12)
    # inside the searched span only
    np.testing.assert_allclose(contact_trial_separations(np.array([1, 2, 4]) * pm, 1 * pm, 4 * pm, 0.1 * pm),
                               np.array([1.5, 3.0]) * pm, rtol=1e-12)
    # thresholds closer than the resolution are one; a single one is tried the resolution either side
    np.testing.assert_allclose(contact_trial_separations(np.array([1.0, 1.05]) * pm, 0.0, 1.0, 0.1 * pm),
                               np.array([0.9, 1.1]) * pm, rtol=1e-12)
    assert contact_trial_separations(np.zeros(0), 0.0, 1.0, 0.1 * pm).size == 0


def test_the_trials_are_bounded_on_a_record_whose_taps_spread_far():
    """A record built up from rest has taps over nanometres: at most CONTACT_TRIALS_MAX + 2 trials (an interval
    between each two of at most CONTACT_TRIALS_MAX + 1 thresholds kept, and one beyond each end), spread over
    them."""
    from afmid.fit.contact_thresholds import CONTACT_TRIALS_MAX, contact_trial_separations

    thresholds = np.linspace(5e-9, 10e-9, 5000)
    trials = contact_trial_separations(thresholds, 0.0, 1.0, 2e-12)
    assert trials.size <= CONTACT_TRIALS_MAX + 2
    assert trials[0] < 5e-9 and trials[-1] > 10e-9 and np.all(np.diff(trials) > 0)

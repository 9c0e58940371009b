"""Records that are not in steady state: the drive switched on from rest, or the tip still settling into tapping.

The fit's weak form needs no periodicity, but its drive columns cos(w t),
sin(w t) need the drive frequency, and the spectral peak of a transient's
deflection is off the drive by 1e-4 to 1e-2 (the free response rings at its
own frequency): before :mod:`afmid.fit.drive_search`, the force error on such
records was 0.8-3.4 % of the peak with the separation off by up to 0.4 nm. The
cases below were fixed before any of them was run (parameters and seeds unlike
those the search was developed on); the tolerances are the issue's targets.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from afmid.config import build_config
from afmid.fit.drive_search import MARGIN_VALLEYS, search_window, with_drive_frequency

pytestmark = pytest.mark.slow

#: Force error allowed on a clean record, fraction of the peak force (issue 13: <= 1 % with an ideal instrument).
FORCE_TOLERANCE = 0.01
#: The separation: a0 / 3 (docs/accuracy.md's target when the fit searches it).
SEPARATION_TOLERANCE = 0.055e-9
#: The drive frequency: within this many of its reported sigmas, and this relative error.
DRIVE_SIGMAS = 3.0
DRIVE_RELATIVE = 2e-5


def _raw(Q: float, A0: float, d: float, drive: float, periods: int, spp: int, start: str, seed: int) -> dict:
    return {
        "cantilever": {"spring_constant": 40.0, "resonance_frequency": 300e3, "quality_factor": Q,
                       "tip_radius": 10e-9},
        "drive": {"frequency": drive, "free_amplitude": A0},
        "sample": {"separation": d, "a0": 0.165e-9},
        "model": {"effects": ["dmt"]},
        "fit": {"bootstrap": 0},
        "simulate": {"model": "dmt", "parameters": {"E_star": 1.5e9, "hamaker": 8e-20}, "mode": "transient",
                     "transient_start": start, "periods": periods, "samples_per_period": spp,
                     "steps_per_period": 2000, "seed": seed,
                     "noise": {"thermal": True, "temperature": 300.0, "detector_rms": 1e-12}},
    }


CASES = {
    "from_rest": _raw(250, 10e-9, 6.5e-9, 300e3, 150, 200, "rest", 11),
    "from_rest_detuned_low_q": _raw(120, 15e-9, 9e-9, 299.4e3, 100, 100, "rest", 12),
    "settling_from_free": _raw(250, 10e-9, 4.5e-9, 300e3, 120, 200, "free", 13),
    "from_rest_high_q_50_spp": _raw(400, 8e-9, 5e-9, 300.6e3, 200, 50, "rest", 14),
}


@pytest.fixture(scope="module")
def transient_fits(tmp_path_factory):
    """``get(case)`` -> (trace, fit result) with the separation searched (fitted once per module)."""
    from afmid.fit.pipeline import run_fit
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("transient")
    cache = {}

    def get(case: str):
        if case not in cache:
            raw = CASES[case]
            trace = simulate(build_config(raw, base_dir=folder))
            fit_raw = dict(raw, sample=dict(raw["sample"], separation=None))
            cache[case] = trace, run_fit(build_config(fit_raw, base_dir=folder), trace=trace)
        return cache[case]

    return get


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_transient_record_is_fitted_to_the_accuracy_of_a_steady_one(transient_fits, case):
    trace, result = transient_fits(case)
    assert trace.truth is not None
    force = trace.truth.force
    estimated = np.isfinite(result.force_estimate)
    peak = float(force[estimated].max())
    error = float(np.sqrt(np.mean((result.force_estimate[estimated] - force[estimated]) ** 2))) / peak
    d_error = float(result.system.params["d"]) - float(trace.truth.extra["separation"])
    assert result.selected_terms() == ["dmt.vdw", "dmt.hertz"]
    assert error <= FORCE_TOLERANCE, f"force error {100 * error:.3f} % of the peak"
    assert abs(d_error) <= SEPARATION_TOLERANCE, f"separation off by {d_error * 1e12:.1f} pm"


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_drive_frequency_of_a_transient_is_the_regressions(transient_fits, case):
    trace, result = transient_fits(case)
    found = result.drive_search
    true = CASES[case]["drive"]["frequency"]
    assert found is not None, "a record whose amplitude changes is searched"
    assert result.prep.drive.frequency == found.frequency
    assert math.isfinite(found.sigma) and found.sigma > 0
    assert abs(found.frequency - true) <= DRIVE_SIGMAS * found.sigma, (found.frequency - true, found.sigma)
    assert abs(found.frequency / true - 1) <= DRIVE_RELATIVE
    # The spectral peak it replaced was off by more than the search's error.
    assert abs(found.response_frequency - true) > abs(found.frequency - true)


def test_the_run_file_says_where_the_drive_frequency_came_from(transient_fits, tmp_path):
    import h5py

    from afmid.runfile import run_data, write_run

    _, result = transient_fits("from_rest")
    path = write_run(tmp_path / "run.h5", run_data(result, result.config))
    with h5py.File(path, "r") as h5:
        drive = h5["model/drive"]
        assert drive.attrs["frequency_source"].startswith("regression search")
        assert drive["frequency"][()] == result.drive_search.frequency
        assert drive["frequency_sigma"].attrs["units"] == "Hz" and drive["frequency_sigma"].attrs["meaning"] == "1 sigma"
        assert drive["response_frequency"][()] == result.drive_search.response_frequency


def test_a_steady_record_keeps_the_spectral_peak(tmp_path):
    """auto searches only records whose amplitude changes: a steady trace is fitted exactly as before."""
    from afmid.fit.pipeline import run_fit
    from afmid.preprocess.harmonics import estimate_drive
    from afmid.simulate.driver import simulate

    raw = _raw(250, 10e-9, 8.5e-9, 300e3, 30, 200, "rest", 3)
    raw["simulate"]["mode"] = "steady"
    trace = simulate(build_config(raw, base_dir=tmp_path))
    result = run_fit(build_config(raw, base_dir=tmp_path), trace=trace, uncertainty=False)
    assert result.drive_search is None
    assert result.prep.drive.frequency == estimate_drive(trace.deflection, trace.times, trace.drive_frequency).frequency
    searched = run_fit(build_config(dict(raw, fit={"bootstrap": 0, "drive_frequency": "search"}), base_dir=tmp_path),
                       trace=trace, uncertainty=False)
    # On a steady record the search and the spectral peak agree (to a small part of the valley 1 / (2 pi N)).
    valley = 300e3 / (2 * math.pi * 30)
    assert abs(searched.drive_search.frequency - result.prep.drive.frequency) < 0.05 * valley


@pytest.mark.parametrize("spring_constant, quality_factor, f0, seed", [(0.3, 2.0, 15e3, 908), (1.0, 8.0, 40e3, 909),
                                                                    (0.8, 4.0, 25e3, 11)])
def test_a_steady_soft_lever_in_liquid_is_not_a_transient(tmp_path, spring_constant, quality_factor, f0, seed):
    """The thermal motion of a soft lever in liquid (64-117 pm rms on a 5 nm amplitude) moves the amplitude by a
    few % over 50 periods: read as a 2.2-2.4 % change, these steady records were warned "not in steady state"
    and their drive searched (seeds 908, 909 found so: 2.42 and 2.24 %; the third, 1.47 %, is a control). The limit
    now counts the thermal motion (afmid.preprocess.harmonics.transient_limit: 9.9 / 5.4 / 5.9 % here); the stiff
    lever in air keeps 2 %."""
    from afmid.config import load_config
    from afmid.fit.drive_search import is_transient
    from afmid.fit.prepare import prepare
    from afmid.io.defects import check_steady, settings_for
    from afmid.io.trace_analysis import analyse
    from afmid.preprocess.harmonics import TRANSIENT_CHANGE, transient_limit
    from afmid.simulate.driver import simulate
    from repo_paths import TEST_CONFIGS

    overrides = [f"cantilever.spring_constant={spring_constant}", f"cantilever.quality_factor={quality_factor}",
                 f"cantilever.resonance_frequency={f0}", f"drive.frequency={f0}", "sample.separation=4.5e-9",
                 f"simulate.seed={seed}"]
    config = load_config(TEST_CONFIGS / "liquid.yaml", overrides)
    trace = simulate(config)
    prep = prepare(trace, config.fit)
    assert not is_transient(prep) and prep.transient_limit > TRANSIENT_CHANGE
    settings = settings_for(trace, config)
    analysis = analyse(trace.deflection, quality_factor=quality_factor)
    assert check_steady(analysis, settings) == []
    assert transient_limit(10e-9, 1.380649e-23 * 300 / 40.0) == TRANSIENT_CHANGE  # k 40 N/m, A 10 nm


def test_new_drive_columns_at_the_same_frequency_are_the_prepared_ones(tmp_path):
    from afmid.fit.prepare import prepare
    from afmid.simulate.driver import simulate

    raw = _raw(250, 10e-9, 6.5e-9, 300e3, 40, 200, "rest", 5)
    config = build_config(raw, base_dir=tmp_path)
    trace = simulate(config)
    for form in ("weak", "strong"):
        fit = config.fit.model_copy(update={"form": form})
        prep = prepare(trace, fit)
        again = with_drive_frequency(prep, prep.drive.frequency)
        scale = np.abs(prep.nuisance).max()
        assert np.allclose(again.nuisance, prep.nuisance, rtol=0, atol=1e-12 * scale)
        assert np.allclose(again.nuisance_block, prep.nuisance_block, rtol=0,
                           atol=1e-12 * np.abs(prep.nuisance_block).max())
        assert again.drive.frequency == prep.drive.frequency and prep.nuisance is not again.nuisance


def test_the_search_window_holds_both_candidates_with_a_margin():
    low, high, points = search_window(300.3e3, 300e3, 100)
    valley = 300.3e3 / (2 * math.pi * 100)
    assert low == pytest.approx(300e3 - MARGIN_VALLEYS * valley)
    assert high == pytest.approx(300.3e3 + MARGIN_VALLEYS * valley)
    assert (high - low) / (points - 1) <= valley / 2
    # A nominal frequency far off: the grid is capped, never empty.
    assert search_window(300e3, 200e3, 1e4)[2] >= 11


# --------------------------------------------------------------------------- a record that starts at rest
QUIET_PERIODS = 15


@pytest.fixture(scope="module")
def quiet_start(tmp_path_factory):
    """(folder, config dict, samples at rest): a trace file whose first QUIET_PERIODS periods are the cantilever at
    rest (detector noise only), then the drive switches on and the tip taps into the sample (simulated from rest)."""
    import yaml

    from afmid.io.trace import write_trace_file
    from afmid.io.onset import crop
    from afmid.simulate.driver import simulate

    folder = tmp_path_factory.mktemp("quiet_start")
    raw = _raw(250, 10e-9, 6.5e-9, 300e3, 150, 200, "rest", 21)
    trace = simulate(build_config(raw, base_dir=folder))
    n_rest = QUIET_PERIODS * 200 + 37  # the drive switches on mid-period
    rest = np.random.default_rng(22).normal(0.0, 1e-12, n_rest)
    # Prepend the rest to the deflection and the truth (force 0, separation d, velocity 0 at rest).
    truth = trace.truth
    full = dataclasses.replace(trace, deflection=np.concatenate([rest, trace.deflection]), truth=dataclasses.replace(
        truth, force=np.concatenate([np.zeros(n_rest), truth.force]),
        separation=np.concatenate([np.full(n_rest, truth.separation[0]), truth.separation]),
        velocity=np.concatenate([np.zeros(n_rest), truth.velocity])))
    write_trace_file(folder / "quiet.h5", full, yaml.safe_dump(raw))
    dropped = crop(full, 0)
    dropped.deflection = np.delete(full.deflection, n_rest + 90 * 200 + 11)  # a sample lost in period ~105
    dropped.truth = None
    write_trace_file(folder / "dropped.h5", dropped, yaml.safe_dump(raw))
    fit_raw = dict(raw, sample=dict(raw["sample"], separation=None), data={"path": "quiet.h5"})
    fit_raw.pop("simulate")
    return folder, fit_raw, n_rest


def test_a_record_that_starts_at_rest_is_fitted_from_the_onset(quiet_start):
    from afmid.fit.pipeline import run_fit
    from afmid.io.trace import load_trace

    folder, raw, n_rest = quiet_start
    config = build_config(raw, base_dir=folder)
    trace = load_trace(config)  # before: refused ("the oscillation phase jumps ...: samples were dropped")
    onset = [f for f in trace.findings if f.name == "onset"]
    assert [f.severity for f in onset] == ["repaired"] and not any(f.severity == "error" for f in trace.findings)
    assert n_rest <= trace.first_sample <= n_rest + 3 * 200, "cut within 3 periods after the drive switched on"
    assert trace.first_sample == onset[0].numbers["sample"] and "onset" in trace.sources["crop"]
    assert trace.truth.force.size == trace.n_samples
    result = run_fit(config, trace=trace)
    assert result.prep.t[0] == pytest.approx(trace.first_sample / trace.sample_rate, rel=1e-12), "the file's time base"
    force = trace.truth.force
    estimated = np.isfinite(result.force_estimate)
    error = float(np.sqrt(np.mean((result.force_estimate[estimated] - force[estimated]) ** 2))) / force.max()
    assert error <= FORCE_TOLERANCE and result.selected_terms() == ["dmt.vdw", "dmt.hertz"]


def test_a_dropped_sample_after_the_onset_is_still_an_error(quiet_start):
    from afmid.errors import InputError
    from afmid.io.trace import load_trace

    folder, raw, _ = quiet_start
    with pytest.raises(InputError, match=r"phase jumps by .* samples were dropped") as info:
        load_trace(build_config(dict(raw, data={"path": "dropped.h5"}), base_dir=folder))
    assert info.value.key == "data.path"


def test_data_start_and_stop_choose_the_part_fitted(quiet_start):
    from afmid.errors import ConfigError
    from afmid.io.trace import load_trace

    folder, raw, n_rest = quiet_start
    rate = 300e3 * 200
    trace = load_trace(build_config(dict(raw, data={"path": "quiet.h5", "start": 100 / 300e3, "stop": 140 / 300e3}),
                                    base_dir=folder))
    assert trace.first_sample == 100 * 200 and trace.n_samples == 40 * 200
    assert not any(f.name == "onset" for f in trace.findings)
    assert trace.times[0] == pytest.approx(100 / 300e3, rel=1e-12)
    # The user's start wins over the onset: the quiet part kept, said as a warning.
    kept = load_trace(build_config(dict(raw, data={"path": "quiet.h5", "start": 0.0}), base_dir=folder))
    assert kept.first_sample == 0 and [f.severity for f in kept.findings if f.name == "onset"] == ["warning"]
    with pytest.raises(ConfigError) as info:
        load_trace(build_config(dict(raw, data={"path": "quiet.h5", "start": 1.0}), base_dir=folder))
    assert info.value.key == "data.start" and "beyond the end of the record" in info.value.message
    with pytest.raises(ConfigError, match="data.stop"):
        build_config(dict(raw, data={"path": "quiet.h5", "start": 2e-4, "stop": 1e-4}), base_dir=folder)
    del rate, n_rest

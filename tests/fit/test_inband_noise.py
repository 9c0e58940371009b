"""The noise inside the harmonics' band (afmid.fit.inband_noise): measured where coloured detector noise makes
the per-period fits' residual understate it, and used by the error's noise floor and its signal gate.

Tolerances: a harmonic's measured variance ratio (cos and sin pooled, N second differences) has a relative
standard error sqrt(SECOND_DIFFERENCE_SPREAD / (2 N)) = 0.081 at N = 298; the tests allow 5 of them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmid.fit.inband_noise import SECOND_DIFFERENCE_SPREAD, excess_variance, measured_noise_words

PERIODS = 300
HARMONICS = np.concatenate([[0], np.repeat(np.arange(1, 31), 2)])  # c0, (a_n, b_n) for n = 1..30


def _rows(rng, scale_of_harmonic):
    """Per-period coefficients: a fixed orbit in harmonics 1-3 plus independent noise of sd scale(n) per row."""
    orbit = np.where(HARMONICS <= 3, 50.0, 0.0)
    sd = np.array([scale_of_harmonic(n) for n in HARMONICS])
    return orbit + rng.standard_normal((PERIODS, HARMONICS.size)) * sd


def test_white_noise_as_predicted_is_left_alone():
    rng = np.random.default_rng(7)
    values = _rows(rng, lambda n: 1.0)
    factor = excess_variance(values, np.ones(HARMONICS.size), HARMONICS)
    assert np.array_equal(factor, np.ones(HARMONICS.size))
    assert measured_noise_words(factor, HARMONICS) is None


def test_coloured_noise_is_measured_per_harmonic():
    """Noise 3x (in sd) the prediction up to harmonic 15, 1.5x above: each harmonic's factor is its measured
    variance ratio (9, 2.25) within 5 standard errors; the orbit's harmonics (1-3) are capped at the quiet
    harmonics' largest factor."""
    rng = np.random.default_rng(8)
    values = _rows(rng, lambda n: 3.0 if n <= 15 else 1.5)
    factor = excess_variance(values, np.ones(HARMONICS.size), HARMONICS)
    tolerance = 5 * math.sqrt(SECOND_DIFFERENCE_SPREAD / (2 * (PERIODS - 2)))
    for n in range(4, 31):
        expected = 9.0 if n <= 15 else 2.25
        assert abs(factor[HARMONICS == n][0] / expected - 1) < tolerance, (n, factor[HARMONICS == n])
    quiet_largest = max(factor[HARMONICS == n][0] for n in range(4, 31))
    assert np.all(factor[(HARMONICS >= 1) & (HARMONICS <= 3)] <= quiet_largest)


def test_a_coherent_change_of_orbit_is_not_taken_for_noise():
    """Every harmonic moved by one shared random series per period (a changing orbit, as chaos or a transient's
    free oscillation): the second differences exceed the prediction 9-fold but together, so nothing changes."""
    rng = np.random.default_rng(9)
    shared = rng.standard_normal(PERIODS)[:, None] * 3.0
    values = _rows(rng, lambda n: 0.1) + shared * np.ones(HARMONICS.size)
    assert np.array_equal(excess_variance(values, np.ones(HARMONICS.size), HARMONICS), np.ones(HARMONICS.size))


def test_noise_free_and_short_records_are_left_alone():
    rng = np.random.default_rng(10)
    values = _rows(rng, lambda n: 3.0)
    ones = np.ones(HARMONICS.size)
    assert np.array_equal(excess_variance(values, ones, HARMONICS, noise_free=True), ones)
    assert np.array_equal(excess_variance(values[:10], ones, HARMONICS), ones)


def _coloured_dmt(tmp_path, periods: int = 120):
    """A DMT trace (tests/configs/dmt.yaml, thermal noise off) with coloured detector noise: 1 pm white plus 3 pm
    below the 20th harmonic; returns (trace, raw config with [dmt] and the separation given)."""
    from afmid.config import apply_overrides, build_config, parse_override, read_yaml
    from afmid.io.trace import Trace
    from afmid.simulate.driver import simulate
    from repo_paths import TEST_CONFIGS

    raw = apply_overrides(read_yaml(TEST_CONFIGS / "dmt.yaml"),
                          [parse_override(o) for o in ("simulate.noise.detector_rms=0.0", "simulate.noise.thermal=false",
                                                       f"simulate.periods={periods}")])
    clean = simulate(build_config(raw, source=tmp_path / "sim.yaml", base_dir=tmp_path))
    rng = np.random.default_rng(11)
    n = clean.deflection.size
    spectrum = np.fft.rfft(rng.standard_normal(n))
    frequencies = np.fft.rfftfreq(n, 1.0 / clean.sample_rate)
    spectrum[frequencies > 20 * clean.drive_frequency] = 0.0
    band = np.fft.irfft(spectrum, n)
    deflection = clean.deflection + 1e-12 * rng.standard_normal(n) + 3e-12 * band / band.std()
    trace = Trace(deflection=deflection, sample_rate=clean.sample_rate, cantilever=clean.cantilever,
                  drive_frequency=clean.drive_frequency)
    raw["model"] = {"effects": ["dmt"]}
    return trace, raw


@pytest.mark.numerics
def test_a_right_model_under_coloured_detector_noise_sits_at_its_floor(tmp_path):
    """The coloured trace (:func:`_coloured_dmt`): the per-period fits' residual (above the harmonics) shows the
    white part only and the noise at the harmonics is ~6x (in sd) the prediction. The right model's error stands
    within its floor's own threshold, and the fit says why in one line; with the predicted floor it was
    model-limited (error / floor 0.65 / 0.070, harmonics 11, 13, 15 counted as signal)."""
    from afmid.config import build_config
    from afmid.fit.pipeline import run_fit
    from afmid.fit.uncertainty import floor_threshold

    trace, raw = _coloured_dmt(tmp_path)
    result = run_fit(build_config(raw, source=tmp_path / "fit.yaml", base_dir=tmp_path), trace=trace,
                     uncertainty=False)
    ratio = result.cv_error / result.cv_error_noise_floor
    assert ratio < floor_threshold(result.cv_error_floor_dof), (result.cv_error, result.cv_error_noise_floor,
                                                                 result.cv_error_floor_dof)
    assert not result.model_limited
    assert any("coloured detector noise: at harmonics" in w for w in result.warnings), result.warnings


@pytest.mark.numerics
def test_a_joint_fit_of_coloured_traces_judges_each_against_the_measured_floor(tmp_path):
    """The coloured trace cut in two 60-period traces, fitted jointly (one law, the separations given): each
    trace's error stands within its floor's threshold, as the single fit's does."""
    from afmid.config import build_config
    from afmid.fit.joint import fit_traces_jointly
    from afmid.fit.uncertainty import floor_threshold
    from afmid.io.trace import Trace

    trace, raw = _coloured_dmt(tmp_path)
    half = trace.deflection.size // 2
    parts = [Trace(deflection=trace.deflection[s], sample_rate=trace.sample_rate, cantilever=trace.cantilever,
                   drive_frequency=trace.drive_frequency)
             for s in (slice(0, half), slice(half, None))]
    config = build_config(raw, source=tmp_path / "fit.yaml", base_dir=tmp_path)
    result = fit_traces_jointly(config, [config, config], parts, uncertainty=False)
    for t in result.traces:
        assert t.cv_error / t.cv_error_noise_floor < floor_threshold(t.cv_error_floor_dof), (
            t.cv_error, t.cv_error_noise_floor, t.cv_error_floor_dof)
        assert not t.model_limited


def test_real_hsdc_halves_count_no_harmonic_that_is_noise(tmp_path):
    """Bruker's HSDC record, each half ([dmt], k 0.8 N/m, Q 400, R 12 nm, 50 nm/V, f0 57 kHz: an assumed
    calibration): every harmonic the error counts has a mean over the half above its per-period noise as
    measured from the record (second differences across periods, sd / sqrt(6)); before, the second half counted
    harmonics 15, 17 and 25, 0.13-0.15 of that noise, and its floor stood 5x the first half's."""
    from afmid.config import build_config
    from afmid.fit.forces import inverted_force_coefficients
    from afmid.fit.pipeline import run_fit
    from tests.io.test_hsdc import EXAMPLE

    if not EXAMPLE.is_file():
        pytest.skip(f"Bruker's example file is not at {EXAMPLE}")
    half = 524288 / 50e6 / 2  # s: the record's 524,288 samples at 50 MHz, halved
    floors = []
    for part in ({"stop": half}, {"start": half}):
        config = build_config({"data": {"path": str(EXAMPLE), "invols": 50e-9, **part},
                               "cantilever": {"spring_constant": 0.8, "resonance_frequency": 57e3,
                                              "quality_factor": 400.0, "tip_radius": 12e-9},
                               "model": {"effects": ["dmt"]}}, source=tmp_path / "run.yaml")
        result = run_fit(config, uncertainty=False)
        F = inverted_force_coefficients(result.prep, result.system, result.coef)
        measured_sd = np.sqrt(np.mean((F[2:] - 2 * F[1:-1] + F[:-2]) ** 2, axis=0) / 6)
        harmonics = result.prep.blocks.harmonics
        for n in np.unique(harmonics[result.signal_rows]):
            at = harmonics == n
            if n > 1:  # the drive's harmonic and the mean force are counted by their own rows' size
                assert np.max(np.abs(F[:, at].mean(axis=0)) / measured_sd[at]) > 1.0, (part, n)
        assert not set(np.unique(harmonics[result.signal_rows])) & {15, 17, 25}, part
        floors.append(result.cv_error_noise_floor)
    assert max(floors) / min(floors) < 2.5, floors  # measured 1.8 (the first half counts harmonic 4), 5.0 before

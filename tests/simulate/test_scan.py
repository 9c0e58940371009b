"""``simulate.scan``: a record taken while scanning, d(t) = z_piezo(t) - h(x_lat(t)) under amplitude feedback."""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest

from afmid.config import build_config
from afmid.errors import ConfigError
from afmid.io.trace import read_truth, write_trace_file
from afmid.physics.effects import BOLTZMANN
from afmid.simulate.driver import simulate
from afmid.simulate.scan import surface_height
from afmid.sections.scan import ScanSimulation

pytestmark = pytest.mark.numerics

K, F0_HZ, Q = 40.0, 300e3, 250.0
#: The free lever's amplitude (envelope) time constant 2Q / w0, s.
ENVELOPE_TIME = 2.0 * Q / (2.0 * math.pi * F0_HZ)


def scan_config(scan=None, periods=300, d=8.5e-9, setpoint=None, samples_per_period=50, steps_per_period=1000,
                thermal=False, seed=1):
    sim = {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "noise": {"thermal": thermal},
           "periods": periods, "samples_per_period": samples_per_period, "steps_per_period": steps_per_period,
           "seed": seed}
    if scan is not None:
        sim["scan"] = scan
    if setpoint is not None:
        sim["setpoint"] = setpoint
    raw = {"cantilever": {"spring_constant": K, "resonance_frequency": F0_HZ, "quality_factor": Q, "tip_radius": 1e-8},
           "drive": {"frequency": F0_HZ, "free_amplitude": 1e-8}, "sample": {"separation": d}, "simulate": sim}
    return build_config(raw)


def rest_separation(trace) -> np.ndarray:
    values, unit = trace.truth.tracks["rest_separation"]
    assert unit == "m"
    return values


def test_step_profile_has_its_height_and_10_90_width():
    scan = ScanSimulation(speed=1e-6, step={"height": 2e-9, "position": 5e-9, "width": 1e-9})
    h = surface_height(scan, np.array([-1.0, 4.5e-9, 5e-9, 5.5e-9, 1.0]), 0)
    np.testing.assert_allclose(h, [0.0, 0.2e-9, 1e-9, 1.8e-9, 2e-9], rtol=1e-12, atol=1e-24)


def test_rough_profile_has_its_rms_and_correlation_length_and_is_seeded():
    length, rms = 2e-9, 0.5e-9
    scan = ScanSimulation(speed=1e-6, rough={"rms": rms, "correlation_length": length, "seed": 3})
    x = np.arange(0.0, 4000 * length, length / 8)
    h = surface_height(scan, x, 0)
    # ~4000 correlation lengths: the drawn rms scatters by ~1/sqrt(4000 / 1.25) ~ 2 % around the expected one.
    assert abs(h.std() / rms - 1) < 0.08
    lag = 8  # one correlation length: exp(-1)
    correlation = np.mean((h[:-lag] - h.mean()) * (h[lag:] - h.mean())) / h.var()
    assert abs(correlation - math.exp(-1.0)) < 0.05
    np.testing.assert_array_equal(h, surface_height(scan, x, 0))
    other = ScanSimulation(speed=1e-6, rough={"rms": rms, "correlation_length": length, "seed": 4})
    assert np.abs(h - surface_height(other, x, 0)).max() > rms  # another seed, another surface


def test_flat_surface_with_feedback_holds_d_within_the_noise():
    # Without noise the settled oscillation's lock-in amplitude is the setpoint's: the piezo does not move
    # (beyond the integrator's own error, ~1e-4 pm here).
    quiet = simulate(scan_config({"speed": 4e-6, "feedback": {"gain": 2000.0, "bandwidth": 5e3}}, setpoint=0.85))
    d = rest_separation(quiet)
    assert np.abs(d - d[0]).max() < 0.1e-12
    # With thermal noise the loop follows the amplitude noise within its band: never more than the thermal rms
    # sqrt(kT/k) (10 pm) of the whole deflection (measured: 1.2 pm sd).
    noisy = simulate(scan_config({"speed": 4e-6, "feedback": {"gain": 2000.0, "bandwidth": 5e3}}, setpoint=0.85,
                                 thermal=True, periods=600))
    d = rest_separation(noisy)
    thermal_rms = math.sqrt(BOLTZMANN * 300.0 / K)
    assert d.std() < thermal_rms
    assert abs(d.mean() - d[0]) < 0.5 * thermal_rms
    assert noisy.truth.extra["separation"] == pytest.approx(d.mean(), rel=1e-12)


def test_step_response_has_the_feedback_time_constant():
    """After a sharp 0.3 nm step the loop brings d back at rate g S, where S = dA/dd at the operating point
    (measured from two steady simulations); the amplitude's own lag (at most the free lever's envelope time
    2Q/w0) makes it faster, up to the root of s (1 + s tau) + g S = 0 (measured: 177 /s for g S = 173 /s)."""
    amplitudes = [simulate(scan_config(periods=3, d=d)).truth.extra["steady_amplitude"] for d in (8.45e-9, 8.55e-9)]
    slope = (amplitudes[1] - amplitudes[0]) / 0.1e-9
    gain, height = 200.0, 0.3e-9
    trace = simulate(scan_config({"speed": 4e-6, "start": -0.2e-9,
                                  "step": {"height": height, "position": 0.0, "width": 0.05e-9},
                                  "feedback": {"gain": gain, "bandwidth": 20e3}}, periods=2500))
    d = rest_separation(trace)
    t = np.arange(d.size) / trace.sample_rate
    error = d - d[0]
    assert error.min() == pytest.approx(-height, rel=0.01)  # the step reaches d before the loop reacts
    window = (t > 2e-3) & (t < 7e-3)  # past the step and the amplitude's lag, above the integrator's error
    rate = -np.polyfit(t[window], np.log(-error[window]), 1)[0]
    one_pole = gain * slope
    two_pole = (1.0 - math.sqrt(1.0 - 4.0 * one_pole * ENVELOPE_TIME)) / (2.0 * ENVELOPE_TIME)
    assert 0.99 * one_pole < rate < 1.01 * two_pole
    surface = trace.truth.tracks["surface_height"][0]
    piezo = trace.truth.tracks["piezo"][0]
    np.testing.assert_allclose(d, piezo - surface, rtol=0, atol=1e-21)


def test_time_varying_d_adds_no_integration_error():
    """Halving the RK4 step changes a scanning record no more than it changes a record at constant d: d(t) is
    held over each sample's steps and the kernel steps exactly as at constant d. (Updating d twice as often,
    at twice the samples per period, moves the record by < 1 pm, a tenth of the thermal rms.)"""
    scan = {"speed": 4e-6, "start": -0.3e-9, "step": {"height": 1e-9, "position": 0.0, "width": 0.5e-9},
            "feedback": {"gain": 2000.0, "bandwidth": 5e3}}

    def step_change(scan):
        coarse = simulate(scan_config(scan, samples_per_period=100, steps_per_period=2000))
        fine = simulate(scan_config(scan, samples_per_period=100, steps_per_period=4000))
        return np.abs(coarse.deflection - fine.deflection).max(), coarse

    scanning_change, coarse = step_change(scan)
    static_change, _ = step_change(None)
    assert scanning_change <= 2.0 * static_change
    sparse = simulate(scan_config(scan, samples_per_period=50, steps_per_period=1000))
    assert np.abs(sparse.deflection - coarse.deflection[::2]).max() < 1e-12


def test_the_tracks_are_written_with_units(tmp_path):
    trace = simulate(scan_config({"speed": 4e-6, "step": {"height": 1e-9, "position": 2e-10}}, periods=20))
    path = write_trace_file(tmp_path / "scan.h5", trace, "")
    with h5py.File(path, "r") as h5:
        for name in ("rest_separation", "surface_height", "piezo", "lateral_position", "feedback_amplitude"):
            assert h5[f"truth/tracks/{name}"].attrs["units"] == "m"
    truth = read_truth(path)
    np.testing.assert_array_equal(truth.tracks["rest_separation"][0], rest_separation(trace))
    # Without feedback the piezo stays put and d follows the topography.
    d, h = rest_separation(trace), trace.truth.tracks["surface_height"][0]
    np.testing.assert_allclose(d + h, d[0] + h[0], rtol=0, atol=1e-21)


def test_scan_refuses_what_it_cannot_simulate():
    with pytest.raises(ConfigError, match="simulate.scan"):
        simulate(scan_config({"speed": 4e-6}).model_copy(
            update={"simulate": scan_config({"speed": 4e-6}).simulate.model_copy(update={"mode": "transient"})}))
    with pytest.raises(ConfigError, match="step or rough"):
        scan_config({"speed": 1e-6, "step": {"height": 1e-9, "position": 0.0},
                     "rough": {"rms": 1e-9, "correlation_length": 1e-9}})

"""The lever's mass and damping are computed in one place (afmid.io.cantilever, issue 30): every view of the
lever (the simulator's Oscillator, the fit's ThermalForce, the report's DrivenLever) gives the same bits."""

from __future__ import annotations

import math

import pytest

from afmid.fit.thermal_bias import ThermalForce, TrajectorySmoother
from afmid.io.cantilever import Cantilever, lever_damping, lever_mass
from afmid.report.observables import DrivenLever
from afmid.simulate.model import Oscillator

LEVERS = [(40.0, 300e3, 400.0), (0.3, 15e3, 2.5), (2.0, 70e3, 3.0), (1800.0, 32768.0, 2e4)]


@pytest.mark.parametrize("k, f0, Q", LEVERS)
def test_mass_and_damping_are_the_point_mass_formulas(k, f0, Q):
    """m = k / w0^2 and c = k / (Q w0): each side is a couple of correctly rounded operations, so they agree to
    a few units in the last place (relative 1e-15 is about 4.5 ulp)."""
    w0 = 2.0 * math.pi * f0
    assert lever_mass(k, w0) == pytest.approx(k / w0**2, rel=1e-15)
    assert lever_damping(k, w0, Q) == pytest.approx(k / (Q * w0), rel=1e-15)
    lever = Cantilever(k, f0, Q)
    assert (lever.mass, lever.damping) == (lever_mass(k, w0), lever_damping(k, w0, Q))


@pytest.mark.parametrize("k, f0, Q", LEVERS)
def test_every_view_of_the_lever_has_its_mass_and_damping(k, f0, Q):
    """The same function, so the same bits (no tolerance): a view computing its own k / (Q w0) would differ in
    the last place for three of these four levers (checked when this test was written)."""
    lever = Cantilever(k, f0, Q)
    oscillator = Oscillator.of(lever, 1.01 * f0, 1e-9)
    thermal = ThermalForce(k, lever.omega0, Q, 300.0, TrajectorySmoother("none", 1))
    driven = DrivenLever(k, f0, Q, 1.01 * f0, 1e-9)
    for view in (oscillator, thermal, driven):
        assert (view.mass, view.damping) == (lever.mass, lever.damping), type(view).__name__
    assert (oscillator.spring_constant, oscillator.resonance_frequency, oscillator.quality_factor) == (k, f0, Q)

"""The ``simulate.scan`` section: a record taken while the tip scans a surface under amplitude feedback.

The tip moves laterally at ``speed`` (m/s) from ``start`` (m) over a surface whose height h(x_lateral) (m,
positive = the sample rises toward the tip) is a smoothed ``step`` or a seeded ``rough`` profile; the z piezo
holds the rest position of the lever, so the rest separation is d(t) = z_piezo(t) - h(x_lateral(t)).
An amplitude ``feedback`` moves z_piezo to keep the first-harmonic amplitude at ``setpoint`` A0 (see
:mod:`afmid.simulate.scan`). Without ``feedback`` the piezo stays put and d(t) follows the topography. Example::

    simulate:
      setpoint: 0.8
      scan:
        speed: 4.0e-6
        step: {height: 2.0e-9, position: 15.0e-9, width: 5.0e-9}
        feedback: {gain: 3000.0, bandwidth: 5000.0}

Units: SI (m, m/s, Hz, 1/s).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

_Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class SurfaceStep(_Strict):
    """A step of ``height`` (m; negative: down) centred at lateral ``position`` (m), its edge smoothed over ``width``
    (m, 10-90 %; the tip's apex rounds a sharp edge to about its radius)."""

    height: float = Field(..., allow_inf_nan=False, description="m; the sample rises by this much past the edge")
    position: float = Field(..., allow_inf_nan=False, description="m; lateral position of the edge's middle")
    width: _Positive = Field(5e-9, description="m; 10-90 % width of the smoothed edge")


class RoughSurface(_Strict):
    """A Gaussian random surface: ``rms`` height (m) with a Gaussian correlation of ``correlation_length`` (m),
    drawn from ``seed`` (the simulation's seed when not given)."""

    rms: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(..., description="m rms height")
    correlation_length: _Positive = Field(..., description="m; the height's correlation length")
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] | None = Field(None, description="surface seed")


class AmplitudeFeedback(_Strict):
    """An integral amplitude feedback on the z piezo.

    The amplitude is demodulated once per drive period (a lock-in over that period) and low-passed at
    ``bandwidth`` (Hz, first order); the piezo moves as dz/dt = -gain (A_filtered - setpoint A0), so where
    dA/dd ~ 1 (tapping on a stiff sample) the loop's time constant is ~1 / gain (s).
    """

    gain: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(..., description="1/s, integral gain")
    bandwidth: _Positive = Field(..., description="Hz, the amplitude demodulator's -3 dB bandwidth")
    setpoint: Annotated[float, Field(gt=0, lt=1)] | None = Field(
        None, description="A/A0 held; default simulate.setpoint, else the settled amplitude at the start")


class ScanSimulation(_Strict):
    """``simulate.scan``: lateral motion over a surface profile, with an optional amplitude feedback."""

    speed: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(..., description="m/s lateral tip speed")
    start: float = Field(0.0, allow_inf_nan=False, description="m; lateral position at the first sample")
    step: SurfaceStep | None = None
    rough: RoughSurface | None = None
    feedback: AmplitudeFeedback | None = None

    @model_validator(mode="after")
    def _one_profile(self) -> "ScanSimulation":
        if self.step is not None and self.rough is not None:
            raise ValueError("give either step or rough (one surface profile), not both")
        return self

"""The cantilever a trace was recorded with: one type for the trace, the run config and the Python front door.

:class:`Cantilever` holds the calibration (k, f0, Q), the tip (radius, shape, half-angle), the relative 1-sigma
calibration uncertainties of k and Q and the higher flexural modes; it converts to and from the run config's
``cantilever:`` section (:meth:`Cantilever.config_section`, :meth:`Cantilever.from_config`), which is what the fit
reads. The lever's effective mass and damping are computed here only (:func:`lever_mass`, :func:`lever_damping`):
the stages' views of the lever with a drive or a temperature (the simulator's ``Oscillator``, the fit's
``ThermalForce``, the report's ``DrivenLever``) and the fit's equation of motion call them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


def lever_mass(spring_constant: float, omega0: float) -> float:
    """The first mode's effective mass m = k / w0^2, kg (k in N/m, w0 in rad/s)."""
    return spring_constant / omega0**2


def lever_damping(spring_constant: float, omega0: float, quality_factor: float) -> float:
    """The first mode's viscous damping c = m w0 / Q = k / (Q w0), kg/s (k in N/m, w0 in rad/s, Q in 1)."""
    return lever_mass(spring_constant, omega0) * omega0 / quality_factor


class FirstMode:
    """The first mode's dynamics from a lever's calibration, one way everywhere: a class with ``spring_constant``
    k (N/m), ``resonance_frequency`` f0 (Hz) and ``quality_factor`` Q (1) gets w0, m and c from it (the lever, the
    simulation's oscillator, the report's driven lever)."""

    __slots__ = ()

    @property
    def omega0(self) -> float:
        """Angular resonance frequency w0 = 2 pi f0, rad/s."""
        return 2.0 * math.pi * self.resonance_frequency

    @property
    def mass(self) -> float:
        """Effective mass m = k / w0^2, kg (:func:`lever_mass`)."""
        return lever_mass(self.spring_constant, self.omega0)

    @property
    def damping(self) -> float:
        """Viscous damping c = m w0 / Q, kg/s (:func:`lever_damping`)."""
        return lever_damping(self.spring_constant, self.omega0, self.quality_factor)


@dataclass(frozen=True)
class HigherMode:
    """A higher flexural mode of the lever, seen at the tip (``cantilever.higher_modes``)."""

    resonance_frequency: float  # Hz
    quality_factor: float  # 1
    spring_constant: float  # N/m


@dataclass
class Cantilever(FirstMode):
    """The lever: ``spring_constant`` k (N/m), ``resonance_frequency`` f0 (Hz), ``quality_factor`` Q (1),
    ``tip_radius`` R (m, None: unknown), ``tip_shape`` (``afmid effects --tips``), ``tip_half_angle`` (rad, cones
    and pyramids), ``spring_constant_uncertainty`` / ``quality_factor_uncertainty`` (relative 1 sigma, 0.1 = 10 %,
    propagated into every read-out; None: not declared) and ``higher_modes`` (:class:`HigherMode`)."""

    spring_constant: float  # N/m
    resonance_frequency: float  # Hz
    quality_factor: float
    tip_radius: float | None = None  # m
    tip_shape: str = "sphere"
    tip_half_angle: float | None = None  # rad
    spring_constant_uncertainty: float | None = None  # relative, 1 sigma
    quality_factor_uncertainty: float | None = None  # relative, 1 sigma
    higher_modes: tuple[HigherMode, ...] = field(default_factory=tuple)

    def config_section(self) -> dict[str, Any]:
        """The run config's ``cantilever:`` section for this lever (SI; keys left out where not declared)."""
        section: dict[str, Any] = {"spring_constant": self.spring_constant,
                                   "resonance_frequency": self.resonance_frequency,
                                   "quality_factor": self.quality_factor, "tip_shape": self.tip_shape}
        for key in ("tip_radius", "tip_half_angle", "spring_constant_uncertainty", "quality_factor_uncertainty"):
            if getattr(self, key) is not None:
                section[key] = getattr(self, key)
        if self.higher_modes:
            section["higher_modes"] = [{"resonance_frequency": m.resonance_frequency,
                                        "quality_factor": m.quality_factor,
                                        "spring_constant": m.spring_constant} for m in self.higher_modes]
        return section

    @classmethod
    def from_config(cls, section, **calibration: float) -> "Cantilever":
        """The lever of a validated ``cantilever:`` section (:class:`afmid.io.sections.CantileverConfig`);
        ``calibration`` (spring_constant, resonance_frequency, quality_factor, tip_radius) replaces the section's
        values, e.g. with those merged from a trace file's metadata."""
        values = {"spring_constant": section.spring_constant, "resonance_frequency": section.resonance_frequency,
                  "quality_factor": section.quality_factor, "tip_radius": section.tip_radius, **calibration}
        modes = tuple(HigherMode(m.resonance_frequency, m.quality_factor, m.spring_constant)
                      for m in section.higher_modes)
        return cls(tip_shape=section.tip_shape, tip_half_angle=section.tip_half_angle,
                   spring_constant_uncertainty=section.spring_constant_uncertainty,
                   quality_factor_uncertainty=section.quality_factor_uncertainty, higher_modes=modes, **values)

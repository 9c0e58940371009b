"""A calibrated drive force (``drive.force_amplitude`` and ``drive.phase``): the fit uses it instead of fitting it.

Without a calibration the regression fits the drive force F0 cos(w t + phi) as two free nuisance columns
(cos, sin) beside the force law. The inverted tip-sample force

    F_ts = F_drive - (m x'' + c x' + k x)

then depends on the force model through the fitted drive: a model that lacks a dissipative term makes the fit
shift the drive's phase until the force's work on the sample is what the model can describe (the demo's
[dmt] fit of a viscoelastic sample: 3.35 eV dissipated per period from the inverted force, truth 56.7 eV).
With the drive declared, F_drive is known: it moves to the left-hand side of every row, the drive columns
leave the regression, and the inverted force depends on the data and the cantilever calibration (k, Q, f0)
only, whatever the force law.

Convention (the simulator's, so a simulated trace fitted with its own drive declared is the natural test):
F_drive(t) = F0 cos(2 pi f t + phi), t the trace's time axis (t = 0 at the first sample of the file, or the
zero of its time column; cropping with data.start keeps that zero), f = drive.frequency (the nominal
frequency, which a calibrated drive's generator gives exactly). F0 in N, phi in rad; positive phi: the drive
leads. Amplitude: ``drive.force_amplitude`` in the config, else the trace file's ``/drive`` attribute.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from afmid.errors import ConfigError
from afmid.fit.drive_search import with_drive_frequency
from afmid.io.cantilever import lever_damping, lever_mass

#: The nuisance columns of the drive (afmid.preprocess.baseline.BaselineColumns): first, in this order.
DRIVE_COLUMNS = ("drive_cos", "drive_sin")


@dataclass(frozen=True)
class DeclaredDrive:
    """A calibrated drive force F_drive = F0 cos(2 pi f t + phi)."""

    force_amplitude: float  # F0, N
    phase: float  # phi, rad
    frequency: float  # f, Hz
    force_amplitude_uncertainty: float = 0.0  # relative, 1 sigma (0: not given)
    phase_uncertainty: float = 0.0  # rad, 1 sigma (0: not given)
    amplitude_source: str = "config:drive.force_amplitude"

    @property
    def cos(self) -> float:
        """N: F_drive = cos * cos(w t) + sin * sin(w t)."""
        return self.force_amplitude * math.cos(self.phase)

    @property
    def sin(self) -> float:
        """N, see :attr:`cos`."""
        return -self.force_amplitude * math.sin(self.phase)

    def describe(self) -> str:
        text = f"calibrated drive F0 = {self.force_amplitude:.6g} N, phase {self.phase:.6g} rad at {self.frequency:.9g} Hz"
        if self.force_amplitude_uncertainty or self.phase_uncertainty:
            text += (f" (1 sigma: {100 * self.force_amplitude_uncertainty:.3g} % in F0, "
                     f"{self.phase_uncertainty:.3g} rad in phase)")
        return text


def drive_from_free_oscillation(spring_constant: float, resonance_frequency: float, quality_factor: float,
                                drive_frequency: float, free_amplitude: float, free_phase: float) -> tuple[float, float]:
    """(F0 in N, phase in rad) of the drive, for ``drive.force_amplitude`` and ``drive.phase``, from a free
    oscillation x = A0 cos(2 pi f t + phi_x) recorded with the same drive settings, detector and time zero (the
    tip far from the sample): m x'' + c x' + k x = F0 cos(2 pi f t + phi) gives
    A0 = F0 / |k - m w^2 + i c w| and phi = phi_x + atan2(c w, k - m w^2) (the lever lags its drive by pi/2 at
    resonance, where F0 = k A0 / Q). k in N/m, f0 and f in Hz, A0 in m, phi_x in rad.

    The calibration enters the inverted force twice, through the drive and through m x'' + c x' + k x: F0
    derived here with the k, Q and f0 the fit uses keeps an error of k or Q proportional in the force, where an
    F0 of its own error moves the dissipated energy by that error times the drive's work per period (an order
    of magnitude more, docs/calibrated-drive.md)."""
    omega = 2.0 * math.pi * drive_frequency
    omega0 = 2.0 * math.pi * resonance_frequency
    mass = lever_mass(spring_constant, omega0)
    damping = lever_damping(spring_constant, omega0, quality_factor)
    real, imaginary = spring_constant - mass * omega**2, damping * omega
    return free_amplitude * math.hypot(real, imaginary), free_phase + math.atan2(imaginary, real)


def declared_drive(config, trace) -> DeclaredDrive | None:
    """The calibrated drive of ``config`` (a RunConfig) for ``trace``, or None when ``drive.phase`` is not given
    (the drive is then fitted). Raises ConfigError (one line) when the declaration cannot be used."""
    drive = config.drive
    if drive.phase is None:
        return None
    amplitude, source = drive.force_amplitude, "config:drive.force_amplitude"
    if amplitude is None:
        amplitude, source = trace.drive_force_amplitude, "file"
    if amplitude is None:
        raise ConfigError("drive.phase declares a calibrated drive, which needs its amplitude: give "
                          "drive.force_amplitude (N), e.g. k A0 / Q from the free oscillation at resonance",
                          file=config.source, key="drive.force_amplitude")
    if config.fit.cantilever != "fixed":
        raise ConfigError("a calibrated drive (drive.phase) needs the calibrated cantilever: fit.cantilever: free "
                          "fits k and c, which the drive's calibration rests on; use fit.cantilever: fixed",
                          file=config.source, key="drive.phase")
    if config.fit.drive_frequency in ("search", "response"):
        raise ConfigError(f"a calibrated drive (drive.phase) is a sinusoid at drive.frequency: fit.drive_frequency "
                          f"must be auto or nominal, got {config.fit.drive_frequency!r}",
                          file=config.source, key="fit.drive_frequency")
    return DeclaredDrive(float(amplitude), float(drive.phase), float(trace.drive_frequency),
                         float(drive.force_amplitude_uncertainty or 0.0), float(drive.phase_uncertainty or 0.0),
                         source)


def with_declared_drive(prep, drive: DeclaredDrive):
    """``prep`` (an :class:`afmid.fit.prepare.Prepared`) with the drive known: its columns at the nominal
    frequency, their contribution -F_drive moved into the left-hand side (weak-form rows and per-period
    coefficients), and the two columns removed from the regression. A new object; ``prep`` is not modified.
    A prep that already carries a declared drive is returned as it is."""
    if prep.declared_drive is not None:
        return prep
    if tuple(prep.nuisance_names[:2]) != DRIVE_COLUMNS:
        raise ValueError(f"expected the drive columns first, got {prep.nuisance_names}")
    prep = with_drive_frequency(prep, drive.frequency)
    # The fit's drive coefficients are -F_drive's (afmid.fit.forces.direct_force_coefficients: F_ts = Y - N nu).
    known = np.array([-drive.cos, -drive.sin])
    Y = prep.Y - prep.nuisance[..., :2] @ known
    Y_block = prep.Y_block - prep.nuisance_block[..., :2] @ known
    return dataclasses.replace(prep, Y=Y, Y_block=Y_block, nuisance=np.ascontiguousarray(prep.nuisance[..., 2:]),
                               nuisance_block=np.ascontiguousarray(prep.nuisance_block[..., 2:]),
                               nuisance_names=list(prep.nuisance_names[2:]), declared_drive=drive,
                               declared_drive_rows=np.array(prep.nuisance[..., :2]))


def propagate_drive_calibration(quantities: dict, prep, library, system, coef: np.ndarray, mask: np.ndarray,
                                params: dict, trace, read_out) -> None:
    """Add the declared drive's calibration (``drive.force_amplitude_uncertainty``, ``drive.phase_uncertainty``)
    to every read-out, in place, as :func:`afmid.fit.uncertainty.propagate_calibration` adds k and Q's: the
    half-difference of the read-outs refitted (linearly, on the fit's support and weights) with F0 or the phase
    at +-1 sigma, in quadrature into ``error_calibration``, ``error`` and the 95 % interval."""
    from afmid.fit.uncertainty import coefficient_shift, shift_variance, widen_interval

    drive = prep.declared_drive
    if drive is None or not (drive.force_amplitude_uncertainty > 0 or drive.phase_uncertainty > 0):
        return
    base = np.array([drive.cos, drive.sin])
    pairs = []
    if drive.force_amplitude_uncertainty > 0:
        pairs.append([base * (1 + sign * drive.force_amplitude_uncertainty) for sign in (1, -1)])
    if drive.phase_uncertainty > 0:
        turned = [dataclasses.replace(drive, phase=drive.phase + sign * drive.phase_uncertainty) for sign in (1, -1)]
        pairs.append([np.array([d.cos, d.sin]) for d in turned])
    # Y = Y0 + rows @ (cos, sin): the change of the drive is a change of the left side
    shifts = [tuple(coef + coefficient_shift(prep, system, prep.declared_drive_rows @ (new - base), mask)
                    for new in pair) for pair in pairs]
    variance = shift_variance(quantities, shifts, lambda c: read_out(library, c, None, params, mask, trace))
    for name, q in quantities.items():
        if variance[name] <= 0:
            continue
        q.setdefault("error_statistical", q["error"])
        q["error_calibration"] = math.hypot(q.get("error_calibration", 0.0), math.sqrt(variance[name]))
        widen_interval(q, math.sqrt(variance[name]))

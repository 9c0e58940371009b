"""The report's energy check, row by row, each saying what it depends on.

:func:`afmid.diagnosis.localize.energy_check` gives the energy the sample takes from the tip per period three
ways (and the truth of a simulation); which of them depend on the force model turns on whether the drive was
fitted with the force law or given as a calibrated drive (:mod:`afmid.fit.declared_drive`).
"""

from __future__ import annotations

#: The cantilever quantities every estimate from the measured motion rests on.
CALIBRATION = "k, Q, f0"


def inverted_force_name(calibrated: bool) -> str:
    """The inverted force F = F_drive - (m x'' + c x' + k x), named for the drive it uses."""
    return "inverted force (cantilever equation, " + ("calibrated drive)" if calibrated else "fitted drive)")


def energy_rows(energy: dict, calibrated: bool) -> list[tuple[str, str, str, str | None]]:
    """(what, depends on, key of ``energy``, key of its 1-sigma drive-calibration error or None) for each row
    of the energy check, in the report's order."""
    drive = ("the calibrated drive (drive.force_amplitude, drive.phase) and " + CALIBRATION if calibrated
             else "the drive fitted with the force law, so on the model, and " + CALIBRATION)
    sigma = "drive_calibration_sigma" if energy.get("drive_calibration_sigma", 0.0) > 0 else None
    rows = [
        (inverted_force_name(calibrated) + ": −∮F dz", "the measured motion, " + drive, "inverted", sigma),
        ("cantilever balance: drive work − viscous loss", "the measured motion, " + drive, "energy_balance", sigma),
        ("model: −∮F_model dz", "the identified force law (its parameters and selected terms)", "model", None),
    ]
    if "truth" in energy:
        rows.append(("truth (simulation)", "the simulator's force", "truth", None))
    return rows


def energy_caveat(calibrated: bool) -> str:
    """The sentence under the table: how far the first two rows can be trusted as independent of the model."""
    if calibrated:
        return ("The first two rows use the calibrated drive: they do not depend on the force model, but on the "
                "calibration: an error e in F0 that k and Q do not share moves them by e times the drive's work per "
                "period, a phase error of p rad by up to p times it (docs/calibrated-drive.md); ± is the 1σ of the "
                "declared drive.force_amplitude_uncertainty and drive.phase_uncertainty. A model row far from them "
                "means the model misses a dissipation.")
    return ("The first two rows use the drive fitted together with the force law: a model that lacks a "
            "dissipative effect pulls the fitted drive, and with it these rows, towards its own value. Declare a "
            "calibrated drive (drive.force_amplitude, drive.phase) for an energy that does not depend on the model.")

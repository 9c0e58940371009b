"""The residual's character at one pixel of a force map (for the missing-effect map).

After a pixel's fit, the residual between the inverted and the model force is broken down exactly as the single-trace
diagnosis does it (:func:`afmid.diagnosis.localize.localize`: period average at equal drive phase, band-limited to the
signal harmonics, split into a part common to approach and retraction and a part that reverses with the motion). The
map keeps, per pixel, what groups pixels by their residual (:mod:`afmid.maps.groups`):

- ``residual_region``: where most of the residual sits (index into :data:`REGIONS`);
- ``residual_character``: conservative / dissipative / mixed / none (index into :data:`CHARACTERS`);
- ``residual_snr``: the systematic residual's rms over the noise left in the period average (about 1: nothing
  systematic there);
- ``residual_dissipative_share``: the direction-dependent part's share of the split residual, diss / (cons + diss)
  (rms), 0..1 (NaN when the split has too few points).

Cost: the period curves of the pixel's fit (one library evaluation on the phase grid) and the breakdown; no fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Index stored in /maps/residual_region (names in its ``meaning`` attribute).
REGIONS = ("contact", "near", "far")
#: Index stored in /maps/residual_character (names in its ``meaning`` attribute).
CHARACTERS = ("none", "conservative", "dissipative", "mixed")
#: The signature's maps that hold codes (int8; -1: not fitted), not values.
CODED = ("residual_region", "residual_character")
#: The per-pixel signature: name -> (unit, meaning) of its /maps dataset.
SIGNATURE = {
    "residual_region": ("1", "where most of the systematic residual sits: "
                        + ", ".join(f"{i}: {n}" for i, n in enumerate(REGIONS)) + ", -1: not fitted "
                        "(afmid.diagnosis.localize: contact z <= a0, near up to 2 nm above, far beyond)"),
    "residual_character": ("1", ", ".join(f"{i}: {n}" for i, n in enumerate(CHARACTERS)) + ", -1: not fitted "
                           "(approach and retraction compared at equal separation; significant above 3x the noise)"),
    "residual_snr": ("1", "systematic residual rms over the noise left in the period average (about 1: nothing "
                     "systematic; afmid.diagnosis.localize)"),
    "residual_dissipative_share": ("1", "rms of the part of the residual that reverses with the direction of motion "
                                   "over the sum of both parts' rms (0: conservative, 1: dissipative)"),
}


@dataclass
class ResidualView:
    """What :func:`afmid.diagnosis.localize.localize` reads of a run, made from a fit in memory (a map's pixel has
    no run file): the per-period curves, the Fourier rows' harmonics and signal rows, the config and the drive
    frequency (Hz)."""

    periods: object  # mapping name -> (periods, phase points) arrays (afmid.fit.forces.PeriodCurves)
    harmonics: np.ndarray
    signal_rows: np.ndarray
    config: object
    drive: dict = field(default_factory=dict)


def empty_signature() -> dict:
    """The signature of a pixel that was not fitted."""
    return {"residual_region": -1, "residual_character": -1, "residual_snr": math.nan,
            "residual_dissipative_share": math.nan}


def signature_of(view: ResidualView) -> dict:
    """The pixel's residual signature (see the module docstring) from :func:`localize` of ``view``."""
    from afmid.diagnosis.localize import localize

    local = localize(view)
    cons, diss = local["conservative_rms"], local["dissipative_rms"]
    share = diss / (cons + diss) if (cons + diss) > 0 else math.nan
    return {"residual_region": REGIONS.index(local["region"]),
            "residual_character": CHARACTERS.index(local["character"]),
            "residual_snr": float(local["snr"]), "residual_dissipative_share": float(share)}


def curves_of(view: ResidualView) -> dict:
    """The pixel's force curves for the map explorer (afmid.maps.pixel_curves): the period averages over the settled
    periods, as :func:`afmid.diagnosis.localize.localize` takes them, on the pixel's separation grid."""
    from afmid.diagnosis.localize import band_limit
    from afmid.maps.pixel_curves import pixel_curves
    from afmid.preprocess.harmonics import settled_start

    P = view.periods
    first = settled_start(0.5 * (P["separation"].max(axis=1) - P["separation"].min(axis=1)))
    inverted = P["force_inverted"][first:]
    n_periods = inverted.shape[0]
    sigma = (inverted.std(axis=0, ddof=1) / math.sqrt(n_periods) if n_periods > 1
             else np.full(inverted.shape[1], np.nan))
    residual = inverted - band_limit(P["force_model"], view)[first:]
    return pixel_curves(P["separation"][first:].mean(axis=0), -P["velocity"][first:].mean(axis=0),
                        {"force_inverted": inverted.mean(axis=0), "force_inverted_sigma": sigma,
                         "force_model": P["force_model"][first:].mean(axis=0), "residual": residual.mean(axis=0)})


def fit_view(prep, library, system, coef, params: dict, rows: np.ndarray, config) -> ResidualView:
    """The :class:`ResidualView` of a fit in memory (prepared trace, library, system, coefficients, parameters
    with ``d``, signal rows): its period curves on ``config.fit.phase_points``."""
    from afmid.fit.forces import period_curves

    periods = period_curves(prep, library, system, coef, params, rows, config.fit.phase_points, keep_curves=True)
    return ResidualView(periods, prep.blocks.harmonics, rows, config, {"frequency": prep.drive.frequency})


def signature_of_fit(prep, library, system, coef, params: dict, rows: np.ndarray, config) -> dict:
    """The residual signature of a fit in memory (arguments of :func:`fit_view`): :func:`signature_of`."""
    return signature_of(fit_view(prep, library, system, coef, params, rows, config))


def view_signature(view: ResidualView) -> tuple[dict, dict]:
    """The residual signature (:func:`signature_of`) and the force curves (:func:`curves_of`) of ``view``."""
    return signature_of(view), curves_of(view)

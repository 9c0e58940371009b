"""A fit against its simulation's truth: z = (estimate - truth) / reported sigma for every read-out, the rest
separation and the force curve, with the flags that say the fit itself doubted the number.

Which sigma: every read-out's ``error`` and every nonlinear parameter's ``sigma`` are 1 sigma in afmid (the
bootstrap with the nonlinear parameters' and the calibration's shares, afmid.fit.uncertainty); the read-outs'
``ci_low`` / ``ci_high`` are a 95 % interval, compared apart (``in_ci95``). Nothing is converted.

The force curve: the fit reports its 1-sigma band as one number relative to the peak |force|, an RMS over the
estimated samples (``RunData.force_total_uncertainty``, afmid.fit.force_band). The matching error is the RMS
over the same samples of (estimated - true force); its z is RMS error / (band x peak), >= 0. Where the curve's
error is dominated by one direction (one coefficient, the separation), that ratio is distributed like |z| of a
normal variable (68 % <= 1, 95 % <= 2); where many independent directions contribute it concentrates at 1
(fewer <= 1, more <= 2). So the force curve's fractions are read against the same 68 / 95 % only loosely; its
rms z (which should be about 1 either way) is the sharper number.

Flags (a number the fit itself marked): ``model_limited`` (the fit's error stands above its noise floor) and
``separation_limited`` (the separation-limited warning) for every number of the draw, ``undetermined`` (the
term was not selected) and ``implausible`` (afmid.fit.plausibility) per read-out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from afmid.fit.separation_share import is_separation_limited
from afmid.physics.effects import EFFECTS
from afmid.physics.tips import TipGeometry, effect_for
from afmid.runfile import RunData, nonlinear_order, readout_order

#: Names of the two quantities that are not read-outs (in the table and the output file).
SEPARATION = "separation"
FORCE_CURVE = "force_curve"


def z_score(estimate: float, truth: float, sigma: float) -> float:
    """(estimate - truth) / sigma; NaN when any is not finite or sigma <= 0."""
    if not (math.isfinite(estimate) and math.isfinite(truth) and math.isfinite(sigma) and sigma > 0):
        return math.nan
    return (estimate - truth) / sigma


def true_readouts(truth, tip: TipGeometry, effect_name: str) -> dict[str, float]:
    """Effect ``effect_name``'s read-out of the true force law (SI): its terms' coefficients at the simulation's
    parameters (``truth.parameters``), read out as the fit reads out its own; for an effect the simulation did
    not have, the read-out of zero coefficients (an absent viscosity is 0). Non-finite values are left out."""
    if effect_name not in EFFECTS:
        return {}
    effect = effect_for(effect_name, tip)
    params = dict(truth.parameters)
    present = effect_name in truth.effects
    try:
        coefficients = {t.label: (float(t.coefficient(params)) if present else 0.0) for t in effect.terms}
        with np.errstate(all="ignore"):
            values = effect.readout(coefficients, params)
    except (KeyError, ValueError, ZeroDivisionError):
        return {}
    return {k: float(v) for k, v in values.items() if math.isfinite(float(v))}


def truth_of_quantities(quantities: Mapping[str, Mapping], truth, tip: TipGeometry) -> dict[str, float]:
    """The true value of each read-out key of ``quantities`` (afmid.fit.forces.read_out's keys: the quantity's
    name, or ``effect.name`` when two effects report it): from its own effect, or, when that effect was not
    simulated, from a simulated effect that reports the same quantity (a Hamaker constant of either), else 0
    from the absent effect's zero coefficients."""
    simulated: dict[str, float] = {}
    for name in truth.effects:
        for key, value in true_readouts(truth, tip, name).items():
            simulated.setdefault(key, value)
    out: dict[str, float] = {}
    for key, q in quantities.items():
        effect = q.get("effect") or ""
        name = key.removeprefix(f"{effect}.") if effect else key
        if effect in truth.effects:
            value = true_readouts(truth, tip, effect).get(name)
        else:
            value = simulated.get(name, true_readouts(truth, tip, effect).get(name))
        if value is not None:
            out[key] = value
    return out


def draw_flags(result) -> list[str]:
    """The flags of a whole fit (every number of it): model-limited, separation-limited."""
    flags = ["model_limited"] if getattr(result, "model_limited", False) else []
    if any(is_separation_limited(w) for w in getattr(result, "warnings", [])):
        flags.append("separation_limited")
    return flags


def record(estimate: float, sigma: float, truth: float, unit: str, flags: list[str],
           ci: tuple[float, float] | None = None) -> dict:
    """One number of one draw as the output file holds it (SI; ``sigma`` 1 sigma; ``ci`` a 95 % interval)."""
    out = {"estimate": float(estimate), "sigma": float(sigma), "truth": float(truth), "unit": unit,
           "z": z_score(estimate, truth, sigma), "flags": list(flags)}
    if ci is not None:
        low, high = (float(v) for v in ci)
        out.update(ci95_low=low, ci95_high=high,
                   in_ci95=bool(low <= truth <= high) if math.isfinite(low) and math.isfinite(high) else None)
    return out


def force_curve_record(run: RunData, truth_force: np.ndarray, flags: list[str]) -> dict:
    """The force curve's record: RMS error and the reported band (both N: relative x peak |estimated force|)
    over the estimated samples, and z = their ratio (see the module docstring)."""
    estimate = np.asarray(run.force["estimate"], dtype=float)
    used = np.isfinite(estimate) & np.isfinite(truth_force)
    if not used.any():
        return record(math.nan, math.nan, math.nan, "N", flags)
    peak = float(np.max(np.abs(estimate[used])))
    error = float(np.sqrt(np.mean((estimate[used] - truth_force[used]) ** 2)))
    band = float(run.force_total_uncertainty) * peak
    out = record(error, band, 0.0, "N", flags)  # the estimate is the RMS error, its truth 0
    out.update(peak=peak, error_relative=error / peak if peak > 0 else math.nan,
               sigma_relative=float(run.force_total_uncertainty))
    return out


def compare(run: RunData, trace, tip: TipGeometry, separation_given: bool) -> dict[str, dict]:
    """Every number of the fit's run record ``run`` (afmid.runfile.run_data) against the truth of the simulated
    ``trace``: {name: record} for the read-outs that have a truth, the nonlinear parameters the simulation had
    (decay lengths), the rest separation (unless given) and the force curve, in the fit's order."""
    flags = draw_flags(run)
    truths = truth_of_quantities(run.quantities, trace.truth, tip)
    out: dict[str, dict] = {}
    for key in readout_order(run.quantities, run.effects):
        q = run.quantities[key]
        if key not in truths:
            continue
        own = list(flags)
        if q.get("determined", True) is False:
            own.append("undetermined")
        if not q.get("plausible", True):  # the fit's verdict (afmid.fit.plausibility.check_run)
            own.append("implausible")
        out[key] = record(q["value"], q["error"], truths[key], q.get("unit", ""), own, (q["ci_low"], q["ci_high"]))
    for name in nonlinear_order(run.nonlinear, run.effects):
        est = run.nonlinear[name]
        if name == "d" or name in out or name not in trace.truth.parameters:
            continue
        out[name] = record(est["value"], est["error"], float(trace.truth.parameters[name]), est["unit"], flags)
    if not separation_given and "d" in run.nonlinear:
        est = run.nonlinear["d"]
        out[SEPARATION] = record(est["value"], est["error"], float(trace.truth.extra["separation"]), "m", flags)
    out[FORCE_CURVE] = force_curve_record(run, trace.truth.force, flags)
    return out

"""A nonlinear parameter's other valleys: an interval from its profile over the whole searched window.

The profile of a nonlinear parameter (a decay length, the rest separation) is refined around the lowest point
of the outer search's grid (:func:`afmid.fit.pipeline.estimate_nonlinear`), and its sigma is the width of that
one valley (:func:`afmid.fit.profile.robust_profile`). When the residual has a second valley elsewhere in the
window that the data cannot tell from the first, that sigma is confidently wrong: measured on a liquid record
(Q 4, hydration 0.3 nN over 0.5 nm, separation given) the hydration length's profile had valleys at 0.084 nm
and 0.51 nm, 0.8 chi-square units apart; the fit reported 0.077 +- 0.021 nm, 20 sigma from the truth.

Here every local minimum of the outer grid that rises less than :data:`REACH` effective chi-square units above
the lowest point and is cut off from the fit's valley by a rise of more than one unit (so the fit's own
chi-square interval did not reach it) is refined on the fit's support; then

- if it is lower than the fit's minimum by more than one effective unit, the fit moves there (the caller
  profiles again);
- otherwise the 1-sigma grows so that the other valley sits at sqrt(delta chi-square) sigmas: at one sigma
  when the two are equally good, at two sigmas when it is 4 units higher (the profile-likelihood interval
  over the whole window, read at its valleys), and the run warns, naming both valleys.

"Effective" units: the rows of the weak form are correlated (overlapping windows, the smoother across
periods), so one chi-square unit of the residual is worth less than one of independent rows. The profile
measures that: its reported sigma (the block jackknife's where larger) over its chi-square width squared is
the inflation of the chi-square scale, never taken below 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmid.fit.profile import ProfileResult

#: Valleys rising more than this many effective chi-square units above the lowest are not considered (a 3-sigma
#: reach: beyond it the other valley would sit outside any interval afmid reports).
REACH = 9.0


@dataclass(frozen=True)
class Valley:
    """One refined valley of a profile (SI, the parameter's unit): its minimum, its residual, and its rise above
    the fit's minimum in effective chi-square units (negative: lower than the fit's)."""

    value: float
    rss: float
    rise: float


def chi2_inflation(found: ProfileResult) -> float:
    """How much wider the profile's reported sigma is than its chi-square width, squared (>= 1)."""
    if not (math.isfinite(found.sigma) and math.isfinite(found.sigma_width) and found.sigma_width > 0):
        return 1.0
    return max(1.0, (found.sigma / found.sigma_width) ** 2)


def separated_minima(grid: np.ndarray, values: np.ndarray, best: float, level: float, barrier: float) -> list[float]:
    """Grid points of the local minima of ``values`` that lie at or below ``level`` and are separated from the
    valley holding ``best`` by a point above ``barrier`` (both in the units of ``values``), lowest first.

    An end point of the grid counts as a minimum when it is below its one neighbour (the valley may continue
    beyond the searched window: its value there is what the data allow inside it)."""
    grid, values = np.asarray(grid, float), np.asarray(values, float)
    finite = np.isfinite(values)
    grid, values = grid[finite], values[finite]
    if grid.size < 3:
        return []
    order = np.argsort(grid)
    grid, values = grid[order], values[order]
    home = int(np.argmin(np.abs(grid - best)))
    found = []
    for j in range(grid.size):
        left = values[j - 1] if j > 0 else math.inf
        right = values[j + 1] if j < grid.size - 1 else math.inf
        lowest_here = values[j] <= left and values[j] <= right and (values[j] < left or values[j] < right)
        if not (lowest_here and values[j] <= level):  # a flat stretch is no minimum of its own
            continue
        lo, hi = sorted((j, home))
        if hi - lo < 2 or float(np.max(values[lo:hi + 1])) <= barrier:
            continue
        found.append((values[j], float(grid[j])))
    return [g for _, g in sorted(found)]


def other_valleys(found: ProfileResult, grid: np.ndarray, values: np.ndarray, s2: float,
                  refine: Callable[[float], ProfileResult | None], scale: float = 1.0,
                  allowance: float = 0.0) -> list[Valley]:
    """The refined other valleys of a profile within :data:`REACH` effective units, lowest first.

    ``found`` is the fit's profile (its minimum's residual is the lowest of its values); ``grid``/``values`` the
    outer search's coarse profile over the whole window (any library: only its shape is used to find the
    valleys); ``s2`` the residual variance of one chi-square unit; ``refine(start)`` profiles the parameter
    again from ``start`` on the fit's support (None where it cannot be evaluated). A model-limited fit weighs
    the rises against its misfit (:class:`Misfit`): ``scale`` (>= 1) multiplies the effective unit and
    ``allowance`` (residual units) is taken off every rise before it is counted."""
    if not (math.isfinite(found.value) and s2 > 0 and np.size(grid) >= 3):
        return []
    here = float(np.min(found.values)) if np.size(found.values) else math.nan
    if not math.isfinite(here):
        return []
    unit = s2 * chi2_inflation(found) * max(scale, 1.0)
    allowance = max(allowance, 0.0) if math.isfinite(allowance) else 0.0
    coarse = np.asarray(values, float)
    lowest = float(np.min(coarse[np.isfinite(coarse)])) if np.isfinite(coarse).any() else math.nan
    if not math.isfinite(lowest):
        return []
    starts = separated_minima(grid, coarse, found.value, lowest + allowance + REACH * unit, lowest + unit)
    valleys: list[Valley] = near_valleys(found, unit, allowance)
    for start in starts:
        other = refine(start)
        if other is None or not math.isfinite(other.value) or not np.size(other.values):
            continue
        rss = float(np.min(other.values))
        if not math.isfinite(rss) or abs(other.value - found.value) <= max(found.sigma, 0.0):
            continue  # refined back into the fit's own valley, or inside its interval already
        if any(abs(other.value - v.value) <= max(found.sigma, 0.0) for v in valleys):
            continue  # already found among the profile's own points
        rise = (rss - here - allowance) / unit
        if rise <= REACH:
            valleys.append(Valley(other.value, rss, rise))
    return sorted(valleys, key=lambda v: v.rss)


def near_valleys(found: ProfileResult, unit: float, allowance: float = 0.0) -> list[Valley]:
    """The other valleys among the fit's own profile points (``found.grid`` / ``found.values``: the zoom, the
    chi-square interval and the jackknife's grid, a few sigma either side of the minimum, on the fit's support).

    The outer search's grid (0.375 nm for the separation) steps over a valley a few tenths of a nanometre from
    the fit's: measured on a coverage draw behind a 4.4 f0 detector with 11 pm of noise (instrument.yaml, seed
    2804, draw 9) the separation's profile had its minimum at 7.00 nm (chi-square width 53 pm) and a second
    valley at 6.68-6.71 nm, 3.0 units higher behind a 6.1-unit barrier; the truth was 6.67 nm (z +6.1). A point
    counts when it is a local minimum of the points, within :data:`REACH` effective units (``unit``: residual
    per effective chi-square unit) of the fit's minimum, and cut off from it by a rise of more than one unit
    above itself (a wiggle on the valley's flank is not). Its rise is read at the point (no refit: a refit from
    there slides back into the deeper valley a few grid steps away). ``allowance`` (residual units) is taken
    off each rise, as in :func:`other_valleys`."""
    grid, values = np.asarray(found.grid, float), np.asarray(found.values, float)
    keep = np.isfinite(values)
    grid, values = grid[keep], values[keep]
    if grid.size < 3 or not unit > 0:
        return []
    order = np.argsort(grid)
    grid, values = grid[order], values[order]
    here = float(np.min(values))
    home = int(np.argmin(np.abs(grid - found.value)))
    valleys = []
    for j in range(grid.size):
        left = values[j - 1] if j > 0 else math.inf
        right = values[j + 1] if j < grid.size - 1 else math.inf
        # the window's end points are not minima here: the profile was only followed that far
        if not (j > 0 and j < grid.size - 1 and values[j] <= left and values[j] <= right):
            continue
        lo, hi = sorted((j, home))
        if hi - lo < 2 or float(np.max(values[lo:hi + 1])) - values[j] <= unit:
            continue
        rise = (float(values[j]) - here - allowance) / unit
        if rise <= REACH and abs(grid[j] - found.value) > max(found.sigma, 0.0):
            valleys.append(Valley(float(grid[j]), float(values[j]), rise))
    return valleys


def covering_sigma(value: float, sigma: float, valleys: list[Valley]) -> float:
    """The 1-sigma that puts each other valley at sqrt(rise) sigmas from ``value`` (at one sigma when it is as
    good or better), never below ``sigma``."""
    needed = [abs(v.value - value) / max(1.0, math.sqrt(max(v.rise, 0.0))) for v in valleys]
    return max([sigma if math.isfinite(sigma) else 0.0, *needed])


def describe(name: str, unit: str, value: float, sigma: float, valleys: list[Valley]) -> str:
    """The warning of a parameter whose interval was widened to cover other valleys (nm for lengths)."""
    scale, shown = (1e9, "nm") if unit == "m" else (1.0, unit)
    others = "; ".join(f"{scale * v.value:.3g} {shown} ({max(v.rise, 0.0):.2g} effective chi-square units higher)"
                       for v in valleys)
    return (f"{name}: the residual has another valley the data cannot rule out: {others}, besides the fit's "
            f"{scale * value:.3g} {shown}; its 1-sigma now covers them ({scale * sigma:.3g} {shown}), and so do the "
            "read-outs that depend on it")


def cover_other_valleys(name: str, est, found: ProfileResult, params: dict,
                        profile: Callable[[str, object], ProfileResult], warnings: list[str]) -> bool:
    """Check the fit's profile of nonlinear parameter ``name`` against the other valleys of its outer search.

    ``est`` is its :class:`afmid.fit.search.NonlinearEstimate` (the outer grid, value and sigma: updated in
    place), ``found`` its profile on the fit's support, ``params`` the fit's parameters (updated in place when
    the fit moves), ``profile(name, est)`` profiles it again at the current ``params`` on the fit's support
    (with its jackknife). Appends a warning when the sigma grows. Returns True when the fit moved to a lower
    valley (the caller selects the support again)."""
    s2 = found.s2
    moved = False

    def refine(start: float) -> ProfileResult | None:
        held = params[name]
        params[name] = start
        try:
            return profile(name, est)
        finally:
            params[name] = held

    valleys = other_valleys(found, est.grid, est.objective, s2, refine)
    if valleys and valleys[0].rise < -1.0:  # a lower valley: the fit moves there and looks again
        params[name] = valleys[0].value
        found = profile(name, est)
        params[name] = found.value
        est.value, est.sigma = found.value, found.sigma
        est.sigma_width, est.sigma_jackknife = found.sigma_width, found.sigma_jackknife
        moved = True
        valleys = other_valleys(found, est.grid, est.objective, found.s2, refine)
    if not valleys:
        return moved
    sigma = covering_sigma(est.value, est.sigma, valleys)
    if sigma > (est.sigma if math.isfinite(est.sigma) else 0.0):
        est.sigma = sigma
        warnings.append("warning: " + describe(name, est.unit, est.value, sigma, valleys))
    return moved


@dataclass(frozen=True)
class Misfit:
    """What a model-limited fit's failure is worth on a nonlinear parameter's profile (the profile's chi-square
    is then not the noise's alone, so neither its curvature nor the rise to another valley is a noise interval).

    ``ratio``: the cross-validated error over its noise floor; the chi-square unit is scaled by ``ratio**2``
    when above 1 (the residual per row the model leaves, as a scale factor on a chi-square with a misfit).
    ``allowance`` (residual units, the profile's weighted sum of squares): the rise at the fit's own minimum when
    its unphysical read-outs are held at their physical range's edge (their terms dropped): a law with physical
    parameters is that much worse there, so another valley up to that much higher is one such a law prefers.
    Measured on instrument.yaml seed 2804 draw 48 (20 samples per period, aliasing warned, error / floor 0.97):
    the separation's minimum at 9.43 nm needs a negative Hamaker constant and E*; dropping the tail costs 2339
    units there; a second valley at 7.50 nm, 37.5 units higher (19 effective), has H 9.2e-20 J and E* 3.4 GPa
    (truth 7.70 nm, 6.3e-20 J, 3.7 GPa); the fit's own curvature sigma was 49 pm (z +35)."""

    ratio: float = math.nan
    allowance: float = 0.0

    @property
    def scale(self) -> float:
        """The chi-square unit's factor (>= 1)."""
        return max(1.0, self.ratio**2) if math.isfinite(self.ratio) else 1.0


def misfit_text(misfit: Misfit, s2: float) -> str:
    """How the profile was weighed, in words (``s2``: residual units per chi-square unit)."""
    parts = []
    if misfit.scale > 1.0:
        parts.append(f"its chi-square unit scaled by (error / floor)^2 = {misfit.scale:.2g}")
    if misfit.allowance > 0 and s2 > 0:
        parts.append(f"a valley up to {misfit.allowance / s2:.3g} chi-square units higher counted as good as the "
                     "fit's: a law with physical parameters loses that much at the fit's own minimum")
    return " and ".join(parts) or "its chi-square as the noise's"


def cover_model_limited(name: str, est, found: ProfileResult, misfit: Misfit,
                        refine: Callable[[float], ProfileResult | None], warnings: list[str]) -> float:
    """The 1-sigma of nonlinear parameter ``name`` of a model-limited fit: its profile over the whole searched
    window weighed against the model's misfit (:class:`Misfit`), never a local curvature sigma alone.

    The fit's own valley's sigma grows by sqrt(scale); every other valley of the window within :data:`REACH`
    weighed units (:func:`other_valleys` with the misfit) is put at sqrt(rise) sigmas (at one sigma when the
    misfit allows it as good), and the run warns naming them. ``est`` (its ``sigma``) is updated in place;
    returns the sigma before (the caller propagates the difference into the read-outs)."""
    before = est.sigma
    if not (math.isfinite(found.value) and math.isfinite(before)):
        return before
    local = before * math.sqrt(misfit.scale)
    valleys = other_valleys(found, est.grid, est.objective, found.s2, refine, misfit.scale, misfit.allowance)
    sigma = covering_sigma(est.value, local, valleys)
    if sigma <= before:
        return before
    est.sigma = sigma
    scale, shown = (1e9, "nm") if est.unit == "m" else (1.0, est.unit)
    others = "; ".join(f"{scale * v.value:.3g} {shown} ({max(v.rise, 0.0):.2g} weighed units higher)" for v in valleys)
    where = (f"the profile over the searched window has other valleys the model's failure cannot rule out: "
             f"{others}; " if valleys else "")
    warnings.append(f"warning: {name}: the fit is model-limited, so its profile is weighed against the model's "
                    f"misfit ({misfit_text(misfit, found.s2)}): {where}its 1-sigma grows from "
                    f"{scale * before:.3g} to {scale * sigma:.3g} {shown}, and so do the read-outs that depend on it")
    return before

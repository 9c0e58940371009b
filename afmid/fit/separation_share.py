"""The estimated rest separation's share of the force curve's uncertainty, and the record that would shrink it.

With ``sample.separation`` absent the fit estimates d, and its force law's coefficients move with d along a
valley: a smaller d (deeper indentation) with a softer sample imitates the data almost as well. The
separation's 1-sigma (:mod:`afmid.fit.profile`) says how far along the valley the data still agree; the
force curve at d +- sigma says what that costs. On short or noisy records this is the force's largest
uncertainty, and no better estimator removes it: the record does not hold the information (measured with
``scripts/separation_budget.py --information``: on the poor instrument, 10 pm detector noise, 50 samples per
period, 50 periods, a DMT law 600 pm off with E* and H re-chosen differs from the truth by chi-square 0.86 over
the whole record while its force curve differs by 12.5 % of the peak; docs/accuracy.md, "Separation
unknown").

The share is the RMS over the estimated samples of the change of the model force refitted at d + sigma or at
d - sigma (the support selected again there, the other nonlinear parameters held), the larger of the two,
divided by the largest |force|: a relative 1 sigma, like the calibration share. (Half the difference of the two
sides, as before, equals it where the force is linear in d; where it is not, it missed the change: poor
instrument seed 206, d 0.8 nm off at 1.3 sigma, force error 21 % against a share of 3.8 %, the tip barely
touching at d + sigma.) The separation's sigma falls as 1 / sqrt(periods)
(the profile's chi-square curvature grows with the number of periods), and so, to first order, does the
share: ``periods_for`` says how long a record would bring it to a target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import afmid.fit.regression as regression
from afmid.errors import AfmidError
from afmid.fit.forces import estimated_peak, model_force_samples
from afmid.fit.system import build_system

#: A separation share above this fraction of the peak force is reported as a warning (the force curve is then
#: known no better than this, whatever its statistical error bars say).
WARN_FRACTION = 0.01

#: How the warning starts (a map pixel is not made suspect by it: its read-outs' error bars already carry the
#: separation's sigma; the share is about the force curve).
WARNING_START = "separation-limited:"
#: Warning text (numbers filled in).
SEPARATION_LIMITED_TEXT = (
    WARNING_START + " the rest separation is estimated to +-{sigma_nm:.3g} nm (1 sigma), and within it the "
    "force curve moves by {share:.2g} % of its peak (1 sigma): the record cannot tell a deeper indentation of a "
    "softer sample from the fitted one; give sample.separation if it is known, or record about {periods} periods "
    "(now {now}) to bring this share to {target:.2g} %")


@dataclass(frozen=True)
class SeparationShare:
    """The separation's share of the force's uncertainty (relative to the peak |force|, 1 sigma)."""

    relative: float  # NaN when not computed (separation given, no sigma, a refit failed)
    sigma: float  # m, the separation's 1 sigma it was computed with
    periods: int  # drive periods in the record

    def periods_for(self, target: float = WARN_FRACTION) -> int | None:
        """Periods after which the share would fall to ``target`` (1 / sqrt(periods) scaling); None if not
        computed."""
        if not (math.isfinite(self.relative) and self.relative > 0):
            return None
        return int(math.ceil(self.periods * max(self.relative / target, 1.0) ** 2))

    def warning(self) -> str | None:
        """The warning line when the share exceeds :data:`WARN_FRACTION`, else None."""
        if not (math.isfinite(self.relative) and self.relative > WARN_FRACTION):
            return None
        return SEPARATION_LIMITED_TEXT.format(sigma_nm=1e9 * self.sigma, share=100 * self.relative,
                                              periods=f"{self.periods_for():,}", now=f"{self.periods:,}",
                                              target=100 * WARN_FRACTION)


NOT_COMPUTED = SeparationShare(math.nan, math.nan, 0)


def is_separation_limited(warning: str) -> bool:
    """True for the warning line :meth:`SeparationShare.warning` gives (with or without its "warning: ")."""
    return warning.removeprefix("warning: ").startswith(WARNING_START)


def separation_share(prep, library, params: dict, select, sigma: float,
                     force_estimate: np.ndarray) -> SeparationShare:
    """The force's share of the separation's uncertainty ``sigma`` (m, 1 sigma) around ``params["d"]``.

    ``select`` maps the system at d +- sigma to the support fitted there (the fit's own selection: near the
    contact point a term's column can vanish on one side, e.g. a contact term once the tip no longer
    touches, and another support then explains the data); ``force_estimate`` is the fit's per-sample force
    (N; NaN where not estimated), whose largest |value| is the peak the share is relative to.
    """
    if not (math.isfinite(sigma) and sigma > 0):
        return NOT_COMPUTED
    used, peak = estimated_peak(force_estimate)
    if peak <= 0:
        return NOT_COMPUTED
    changes = []
    for sign in (1, -1):
        trial = dict(params, d=params["d"] + sign * sigma)
        try:
            system = build_system(prep, library, trial)
        except AfmidError:  # e.g. the library cannot be evaluated there: the other side alone
            continue
        coef, _ = regression.subset_fit(regression.combine(system.T_blocks), select(system))
        change = (model_force_samples(prep, library, system, coef) - force_estimate)[used]
        if np.isfinite(change).all():
            changes.append(float(np.sqrt(np.mean(change**2))))
    if not changes:
        return NOT_COMPUTED
    return SeparationShare(max(changes) / peak, float(sigma), int(prep.blocks.n_blocks))

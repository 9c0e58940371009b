"""When the data cannot decide between candidate effects (issue 13 part 4: poor signals).

On a poor trace (10 pm of detector noise, 50 samples per period) several catalog effects can each explain a
residual to its noise floor: a hidden viscoelastic sample was read as "missing effect: capillary" because the
capillary refit beat the viscoelastic one by 14 BIC units. Such a difference between two non-nested models
carries its own sampling error, which BIC does not state. Vuong's test (Econometrica 57, 307 (1989)) measures
it: with the per-period (per-block) chi-square of both refits, the difference of their BICs is compared with
the standard deviation of the summed per-block differences, sqrt(B * var(d_b)). A rival closer than
:data:`VUONG_SIGMAS` of those is not told apart from the best candidate: the diagnosis then says that the
data cannot decide between them and names none.

On a good trace the per-block differences of a right and a wrong effect are consistent across the periods
(the wrong one misses the force in every period), so the summed difference stands many sigmas out.
"""

from __future__ import annotations

import math

import numpy as np

import afmid.fit.regression as regression

#: A rival whose BIC is within this many standard deviations of the summed per-block chi-square difference of
#: the best candidate is not told apart from it (two-sided 5 % for a normal statistic: 1.96).
VUONG_SIGMAS = 2.0


def block_chi2(result) -> np.ndarray:
    """Per-block weighted residual sum of squares of a fit (its whitened rows; length = blocks)."""
    return regression.block_rss(result.system.T_blocks, result.coef)


def separation_sigmas(best, rival) -> float:
    """|BIC(rival) - BIC(best)| in standard deviations of the summed per-block chi-square difference (inf
    when the per-block values are missing or the blocks differ)."""
    a, b = getattr(best, "block_chi2", None), getattr(rival, "block_chi2", None)
    if a is None or b is None or a.shape != b.shape or a.size < 3:
        return math.inf
    diff = b - a
    sd = math.sqrt(a.size * float(np.var(diff, ddof=1)))
    gap = abs(rival.delta_bic - best.delta_bic)
    return gap / sd if sd > 0 else math.inf


def rivals(best, trials: list) -> list:
    """The other candidates that explain the residual (no significant misfit left, plausible values) and that
    the per-block evidence does not tell apart from ``best`` (closer than :data:`VUONG_SIGMAS`)."""
    out = []
    for t in trials:
        if t is best or t.effect == best.effect or not t.explains or t.implausible:
            continue
        if separation_sigmas(best, t) < VUONG_SIGMAS:
            out.append(t)
    return out


def verdict(best, others: list) -> str:
    names = ", ".join(f"`{t.effect}`" for t in [best] + others)
    gaps = "; ".join(f"{t.effect} ΔBIC {t.delta_bic - best.delta_bic:+.0f} ({separation_sigmas(best, t):.1f} σ)"
                     for t in others)
    return (f"missing effect, but the data cannot decide which: {names} each explain the residual "
            f"(error {best.error_after:.3g} vs noise floor {best.noise_floor_after:.3g}), and their BIC differences "
            f"are within {VUONG_SIGMAS:g} standard deviations of the per-period evidence ({gaps}); record more "
            "periods, with less detector noise or at a higher sample rate, or fix the separation")

"""Requests that cannot be carried out as written: terms with nothing to fit.

A custom term in ``model.terms`` becomes one column of the regression. A term
that is zero for every value of the variables (``0``, ``x - x``) or not finite
anywhere (``1/0``, ``log(-1)``) gives a column the fit cannot use; without this
check the first is silently given a coefficient of 0 and the second stops the
fit later with a message about the trajectory. A constant term (``1``) is a
constant force: legitimate, unless ``fit.baseline: free`` already fits one (the
two columns would be the same, and the split between them arbitrary).

Only terms made of numbers and the variables are probed: a term with
parameters or states depends on values not known before the fit.
"""

from __future__ import annotations

import numpy as np

import afmid.terms.expr as expr

#: Probe values of every variable: 0 and +- 10^-15 .. 10^3 (SI), wide enough for any unit of the variables
#: (m, m/s, s) so that a gate that is true somewhere in a physical range is true at some probe point.
_MAGNITUDES = np.concatenate([[0.0], np.logspace(-15, 3, 37), -np.logspace(-15, 3, 37)])


def _probe() -> np.ndarray:
    """(variables, points) of values: each variable runs through the magnitudes in its own order."""
    rng = np.random.default_rng(0)  # fixed: the same verdict on every run
    rows = [_MAGNITUDES] + [rng.permutation(_MAGNITUDES) for _ in expr.VARIABLES[1:]]
    return np.array(rows)


def term_problem(text: str, baseline: str) -> str | None:
    """Why the custom term ``text`` cannot be a column of the fit, or None (also for a malformed term:
    the library reports those with the place of the error)."""
    try:
        if expr.free_names(text):
            return None
        values = expr.evaluate_numpy(text, _probe())
    except (expr.ExpressionError, ValueError):
        return None
    finite = np.isfinite(values)
    if not finite.any():
        return f"the term {text!r} is not finite for any value of the variables ({values[0]}): nothing to fit"
    if np.all(values[finite] == 0) and finite.all():
        return f"the term {text!r} is zero for every value of the variables: nothing to fit"
    if finite.all() and np.ptp(values) == 0 and baseline == "free":
        return (f"the term {text!r} is a constant force, which fit.baseline: free already fits (the offset); "
                "remove the term or set fit.baseline: zero")
    return None

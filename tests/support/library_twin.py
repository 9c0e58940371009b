"""The plain-NumPy twin of :meth:`afmid.physics.library.Library.evaluate` (numba only in small kernels, each with a
NumPy twin the tests compare against): every column by :func:`afmid.terms.expr.evaluate_numpy` of its term's
expression, the states scanned by the NumPy twins of the hysteresis kernels. Test code: the shipped Library has
one path, the kernels (issue 30: no backend switch for the tests in the package).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

import afmid.terms.expr as expr
from afmid.kernels.hysteresis import scan_hysteresis_numpy, scan_relaxation_numpy
from afmid.physics.library import Library, trajectory_variables


def evaluate_numpy(library: Library, x: np.ndarray, xdot: np.ndarray, t: np.ndarray,
                   params: Mapping[str, float]) -> np.ndarray:
    """Library columns (N, p) along a trajectory (x m, xdot m/s, t s), as ``library.evaluate`` gives them, without
    numba. Slow; for comparisons only."""
    variables = trajectory_variables(x, xdot, t, params["d"], params["a0"], len(library.states))
    _, gates = library.compile(params)
    base = len(expr.VARIABLES)
    for k, (first, second) in enumerate(gates):
        if not isinstance(second, expr.Program):  # a relaxing state: (its source, its time constant in s)
            source = expr.evaluate_numpy(first, variables)
            variables[base + k] = scan_relaxation_numpy(source, variables[6], second, source[0])
            continue
        on = expr.evaluate_numpy(first, variables)
        variables[base + k] = scan_hysteresis_numpy(on, expr.evaluate_numpy(second, variables), float(on[0] != 0))
    out = np.empty((x.size, len(library.terms)))
    for j, term in enumerate(library.terms):
        out[:, j] = expr.evaluate_numpy(term.expression, variables, dict(params), library.state_names)
    return out

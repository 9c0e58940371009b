"""One-dimensional searches of the fit's nonlinear parameters (rest separation, decay lengths).

Plain numerics on an objective (a residual sum of squares as a function of one
parameter) plus the range each parameter is searched over: no data, no
library columns. :mod:`afmid.fit.pipeline` builds the objectives; the refinement of a
minimum on its profile and its sigma are in :mod:`afmid.fit.profile`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afmid.physics.library import Library
from afmid.physics.effects import EFFECTS

#: Searched decay lengths and distances stop here, m (the library columns vanish beyond).
LENGTH_SEARCH_MAX = 20e-9
#: A log grid cannot hold a lower bound of 0 (no neck, no hysteresis): the grid starts here, m, and 0 is
#: tried on its own.
LOG_GRID_START = 0.02e-9


@dataclass(frozen=True)
class SearchRange:
    """Where the outer search looks for one nonlinear parameter of a library (SI)."""

    name: str
    low: float  # first grid point (> 0: the grid is logarithmic)
    high: float
    unit: str
    zero_allowed: bool  # the parameter may be 0 (tried on its own, off the log grid)


def search_range(library: Library, name: str, medium: str = "air") -> SearchRange:
    """The search range of the nonlinear parameter ``name`` of one of ``library``'s effects in the sample's
    ``medium`` (the declared one there, else the valid range)."""
    p = next(p for e in library.effects for p in EFFECTS.get(e).parameters if p.name == name)
    low, high = p.search_span(medium)
    first = max(low, 1e-12) if low > 0 else LOG_GRID_START
    top = min(high, LENGTH_SEARCH_MAX) if p.unit == "m" else high  # a time (relaxation_time) keeps its range
    return SearchRange(name, first, top, p.unit, low == 0)


@dataclass
class NonlinearEstimate:
    name: str
    value: float
    sigma: float
    unit: str
    estimated: bool
    grid: np.ndarray = field(default_factory=lambda: np.zeros(0))
    objective: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bounds: tuple[float, float] = (-math.inf, math.inf)  # searched range
    # the parts of sigma from the profile (afmid.fit.profile.ProfileResult; NaN: not profiled)
    sigma_width: float = math.nan
    sigma_jackknife: float = math.nan
    #: the record's Cramér-Rao bound on sigma (afmid.fit.information_bound; NaN: not computed)
    information_bound: float = math.nan


def search_1d(objective, lo: float, hi: float, n_grid: int, log_scale: bool, tolerance: float = 1e-6
              ) -> tuple[float, np.ndarray, np.ndarray]:
    """Grid then bounded Brent refinement to ``tolerance`` times the width of the bracket around the grid's best
    point (on a log scale: to ``tolerance`` in the logarithm); returns (argmin, grid, values)."""
    from scipy.optimize import minimize_scalar

    grid = np.geomspace(lo, hi, n_grid) if log_scale else np.linspace(lo, hi, n_grid)
    values = np.array([objective(g) for g in grid])
    values[~np.isfinite(values)] = np.inf
    i = int(np.argmin(values))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    if a == b:
        return float(grid[i]), grid, values
    if log_scale:
        res = minimize_scalar(lambda u: objective(math.exp(u)), bounds=(math.log(a), math.log(b)), method="bounded",
                              options={"xatol": tolerance})
        best = math.exp(res.x)
    else:
        res = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": (b - a) * tolerance})
        best = float(res.x)
    return (best, grid, values) if res.fun <= values[i] else (float(grid[i]), grid, values)

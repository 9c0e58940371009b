"""One-dimensional searches of the fit's nonlinear parameters (rest separation, decay lengths).

Plain numerics on an objective (a residual sum of squares as a function of one
parameter) plus the range each parameter is searched over: no data, no
library columns. :mod:`afmid.fit` builds the objectives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .library import Library
from .physics import EFFECTS

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


def search_range(library: Library, name: str) -> SearchRange:
    """The search range of the nonlinear parameter ``name`` of one of ``library``'s effects."""
    p = next(p for e in library.effects for p in EFFECTS.get(e).parameters if p.name == name)
    low = max(p.low, 1e-12) if p.low > 0 else LOG_GRID_START
    return SearchRange(name, low, min(p.high, LENGTH_SEARCH_MAX), p.unit, p.low == 0)


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


def search_1d(objective, lo: float, hi: float, n_grid: int, log_scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Grid then bounded Brent refinement; returns (argmin, grid, values)."""
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
                              options={"xatol": 1e-6})
        best = math.exp(res.x)
    else:
        res = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": (b - a) * 1e-6})
        best = float(res.x)
    return (best, grid, values) if res.fun <= values[i] else (float(grid[i]), grid, values)


def parabola_vertex(grid: np.ndarray, values: np.ndarray, s2: float) -> tuple[float, float, int]:
    """Vertex and curvature of a parabola through the profile points within 9 chi-square units of its minimum
    (at least the 5 around it); returns (vertex clipped to those points, curvature, number of points)."""
    i = int(np.argmin(values))
    near = np.flatnonzero(values - values[i] <= 9 * s2)
    if near.size < 5:
        near = np.arange(max(i - 2, 0), min(i + 3, grid.size))
    c2, c1, _ = np.polyfit(grid[near], values[near], 2)
    if not c2 > 0:
        return float(grid[i]), c2, near.size
    return float(np.clip(-c1 / (2 * c2), grid[near].min(), grid[near].max())), c2, near.size


def profile_minimum(objective, center: float, half_width: float, s2: float, lo: float = -math.inf,
                    hi: float = math.inf, n_points: int = 13) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Minimum and 1-sigma of a chi-square-like profile ``objective`` (a residual sum of squares), from a parabola.

    ``s2`` is the residual variance (rss / s2 is the chi-square). The profile
    is evaluated on a grid of ``n_points`` over ``center +- half_width``
    (clipped to [lo, hi]); the window moves while the minimum sits on its
    edge, widens while the profile is flatter than the window and narrows
    while it is much sharper. A parabola through the points within 9
    chi-square units of the minimum gives the estimate (its vertex) and
    sigma = sqrt(s2 / curvature): robust to the small steps the quadrature
    leaves in the residual, where a three-point curvature is not. Returns
    (value, sigma, grid, values); sigma is NaN when the profile has no minimum
    in [lo, hi] (the parameter is not determined by the data).
    """
    grid = values = np.zeros(0)
    for _ in range(8):
        a, b = max(lo, center - half_width), min(hi, center + half_width)
        grid = np.linspace(a, b, n_points)
        values = np.array([objective(g) for g in grid])
        values[~np.isfinite(values)] = np.inf
        i = int(np.argmin(values))
        if not np.isfinite(values[i]) or np.isfinite(values).sum() < 5:
            return center, math.nan, grid, values
        if (i == 0 and a > lo) or (i == n_points - 1 and b < hi):  # on the window's edge: move
            center = float(grid[i])
            continue
        ok = np.isfinite(values)
        best, c2, n_near = parabola_vertex(grid[ok], values[ok], s2)
        if not c2 > 0:
            break
        sigma = math.sqrt(s2 / c2)
        if sigma > half_width and half_width < (hi - lo):  # flatter than the window: look wider
            half_width *= 3
            center = best
        elif n_near < 5 and sigma < half_width / 6:  # much sharper than the grid: look closer
            half_width = 3 * sigma
            center = best
        else:
            return best, sigma, grid, values
    i = int(np.argmin(values))
    return float(grid[i]), math.nan, grid, values

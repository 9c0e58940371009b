"""Robust profile of one nonlinear parameter (rest separation, decay length) and an honest 1-sigma.

The fit's residual as a function of a nonlinear parameter is not a parabola:
the contact point makes it V-shaped near the minimum when the sample is stiff,
the quadrature leaves small steps in it, and its rows (overlapping weak-form
windows of neighbouring periods, a smoother across periods, noise in the
regressors) are correlated, so the chi-square curvature with a white-noise
residual variance understates the spread of the minimum. Hence:

- the minimum is located by zooming in on the grid point with the lowest
  residual, until the grid step is below a tenth of the chi-square
  half-width (so there are always enough points near the minimum: the old
  fallback to 5 points 50 pm apart is gone);
- where the profile is a parabola around its minimum, the vertex of a
  parabola through the points within 9 chi-square units is the estimate (it
  averages over the small steps the quadrature leaves) and its curvature gives
  the chi-square sigma; where it is not (the vertex lands away from the lowest
  point: a V, a kink at the contact point), the lowest point refined between
  its neighbours is the estimate and the chi-square sigma is half the interval
  where the profile rises by one chi-square unit (residual variance ``s2``),
  read off the evaluated points (a V gets its true width, not the zero width of
  its kink's curvature), with the finest grid step added in quadrature;
- the spread of the minimum over a block jackknife (the periods split into
  contiguous groups, each left out in turn: the correlation between
  neighbouring rows stays inside a group) measures what the chi-square misses;
- the reported 1-sigma is the larger of the two.

Everything here is plain numerics on per-block factors (:func:`afmid.fit.regression.combine`):
the caller (:func:`afmid.fit.pipeline.profile_parameter`) gives a function that returns
the weak-form system's block factors at a parameter value. SI units throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import afmid.fit.regression as regression

#: Contiguous groups of periods in the block jackknife (fewer when the record has fewer blocks than
#: 2 per group). 12 groups: the jackknife's own spread is ~20 % (11 degrees of freedom), so |error| < 2 sigma
#: holds in ~93 % of fits when the sigma is right.
JACKKNIFE_GROUPS = 12
#: The finest grid step near the minimum is at most this fraction of the chi-square half-width.
RESOLUTION_FRACTION = 0.1
#: Points per zoom / per bracketing window.
ZOOM_POINTS = 9
WINDOW_POINTS = 13
#: Replicate minima must lie this many half-widths inside the evaluated range; the range grows (x3) until
#: they do, at most JACKKNIFE_WIDENINGS times.
JACKKNIFE_WIDENINGS = 3


@dataclass
class ProfileResult:
    """The minimum of a residual profile and its 1-sigma (SI, the parameter's unit)."""

    value: float
    sigma: float  # reported 1 sigma: max(width, jackknife) with the resolution in quadrature; NaN: undetermined
    sigma_width: float = math.nan  # half the interval where the chi-square rises by 1
    sigma_jackknife: float = math.nan  # spread of the minimum over the block jackknife (NaN: not computed)
    resolution: float = math.nan  # finest grid step at the minimum
    grid: np.ndarray = field(default_factory=lambda: np.zeros(0))  # every evaluated value, sorted
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))  # residual sum of squares there
    evaluations: int = 0
    s2: float = math.nan  # the residual variance of one chi-square unit the profile was read with
    #: where the chi-square interval runs to a searched bound instead of closing: "" (closed), "below",
    #: "above" or "both" (the profile is flatter than one unit over the whole window: not located)
    open_side: str = ""


class GroupedProfile:
    """A residual profile evaluated from per-block factors, kept per group of contiguous blocks.

    ``factors_at(value)`` returns the system's block factors (blocks, rows, columns + 1) and its number of
    weak-form rows at a parameter value (None when the library cannot be evaluated there); ``mask`` selects the fitted columns. The factors of each
    group are combined once per value, so the full profile and every leave-one-group-out profile cost one small
    QR each, no library evaluation.
    """

    def __init__(self, factors_at, mask: np.ndarray | None, n_groups: int = JACKKNIFE_GROUPS):
        self.factors_at = factors_at
        self.mask = mask
        self.n_groups = n_groups
        self.groups: dict[float, np.ndarray | None] = {}
        self.full: dict[float, float] = {}
        self.n_rows = 0

    def __call__(self, value: float) -> float:
        value = float(value)
        if value not in self.full:
            found = self.factors_at(value)
            if found is None:
                self.groups[value], self.full[value] = None, math.inf
            else:
                T, n_rows = found
                self.n_rows = max(self.n_rows, n_rows)
                n_groups = min(self.n_groups, T.shape[0] // 2)
                R = _group_factors(T, max(n_groups, 1))
                self.groups[value] = R if n_groups >= 2 else None
                self.full[value] = self._rss(R)
        return self.full[value]

    def _rss(self, R: np.ndarray) -> float:
        mask = np.ones(R.shape[-1] - 1, dtype=bool) if self.mask is None else self.mask
        rss = regression.subset_fit(regression.combine(R), mask)[1]
        return rss if math.isfinite(rss) else math.inf

    def leave_out(self, value: float, group: int) -> float:
        """The residual at ``value`` without the blocks of ``group`` (inf where not evaluable)."""
        R = self.groups.get(float(value))
        if R is None:
            return math.inf
        return self._rss(np.delete(R, group, axis=0))

    def leave_each_out(self, value: float) -> np.ndarray:
        """:meth:`leave_out` of every group at ``value`` (G,), the leave-one-out factors combined in one call."""
        R = self.groups.get(float(value))
        G = self.jackknife_groups()
        if R is None:
            return np.full(G, math.inf)
        others = np.stack([np.delete(R, group, axis=0) for group in range(R.shape[0])])
        mask = np.ones(R.shape[-1] - 1, dtype=bool) if self.mask is None else self.mask
        rss = np.array([regression.subset_fit(T, mask)[1] for T in regression.combine_each(others)])
        return np.where(np.isfinite(rss), rss, math.inf)

    def jackknife_groups(self) -> int:
        return next((R.shape[0] for R in self.groups.values() if R is not None), 0)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.array(sorted(self.full))
        return x, np.array([self.full[v] for v in x])


def _group_factors(T: np.ndarray, n_groups: int) -> np.ndarray:
    """:func:`afmid.fit.regression.combine` of each of ``n_groups`` contiguous groups of the block factors ``T``
    (``np.array_split``'s groups: at most two sizes), one stacked call per size: the same bits."""
    parts = np.array_split(np.arange(T.shape[0]), n_groups)
    R = np.empty((n_groups, T.shape[-1], T.shape[-1]))
    for size in sorted({p.size for p in parts}):
        same = [g for g, p in enumerate(parts) if p.size == size]
        R[same] = regression.combine_each(np.stack([T[parts[g]] for g in same]))
    return R


def local_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """The lowest point refined by a parabola through it and its two neighbours, kept between them.

    Local on purpose: three adjacent points bend only where the minimum is, so a kink costs at most one grid
    step (a parabola through many points of a V misplaces its vertex)."""
    i = int(np.argmin(y))
    if i == 0 or i == x.size - 1 or not np.isfinite(y[i - 1:i + 2]).all():
        return float(x[i])
    x0, x1, x2 = x[i - 1:i + 2]
    y0, y1, y2 = y[i - 1:i + 2]
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / denom
    if not a > 0:
        return float(x[i])
    return float(np.clip(-b / (2 * a), x0, x2))


def _crossing(x: np.ndarray, y: np.ndarray, i: int, level: float, step: int) -> float:
    """Where y first rises to ``level`` walking from index i in direction ``step`` (linear interpolation); NaN
    when it does not within the points."""
    j = i
    while 0 <= j + step < x.size:
        if y[j + step] >= level:
            y0, y1 = y[j], y[j + step]
            if not math.isfinite(y1):
                return float(x[j + step])
            frac = (level - y0) / (y1 - y0) if y1 > y0 else 1.0
            return float(x[j] + frac * (x[j + step] - x[j]))
        j += step
    return math.nan


def chi2_interval(x: np.ndarray, y: np.ndarray, s2: float, centre: float | None = None) -> tuple[float, float]:
    """The interval around the minimum where the profile stays within one chi-square unit (s2) of it."""
    i = int(np.argmin(y))
    level = y[i] + s2
    return _crossing(x, y, i, level, -1), _crossing(x, y, i, level, +1)


def estimate_minimum(x: np.ndarray, y: np.ndarray, s2: float) -> tuple[float, float, bool]:
    """(minimum, curvature sigma, kinked) of a profile given by its points.

    Where the profile is a parabola around its minimum, the vertex of a
    parabola through the points within 9 chi-square units is the estimate and
    sqrt(s2 / curvature) its chi-square sigma: it averages over the small
    steps the quadrature leaves in the residual, which the lowest point alone
    follows. Where it is not (the vertex lands more than the chi-square
    half-width from the lowest point, or the curvature's sigma differs from
    that half-width by more than 2x: a V, a kink at the contact point), the lowest point refined between its
    neighbours (:func:`local_minimum`) is the estimate and the sigma is NaN
    (the caller takes the chi-square interval instead)."""
    i = int(np.argmin(y))
    lowest = local_minimum(x, y)
    near = np.isfinite(y) & (y - y[i] <= 9 * s2)
    if near.sum() < 5:
        return lowest, math.nan, True
    scale = float(np.ptp(x[near])) or 1.0
    u = (x[near] - x[i]) / scale
    c2, c1, _ = np.polyfit(u, y[near], 2)
    if not c2 > 0:
        return lowest, math.nan, True
    vertex = x[i] + scale * float(np.clip(-c1 / (2 * c2), u.min(), u.max()))
    sigma = scale * math.sqrt(s2 / c2)
    lower, upper = chi2_interval(x, y, s2)
    half = 0.5 * (upper - lower) if math.isfinite(lower) and math.isfinite(upper) else sigma
    if abs(vertex - lowest) > half or not 0.5 <= sigma / half <= 2.0:  # not a parabola: a kink
        return lowest, math.nan, True
    return vertex, sigma, False


def robust_profile(profile: GroupedProfile, center: float, half_width: float, s2: float, lo: float = -math.inf,
                   hi: float = math.inf, min_step: float = 0.0, jackknife: bool = True) -> ProfileResult:
    """Minimum and honest 1-sigma of ``profile`` (a residual sum of squares; rss / s2 is a chi-square).

    Brackets the minimum on a window around ``center`` (moved while the minimum sits on its edge, widened
    while the profile is flatter than one chi-square unit across it), zooms in on the lowest point until the
    grid step is below RESOLUTION_FRACTION of the chi-square half-width (or ``min_step``), reads the interval
    where the chi-square rises by 1 (extending the points outwards until it does), and with ``jackknife``
    measures the spread of the minimum over the block jackknife. Where the interval runs to a bound instead
    of closing (``open_side``), the 1-sigma is the larger of its halves with the open one reaching the bound
    (the whole window's half when both do: the data do not locate the parameter); NaN only when a side neither
    closes nor reaches a finite bound, or the profile cannot be evaluated.
    """
    center = min(max(center, lo), hi)
    full_span = hi - lo
    # 1. Bracket.
    for _ in range(10):
        a, b = max(lo, center - half_width), min(hi, center + half_width)
        for g in np.linspace(a, b, WINDOW_POINTS):
            profile(g)
        x, y = profile.points()
        inside = (x >= a) & (x <= b)
        xi, yi = x[inside], y[inside]
        i = int(np.argmin(yi))
        if not np.isfinite(yi[i]):
            return ProfileResult(center, math.nan, grid=x, values=y, evaluations=x.size)
        if (i == 0 and a > lo) or (i == xi.size - 1 and b < hi):  # on the window's edge: move
            center = float(xi[i])
            continue
        edges = [v for v, at_bound in ((yi[0], a <= lo), (yi[-1], b >= hi)) if not at_bound]
        if edges and min(edges) - yi[i] < s2 and 2 * half_width < full_span:  # flatter than the window: widen
            half_width *= 3
            center = float(xi[i])
            continue
        break
    # 2. Zoom in on the lowest point.
    for _ in range(16):
        x, y = profile.points()
        i = int(np.argmin(y))
        lower, upper = chi2_interval(x, y, s2)
        width = 0.5 * (upper - lower) if math.isfinite(lower) and math.isfinite(upper) else half_width
        target = max(min_step, RESOLUTION_FRACTION * width)
        left = x[i] - x[i - 1] if i > 0 else math.inf
        right = x[i + 1] - x[i] if i < x.size - 1 else math.inf
        if max(left if i > 0 else 0.0, right if i < x.size - 1 else 0.0) <= target:
            break
        a, b = x[max(i - 1, 0)], x[min(i + 1, x.size - 1)]
        for g in np.linspace(a, b, ZOOM_POINTS):
            profile(g)
    # 3. The chi-square interval, extending the points outwards until the profile rises by one unit.
    for side in (-1, +1):
        for _ in range(12):
            x, y = profile.points()
            i = int(np.argmin(y))
            if math.isfinite(_crossing(x, y, i, y[i] + s2, side)):
                break
            edge = x[0] if side < 0 else x[-1]
            if (side < 0 and edge <= lo) or (side > 0 and edge >= hi):
                break
            reach = max(abs(edge - x[i]), min_step, 1e-6 * max(abs(x[i]), 1e-30))
            profile(min(max(edge + side * reach, lo), hi))
    x, y = profile.points()
    i = int(np.argmin(y))
    best, sigma_parabola, kinked = estimate_minimum(x, y, s2)
    resolution = float(max(x[i] - x[max(i - 1, 0)], x[min(i + 1, x.size - 1)] - x[i]))
    lower, upper = chi2_interval(x, y, s2)
    open_side = _open_side(x, lower, upper, lo, hi)
    if open_side is None:  # the interval neither closes nor reaches a bound (an unbounded search)
        return ProfileResult(best, math.nan, resolution=resolution, grid=x, values=y, evaluations=x.size)
    if open_side == "both":  # flatter than one unit over the whole window: the data do not locate it
        sigma = max(best - lo, hi - best)
        return ProfileResult(best, sigma, sigma, math.nan, resolution, x, y, x.size, s2, open_side)
    if open_side:
        # One-sided: the interval runs to the bound on the open side, so the open side's half is at least the
        # distance to the bound; the symmetric 1-sigma is the larger half (a tight sigma from the closed side
        # alone, or NaN, would report a parameter the data do not bound as located: poor instrument, d's
        # profile within 0.04 units of its minimum down to the window's edge, sigma NaN, d 3.2 nm off).
        width = max(best - (lo if open_side == "below" else lower), (hi if open_side == "above" else upper) - best)
    else:
        width = 0.5 * (upper - lower) if kinked else sigma_parabola
    sigma_jk = _jackknife(profile, best, width, s2, lo, hi) if jackknife else math.nan
    sigma = max(width, sigma_jk) if math.isfinite(sigma_jk) else width
    sigma = math.hypot(sigma, resolution if kinked else 0.0)
    x, y = profile.points()
    return ProfileResult(best, sigma, width, sigma_jk, resolution, x, y, x.size, s2, open_side)


def open_side_warning(name: str, unit: str, found: ProfileResult, bounds: tuple[float, float]) -> str | None:
    """The warning of a profile whose chi-square interval runs to a searched bound (None when it closed): the
    data do not bound the parameter on that side inside the window, so its 1-sigma reaches the bound."""
    if not found.open_side:
        return None
    scale, shown = (1e9, "nm") if unit == "m" else (1.0, unit)
    if found.open_side == "both":
        where = (f"over the whole searched window {scale * bounds[0]:.3g} .. {scale * bounds[1]:.3g} {shown}: the "
                 "data do not locate it")
    else:
        edge = bounds[0] if found.open_side == "below" else bounds[1]
        where = (f"up to the searched window's {'lower' if found.open_side == 'below' else 'upper'} edge "
                 f"{scale * edge:.3g} {shown}: the data do not bound it on that side")
    return (f"{name} undetermined on one side: " if found.open_side != "both" else f"{name} undetermined: ") + (
        f"its profile stays within one chi-square unit of its minimum {where}; its 1-sigma "
        f"({scale * found.sigma:.3g} {shown}) spans that side, and so do the read-outs that depend on it")


def _open_side(x: np.ndarray, lower: float, upper: float, lo: float, hi: float) -> str | None:
    """Which side of the chi-square interval (``lower``, ``upper``: NaN where it did not close within the points
    ``x``) runs to the searched bound ``lo`` / ``hi``: "", "below", "above", "both"; None when a side neither
    closes nor reaches a finite bound."""
    sides = []
    for closed, edge, bound, name in ((lower, x[0], lo, "below"), (upper, x[-1], hi, "above")):
        if math.isfinite(closed):
            continue
        if not (math.isfinite(bound) and edge == bound):
            return None
        sides.append(name)
    return "both" if len(sides) == 2 else (sides[0] if sides else "")


def _jackknife(profile: GroupedProfile, best: float, width: float, s2: float, lo: float, hi: float) -> float:
    """Spread (1 sigma) of the profile minimum over the leave-one-group-out profiles; NaN without groups."""
    G = profile.jackknife_groups()
    if G < 3:
        return math.nan
    reach = 4 * width
    for _ in range(JACKKNIFE_WIDENINGS + 1):
        for g in np.linspace(max(lo, best - reach), min(hi, best + reach), 17):
            profile(g)
        x, _ = profile.points()
        x = x[(x >= best - reach) & (x <= best + reach)]
        minima, on_edge = [], False
        left_out = np.array([profile.leave_each_out(v) for v in x])  # (points, groups)
        for group in range(G):
            y = left_out[:, group]
            j = int(np.argmin(y))
            on_edge |= (j == 0 and x[0] > lo) or (j == x.size - 1 and x[-1] < hi)
            minima.append(estimate_minimum(x, y, s2 * (G - 1) / G)[0])
        if not on_edge:
            break
        reach *= 3
    minima = np.array(minima)
    return float(math.sqrt((G - 1) / G * np.sum((minima - minima.mean()) ** 2)))

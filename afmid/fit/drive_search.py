"""The drive frequency of a record that is not in steady state, found by the regression itself.

In a steady oscillation the response and the drive share one frequency, and the
spectral peak of the deflection (:func:`afmid.preprocess.harmonics.estimate_drive`) gives
it to ~1e-7. A record that starts from rest, or whose amplitude still settles,
also holds the cantilever's free response at its own (interaction-shifted)
frequency; the spectral peak then sits between the two, off the drive by 1e-4
to 1e-2 (measured: 0.09 % on a record from rest into tapping, 1.4 % with the
tip starting close to the sample). The regression's drive columns
cos(w t), sin(w t) at that frequency slip in phase by 2 pi N df / f over N
periods: 48 deg after 150 periods at 0.09 %, and the fitted force absorbs the
slip (force error 1.1 % of peak instead of 0.06 %, Hamaker +12 %).

The equation of motion holds the drive force exactly as a sinusoid at the
drive frequency, so that frequency is the one at which the regression's
residual is smallest: :func:`search_drive_frequency` profiles it, the library
columns held (they do not depend on it: only the drive columns are recomputed,
:func:`with_drive_frequency`). The residual's valley is ~1 / (2 pi N) wide
(relative); the search covers the spectral estimate and the nominal frequency
with a margin, on a grid finer than the valley, then refines on the profile.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmid.preprocess.baseline import DRIFT, OFFSET, BaselineColumns

#: Grid points per valley width 1 / (2 pi N) of the residual over the drive frequency.
POINTS_PER_VALLEY = 3
#: Most grid points of the search (a wider window is searched coarser: the nominal frequency far off).
MAX_GRID = 241
#: The window reaches this many valley widths beyond the spectral estimate and the nominal frequency.
MARGIN_VALLEYS = 3.0


def is_transient(prep) -> bool:
    """True if the amplitude of the prepared record changes by more than its transient limit
    (``prep.transient_limit``, :func:`afmid.preprocess.harmonics.transient_limit`: the same limit as the
    not-steady warning of :mod:`afmid.io.defects`), so its drive is searched."""
    return bool(prep.steadiness > prep.transient_limit)


def with_drive_frequency(prep, frequency: float):
    """``prep`` (an :class:`afmid.fit.pipeline.Prepared`) with its drive columns at ``frequency`` (Hz), made as
    :func:`afmid.fit.prepare.prepare` makes them (:class:`afmid.preprocess.baseline.BaselineColumns`); blocks, windows, trajectory
    and noise unchanged. A new object: ``prep`` is not modified."""
    blocks, windows = prep.blocks, prep.windows
    names = prep.nuisance_names
    t = prep.t
    columns = BaselineColumns(2.0 * math.pi * frequency, float(t[0]), float(t[-1]), OFFSET in names, DRIFT in names)
    n_drive = len(columns.names)
    nuisance = prep.nuisance.copy()
    nuisance_block = prep.nuisance_block.copy()
    weak = prep.form == "weak"
    for b0, b1 in blocks.chunks():
        lo = blocks.start + b0 * blocks.L
        n_block = (b1 - b0) * blocks.L
        hi = lo + n_block + (blocks.L + 1 if weak else 0)
        cols = columns(t[lo:hi])
        turn = blocks.rotation(b0, b1)
        nuisance_block[b0:b1, :, :n_drive] = blocks.project_blocks(cols[:n_block], b0, turn)
        w1 = min(b1, windows.n_windows)
        if weak and w1 > b0:
            nuisance[b0:w1, :, :n_drive] = windows.integrate_samples(windows.psi, cols, b0, w1 - b0, turn)
    if not weak:
        shape = (blocks.n_blocks, blocks.L)
        nuisance[..., :n_drive] = columns(t)[blocks.used].reshape(shape + (n_drive,))
    drive = dataclasses.replace(prep.drive, frequency=float(frequency))
    return dataclasses.replace(prep, drive=drive, nuisance=nuisance, nuisance_block=nuisance_block)


@dataclass
class DriveSearch:
    """The drive frequency the regression prefers, and how it was found."""

    frequency: float  # Hz
    sigma: float  # Hz, 1 sigma (the larger of the profile's curvature and a block bootstrap); NaN: not determined
    response_frequency: float  # Hz, the spectral peak of the deflection it replaced
    nominal: float  # Hz, the config's / file's drive frequency
    grid: np.ndarray  # Hz, profile points
    objective: np.ndarray  # weighted residual sum of squares at them


def search_window(response: float, nominal: float, periods: float) -> tuple[float, float, int]:
    """(low, high, points) of the grid over the drive frequency (Hz): both candidates with a margin of
    :data:`MARGIN_VALLEYS` valley widths, :data:`POINTS_PER_VALLEY` points per valley (at most :data:`MAX_GRID`)."""
    valley = response / (2.0 * math.pi * max(periods, 1.0))
    low = min(response, nominal) - MARGIN_VALLEYS * valley
    high = max(response, nominal) + MARGIN_VALLEYS * valley
    points = int(min(MAX_GRID, max(11, math.ceil(POINTS_PER_VALLEY * (high - low) / valley) + 1)))
    return low, high, points


#: Bootstrap resamples of the profile's minimum (its spread is sigma where it exceeds the curvature's).
BOOTSTRAP_RESAMPLES = 100
#: Points of the local profile the bootstrap re-weights (over +- 2 curvature sigmas, at least +- valley / 8).
LOCAL_POINTS = 9


def search_drive_frequency(prep, factors: Callable[[object], np.ndarray], rng: np.random.Generator,
                           response: float | None = None) -> DriveSearch:
    """Profile the regression's weighted residual over the drive frequency of ``prep``.

    ``factors(prepared)`` returns the per-window factors (W, q, q) of the
    whitened [columns | right-hand side] of the prepared record (library
    columns held): the residual sum of squares is that of their combination.
    A grid over :func:`search_window` (around ``response``, default the
    prepared drive frequency, and the nominal one) finds the valley; a bounded
    search refines it. 1 sigma is the larger of the chi-square curvature's
    (Delta chi^2 = 1 with the residual variance per row) and the spread of the
    minimum over a moving-block bootstrap of windows (block length W^(1/3)):
    neighbouring weak-form windows overlap and the trajectory errors are
    correlated over periods, which the curvature alone ignores.
    """
    from scipy.optimize import minimize_scalar

    import afmid.fit.regression as regression

    response = float(prep.drive.frequency if response is None else response)
    nominal = float(prep.drive.nominal)
    periods = prep.blocks.n_blocks * prep.blocks.L * prep.blocks.dt * response
    low, high, points = search_window(response, nominal, periods)
    kept: dict[float, np.ndarray] = {}
    n_rows = 0

    def objective(f: float, keep: bool = False) -> float:
        nonlocal n_rows
        T_blocks = factors(with_drive_frequency(prep, f))
        n_rows = n_rows or T_blocks.shape[0] * T_blocks.shape[1]
        if keep:
            kept[f] = T_blocks
        q = T_blocks.shape[-1]
        value = regression.subset_fit(regression.combine(T_blocks), np.ones(q - 1, dtype=bool))[1]
        return value if math.isfinite(value) else math.inf

    grid = np.linspace(low, high, points)
    values = np.array([objective(f) for f in grid])
    i = int(np.argmin(values))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, points - 1)]
    refined = minimize_scalar(objective, bounds=(a, b), method="bounded", options={"xatol": (b - a) * 1e-6})
    best = float(refined.x) if refined.fun <= values[i] else float(grid[i])
    best_value = min(float(refined.fun), float(values[i]))
    q = next(iter(kept.values())).shape[-1] if kept else None
    # The curvature's sigma, from two points a quarter grid step to either side.
    dof = max(n_rows - (q or 0), 1)
    s2 = best_value / dof
    h = (high - low) / (points - 1) / 4
    curvature = (objective(best - h) + objective(best + h) - 2 * best_value) / h**2
    sigma = math.sqrt(2 * s2 / curvature) if curvature > 0 and s2 > 0 else math.nan
    if not math.isfinite(sigma):
        return DriveSearch(best, sigma, response, nominal, grid, values)
    # The bootstrap: the local profile's per-window factors, re-weighted by moving blocks of windows.
    span = max(2 * sigma, h)
    local = best + span * np.linspace(-1.0, 1.0, LOCAL_POINTS)
    local_values = np.array([objective(f, keep=True) for f in local])
    stack = np.stack([kept[f] for f in local])  # (P, W, q, q)
    W = stack.shape[1]
    length = max(1, round(W ** (1 / 3)))
    vertices = []
    for _ in range(BOOTSTRAP_RESAMPLES):
        counts = np.zeros(W)
        for s in rng.integers(0, W, size=math.ceil(W / length)):
            counts[(s + np.arange(length)) % W] += 1.0
        rss = np.array([regression.subset_fit(regression.combine(stack[j], counts), np.ones(stack.shape[-1] - 1,
                                                                                            dtype=bool))[1]
                        for j in range(local.size)])
        c2, c1, _ = np.polyfit(local - best, rss, 2)
        if c2 > 0:
            vertices.append(best + float(np.clip(-c1 / (2 * c2), -span, span)))
    if len(vertices) >= BOOTSTRAP_RESAMPLES // 2:
        sigma = max(sigma, float(np.std(vertices, ddof=1)))
    return DriveSearch(best, sigma, response, nominal, np.concatenate([grid, local]),
                       np.concatenate([values, local_values]))


def settle_drive_frequency(prep, choice: str, seed: int, factors_at: Callable[[object], Callable],
                           estimate_again: Callable[[object], None] | None = None) -> tuple[object, DriveSearch | None]:
    """The prepared record with its drive frequency by ``fit.drive_frequency`` ``choice``, and the search if one
    ran: in a transient (auto) or always (search) the one the regression prefers, alternating twice with the
    separation and decay lengths; the nominal one; or the response's spectral peak (unchanged ``prep``).

    ``factors_at(prep)`` returns the per-window factor function of :func:`search_drive_frequency` with the
    library's columns evaluated once at the current parameters; ``estimate_again(prep)`` searches those
    parameters again on the new drive (None: nothing to search).
    """
    if choice == "nominal":
        return with_drive_frequency(prep, prep.drive.nominal), None
    if choice == "response" or (choice == "auto" and not is_transient(prep)):
        return prep, None
    response = prep.drive.frequency
    rng = np.random.default_rng([seed, 2])
    found = None
    for _ in range(2):
        found = search_drive_frequency(prep, factors_at(prep), rng, response)
        prep = with_drive_frequency(prep, found.frequency)
        if estimate_again is None:
            break
        estimate_again(prep)
    return prep, found

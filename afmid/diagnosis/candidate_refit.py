"""The diagnosis's refit with a candidate effect, the rest separation re-profiled with it.

When the run estimated the rest separation, that estimate belongs to the run's
(wrong) model: a missing effect pulls it (a missing repulsion moves the
contact point, a missing dissipation tilts the profile). Holding it fixed
while trying a candidate makes the candidate fit a trace seen from the wrong
separation, and the diagnosis then names a stand-in effect or none (measured
in docs/diagnosis.md, "Separation unknown"). So each candidate's refit
searches the separation again around the run's value (within
SEPARATION_WINDOW) and the candidate's own nonlinear parameters (decay
lengths, rupture distance) at the new separation (REPROFILE_ROUNDS
alternations: shape at the current separation, then separation with that
shape), then fits with both fixed. A run made with ``sample.separation`` given
keeps it. Lengths in m.
"""

from __future__ import annotations

import copy
import logging
import math

from afmid.config import RunConfig

log = logging.getLogger(__name__)

#: The separation is searched again within this distance of the run's estimate, m. A missing long-range
#: attraction moves the run's estimate far: a hidden 3 V electrostatic force put a [dmt] fit's separation
#: 1.9 nm too high (the tip seemed not to touch), so the window is wide; the search is a coarse grid refined
#: (:func:`search_separation`): its cost grows only with the logarithm of the window.
SEPARATION_WINDOW = 2.5e-9
#: The window of the later rounds, m (the shape moved, the separation follows by much less).
SEPARATION_REFINE_WINDOW = 0.3e-9
#: Alternations of (candidate's shape parameters at the current separation, separation with that shape).
REPROFILE_ROUNDS = 2


def separation_estimated(run) -> bool:
    """Whether the run estimated the rest separation (``sample.separation`` absent) and holds the estimate."""
    return run.config.sample.separation is None and math.isfinite(run.separation)


#: Points of the coarse grid of the separation search, and of each zoom (a zoom halves the step).
SEPARATION_GRID = 11
SEPARATION_ZOOM = 5
#: The coarse grid's step on the default window, m: a wider window gets more points, not a coarser grid.
SEPARATION_COARSE_STEP = 2 * SEPARATION_WINDOW / (SEPARATION_GRID - 1)
#: A zoom's point within this fraction of its step of a separation already tried is that separation: the same point
#: up to rounding (a few 1e-24 m at 30 nm). Evaluated anew, such a twin cost a library evaluation at each end of
#: every zoom and, beside its twin, put a parabola of :func:`afmid.fit.profile.local_minimum` through two points
#: 1e-24 m apart.
ZOOM_SNAP = 1e-6
#: The search zooms until the step is below this, m (the fit then uses the value; a tenth of the thermal
#: deflection of a stiff lever).
SEPARATION_STEP = 2e-12


def search_separation(prepared, config: RunConfig, low: float, high: float, base_columns=None) -> float:
    """The rest separation in [``low``, ``high``] (and not below ``sample.a0``) that minimises the weighted residual of
    ``config``'s full library (its nonlinear parameters as ``config.model.parameters`` fixes them), m
    (:func:`separation_minimum`)."""
    return separation_minimum(prepared, config, low, high, base_columns)[0]


def separation_minimum(prepared, config: RunConfig, low: float, high: float, base_columns=None
                       ) -> tuple[float, float]:
    """:func:`search_separation`'s separation (m) and the lowest weighted residual sum of squares it evaluated.

    A coarse grid (at most :data:`SEPARATION_COARSE_STEP` apart), then zooms on the lowest point (each a grid of
    SEPARATION_ZOOM points between its neighbours, which are not evaluated again: :data:`ZOOM_SNAP`) and a parabola
    through the last three
    (:func:`afmid.fit.profile.local_minimum`: no parabola through a kink). When the library holds a gate that forms
    at contact (a meniscus, a JKR neck: :attr:`afmid.physics.effect_types.StateGate.forms_at_contact`), the coarse
    grid also holds one separation between each two of the taps' contact thresholds
    (:func:`afmid.fit.contact_thresholds.contact_trial_separations`): the residual steps at each threshold, and the
    valley where the neck forms on the record's own taps can be narrower than any grid step. ``base_columns``: the diagnosis's
    :class:`afmid.diagnosis.base_columns.BaseColumns` (the run's own terms' columns at each separation, shared
    by every candidate: only the added terms are evaluated per trial); None evaluates the whole library."""
    import numpy as np

    from afmid.errors import AfmidError
    from afmid.fit.contact_thresholds import contact_thresholds, contact_trial_separations
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.system import build_system, residual_sum_squares
    from afmid.physics.effect_types import forms_at_contact
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry
    from afmid.fit.profile import local_minimum

    library = build_library(config.model, config.source, tip_geometry(config.cantilever))
    params = library_parameters(prepared, config, library)
    values: dict[float, float] = {}

    def evaluate(grid) -> tuple[np.ndarray, np.ndarray]:
        for d in grid:
            d = float(d)
            if d not in values:
                try:
                    values[d] = (residual_sum_squares(build_system(prepared, library, dict(params, d=d)))
                                 if base_columns is None else base_columns.residual(library, dict(params, d=d)))
                except AfmidError:
                    values[d] = math.inf
        x = np.array(sorted(values))
        return x, np.array([values[v] for v in x])

    # Not below a0: a rest separation there puts the resting tip in the sample (a candidate whose best lies below
    # is fitted at the bound and judged like any other, instead of failing on an unphysical separation).
    lowest = config.sample.a0
    low, high = max(low, lowest), max(high, 2 * lowest)
    # At most the coarse step of the default window (0.5 nm) on a wider one: the grid picks the valley to zoom in.
    points = max(SEPARATION_GRID, math.ceil((high - low) / SEPARATION_COARSE_STEP) + 1)
    grid = np.linspace(low, high, points)
    step = grid[1] - grid[0]
    if forms_at_contact(library.states):
        grid = np.concatenate([grid, contact_trial_separations(contact_thresholds(prepared, config.sample.a0),
                                                               low, high, SEPARATION_STEP)])
    x, y = evaluate(grid)
    while step > SEPARATION_STEP:
        i = int(np.argmin(y))
        zoom = np.maximum(np.linspace(x[i] - step, x[i] + step, SEPARATION_ZOOM), lowest)
        x, y = evaluate(_snapped(zoom, x, ZOOM_SNAP * step))
        step /= (SEPARATION_ZOOM - 1) / 2
    if not np.isfinite(y).any():
        return 0.5 * (low + high), math.inf
    return local_minimum(x, y), float(np.min(y))


def _snapped(points, seen, tolerance: float):
    """``points`` (m), each replaced by the nearest of ``seen`` (sorted, m) within ``tolerance`` (m): a zoom's ends are
    its centre's neighbours of the grid before, recomputed as centre +- step, which rounding puts a few 1e-24 m
    away from them."""
    import numpy as np

    points = np.array(points, dtype=float)
    at = np.clip(np.searchsorted(seen, points), 1, max(len(seen) - 1, 1))
    for k, (p, j) in enumerate(zip(points, at)):
        near = min((seen[j - 1], seen[min(j, len(seen) - 1)]), key=lambda v: abs(v - p))
        if abs(near - p) <= tolerance:
            points[k] = near
    return points


def separation_starts(run, prepared, config: RunConfig) -> tuple[list[float], float, float]:
    """Where a candidate's separation search starts and the span it searches, m: (starts, low, high).

    The span is the window a fit with the candidate added would search (``fit.separation_window`` around first
    contact, its part above ``sample.a0``), widened to hold the run's estimate +- :data:`SEPARATION_WINDOW`.
    The run's estimate alone is not enough: a missing effect can move it out of the candidate's reach. Measured:
    a hidden Kelvin-Voigt sample (eta 400 Pa s, seed 513) put a [dmt] fit 3.4 nm above the truth with no contact
    term selected (the tip seemed not to touch); the viscoelastic candidate, searched within 2.5 nm of it, could
    not reach a contact and changed nothing, and exponential damping was named, while a fit with viscoelastic
    added finds the separation within 4 pm.

    The starts (where a candidate's shape is searched first; :func:`search_candidate` keeps the start that ends
    lowest) are the run's estimate and the middle of the span: a shape searched at a separation far from the
    truth can lead the alternation into a worse valley (measured: a hydration candidate at ΔBIC -239 from the
    middle against -558 from the estimate; on another trace the other way round). An estimate not above zero (no
    physical separation: a double layer's long-range repulsion put a [dmt] fit at -0.86 nm, truth 5 nm) is no
    start."""
    from afmid.fit.pipeline import first_contact

    touch = first_contact(prepared, config.sample.a0)
    below, above = config.fit.separation_window
    # The part of the window above a0 (a rest separation below it puts the resting tip in the sample): centred
    # on the whole window, a first contact below ~1.5 nm would start the candidate at a separation <= 0.
    low = max(touch - below, config.sample.a0)
    high = max(touch + above, 2 * config.sample.a0)
    if run.separation <= 0:
        return [0.5 * (low + high)], low, high
    low = max(min(low, run.separation - SEPARATION_WINDOW), config.sample.a0)
    high = max(high, run.separation + SEPARATION_WINDOW)
    middle = 0.5 * (low + high)
    starts = [run.separation] + ([middle] if abs(middle - run.separation) > SEPARATION_REFINE_WINDOW else [])
    return starts, low, high


def search_candidate(run, prepared, config: RunConfig, effect: str, shape_names: list[str], shapes,
                     quick_shape: bool = True) -> tuple[RunConfig, dict[str, float]]:
    """The search of a refit of ``config`` (the run's effects plus ``effect``) with the separation and the effect's
    shape re-profiled: (the trial config, its separation and the effect's shape fixed; the shape found {name:
    value}, empty when the fit is to search it). ``shapes`` is the diagnosis's
    :class:`afmid.diagnosis.candidate_shapes.ShapeSearch`; :func:`fit_searched` then fits with both fixed.

    The shape (at the current separation) and the separation (with that shape) are searched in turn,
    REPROFILE_ROUNDS times from each of :func:`separation_starts` (the one that ends with the lower residual is
    kept). A failing quick shape search falls back to the fit's own search of the shape (at the separation found
    without it). What it reads of ``shapes`` beyond the call (its kept columns, the check of their shortcut per
    library) is the same whichever candidate ran before: candidates are searched in any order, or apart
    (afmid.diagnosis.forked_work)."""
    free = separation_estimated(run)
    quick = bool(shape_names) and config.fit.estimate_nonlinear and quick_shape
    if not free:
        trial, shape, _ = _reprofile(config, config.sample.separation, None, effect, shape_names, shapes, quick,
                                     prepared)
    else:
        starts, low, high = separation_starts(run, prepared, config)
        # Without a shape to search the grid over the span does not depend on the start.
        ends = [_reprofile(config, start, (low, high), effect, shape_names, shapes, quick, prepared)
                for start in (starts if quick else starts[:1])]
        trial, shape, _ = min(ends, key=lambda end: end[2])
    return trial, shape


def fit_searched(searched: tuple[RunConfig, dict[str, float]], shape_names: list[str], prepared, fit_quick):
    """The candidate's refit: ``fit_quick(config, prepared)`` of :func:`search_candidate`'s trial config; (fit result,
    the effect's shape parameters {name: value}, from the fit when the search left them to it; the separation used,
    m)."""
    trial, shape = searched
    result = fit_quick(trial, prepared)
    if not shape:
        shape = {k: est.value for k, est in result.nonlinear.items() if k in shape_names}
    return result, shape, trial.sample.separation


def _reprofile(config: RunConfig, start: float, span, effect: str, shape_names: list[str], shapes, quick: bool,
               prepared):
    """The alternation of :func:`search_candidate` from separation ``start`` (m) over ``span`` (low, high; None:
    the separation is given): (trial config, shape, the last separation search's residual; inf without one)."""
    trial = copy.deepcopy(config)
    trial.sample.separation = start
    shape: dict[str, float] = {}
    residual = math.inf
    for _ in range(REPROFILE_ROUNDS if span is not None and quick else 1):
        if quick:
            try:
                shape = shapes.search(trial, effect, shape_names)
                trial.model.parameters = {**config.model.parameters, **shape}
            except Exception as exc:  # fall back to the fit's own search
                log.debug("quick search for %s failed (%s); using the fit's own", effect, exc)
                quick, shape = False, {}
                trial.model.parameters = dict(config.model.parameters)
        if span is not None:
            trial.sample.separation, residual = separation_minimum(prepared, trial, *span, shapes.base_columns)
            # The next round starts from a separation that fits the effect.
            separation = trial.sample.separation
            span = (separation - SEPARATION_REFINE_WINDOW, separation + SEPARATION_REFINE_WINDOW)
    return trial, shape, residual

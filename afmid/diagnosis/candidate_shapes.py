"""The shape parameters of a candidate effect (decay lengths, a rupture distance), searched quickly for the diagnosis.

:func:`afmid.diagnosis.diagnose.suggest` refits a trace with each catalog effect the
model lacks; the effect's nonlinear parameters are found here by a coarse
search on the fit's own objective (the whitened residual of the full library,
:func:`afmid.fit.system.residual_sum_squares`) over the fit's own ranges
(:func:`afmid.fit.search.search_range`), on the trace prepared once for all
the refits. Lengths in m.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from afmid.config import RunConfig
from afmid.physics.effects import parameter_unit
from afmid.quantity_text import format_value

log = logging.getLogger(__name__)

#: Points of the coarse logarithmic grid of the search (then refined, see :func:`minimise_bumpy`).
SHAPE_GRID = 10


class ShapeSearch:
    """Nonlinear parameters of a candidate effect (decay lengths, rupture distance) by a coarse search.

    The fit's own outer search is thorough (a fine grid, two rounds and a
    refinement for the chosen terms) and dominates the cost of a refit. For
    ranking candidates a coarse logarithmic grid over the parameter's range,
    refined by parabolas through finer grids, on the same objective (the
    full-library weighted residual) is enough; the fit then runs with the value
    fixed. The data preparation is shared by all candidates, and the columns of
    the terms that do not depend on the searched parameter are computed once:
    only the candidate's own columns are recomputed at each trial value. That
    shortcut is checked against the fit's own system at the first trial value
    and dropped if they disagree.
    """

    def __init__(self, prepared, base_columns=None):
        self.prep = prepared  # afmid.fit.pipeline.Prepared of the trace, shared with the refits
        #: afmid.diagnosis.base_columns.BaseColumns of the run's own terms on ``prepared`` (None: a trial evaluates the
        #: columns of every term not searched, once per search)
        self.base_columns = base_columns
        self.evaluations = 0

    def search(self, config: RunConfig, effect: str, names: list[str]) -> dict[str, float]:
        from dataclasses import replace

        from afmid.errors import AfmidError
        from afmid.fit.pipeline import library_parameters
        from afmid.fit.search import search_range
        from afmid.fit.system import build_system, library_columns, library_thermal_bias, residual_sum_squares
        from afmid.physics.library import build_library
        from afmid.physics.tips import tip_geometry

        prep = self.prep
        library = build_library(config.model, config.source, tip_geometry(config.cantilever))
        params = library_parameters(prep, config, library)
        params["d"] = config.sample.separation
        own = [t for t in library.terms if t.effect == effect]
        rest = [t for t in library.terms if t.effect != effect]
        # The columns (and thermal-bias rows) alone: a whole system would also factor them, for nothing.
        rest_library, own_library = replace(library, terms=rest), replace(library, terms=own)
        # An added state gate: the run's kept columns are not used (BaseColumns.adds_a_gate); the rest's columns are
        # then evaluated once per search with the full library's gates, as without kept columns.
        kept_elsewhere = self.base_columns is not None and not self.base_columns.adds_a_gate(library)
        fixed_theta = library_columns(prep, rest_library, params) if rest and not kept_elsewhere else None
        fixed_bias = library_thermal_bias(prep, rest_library, params) if rest and not kept_elsewhere else None

        def composed(trial: dict) -> float:
            theta = np.concatenate([fixed_theta, library_columns(prep, own_library, trial)], axis=2)
            # the thermal force's bias rows in the same column order as theta (None without a thermal force)
            own_bias = library_thermal_bias(prep, own_library, trial)
            bias = None if own_bias is None else np.concatenate([fixed_bias, own_bias], axis=2)
            # columns in any order: rss only
            return residual_sum_squares(build_system(prep, library, trial, theta=theta, thermal_bias=bias))

        def full(trial: dict) -> float:
            return residual_sum_squares(build_system(prep, library, trial))

        def shared(trial: dict) -> float:  # the run's terms' columns kept across searches and candidates
            return self.base_columns.residual(library, trial)

        rss = [shared if kept_elsewhere else composed if own and rest else full]
        checked = [False]
        found: dict[str, float] = {}
        for _round in range(2 if len(names) > 1 else 1):
            for name in names:
                span = search_range(library, name, config.sample.medium)  # the fit's own range (its log grid: 0 is not tried)
                lo, hi = span.low, span.high

                def objective(log_value, name=name):
                    trial = dict(params, **{name: math.exp(log_value)})
                    self.evaluations += 1
                    try:
                        if self.base_columns is not None and self.base_columns.out_of_reach(own, trial, library.states):
                            return shared(trial)  # the effect's columns are zeros here: the tip never reaches contact
                        value = rss[0](trial)
                        if not checked[0] and rss[0] is composed:
                            checked[0] = True
                            reference = full(trial)
                            if not math.isclose(value, reference, rel_tol=1e-6, abs_tol=1e-9):
                                log.debug("column shortcut disagrees with the fit (%g vs %g); not used", value, reference)
                                rss[0] = full
                                value = reference
                        return value
                    except AfmidError:
                        return math.inf

                best = minimise_bumpy(objective, math.log(lo), math.log(hi))
                params[name] = found[name] = math.exp(best)
        return found


def minimise_bumpy(objective, lo: float, hi: float) -> float:
    """Minimum of a 1-D objective that is smooth on large scales but steppy on small ones.

    Gated terms (a meniscus that ruptures at a distance) switch on the fit's
    quadrature grid, so the residual moves in small steps as the parameter
    changes and a bracketing search stops on a step. A coarse grid finds the
    valley; two rounds of a parabola fitted to a finer grid across it give
    the minimum of the smooth part (clipped to the searched interval).
    """
    grid = np.linspace(lo, hi, SHAPE_GRID)
    values = np.array([objective(g) for g in grid])
    values[~np.isfinite(values)] = np.inf
    i = int(np.argmin(values))
    best = float(grid[i])
    half = grid[1] - grid[0]
    for points in (9, 7):
        a, b = max(lo, best - half), min(hi, best + half)
        fine = np.linspace(a, b, points)
        vals = np.array([objective(g) for g in fine])
        ok = np.isfinite(vals)
        j = int(np.argmin(np.where(ok, vals, np.inf)))
        best = float(fine[j])
        if ok.sum() >= 4:
            c2, c1, _ = np.polyfit(fine[ok], vals[ok], 2)
            if c2 > 0:
                best = float(np.clip(-c1 / (2 * c2), a, b))
        half = (b - a) / 4
    return best


def shape_words(effect: str, shape: dict) -> list[str]:
    """``name = value`` of a candidate's fitted shape parameters (SI in ``shape``), each in the display unit of the
    unit its effect declares (``relaxation_time = 104 µs``, ``damping_length = 1.2 nm``); a value the refit did
    not determine said so."""
    return [f"{k} = {format_value(v, parameter_unit(k, effect))}" if v is not None and math.isfinite(v)
            else f"{k} = not determined" for k, v in shape.items()]

"""How ``afmid map`` fits its pixels: strategies with one protocol, in the registry :data:`PIXEL_FITS`.

A strategy is made once per chunk (``PixelFit(config, library)``), is shown the chunk's traces first
(``start_chunk(traces)``: what they share, e.g. the drive frequency) and fits the chunk's pixels in order
(``fit(trace, pixel) -> PixelResult``); it may carry what it learnt from one pixel to the next.

- ``full``: every pixel fitted exactly as ``afmid fit`` fits a trace (:func:`afmid.fit.pipeline.fit_prepared`: the coarse
  separation search, the profile, three selections, the bootstrap of ``fit.bootstrap``). About 90 evaluations of
  the library columns per pixel.
- ``shared`` (the default): the chunk's pixels cut into periods at one drive frequency (the median of their
  measured ones, for the pixels whose own agrees with it: :meth:`SharedSupportFit.start_chunk`), sharing their
  blocks and test functions; the support and the offset of the separation from first contact are learnt on the
  chunk's first pixel by the full search (no bootstrap) and carried from pixel to pixel (neighbours in a row-major
  chunk: the topography and the phases are smooth). Each pixel then needs only a short 1-D search of its separation
  started from ``first contact + carried offset`` (a few library evaluations: two points and the vertex that the
  last pixel's profile curvature predicts from them, else a bracket, then parabola steps on the residual profile;
  the profile's chi-square width and its block jackknife for sigma), one selection at the found
  separation (no library evaluation: when it picks another support, the separation is searched again with it),
  and error bars from the least-squares covariance of the chosen support (sampled through the read-out so that
  E* etc. get the same kind of interval as the bootstrap gives) with the separation's sigma propagated. A pixel
  whose error stays above its noise floor is searched again over the whole separation window (the single-trace
  coarse search) before it is reported, so a wrong warm start cannot pass as a model-limited pixel; it stays
  flagged suspect (model-limited) when the error is still above the floor. Records that need the drive-frequency
  search (transients) are fitted by ``full``.

Each result names its route (:data:`ROUTES`) so the map shows where the cheap path was left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import afmid.fit.regression as regression
from afmid.errors import AfmidError
from afmid.fit.uncertainty import add_largest_shift, widen_interval
from afmid.registry import Registry

#: How a pixel was fitted (stored per pixel in /maps/fit_route; names in its ``meaning`` attribute).
ROUTES = ("full", "shared", "shared, support re-selected", "shared, separation re-searched",
          "shared, the chunk's anchor (full search first)")
ROUTE_FULL, ROUTE_SHARED, ROUTE_RESELECTED, ROUTE_RESEARCHED, ROUTE_ANCHOR = range(5)
#: Parametric draws from the coefficients' covariance behind each pixel's read-out intervals.
COVARIANCE_DRAWS = 200
#: Most residual evaluations of the short separation search before it gives way to the robust profile.
MAX_SEARCH_EVALUATIONS = 32
#: A bracket wider than this many chi-square widths is halved before a parabola step is trusted.
BRACKET_WIDTHS = 8.0
#: Starts of the separation search remembered across pixels, and how far apart (m) two must be to count twice.
MAX_STARTS = 3
#: The pixel's separation is moved onto an evaluated point within this fraction of its sigma (no extra build).
RESOLUTION = 0.1
DISTINCT_OFFSET = 0.2e-9
#: The anchor's coarse search refines its grid minimum to this fraction of two grid steps (0.75 pm of the blend
#: map's 0.75 nm, ~0.03 of a pixel's separation sigma): it only seeds the chunk's carried search, which finds
#: each minimum to a tenth of its sigma; the single-trace fit's 1e-6 took ~23 library evaluations, this 9-14.
ANCHOR_TOLERANCE = 1e-3
#: A pixel is cut at the chunk's drive frequency when its own measurement lies within this many robust sigmas of
#: the chunk's scatter from it; the chunk needs this many measured pixels for a median and a scatter.
DRIVE_AGREEMENT = 3.0
DRIVE_MIN_PIXELS = 5


@dataclass
class PixelResult:
    """What the map keeps of one pixel's fit (SI)."""

    quantities: dict  # name -> {value, error (1 sigma), ci_low, ci_high, unit, effect, ...} as afmid.fit.pipeline's
    separation: float  # m
    separation_sigma: float  # m, 1 sigma
    cv_error: float
    cv_error_noise_floor: float
    selected: np.ndarray  # bool over the library's terms
    warnings: list[str] = field(default_factory=list)
    route: int = ROUTE_FULL
    evaluations: int = 0  # library evaluations (system builds) this pixel cost; 0 when not counted
    #: the residual's character (afmid.maps.residual.SIGNATURE names -> value); empty when not computed
    signature: dict = field(default_factory=dict)
    curves: dict | None = None  # the force curves for the map explorer (afmid.maps.pixel_curves)


class FullPixelFit:
    """Every pixel as ``afmid fit`` fits a trace (:func:`afmid.fit.pipeline.fit_prepared`, bootstrap per the config)."""

    name = "full"
    title = "every pixel as `afmid fit` fits a trace (coarse search, profile, bootstrap)"
    references = ("docs/maps.md",)

    def __init__(self, config, library):
        self.config, self.library = config, library

    def start_chunk(self, traces: list) -> None:
        """Nothing is shared: every pixel as a trace of its own."""

    def fit(self, trace, pixel: int) -> PixelResult:
        from afmid.fit.pipeline import fit_prepared
        from afmid.fit.prepare import prepare
        from afmid.preprocess.instrument import from_config

        prep = prepare(trace, self.config.fit, from_config(self.config))
        result = fit_prepared(prep, self.library, self.config, uncertainty=self.config.fit.bootstrap > 0)
        from afmid.maps.residual import ResidualView, view_signature

        est = result.nonlinear.get("d")
        view = ResidualView(result.periods, prep.blocks.harmonics, result.signal_rows, self.config,
                            {"frequency": prep.drive.frequency})
        signature, curves = view_signature(view)
        return PixelResult(result.quantities, result.system.params["d"], est.sigma if est is not None else math.nan,
                           result.cv_error, result.cv_error_noise_floor,
                           np.asarray(result.selected[:len(self.library)], bool), list(result.warnings), ROUTE_FULL,
                           signature=signature, curves=curves)


class SharedSupportFit:
    """The support and the separation's offset from first contact carried across pixels; see the module doc."""

    name = "shared"
    title = "support and separation offset carried across pixels: a short separation search, covariance errors"
    references = ("docs/maps.md",)

    def __init__(self, config, library):
        from afmid.fit.pipeline import profile_library
        from afmid.fit.selection import SelectionSettings

        self.config, self.library = config, library
        self.full = FullPixelFit(config, library)
        self.physics, self.extra = profile_library(library, config)
        self.settings_for = lambda n_nuisance: SelectionSettings.for_library(config.fit, library, n_nuisance)
        self.support: np.ndarray | None = None  # over library + nuisance columns
        self.coef: np.ndarray | None = None  # the last pixel's coefficients (library + nuisance), SI
        #: m, separation minus first contact: the last pixel's first, then those of other phases met before
        self.offsets: list[float] = []
        self.step: float = 0.05e-9  # m, the first bracket's half-width (the last pixel's sigma, bounded)
        #: 1/m^2, the curvature of the last pixel's residual profile at its minimum (None: not known, a bracket)
        self.curvature: float | None = None
        self.nonlinear: dict[str, float] = {}  # the library's other nonlinear parameters (from the anchor)
        self.drive_frequency: float | None = None  # Hz, the chunk's (start_chunk); None: each pixel its own
        self.drive_spread: float = math.nan  # Hz, robust 1 sigma of the pixels' measured drive frequencies
        self.layouts: dict = {}  # blocks and test functions of the chunk's drive (afmid.fit.prepare.prepare)

    # ------------------------------------------------------------------ protocol
    def start_chunk(self, traces: list) -> None:
        """The chunk's drive frequency: the median of the frequencies measured on its traces (one piezo drives
        every pixel of a map; each pixel's own measurement scatters by its estimation error, 5.5 Hz rms at
        300 kHz on the 16x16 bench map, whose drive is exactly 300 kHz everywhere). Pixels that agree with it
        within :data:`DRIVE_AGREEMENT` robust sigmas of that scatter are cut at it, so that they share their
        blocks and test functions; a pixel further off keeps its own. Fewer than :data:`DRIVE_MIN_PIXELS`
        measured traces: no chunk frequency."""
        measured = [t.drive_for(self.config.fit.detrend) for t in traces]
        frequencies = np.array([d.frequency for d in measured if d is not None])
        self.drive_frequency, self.drive_spread = None, math.nan
        if frequencies.size >= DRIVE_MIN_PIXELS and self.config.fit.drive_frequency in ("auto", "response"):
            self.drive_frequency = float(np.median(frequencies))
            self.drive_spread = 1.4826 * float(np.median(np.abs(frequencies - self.drive_frequency)))

    def chunk_drive(self, trace):
        """The :class:`afmid.preprocess.harmonics.DriveEstimate` of ``trace`` at the chunk's drive frequency when
        its own measurement agrees with it (see :meth:`start_chunk`), else None (its own)."""
        from afmid.preprocess.harmonics import EXACT_SPECTRUM_MAX, drive_at
        from afmid.preprocess.periods import detrend

        own = trace.drive_for(self.config.fit.detrend)
        if (self.drive_frequency is None or own is None or trace.n_samples > EXACT_SPECTRUM_MAX
                or not abs(own.frequency - self.drive_frequency) <= DRIVE_AGREEMENT * self.drive_spread):
            return None
        x, _ = detrend(trace.deflection, trace.times, self.config.fit.detrend)
        return drive_at(x, trace.times, own.nominal, self.drive_frequency)

    def fit(self, trace, pixel: int) -> PixelResult:
        from afmid.fit.drive_search import is_transient
        from afmid.fit.pipeline import first_contact, library_parameters
        from afmid.fit.prepare import prepare
        from afmid.fit.prepare import with_fine_grid
        from afmid.preprocess.instrument import from_config

        config = self.config
        prep = with_fine_grid(prepare(trace, config.fit, from_config(config), drive=self.chunk_drive(trace),
                                      layouts=self.layouts))
        if config.fit.drive_frequency == "search" or (config.fit.drive_frequency == "auto" and is_transient(prep)):
            return self.full.fit(trace, pixel)
        if config.fit.drive_frequency == "nominal":
            from afmid.fit.drive_search import with_drive_frequency

            prep = with_drive_frequency(prep, prep.drive.nominal)
        touch = first_contact(prep, config.sample.a0)
        anchor = not self.offsets
        if anchor:  # the chunk's first pixel: the coarse search over the whole window, no profile, no bootstrap
            self._learn_from_anchor(prep, touch)
        params = library_parameters(prep, config, self.library)
        params.update(self.nonlinear)
        result = self._fit_shared(prep, params, touch)
        if anchor:
            result.route, result.evaluations = ROUTE_ANCHOR, 0  # the full search's evaluations are not counted
        return result

    def _learn_from_anchor(self, prep, touch: float) -> None:
        """The support, coefficients and separation offset (and the library's other nonlinear parameters) that the
        chunk's pixels start from, from its first pixel: the single-trace coarse search over the whole separation
        window (:func:`afmid.fit.pipeline.estimate_nonlinear`, with its bounded refinement), then the weights with
        the regressors' noise and one selection there, as :func:`afmid.fit.pipeline.fit_prepared` makes them
        before its profile. The profile itself (~30 library evaluations) is left out: the anchor's own result
        comes from the carried path's search started here, which finds the minimum and its sigma."""
        from afmid.fit.pipeline import estimate_nonlinear, library_parameters, select_with_regressor_noise

        library = self.library
        params = library_parameters(prep, self.config, library)
        estimate_nonlinear(prep, library, self.config, params, physics=(self.physics, self.extra),
                           refine_tolerance=ANCHOR_TOLERANCE)
        settings = self.settings_for(len(prep.nuisance_names))
        _, system, selection = select_with_regressor_noise(prep, library, params, settings)
        support = np.asarray(selection.best.mask, bool)
        self.support = support.copy()
        self.coef = np.asarray(regression.subset_fit(regression.combine(system.T_blocks), support)[0], float)
        self.offsets = [params["d"] - touch]
        self.nonlinear = {k: params[k] for k in library.nonlinear}

    # ------------------------------------------------------------------ the cheap path
    def _fit_shared(self, prep, params: dict, touch: float) -> PixelResult:
        from afmid.fit.pipeline import estimate_nonlinear
        from afmid.fit.prepare import with_regressor_noise
        from afmid.fit.uncertainty import model_limited

        config, library = self.config, self.library
        below, above = config.fit.separation_window
        bounds = (touch - below, touch + above)
        counter = {"builds": 0}
        support = self.support
        # Starts: the offset from first contact of the last pixel and of other phases met in this chunk (each
        # one profile point; the search goes on from the lowest). The rows' weights include the regressors' own
        # noise (afmid.fit.prepare.with_regressor_noise) computed with the last pixel's coefficients at the first
        # start: the force law of a neighbour, as the single-trace fit uses its first-pass coefficients.
        starts = [min(max(touch + offset, bounds[0]), bounds[1]) for offset in self.offsets]
        prep = with_regressor_noise(prep, library, dict(params, d=starts[0]), self.coef)
        settings = self.settings_for(len(prep.nuisance_names))
        route = ROUTE_SHARED
        search = self._search(prep, params, support, starts, bounds, counter, curvature=self.curvature)
        system = search.system_at_minimum() or self._build(prep, library, dict(params, d=search.found.value), counter)
        own = settings.select(system).best.mask
        if not np.array_equal(own, support):
            route, support = ROUTE_RESELECTED, own
            search = self._search(prep, params, support, [search.found.value], bounds, counter)
            system = (search.system_at_minimum()
                      or self._build(prep, library, dict(params, d=search.found.value), counter))
        result, coef = self._finish(prep, params, system, support, search, counter, route)
        if model_limited(result.cv_error, result.cv_error_noise_floor):
            # Above the floor: the warm start may have found a wrong minimum. The single-trace coarse search.
            searched = dict(params)
            coarse = estimate_nonlinear(prep, library, config, searched, physics=(self.physics, self.extra))
            counter["builds"] += sum(len(e.grid) for e in coarse.values())
            if abs(searched["d"] - search.found.value) > 3 * max(search.found.sigma, 1e-12):
                again = self._search(prep, params, support, [searched["d"]], bounds, counter)
                system = (again.system_at_minimum()
                          or self._build(prep, library, dict(params, d=again.found.value), counter))
                better, better_coef = self._finish(prep, params, system, support, again, counter, ROUTE_RESEARCHED)
                if better.cv_error < result.cv_error:
                    result, coef, search = better, better_coef, again
            result.route = ROUTE_RESEARCHED if result.route != ROUTE_RESELECTED else result.route
        result.evaluations = counter["builds"]
        self.support, self.coef = support, coef
        found = search.found
        self.remember(found.value - touch)
        if math.isfinite(found.sigma) and found.sigma > 0:
            self.step = min(max(found.sigma, 0.01e-9), 0.2e-9)
        self.curvature = found.curvature if math.isfinite(found.curvature) and found.curvature > 0 else None
        return result

    def remember(self, offset: float) -> None:
        """Put ``offset`` first among the starts; keep up to :data:`MAX_STARTS` that differ by more than
        :data:`DISTINCT_OFFSET` (a pixel of another phase starts from its own phase's offset)."""
        kept = [o for o in self.offsets if abs(o - offset) > DISTINCT_OFFSET]
        self.offsets = [offset] + kept[:MAX_STARTS - 1]

    def _build(self, prep, library, params, counter):
        from afmid.fit.system import build_system

        counter["builds"] += 1
        return build_system(prep, library, params)

    def _search(self, prep, params: dict, support: np.ndarray, starts: list[float], bounds: tuple[float, float],
                counter, curvature: float | None = None) -> "SeparationSearch":
        """The separation's minimum on the residual profile of the support (the profile library's columns when
        the library is a preset, as :func:`afmid.fit.pipeline.fit_prepared` does), from the lowest of ``starts``;
        ``curvature``: the last pixel's profile curvature (1/m^2), to predict the minimum from two points."""
        from afmid.fit.system import build_system
        from afmid.fit.profile import GroupedProfile, robust_profile

        physics = self.physics
        mask = support if physics is self.library else None
        trial_params = dict(params, **self.extra)
        systems = {}

        def factors_at(value: float):
            counter["builds"] += 1
            try:
                system = build_system(prep, physics, dict(trial_params, d=value))
            except AfmidError:
                return None
            if physics is self.library:
                systems[float(value)] = system
            return system.T_blocks, system.n_rows

        profile = GroupedProfile(factors_at, mask)
        n_columns = len(physics) + len(prep.nuisance_names)
        k = int((np.ones(n_columns, bool) if mask is None else mask).sum())
        found = parabolic_minimum(profile, starts[0], self.step, *bounds, k, alternatives=starts[1:],
                                  curvature=curvature)
        if found is None:  # no clean parabola near the start: the single-trace profile on the same points
            x, y = profile.points()
            start = float(x[np.argmin(y)])
            s2 = profile(start) / max(profile.n_rows - k, 1)
            res = robust_profile(profile, start, 0.3e-9, s2, *bounds, min_step=1e-14, jackknife=True)
            found = SeparationFound(res.value, res.sigma)  # its curvature is not read: the next pixel brackets
        return SeparationSearch(found, systems)

    def _finish(self, prep, params, system, support, search, counter, route) -> tuple[PixelResult, np.ndarray]:
        """The pixel's fit at the found separation through the fits' one sequence
        (:func:`afmid.fit.orchestration.orchestrate`): coefficients, their spread from the least-squares covariance
        (:data:`COVARIANCE_DRAWS` draws), the cross-validated error, the read-out, the separation's sigma
        propagated (:class:`CarriedSeparation`), the calibration and the model-limited mark."""
        from afmid.fit.orchestration import CalibrationAndLimits, CovarianceDraws, HeldOutPeriods, orchestrate
        from afmid.maps.residual import fit_view, view_signature

        config, library = self.config, self.library
        done = orchestrate(config, library, CarriedSeparation(prep, library, params, system, support, search, counter),
                           CovarianceDraws(COVARIANCE_DRAWS, [config.fit.seed, 14]),
                           HeldOutPeriods(library, config.fit.folds), [CalibrationAndLimits(True)])
        state, found = done.state, search.found
        signature, curves = view_signature(fit_view(prep, library, system, done.coef, state.params, done.error.rows,
                                                    config))
        return PixelResult(state.quantities, found.value, found.sigma, state.cv_error, state.noise_floor,
                           np.asarray(support[:len(library)], bool), state.warnings, route, signature=signature,
                           curves=curves), done.coef


class CarriedSeparation:
    """A map pixel's separation strategy (:class:`afmid.fit.orchestration.SeparationStrategy`) once its carried
    search has run (:meth:`SharedSupportFit._search`): :meth:`settle` hands on the separation it found, the system
    there and the support (carried from the last pixel, or re-selected); :meth:`propagate` adds d's sigma from the
    search's own points (:meth:`SeparationSearch.propagate`), or, with fewer than three of them near the minimum,
    by refits at d +- sigma (:func:`afmid.fit.orchestration.propagate_nonlinear`, two library evaluations counted
    in ``counter``)."""

    def __init__(self, prep, library, params: dict, system, support: np.ndarray, search: SeparationSearch,
                 counter: dict):
        self.prep, self.library, self.system, self.support, self.search, self.counter = (prep, library, system,
                                                                                        support, search, counter)
        self.params = dict(params, d=search.found.value)

    def settle(self):
        from afmid.fit.orchestration import Settled, record_warnings

        return Settled(self.prep, self.system, self.support, self.params, record_warnings(self.prep))

    def propagate(self, state) -> None:
        from afmid.fit.forces import read_out
        from afmid.fit.orchestration import propagate_nonlinear
        from afmid.fit.search import NonlinearEstimate

        library, params, support, trace, found = self.library, self.params, self.support, state.trace, self.search.found
        if not self.search.propagate(state.quantities, found, lambda c, d: read_out(library, c, None, dict(params, d=d),
                                                                                    support, trace), support):
            nonlinear = {"d": NonlinearEstimate("d", found.value, found.sigma, "m", True)}
            self.counter["builds"] += 2
            propagate_nonlinear(state.quantities, nonlinear, self.prep, library, params, support, trace)


@dataclass
class SeparationSearch:
    """A finished separation search: the minimum and the systems built on the way (d -> System; only when the
    profile library is the fitted library, so that they serve the pixel's fit)."""

    found: "SeparationFound"
    systems: dict

    def system_at_minimum(self):
        """The system at the evaluated point nearest the minimum when it lies within :data:`RESOLUTION` sigma
        (the minimum is then moved onto it: a step far below its error bar), else None (build one)."""
        if not self.systems or not math.isfinite(self.found.sigma):
            return None
        nearest = min(self.systems, key=lambda v: abs(v - self.found.value))
        if abs(nearest - self.found.value) > RESOLUTION * self.found.sigma:
            return None
        self.found.value = nearest
        return self.systems[nearest]

    def propagate(self, quantities: dict, found: "SeparationFound", read, support: np.ndarray) -> bool:
        """Add d's sigma to the quantities' errors (in place) from the evaluated points within 3 sigma of the
        minimum (no library evaluation); ``read(coef, d)`` reads out. Each read-out's change at d +- sigma is
        read off the parabola through those points (in d), and the larger of the two sides is added, the rule of
        the single-trace fit (afmid.fit.uncertainty.add_largest_shift): a slope through them misses a read-out
        that is not monotone in d within its sigma (E* that falls on both sides of the minimum). For a read-out
        linear in d this is the slope times sigma. False when fewer than three points are there (the caller
        refits at d +- sigma instead). Added in quadrature to the error and to both halves of the 95 %
        interval, as afmid.fit.orchestration.propagate_nonlinear does."""
        sigma = found.sigma
        if not (math.isfinite(sigma) and sigma > 0):
            return True  # nothing to propagate
        near = sorted(v for v in self.systems if abs(v - found.value) <= 3 * sigma)
        if len(near) < 3:
            return False
        values = {k: [] for k in quantities}
        for v in near:
            coef, _ = regression.subset_fit(regression.combine(self.systems[v].T_blocks), support)
            read_at = read(coef, v)
            for k in quantities:
                values[k].append(read_at.get(k, {}).get("value", math.nan))
        offsets = (np.asarray(near) - found.value) / sigma  # in sigmas: a well-conditioned parabola
        sides = [{}, {}]  # the read-outs at d - sigma and d + sigma
        for k, y in values.items():
            y = np.asarray(y)
            if np.all(np.isfinite(y)):
                at = np.polynomial.polynomial.polyval([-1.0, 1.0], np.polynomial.polynomial.polyfit(offsets, y, 2))
                sides[0][k], sides[1][k] = {"value": float(at[0])}, {"value": float(at[1])}
        variance = {k: 0.0 for k in quantities}
        add_largest_shift(variance, quantities, sides)
        for k, q in quantities.items():
            widen_interval(q, math.sqrt(variance[k]))
        return True


@dataclass
class SeparationFound:
    value: float  # m
    sigma: float  # m, 1 sigma: max(chi-square width, block jackknife); NaN when undetermined
    curvature: float = math.nan  # 1/m^2, a of the last parabola rss = a (d - vertex)^2 + c; NaN when not read


def parabolic_minimum(profile, start: float, step: float, lo: float, hi: float, k: int,
                      alternatives: tuple[float, ...] | list[float] = (),
                      curvature: float | None = None) -> SeparationFound | None:
    """The minimum of ``profile`` (an :class:`afmid.fit.profile.GroupedProfile`) by a bracket around ``start`` and
    parabola steps, with its 1 sigma; None when it does not converge within :data:`MAX_SEARCH_EVALUATIONS`
    or the profile is not locally parabolic (the caller then runs the robust profile on the same points).

    The bracket moves (doubling its step) while the lowest point is on its edge, and is halved around the lowest
    point while wider than :data:`BRACKET_WIDTHS` chi-square widths; then the parabola through the
    lowest point and its neighbours gives the vertex and the chi-square width sigma = sqrt(s2 / curvature); points
    are added at the vertex and at +-sigma until the vertex moves by less than a tenth of sigma, so the width is
    read where the chi-square rises by about one. sigma is the larger of that width and the spread of the vertex
    over the block jackknife (leave-one-group-out profiles from the same factors, no library evaluation).
    When the lowest point is on the edge and the parabola of the edge's three points (spanning at most 3 sigma)
    has its vertex within a tenth of sigma of it, that is the minimum as well (the same test on one side).

    ``curvature`` (1/m^2, the last pixel's; None: unknown): the bracket's first two points (``start`` and
    ``start + step``) and that curvature predict the vertex (:func:`predicted_third_point`), which is the third point
    when it lies within :data:`EDGE_REACH` steps of ``start`` (the points ``start - step`` and beyond otherwise,
    the plain bracket): on a smooth map the residual profile's curvature changes little from pixel to pixel
    (within ~10 % in a phase on the blend map), so the third point lands within a few tenths of sigma of the vertex
    and the search ends after three or four library evaluations instead of four or five (22 % and 70 % of the
    64x64 blend map's carried pixels).

    ``alternatives``: other starts (the offsets of other phases met before), evaluated only when the first
    bracket's lowest point is on its edge (the minimum is not near ``start``); when one of them is lower, the
    search starts again from it. Only the points of the current bracket take part in its parabolas: a far start
    among them would pass for a neighbour of the lowest point and make the bracket halve its way back.
    """
    def clip(v):
        return min(max(v, lo), hi)

    def bracket(centre: float) -> _BracketPoints:
        points = _BracketPoints(profile)
        for v in (clip(centre - step), clip(centre), clip(centre + step)):
            points(v)
        return points

    first_step = step
    if curvature is not None and curvature > 0 and math.isfinite(curvature):
        local = _BracketPoints(profile)
        for v in (clip(start), clip(start + step)):
            local(v)
        local(predicted_third_point(*local.points(), curvature, clip(start), step, lo, hi))
    else:
        local = bracket(start)
    alternatives = list(alternatives)
    for _ in range(MAX_SEARCH_EVALUATIONS):
        x, y = local.points()
        if not np.all(np.isfinite(y)) or len(profile.full) >= MAX_SEARCH_EVALUATIONS:
            return None
        i = int(np.argmin(y))
        if i == 0 or i == x.size - 1:  # on the edge: another phase's start if lower, else move outwards
            found = _converged_at_edge(profile, x, y, i, profile.n_rows - k)
            if found is not None:
                return found
            near = _vertex_beyond_edge(x, y, i, lo, hi, profile.n_rows - k)
            if near:  # the parabola of the edge's three points bends within reach: bracket its vertex
                for v in near:
                    local(v)
                continue
            if alternatives:
                best = min(alternatives, key=profile)
                alternatives = []
                if profile(best) < y[i]:
                    step = first_step
                    local = bracket(best)
                    continue
            if (i == 0 and x[0] <= lo) or (i == x.size - 1 and x[-1] >= hi):
                return None  # the minimum is on the search window's bound
            step *= 2
            local(clip(x[i] - step if i == 0 else x[i] + step))
            continue
        vertex, curvature = _parabola(x[i - 1:i + 2], y[i - 1:i + 2])
        s2 = y[i] / max(profile.n_rows - k, 1)
        sigma = math.sqrt(s2 / curvature) if curvature > 0 else math.inf
        spacing = max(x[i] - x[i - 1], x[i + 1] - x[i])
        if spacing > BRACKET_WIDTHS * sigma or not math.isfinite(sigma):
            # Too wide a bracket to trust a parabola (after a long move): halve it around the lowest point.
            for v in (0.5 * (x[i - 1] + x[i]), 0.5 * (x[i] + x[i + 1])):
                local(v)
            continue
        wanted = [vertex] if spacing <= 3 * sigma else [vertex - sigma, vertex, vertex + sigma]
        new = [clip(v) for v in wanted if np.min(np.abs(x - v)) > 0.1 * sigma]
        if not new:
            jk = _jackknife_spread(profile, x[i - 1:i + 2])
            return SeparationFound(float(vertex), max(sigma, jk) if math.isfinite(jk) else sigma, curvature)
        for v in new:
            local(v)
    return None


def predicted_third_point(x: np.ndarray, y: np.ndarray, curvature: float, start: float, step: float, lo: float,
                          hi: float) -> float:
    """The third point of a bracket whose first two are ``x`` (sorted, profile values ``y``), given the profile's
    ``curvature`` a (1/m^2, a pixel's neighbour's): the vertex of the parabola of curvature a through both points,
    (x0 + x1) / 2 - (y1 - y0) / (2 a (x1 - x0)). When it lies within half a step of one of them, that point is the
    bracket's middle and the third is the mirror of the other (a symmetric bracket around it); beyond
    :data:`EDGE_REACH` steps from ``start`` (another phase, or the curvature does not hold) the plain bracket's
    ``start - step``. Clipped to [lo, hi] (m)."""
    def clip(v):
        return min(max(v, lo), hi)

    if x.size < 2 or not np.all(np.isfinite(y)) or x[1] <= x[0]:
        return clip(start - step)
    vertex = 0.5 * (x[0] + x[1]) - (y[1] - y[0]) / (2.0 * curvature * (x[1] - x[0]))
    if not abs(vertex - start) <= EDGE_REACH * step:
        return clip(start - step)
    nearest = int(np.argmin(np.abs(x - vertex)))
    if abs(vertex - x[nearest]) < 0.5 * step:
        return clip(2.0 * x[nearest] - x[1 - nearest])
    return clip(vertex)


def _converged_at_edge(profile, x: np.ndarray, y: np.ndarray, i: int, dof: int) -> SeparationFound | None:
    """The minimum when the lowest point ``x[i]`` is on the bracket's edge and the parabola through the edge's three
    points, no more than 3 chi-square widths apart, bends upwards with its vertex within a tenth of a width of
    ``x[i]`` (the convergence test of :func:`parabolic_minimum` on one side); else None."""
    if x.size < 3:
        return None
    three = slice(0, 3) if i == 0 else slice(x.size - 3, x.size)
    vertex, curvature = _parabola(x[three], y[three])
    if not curvature > 0:
        return None
    sigma = math.sqrt(y[i] / max(dof, 1) / curvature)
    spacing = float(np.max(np.diff(x[three])))
    if spacing > 3 * sigma or abs(vertex - x[i]) > 0.1 * sigma:
        return None
    jk = _jackknife_spread(profile, x[three])
    return SeparationFound(float(vertex), max(sigma, jk) if math.isfinite(jk) else sigma, curvature)


#: An edge's parabola is followed when its vertex lies within this many of the bracket's spacings beyond the edge.
EDGE_REACH = 3.0


def _vertex_beyond_edge(x: np.ndarray, y: np.ndarray, i: int, lo: float, hi: float, dof: int) -> list[float]:
    """Where to evaluate next when the lowest point ``x[i]`` is on the bracket's edge: the vertex of the parabola
    through it and its two nearest points and one chi-square width sigma beyond the vertex (so that the vertex
    ends inside the bracket), when the parabola bends upwards and the vertex lies beyond the edge within
    :data:`EDGE_REACH` spacings (inside the search window); the vertex alone when the three points lie within
    3 sigma (the interior rule of :func:`parabolic_minimum`: a parabola that close is trusted, and
    :func:`_converged_at_edge` ends the search at its vertex if the next parabola agrees); points within a tenth
    of sigma of one evaluated are left out. An empty list: move outwards, or try another start."""
    if x.size < 3:
        return []
    three = slice(0, 3) if i == 0 else slice(x.size - 3, x.size)
    vertex, curvature = _parabola(x[three], y[three])
    if not curvature > 0:
        return []
    outwards = -1.0 if i == 0 else 1.0
    spacing = abs(x[i] - x[i + 1 if i == 0 else i - 1])
    beyond = outwards * (vertex - x[i])
    if beyond > EDGE_REACH * spacing:
        return []
    sigma = math.sqrt(y[i] / max(dof, 1) / curvature)
    if np.max(np.diff(x[three])) <= 3 * sigma:  # close enough to trust its vertex (_converged_at_edge ends there)
        wanted = [vertex]
    else:
        wanted = [vertex, vertex + outwards * sigma] if beyond > 0 else [x[i] + outwards * sigma]
    near = [min(max(v, lo), hi) for v in wanted if np.min(np.abs(x - v)) > 0.1 * sigma]
    return [v for v in near if np.min(np.abs(x - v)) > 0.1 * sigma]


class _BracketPoints:
    """The points of one bracket of :func:`parabolic_minimum` on a shared profile (evaluations cached there)."""

    def __init__(self, profile):
        self.profile = profile
        self.values: dict[float, float] = {}

    def __call__(self, value: float) -> float:
        value = float(value)
        self.values[value] = self.profile(value)
        return self.values[value]

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.array(sorted(self.values))
        return x, np.array([self.values[v] for v in x])


def _parabola(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Vertex and curvature a of y = a (x - vertex)^2 + c through three points (x relative to the middle)."""
    u = x - x[1]
    a, b, _ = np.linalg.solve(np.vander(u, 3), y)
    if a <= 0:
        return float(x[1]), float(a)
    return float(x[1] - b / (2 * a)), float(a)


def _jackknife_spread(profile, points: np.ndarray) -> float:
    """1 sigma of the parabola vertex over the leave-one-group-out profiles at ``points`` (NaN without groups)."""
    G = profile.jackknife_groups()
    if G < 2:
        return math.nan
    vertices = []
    left_out = np.array([profile.leave_each_out(v) for v in points])  # (points, groups)
    for g in range(G):
        y = left_out[:, g]
        if not np.all(np.isfinite(y)):
            return math.nan
        v, a = _parabola(points, y)
        if not a > 0:
            return math.nan
        vertices.append(v)
    vertices = np.asarray(vertices)
    return float(math.sqrt((G - 1) / G * np.sum((vertices - vertices.mean()) ** 2)))


PIXEL_FITS: Registry = Registry("pixel fit")
PIXEL_FITS.register(SharedSupportFit)
PIXEL_FITS.register(FullPixelFit)
#: The strategy ``afmid map`` uses unless ``--pixel-fit`` names another.
DEFAULT_PIXEL_FIT = SharedSupportFit.name

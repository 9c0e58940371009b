"""The fit stage: from a deflection trace to a sparse, physically named force law.

Pipeline (each step a plain function; the CLI only wires them):
load (:func:`afmid.io.trace.load_trace`) -> :func:`prepare` (drive frequency, blocks of
one period, Fourier coefficients, noise level, the inverted force) ->
:func:`build_system` (library columns projected like the data, whitened, factored)
-> :func:`afmid.fit.regression.select` (sparsity path + BIC / CV) -> nonlinear
parameters (separation, decay lengths) by an outer search -> bagging for error
bars -> physical read-out -> per-sample and per-period forces -> :func:`afmid.runfile.write_run`.

:func:`run_fit` is load + :func:`prepare` + :func:`fit_prepared`. Fits of many
libraries or parameter sets on one trace (the diagnosis, force maps) prepare
it once and pass it (``run_fit(config, prepared=...)`` or :func:`fit_prepared`);
:func:`build_system`, :func:`residual_sum_squares` and :func:`library_parameters`
serve searches of their own on a prepared trace. The pieces live beside this
module: :mod:`afmid.fit.selection` (selection settings), :mod:`afmid.fit.search`
(1-D searches and search ranges of the nonlinear parameters),
:mod:`afmid.fit.forces` (error metric, read-out, forces).

Equation (SI, x toward the sample, F_ts repulsive positive):
    m x'' + (m w0 / Q) x' + k x = -F_ts + F_drive,   m = k / w0^2
so  Y := -(m x'' + (m w0/Q) x' + k x) = F_ts - F_drive = Theta c - (a cos wt + b sin wt).
In the harmonic form every column is projected on the drive harmonics of each
block (least squares), derivatives act exactly on the Fourier series, and the
rows are weighted by the predicted noise of Y (detector noise amplified by the
cantilever's transfer function plus thermal force noise).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from afmid.config import RunConfig
from afmid.errors import AfmidError, ConfigError
from afmid.preprocess.instrument import from_config as instrument_from_config
from afmid.io.trace import Trace, load_trace
from afmid.physics.library import Library, build_library
from afmid.physics.medium import relative_permittivity
from afmid.physics.tips import tip_geometry
import afmid.fit.regression as regression
from afmid.fit.forces import per_sample_forces, period_curves, read_out
from afmid.fit.information_bound import InformationBound, floor_at_bound
from afmid.fit.search import NonlinearEstimate, search_1d, search_range
from afmid.fit.profile import GroupedProfile, ProfileResult, open_side_warning, robust_profile
from afmid.fit.joint_profile import other_valley
from afmid.fit.plausibility import unphysical
from afmid.fit.uncertainty import widen_interval
from afmid.fit.valleys import Misfit, cover_model_limited, cover_other_valleys
from afmid.fit.selection import SelectionSettings
from afmid.fit.drive_search import DriveSearch, settle_drive_frequency
from afmid.fit.declared_drive import declared_drive, with_declared_drive
from afmid.fit.fit_state import FitState
from afmid.fit.orchestration import (BootstrapBagging, CalibrationAndLimits, ContactLawProbe, DriveCalibration,
                                     HeldOutPeriods, InvolsShare, NoSpread, Settled, Stages, Undetermined, Unphysical,
                                     nonlinear_shift, orchestrate, propagate_nonlinear, record_warnings)
from afmid.fit.undetermined import whole_effects
from afmid.progress import Progress
from afmid.fit.separation_share import NOT_COMPUTED as SHARE_NOT_COMPUTED, SeparationShare, separation_share
from afmid.fit.force_band import selection_share, statistical_share, total_share
from afmid.fit.prepare import Prepared, prepare, with_fine_grid, with_regressor_noise
from afmid.fit.system import System, build_system, library_columns, library_thermal_bias, residual_sum_squares

log = logging.getLogger(__name__)

#: The fit's stages as the progress line counts them (after the trace is loaded): preparing periods, the
#: separation / drive search, selecting terms, the bootstrap, the error and forces.
FIT_STAGES = 5


# --------------------------------------------------------------------------- nonlinear search
def profile_parameter(prep: "Prepared", library: Library, params: dict, name: str, bounds: tuple[float, float],
                      mask: np.ndarray | None, jackknife: bool = True) -> ProfileResult:
    """Profile the weighted residual over one nonlinear parameter (the others held): :class:`ProfileResult`.

    ``mask`` selects the columns (None: all). The minimum, its chi-square
    interval and the block jackknife of the minimum (``jackknife``: the
    honest sigma; off for quick refits) are :func:`afmid.fit.profile.robust_profile`'s.
    """
    def factors_at(value: float):
        try:
            system = build_system(prep, library, dict(params, **{name: value}))
        except AfmidError:
            return None
        return system.T_blocks, system.n_rows

    grouped = GroupedProfile(factors_at, mask)
    rss = grouped(params[name])
    n_columns = len(library) + len(prep.nuisance_names)
    m = np.ones(n_columns, dtype=bool) if mask is None else mask
    s2 = rss / max(grouped.n_rows - int(m.sum()), 1)
    half = 0.3e-9 if name == "d" else max(0.3 * abs(params[name]), 1e-3 * (bounds[1] - bounds[0]))
    min_step = 1e-14 if name == "d" else 1e-4 * half
    return robust_profile(grouped, params[name], half, s2, *bounds, min_step=min_step, jackknife=jackknife)


def profile_library(library: Library, config: RunConfig) -> tuple[Library, dict[str, float]]:
    """The library whose residual profiles the rest separation and decay lengths, and the parameters it adds.

    These are parameters of the physical model, so they are profiled with it.
    A preset's distractors (z^-3 beside z^-2, delta^2 beside delta^1.5) absorb
    a misplaced contact point and leave the preset's residual flat in d; and
    its split columns (tail out of contact, a free adhesion constant in
    contact) lose the continuity of the DMT force at contact, which is what
    pins the contact point. So a preset is profiled with the catalog effects it
    stands for (``dmt`` ties the tail and the adhesion), then selected among
    its own terms at that separation. A library built from effects (plus any
    custom terms) is its own profile library. Nonlinear parameters of the
    profile library that the run's library lacks (e.g. a JKR neck length) stay
    at their defaults (returned as the second value).
    """
    if config.model.library is None:
        return library, {}
    from afmid.config import ModelConfig

    physics = build_library(ModelConfig(effects=list(library.effects)), config.source, library.tip)
    extra = {k: v for k, v in physics.nonlinear.items() if k not in library.nonlinear}
    return physics, extra


# --------------------------------------------------------------------------- result
@dataclass
class FitResult:
    config: RunConfig
    prep: Prepared
    library: Library
    system: System
    selection: regression.Selection
    coef: np.ndarray  # all columns (library + nuisance), SI
    coef_std: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    inclusion: np.ndarray
    bagging: regression.Bagging | None
    nonlinear: dict[str, NonlinearEstimate]
    quantities: dict[str, dict]  # name -> {value, error, ci_low, ci_high, unit, effect}
    cv_error: float
    cv_error_folds: np.ndarray
    cv_error_noise_floor: float  # the error a perfect model would show at this noise
    signal_rows: np.ndarray  # bool (2K+1): rows counted in the error metric
    force_estimate: np.ndarray  # N per input sample (NaN where not estimated)
    force_inverted: np.ndarray  # N per input sample, drive - (m x'' + c x' + k x) (band-limited; prep.declared_drive)
    periods: dict[str, np.ndarray]
    warnings: list[str] = field(default_factory=list)
    drive_search: DriveSearch | None = None  # the drive frequency searched by the regression (transient records)
    force_calibration_uncertainty: float = 0.0  # relative, 1 sigma: the force's share of the k / Q calibration
    model_limited: bool = False  # cv_error above its noise floor: parameters biased beyond their error bars
    #: the estimated separation's share of the force's uncertainty (relative to the peak, 1 sigma; NaN: d given)
    separation_share: SeparationShare = SHARE_NOT_COMPUTED
    #: the bootstrap's share of the force's uncertainty (relative to the peak, 1 sigma; NaN: no bootstrap)
    force_statistical_uncertainty: float = math.nan
    #: half the force's change with the dropped terms of its effects forced in (relative, 1 sigma; NaN: not computed)
    force_selection_uncertainty: float = math.nan
    #: the record's Cramér-Rao bound (afmid.fit.information_bound; None: not computed), the floor of the sigmas
    information_bound: InformationBound | None = None
    #: the noise floor's effective degrees of freedom (afmid.fit.uncertainty.floor_threshold; NaN: not known)
    cv_error_floor_dof: float = math.nan

    @property
    def force_separation_uncertainty(self) -> float:
        return self.separation_share.relative

    @property
    def force_total_uncertainty(self) -> float:
        """The force curve's 1 sigma relative to its peak: the statistical, separation and calibration shares
        in quadrature (afmid.fit.force_band); NaN when none was computed."""
        return total_share(self.force_statistical_uncertainty, self.force_separation_uncertainty,
                           self.force_selection_uncertainty,
                           self.force_calibration_uncertainty if self.force_calibration_uncertainty > 0 else math.nan)

    @property
    def selected(self) -> np.ndarray:
        return self.selection.best.mask

    @property
    def n_periods(self) -> int:
        """The drive periods of the record the fit used: its blocks times ``fit.periods_per_block``."""
        return int(self.prep.blocks.n_blocks * self.config.fit.periods_per_block)

    @property
    def n_library(self) -> int:
        return len(self.library)

    def selected_terms(self) -> list[str]:
        return [n for n, m in zip(self.library.names, self.selected[: self.n_library]) if m]

    def summary_line(self) -> str:
        terms = ", ".join(self.selected_terms()) or "none"
        return f"cv_error {self.cv_error:.4f}; terms: {terms}"


def library_parameters(prep: Prepared, config: RunConfig, library: Library) -> dict:
    """The parameters the library's columns are evaluated with, before the outer search (SI).

    The sample's a0 and medium's permittivity ``eps_r``, the measured drive frequency ``w`` (rad/s), the tip radius
    ``R`` when the cantilever has one, and the library's nonlinear parameters at
    their defaults or fixed values. The rest separation ``d`` is not included:
    the outer search (or ``sample.separation``) sets it.
    """
    params = {"a0": config.sample.a0, "w": prep.drive.omega, "eps_r": relative_permittivity(config.sample)}
    if prep.trace.cantilever.tip_radius is not None:
        params["R"] = prep.trace.cantilever.tip_radius
    params.update(library.nonlinear)
    return params


def first_contact(prep: Prepared, a0: float) -> float:
    """Separation at which the lowest turning point just touches (z_min = a0), m."""
    x_max = float(np.max(prep.blocks.synthesize(prep.X[..., None])[:, 0]))
    return x_max + a0


def estimate_nonlinear(prep, library, config, params, physics=None, refine_tolerance: float = 1e-6
                       ) -> dict[str, NonlinearEstimate]:
    """Coarse outer search over the rest separation and the library's decay lengths.

    The objective is the residual of the profile library (:func:`profile_library`: the run's catalog
    effects, all their terms; ``physics`` = its (library, extra parameters) when already built);
    :func:`run_fit` then refines each on its profile. ``refine_tolerance``: of the grid search's Brent refinement
    (:func:`afmid.fit.search.search_1d`), relative to its bracket (two grid steps).
    """
    fit = config.fit
    estimates: dict[str, NonlinearEstimate] = {}
    to_search: list[tuple[str, float, float, bool, str]] = []
    zero_allowed: set[str] = set()
    if config.sample.separation is None:
        d_touch = first_contact(prep, config.sample.a0)
        below, above = fit.separation_window
        to_search.append(("d", d_touch - below, d_touch + above, False, "m"))
    else:
        params["d"] = config.sample.separation
    if fit.estimate_nonlinear:
        for name in library.nonlinear:
            if name in config.model.parameters:
                continue
            span = search_range(library, name, config.sample.medium)
            to_search.append((name, span.low, span.high, True, span.unit))
            if span.zero_allowed:
                zero_allowed.add(name)
    if "d" not in params:
        params["d"] = to_search[0][1] + 0.5 * (to_search[0][2] - to_search[0][1])
    physics, extra = physics or profile_library(library, config)
    for round_ in range(2 if len(to_search) > 1 else 1):
        for name, lo, hi, log_scale, unit in to_search:
            def objective(value, name=name):
                trial = dict(params, **extra, **{name: value})
                try:
                    return residual_sum_squares(build_system(prep, physics, trial), None)
                except AfmidError:
                    return math.inf
            n_grid = 25 if round_ == 0 else 11
            if round_ > 0:  # narrow around the current value
                cur = params[name]
                span = (hi - lo) / 8 if not log_scale else None
                if span:
                    lo_r, hi_r = max(lo, cur - span), min(hi, cur + span)
                else:
                    lo_r, hi_r = (max(lo, cur / 2), min(hi, cur * 2)) if cur > 0 else (lo, min(hi, 4 * lo))
            else:
                lo_r, hi_r = lo, hi
            best, grid, values = search_1d(objective, lo_r, hi_r, n_grid, log_scale, refine_tolerance)
            if name in zero_allowed and objective(0.0) <= min(objective(best), float(np.min(values))):
                best = 0.0
            params[name] = best
            estimates[name] = NonlinearEstimate(name, best, math.nan, unit, True, grid, values,
                                                (0.0 if name in zero_allowed else lo, hi))
    return estimates


def run_fit(config: RunConfig, progress: bool | Progress = False, trace: Trace | None = None,
            uncertainty: bool = True, prepared: Prepared | None = None) -> FitResult:
    """Fit the trace named by ``config`` (or ``trace``) and return everything the run file holds.

    ``uncertainty=False`` skips the error bars (bootstrap, profile widths of the
    nonlinear parameters and their propagation): for quick comparative refits.
    ``prepared`` is :func:`prepare` of the trace with ``config.fit`` done once
    and shared by fits of other libraries or parameters on the same trace (it
    is never modified); its trace is the one fitted.
    """
    bar = progress if isinstance(progress, Progress) else Progress("fit", enabled=progress)
    try:
        if prepared is not None:
            if trace is not None and trace is not prepared.trace:
                raise ValueError("run_fit: `trace` is not the trace `prepared` was made from")
            trace = prepared.trace
        elif trace is None:
            trace = load_trace(config)  # no stage line before: a file afmid refuses gives its one error line only
        library = build_library(config.model, config.source, tip_geometry(config.cantilever))
        if len(library) == 0:
            raise ConfigError("the library is empty: list effects, a preset or terms", file=config.source,
                              key="model")
        if prepared is None:
            bar.stage("preparing periods", step=(1, FIT_STAGES))
        prep = prepared if prepared is not None else prepare(trace, config.fit, instrument_from_config(config))
        return fit_prepared(prep, library, config, progress=bar, uncertainty=uncertainty)
    finally:
        if bar is not progress:
            bar.close()


def fit_prepared(prep: Prepared, library: Library, config: RunConfig, progress: bool | Progress = False,
                 uncertainty: bool = True) -> FitResult:
    """Fit ``library`` to a prepared trace (:func:`prepare` with ``config.fit``): the fit after the preparation.

    ``config`` gives the sample (a0, a fixed separation), fixed model parameters
    and the fit settings; ``config.model`` is not read (``library`` is fitted).
    ``prep`` is not modified, so one preparation serves fits of many libraries
    and parameter sets. ``uncertainty`` as in :func:`run_fit`; ``progress`` a bool (show the stages) or the
    caller's :class:`afmid.progress.Progress`.
    """
    bar = progress if isinstance(progress, Progress) else Progress("fit", enabled=progress)
    try:
        return _fit_prepared(prep, library, config, bar, uncertainty)
    finally:
        if bar is not progress:
            bar.close()


def _fit_prepared(prep: Prepared, library: Library, config: RunConfig, bar: Progress, uncertainty: bool) -> FitResult:
    fit = config.fit
    trace = prep.trace
    # The trajectory on the fine grid made once for the ~90 library evaluations (the same values); not kept with
    # the result (up to 64 MB: callers keep many results).
    grid_made_here = prep.fine_grid is None
    prep = with_fine_grid(prep)
    # Defects were detected and reported when the trace was loaded (afmid.io.defects); keep them with the run.
    warnings = record_warnings(prep)
    drive = declared_drive(config, trace)
    if drive is not None:  # a calibrated drive: not fitted, so the inverted force does not depend on the model
        prep = with_declared_drive(prep, drive)
        log.info("drive not fitted: %s", drive.describe())
    separation = ProfiledSeparation(prep, library, config, warnings, uncertainty, bar, drive is not None)
    settings = separation.settings
    finishing = [CalibrationAndLimits(uncertainty)]
    if uncertainty:
        finishing += [InvolsShare(separation.nonlinear, separation.resettle), ContactLawProbe(separation.select_with),
                      DriveCalibration()]
    finishing += [Undetermined(fit.bootstrap if uncertainty else 0, fit.seed), Unphysical()]
    information = InformationFloor(separation)
    if uncertainty:  # a model-limited fit's intervals from the whole profile; none below the Cramér-Rao bound
        finishing += [ModelLimitedProfile(separation), information]
    spread = (BootstrapBagging(settings, fit.bootstrap, fit.seed) if fit.bootstrap > 0 and uncertainty
              else NoSpread())
    done = orchestrate(config, library, separation, spread, HeldOutPeriods(library, fit.folds), finishing, bar,
                       Stages(spread=(4, FIT_STAGES), error=(5, FIT_STAGES)))
    state, coef, chosen, rows = done.state, done.coef, done.settled.chosen, done.error.rows
    prep, system, params, warnings = state.prep, state.system, state.params, state.warnings
    nonlinear = separation.nonlinear
    force_estimate, force_inverted = per_sample_forces(prep, library, system, coef, rows)
    share = SHARE_NOT_COMPUTED
    if uncertainty and "d" in nonlinear and config.sample.separation is None:
        # the force curve along the separation's valley (afmid.fit.separation_share): often the largest part
        share = separation_share(prep, library, params, lambda system: settings.select(system).best.mask,
                                 nonlinear["d"].sigma, force_estimate)
        if share.warning():
            warnings.append("warning: " + share.warning())
    bagging = done.spread.bagging
    statistical = (statistical_share(prep, library, system, bagging.coef_samples, force_estimate)
                   if uncertainty and bagging is not None else math.nan)
    selection_doubt = (selection_share(prep, library, system, chosen, whole_effects(library, chosen), force_estimate)
                       if uncertainty else math.nan)
    periods = period_curves(prep, library, system, coef, params, rows, fit.phase_points)
    for name, est in nonlinear.items():
        log.debug("estimated %s = %.4g ± %.2g %s", name, est.value, est.sigma, est.unit)
    if grid_made_here:
        prep = replace(prep, fine_grid=None)
    spread_out, error = done.spread, done.error
    return FitResult(config, prep, library, system, done.settled.selection, coef, spread_out.coef_std,
                     spread_out.ci_low, spread_out.ci_high, spread_out.inclusion, bagging, nonlinear, state.quantities,
                     error.cv_error, error.per_fold, error.noise_floor, rows, force_estimate, force_inverted, periods,
                     warnings, separation.drive_search, state.force_calibration, state.model_limited, share,
                     statistical, selection_doubt, information.bound, cv_error_floor_dof=error.floor_dof)


class ModelLimitedProfile:
    """A model-limited fit's nonlinear parameters (the separation first) get the interval of their profile over
    the whole searched window weighed against the model's misfit (:func:`afmid.fit.valleys.cover_model_limited`):
    the chi-square unit scaled by (error / floor)^2, and, when read-outs are unphysical, the rise a law with
    physical parameters loses at the fit's own minimum allowed to every other valley. The widened sigma's extra
    share is propagated into the read-outs (the larger change at +-sigma, in quadrature with what they carry).
    A fit that is not model-limited is left as it is."""

    name = "model-limited profile"

    def __init__(self, separation: "ProfiledSeparation"):
        self.separation = separation

    def apply(self, state) -> None:
        sep = self.separation
        if not state.model_limited or not sep.profiled:
            return
        misfit = Misfit(state.cv_error / state.noise_floor if state.noise_floor > 0 else math.nan,
                        physical_allowance(state))
        for name, est in sep.nonlinear.items():
            found = sep.profiled.get(name)
            if found is None:
                continue
            if not math.isclose(found.value, est.value, rel_tol=0.0, abs_tol=1e-3 * max(found.sigma, 0.0)):
                found = sep.profile_from(name, est.value, jackknife=True)  # moved since (another valley)

            def refine(start: float, name=name) -> ProfileResult | None:
                try:
                    return sep.profile_from(name, start)
                except AfmidError:
                    return None

            before = cover_model_limited(name, est, found, misfit, refine, state.warnings)
            if not est.sigma > before:
                continue
            args = (state.prep, state.library, state.params, state.mask, state.trace)
            wide = nonlinear_shift(state.quantities, name, est.sigma, *args)
            narrow = nonlinear_shift(state.quantities, name, before, *args)
            for k, q in state.quantities.items():
                widen_interval(q, math.sqrt(max(wide[k] - narrow[k], 0.0)))


def physical_allowance(state) -> float:
    """How much the fit's weighted residual grows at its own parameters when its unphysical read-outs
    (:func:`afmid.fit.plausibility.unphysical`) are held at their physical range's edge, zero: their source
    terms dropped from the support (one-sided bounds on a least-squares fit: the bounded optimum sits on the
    bound). 0 when none is unphysical or a source is not a column of the fit."""
    names = list(state.system.names)
    dropped = np.array(state.mask, dtype=bool, copy=True)
    for key, q in state.quantities.items():
        if not unphysical(key, q):
            continue
        for source in q.get("sources") or ():
            label = f"{q.get('effect')}.{source}" if q.get("effect") else source
            if label not in names:
                return 0.0
            dropped[names.index(label)] = False
    if np.array_equal(dropped, state.mask):
        return 0.0
    T = regression.combine(state.system.T_blocks)
    full, without = regression.subset_fit(T, state.mask)[1], regression.subset_fit(T, dropped)[1]
    return max(float(without - full), 0.0) if math.isfinite(without) and math.isfinite(full) else 0.0


class InformationFloor:
    """The record's Cramér-Rao bound as a floor under d's and the read-outs' sigmas
    (:func:`afmid.fit.information_bound.floor_at_bound`); ``bound`` keeps it (None: not computed). A preset is
    bounded with its catalog effects' law (profile_library), the law that pins d."""

    name = "information bound"

    def __init__(self, separation: "ProfiledSeparation"):
        self.separation = separation
        self.bound: InformationBound | None = None

    def apply(self, state) -> None:
        sep = self.separation
        library, system, coef, mask, params = state.library, state.system, state.coef, state.mask, state.params
        if sep.physics is not library:
            library, params = sep.physics, dict(params, **sep.extra)
            system = build_system(state.prep, library, params)
            mask = np.ones(len(system.names), dtype=bool)
            coef, _ = regression.subset_fit(regression.combine(system.T_blocks), mask)
        trace = state.trace
        self.bound = floor_at_bound(
            state.prep, library, state.config, system, coef, mask, params, sep.nonlinear, state.quantities,
            state.warnings, sep.drive_search,
            lambda c, p: {k: q["value"] for k, q in read_out(library, c, None, p, mask, trace).items()})


def select_with_regressor_noise(prep: Prepared, library: Library, params: dict, settings: SelectionSettings
                                ) -> tuple[Prepared, System, regression.Selection]:
    """The first selection of a fit at ``params`` (SI): the rows weighted with the regressors' own noise (from a
    first support's stiffness: :func:`afmid.fit.prepare.with_regressor_noise`), then the support selected on the
    reweighted system (the same columns). Returns (the reweighted preparation, its system, the selection)."""
    system = build_system(prep, library, params)
    coef0, _ = regression.subset_fit(regression.combine(system.T_blocks), settings.weighting_support(system))
    prep = with_regressor_noise(prep, library, params, coef0)
    system = build_system(prep, library, params, theta=system.theta,  # same columns, new row weights
                          thermal_bias=system.thermal_bias)
    return prep, system, settings.select(system)


class ProfiledSeparation:
    """The single trace's separation strategy (:class:`afmid.fit.orchestration.SeparationStrategy`): the coarse
    search of the separation and decay lengths on the profile library (:func:`estimate_nonlinear`), the drive
    frequency settled on the residual (a transient), the row weights with the regressors' noise, a selection,
    each parameter refined on its profile over the chosen support (:func:`profile_parameter`) and a re-selection,
    a second valley of d with a decay length (afmid.fit.joint_profile), the open side of a profile and the other
    valleys covered (afmid.fit.valleys); the profiles' widths are the sigmas propagated into the read-outs.

    ``warnings`` is the fit's list of lines (appended to); ``drive_declared``: a calibrated drive (not searched).
    After :meth:`settle`: ``nonlinear`` (name -> :class:`afmid.fit.search.NonlinearEstimate`) and ``drive_search``.
    """

    def __init__(self, prep: Prepared, library: Library, config: RunConfig, warnings: list[str], uncertainty: bool,
                 bar: Progress, drive_declared: bool):
        self.prep, self.library, self.config, self.warnings = prep, library, config, warnings
        self.uncertainty, self.bar, self.drive_declared = uncertainty, bar, drive_declared
        self.params = library_parameters(prep, config, library)
        self.physics, self.extra = profile_library(library, config)
        self.settings = SelectionSettings.for_library(config.fit, library, len(prep.nuisance_names))
        self.nonlinear: dict[str, NonlinearEstimate] = {}
        self.profiled: dict[str, ProfileResult] = {}  # each nonlinear parameter's profile on the final support
        self.drive_search: DriveSearch | None = None
        self.chosen: np.ndarray | None = None

    def settle(self) -> Settled:
        """The search, selections and profiles in the order of the class docstring."""
        config, library, params, physics, extra = self.config, self.library, self.params, self.physics, self.extra
        fit, uncertainty, warnings, prep = config.fit, self.uncertainty, self.warnings, self.prep
        searched = ("the separation" if config.sample.separation is None  # a calibrated drive is not searched
                    else "the shape parameters" if self.drive_declared else "the drive")
        self.bar.stage(f"searching {searched}", step=(2, FIT_STAGES))
        nonlinear = self.nonlinear
        nonlinear.update(estimate_nonlinear(prep, library, config, params, physics=(physics, extra)))

        def factors_at(p: Prepared):  # the profile library's columns at the current parameters, held
            trial = dict(params, **extra)
            theta, bias = library_columns(p, physics, trial), library_thermal_bias(p, physics, trial)
            return lambda q: build_system(q, physics, trial, theta=theta, thermal_bias=bias).T_blocks

        def estimate_again(p: Prepared) -> None:
            nonlinear.update(estimate_nonlinear(p, library, config, params, physics=(physics, extra)))

        prep, self.drive_search = (prep, None) if prep.declared_drive is not None else settle_drive_frequency(
            prep, fit.drive_frequency, fit.seed, factors_at, estimate_again if nonlinear else None)
        self.bar.stage("selecting terms", step=(3, FIT_STAGES))
        settings = self.settings
        prep, system, selection = select_with_regressor_noise(prep, library, params, settings)
        self.prep = prep
        chosen = selection.best.mask
        # Refine the nonlinear parameters on the profile of the chosen support, then re-select once; the
        # profile's width is their uncertainty (propagated into the read-out).
        if nonlinear:
            def profile(name, est, mask, jackknife=uncertainty):
                # A preset is profiled with all the terms of its catalog effects.
                return profile_parameter(prep, physics, dict(params, **extra), name, est.bounds,
                                         whole_effects(library, mask) if physics is library else None,
                                         jackknife=jackknife)

            profiled = {}
            for name, est in nonlinear.items():
                found = profile(name, est, chosen)
                params[name] = found.value
                profiled[name] = found
            support = chosen
            system = build_system(prep, library, params)
            selection = settings.select(system)
            chosen = selection.best.mask
            for name, est in nonlinear.items():
                est.value = params[name]
                if uncertainty:
                    # The profile of the final support (the first one's when the support did not change).
                    same = np.array_equal(chosen, support) or physics is not library
                    found = profiled[name] if same else profile(name, est, chosen)
                    est.sigma, est.sigma_width, est.sigma_jackknife = (found.sigma, found.sigma_width,
                                                                       found.sigma_jackknife)
                    profiled[name] = found
            if uncertainty and "d" in nonlinear and len(nonlinear) > 1:  # d and a decay length: a second valley?
                moved, warning = other_valley(prep, physics, extra, params, nonlinear, system.n_rows,
                                              whole_effects(library, chosen) if physics is library else None,
                                              lambda name, est: profile(name, est, chosen))
                if moved:
                    system = build_system(prep, library, params)
                    selection = settings.select(system)
                    chosen = selection.best.mask
                if warning:
                    warnings.append("warning: " + warning)
            if uncertainty:
                for name, est in nonlinear.items():
                    opened = open_side_warning(name, est.unit, profiled[name], est.bounds)
                    if opened:
                        warnings.append("warning: " + opened)
                    if cover_other_valleys(name, est, profiled[name], params,
                                           lambda name, est: profile(name, est, chosen), warnings):
                        system = build_system(prep, library, params)
                        selection = settings.select(system)
                        chosen = selection.best.mask
        for name, est in nonlinear.items():
            est.value = params[name]
        self.chosen = chosen
        if nonlinear and uncertainty:
            self.profiled = profiled
        return Settled(prep, system, chosen, params, warnings, selection)

    def profile_from(self, name: str, start: float, jackknife: bool = False) -> ProfileResult:
        """Nonlinear parameter ``name`` profiled again from ``start`` (its unit) on the settled support and row
        weights, the other parameters held at their settled values."""
        library, physics, est = self.library, self.physics, self.nonlinear[name]
        trial = dict(self.params, **self.extra, **{name: start})
        return profile_parameter(self.prep, physics, trial, name, est.bounds,
                                 whole_effects(library, self.chosen) if physics is library else None,
                                 jackknife=jackknife)

    def propagate(self, state: FitState) -> None:
        """The profiles' sigmas into the read-outs (refits at +-1 sigma: :func:`propagate_nonlinear`), with
        error bars only."""
        if self.uncertainty:
            propagate_nonlinear(state.quantities, self.nonlinear, state.prep, self.library, state.params, state.mask,
                                state.trace)

    def resettle(self, scaled: Prepared, trial: dict) -> dict:
        """The nonlinear parameters searched again on a scaled record (the deflection sensitivity's share,
        afmid.fit.invols_share), each on its profile over the chosen support; ``trial`` updated and returned."""
        library, physics, chosen = self.library, self.physics, self.chosen
        for name, est in self.nonlinear.items():
            trial[name] = profile_parameter(scaled, physics, dict(trial, **self.extra), name, est.bounds,
                                            whole_effects(library, chosen) if physics is library else None,
                                            jackknife=False).value
        return trial

    def select_with(self, extra_terms: list[str]) -> tuple[Library, np.ndarray]:
        """The library with ``extra_terms`` added and its support selected at the settled parameters (the
        contact-law probe, afmid.fit.contact_probe)."""
        config = self.config
        model = config.model.model_copy(update={"terms": [*config.model.terms, *extra_terms]})
        probed = build_library(model, config.source, self.library.tip)
        probed_settings = SelectionSettings.for_library(config.fit, probed, len(self.prep.nuisance_names))
        return probed, probed_settings.select(build_system(self.prep, probed, self.params)).best.mask


# --------------------------------------------------------------------------- effects from the CLI
def apply_effect_changes(config: RunConfig, add: tuple[str, ...] | list[str], remove: tuple[str, ...] | list[str]) -> None:
    """``--add`` / ``--remove`` effects on the loaded config (validated like the YAML)."""
    if not add and not remove:
        return
    if config.model.library is not None:
        raise ConfigError("--add/--remove change model.effects, but this config uses model.library",
                          file=config.source, key="model.library")
    both = sorted(set(add) & set(remove))
    if both:
        raise ConfigError(f"--add {both[0]} and --remove {both[0]} contradict each other; give one of them",
                          key="--add")
    effects = list(config.model.effects)
    for name in remove:
        if name not in effects:
            raise ConfigError(f"--remove {name}: not in model.effects {effects}", file=config.source, key="model.effects")
        effects.remove(name)
    for name in add:
        if name in effects:
            log.warning("%s: --add %s: already in model.effects %s; nothing to add", config.source, name, effects)
        else:
            effects.append(name)
    try:
        config.model.effects = effects
    except Exception as exc:  # pydantic ValidationError from the effects validator
        from pydantic import ValidationError

        from afmid.config import validation_error

        if isinstance(exc, ValidationError):
            err = validation_error(exc, config.source)
            raise ConfigError(err.message.replace("unknown effect", "--add: unknown effect"), file=config.source,
                              key="model.effects") from None
        raise

"""The one sequence every fit runs, with the parts that differ as strategy objects.

A single trace's fit (:func:`afmid.fit.pipeline.fit_prepared`), a map pixel's carried fit
(:class:`afmid.maps.pixel_fit.SharedSupportFit`) and, through the same protocols, any fit of one support go

    settle the separation (and the other nonlinear parameters) and select the support  -- a SeparationStrategy
    -> the support's least-squares coefficients
    -> their spread                                                                  -- a SpreadStrategy
    -> the cross-validated error and its noise floor (an unusable fit stops here)    -- an ErrorStrategy
    -> the read-out of physical quantities (afmid.fit.forces.read_out, with the spread's intervals)
    -> the separation's sigma propagated into them                                   -- the SeparationStrategy
    -> the finishing steps, in order (calibration and model limits, ...)             -- FinishingStep objects

(:func:`orchestrate`). The strategies are composed by the caller, as PySINDy composes an optimizer, a library and
a differentiation: the spread of the coefficients is a bootstrap of the periods with re-selection
(:class:`BootstrapBagging`), the same stratified by trace (:class:`StratifiedBagging`, a joint fit's traces are
records of fixed length), draws from the least-squares covariance (:class:`CovarianceDraws`, a map pixel: no
re-selection per resample) or none (:class:`NoSpread`, quick refits). The finishing steps take one
:class:`afmid.fit.fit_state.FitState` and change its quantities and warnings in place.

Units: SI (coefficients such that coefficient x term = N; the separation in m); errors 1 sigma, intervals 95 %.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

import numpy as np

import afmid.fit.regression as regression
from afmid.errors import AfmidError, InputError
from afmid.fit.contact_probe import check_contact_law
from afmid.fit.declared_drive import propagate_drive_calibration
from afmid.fit.fit_state import FitState
from afmid.fit.forces import force_cv_error, read_out, signal_rows
from afmid.fit.invols_share import propagate_invols
from afmid.fit.plausibility import unphysical
from afmid.fit.system import build_system
from afmid.fit.uncertainty import add_largest_shift, finish as finish_uncertainty, mark_model_limited, widen_interval
from afmid.fit.undetermined import mark as mark_undetermined

if TYPE_CHECKING:  # annotations only
    from afmid.config import RunConfig
    from afmid.fit.prepare import Prepared
    from afmid.io.trace import Trace
    from afmid.physics.library import Library
    from afmid.progress import Progress


# --------------------------------------------------------------------------- the settled support
@dataclass
class Settled:
    """What a separation strategy hands on: the prepared trace the support was chosen on (its row weights), the
    system at the settled parameters, the chosen support (all columns), the parameters (SI) and the warning
    lines so far. ``selection`` is the :class:`afmid.fit.regression.Selection` when one was made there (None:
    the support was carried in)."""

    prep: Prepared
    system: Any
    chosen: np.ndarray
    params: dict
    warnings: list[str]
    selection: regression.Selection | None = None


class SeparationStrategy(Protocol):
    """How the nonlinear parameters (the rest separation first) are found and what their uncertainty does."""

    def settle(self) -> Settled:
        """Search the parameters, choose the support there: the :class:`Settled` fit."""

    def propagate(self, state: FitState) -> None:
        """Add the parameters' sigmas to the read-outs' errors and intervals (in place on ``state.quantities``)."""


def record_warnings(prep: Prepared) -> list[str]:
    """The warning lines a fit starts with: the record's findings on load (afmid.io.defects etc., errors
    excluded: those stopped the load) and a non-periodic motion's warning (afmid.preprocess.motion)."""
    warnings = [f"{f.severity}: {f.message}" for f in prep.trace.findings if f.severity != "error"]
    if prep.motion is not None and prep.motion.non_periodic:
        from afmid.preprocess.motion import fit_warning

        warnings.append(fit_warning(prep.motion, prep.noise_rms))
    return warnings


def propagate_nonlinear(quantities: dict, nonlinear: dict, prep, library, params, mask, trace) -> None:
    """Add the uncertainty of estimated nonlinear parameters (separation, decay lengths) to the quantities.

    The bootstrap holds them fixed; refitting at +-1 sigma of each and reading
    out again gives the sensitivity (the larger change of the two sides:
    :func:`afmid.fit.uncertainty.add_largest_shift`), added in quadrature to the
    error and to both halves of the 95 % interval (in place). A read-out that bends with the parameter (E* as d
    nears contact on the poor instrument) is understated by the 1-sigma sides; counting the 2-sigma sides
    (halved) covered draw 132 of configs/coverage/poor.yaml but widened E*'s sigma past what the seed spread of
    the accuracy suite allows (tests/fit/test_fit_accuracy.py, poor rows): one symmetric sigma cannot serve a
    read-out this skewed; an asymmetric interval is the open fix (docs/coverage.md).
    """
    extra = {k: 0.0 for k in quantities}
    for name, est in nonlinear.items():
        for k, v in nonlinear_shift(quantities, name, est.sigma, prep, library, params, mask, trace).items():
            extra[k] += v
    for k, q in quantities.items():
        widen_interval(q, math.sqrt(extra[k]))


def nonlinear_shift(quantities: dict, name: str, sigma: float, prep, library, params, mask, trace) -> dict[str, float]:
    """Per read-out of ``quantities``, the square of its largest change when nonlinear parameter ``name`` moves by
    +-``sigma`` (its unit) and the support's coefficients are refitted there
    (:func:`afmid.fit.uncertainty.add_largest_shift`); all 0 when ``sigma`` is not a positive number."""
    extra = {k: 0.0 for k in quantities}
    if not math.isfinite(sigma) or sigma <= 0:
        return extra
    shifted = []
    for sign in (1, -1):
        trial = dict(params, **{name: params[name] + sign * sigma})
        try:
            system = build_system(prep, library, trial)
        except AfmidError:
            continue  # e.g. a separation below a0: the other side alone
        coef, _ = regression.subset_fit(regression.combine(system.T_blocks), mask)
        shifted.append(read_out(library, coef, None, trial, mask, trace))
    add_largest_shift(extra, quantities, shifted)
    return extra


# --------------------------------------------------------------------------- the coefficients' spread
@dataclass
class Spread:
    """The spread of a support's coefficients (all columns, SI): the samples (``bagging``, None: none drawn),
    their 1-sigma ``coef_std`` and 95 % interval ``ci_low`` .. ``ci_high``, and per column the fraction of
    resamples that select it (``inclusion``; the support itself when nothing was re-selected)."""

    bagging: regression.Bagging | None
    coef_std: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    inclusion: np.ndarray

    @classmethod
    def none(cls, coef: np.ndarray, chosen: np.ndarray) -> Spread:
        """No spread: zero sigma, the interval the value itself."""
        return cls(None, np.zeros_like(coef), coef.copy(), coef.copy(), chosen.astype(float))

    @classmethod
    def of(cls, bagging: regression.Bagging) -> Spread:
        """The spread of coefficient samples: their standard deviation (ddof 1) and 2.5 / 97.5 % percentiles."""
        ci_low, ci_high = np.percentile(bagging.coef_samples, [2.5, 97.5], axis=0)
        return cls(bagging, bagging.coef_samples.std(axis=0, ddof=1), ci_low, ci_high, bagging.inclusion)


class SpreadStrategy(Protocol):
    """How the coefficients' spread is drawn: ``spread(system, coef, chosen) -> Spread``; ``describe()`` the
    progress line (None: no stage of its own); ``error_kind`` what each read-out's ``error`` then is (None: the
    read-out's own, the bootstrap's)."""

    error_kind: str | None

    def describe(self) -> str | None: ...

    def spread(self, system, coef: np.ndarray, chosen: np.ndarray) -> Spread: ...


class NoSpread:
    """No error bars (a quick comparative refit, ``fit.bootstrap: 0``)."""

    error_kind = None
    n_resamples = 0

    def describe(self) -> str | None:
        return None

    def spread(self, system, coef: np.ndarray, chosen: np.ndarray) -> Spread:
        return Spread.none(coef, chosen)


@dataclass
class BootstrapBagging:
    """The periods resampled with replacement ``n_resamples`` times from ``seed``: each resample re-selects (the
    inclusion frequencies) and refits the chosen support (the coefficients' spread);
    :meth:`afmid.fit.selection.SelectionSettings.bag` (the selection scope decides what is resampled)."""

    settings: Any  # afmid.fit.selection.SelectionSettings
    n_resamples: int
    seed: int | None
    error_kind = None

    def describe(self) -> str | None:
        return f"error bars ({self.n_resamples} resamples)"

    def spread(self, system, coef: np.ndarray, chosen: np.ndarray) -> Spread:
        rng = np.random.default_rng(self.seed)
        return Spread.of(self.settings.bag(system, chosen, self.n_resamples, rng))


@dataclass
class StratifiedBagging:
    """A joint fit's bootstrap: the inclusion frequencies from resamples of all periods (re-selecting, as
    :class:`BootstrapBagging`), the coefficients' spread from resamples drawn within each trace
    (:func:`stratified_coefficients`), both from one generator seeded with ``seed``."""

    settings: Any  # afmid.fit.selection.SelectionSettings
    n_resamples: int
    seed: int | None
    error_kind = None

    def describe(self) -> str | None:
        return f"error bars ({self.n_resamples} resamples of the periods of all traces)"

    def spread(self, system, coef: np.ndarray, chosen: np.ndarray) -> Spread:
        rng = np.random.default_rng(self.seed)
        pooled = self.settings.bag(system, chosen, self.n_resamples, rng)
        samples = stratified_coefficients(system.T_blocks, system.block_start, chosen, self.n_resamples, rng)
        return Spread.of(regression.Bagging(pooled.inclusion, samples, self.n_resamples, pooled.supports))


def stratified_coefficients(T_blocks: np.ndarray, block_start: np.ndarray, chosen: np.ndarray, n_boot: int,
                            rng: np.random.Generator) -> np.ndarray:
    """(n_boot, columns) coefficients of the ``chosen`` support refitted on resamples of the blocks (periods)
    drawn within each group ``block_start[i] .. block_start[i + 1]`` (a joint fit's traces: each keeps its number
    of periods, the traces are independent records of fixed length).

    Resampling the pooled periods instead lets a trace's share of the record vary from resample to resample:
    measured (seed 3, separations given), the joint E* std became 4.4e7 Pa, twice the best single trace's 2.2e7.
    """
    samples = np.empty((n_boot, T_blocks.shape[-1] - 1))
    counts = np.diff(block_start)
    for k in range(n_boot):
        multiplicity = np.concatenate([rng.multinomial(n, np.full(n, 1.0 / n)) for n in counts]).astype(float)
        samples[k], _ = regression.subset_fit(regression.combine(T_blocks, multiplicity), chosen)
    return samples


@dataclass
class CovarianceDraws:
    """``n_draws`` coefficient vectors from the least-squares covariance of the chosen support
    (:func:`covariance_draws`; the generator seeded with ``seed``): no re-selection (the inclusion is the support),
    a map pixel's error bars at the cost of one factorisation. The read-outs' ``error_kind`` says so."""

    n_draws: int
    seed: Any  # what numpy.random.default_rng takes
    error_kind = "1 sigma (least-squares covariance)"

    def describe(self) -> str | None:
        return None

    def spread(self, system, coef: np.ndarray, chosen: np.ndarray) -> Spread:
        T = regression.combine(system.T_blocks)
        _, rss = regression.subset_fit(T, chosen)
        draws = covariance_draws(T, coef, chosen, rss, system.n_rows, self.n_draws, np.random.default_rng(self.seed))
        return Spread.of(regression.Bagging(chosen.astype(float), draws, self.n_draws))


def covariance_draws(T: np.ndarray, coef: np.ndarray, support: np.ndarray, rss: float, n_rows: int, n: int,
                     rng: np.random.Generator) -> np.ndarray:
    """``n`` coefficient vectors drawn from the least-squares covariance s2 (A_S^T A_S)^-1 of the support (zero
    elsewhere), s2 = rss / (rows - k); ``T`` is the combined triangular factor of [A | y] (so A^T A = T_A^T T_A).
    Columns are scaled to unit norm first: SI columns span tens of orders of magnitude."""
    index = np.flatnonzero(support)
    A = T[:, index]
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    gram = (A / norms).T @ (A / norms)
    s2 = rss / max(n_rows - index.size, 1)
    w, V = np.linalg.eigh(gram)
    w = np.where(w > w.max() * 1e-14, w, np.inf)  # a direction the data do not determine gets no spread here
    root = V / np.sqrt(w)  # cov_scaled = root @ root.T / s2^-1
    draws = np.tile(coef, (n, 1))
    draws[:, index] += (rng.standard_normal((n, index.size)) @ root.T) * math.sqrt(s2) / norms
    return draws


# --------------------------------------------------------------------------- the cross-validated error
@dataclass
class ErrorEstimate:
    """The cross-validated force error (relative: 0 perfect, 1 a constant force), per fold, its noise floor, and
    the rows (drive harmonics) counted in it."""

    cv_error: float
    per_fold: np.ndarray
    noise_floor: float
    rows: np.ndarray
    floor_dof: float = math.nan  # the floor's effective degrees of freedom (afmid.fit.uncertainty.floor_threshold)


class ErrorStrategy(Protocol):
    def estimate(self, prep: Prepared, system, coef: np.ndarray, chosen: np.ndarray) -> ErrorEstimate: ...


@dataclass
class HeldOutPeriods:
    """A trace's error over ``folds`` held-out folds of periods (:func:`afmid.fit.forces.force_cv_error`); a fit
    with no usable result stops here (:func:`refuse_unusable`, InputError)."""

    library: Library
    folds: int

    def estimate(self, prep: Prepared, system, coef: np.ndarray, chosen: np.ndarray) -> ErrorEstimate:
        rows = signal_rows(prep, system, coef)
        cv_error, per_fold, noise_floor, floor_dof = force_cv_error(prep, system, chosen, rows, self.folds)
        refuse_unusable(prep.trace, self.library, coef[:len(self.library)], cv_error)
        return ErrorEstimate(cv_error, per_fold, noise_floor, rows, floor_dof)


def refuse_unusable(trace: Trace, library: Library, coef: np.ndarray, cv_error: float) -> None:
    """Stop (InputError, nothing written) when the fit has no result afmid can stand behind.

    A NaN error metric means no drive harmonic of the inverted force stood out of the noise on the
    held-out periods: there was no tip-sample force to identify, and the coefficients only describe noise.
    """
    bad = [name for name, c in zip(library.names, coef) if not math.isfinite(c)]
    if bad:
        raise InputError(f"the fit's coefficients are not finite for {', '.join(bad)}: the library columns are "
                         "degenerate on this trace; nothing was written", file=trace.path, key="model")
    if not math.isfinite(cv_error):
        raise InputError("the fit has no usable result: its cross-validated error is NaN because no harmonic of "
                         "the inverted tip-sample force stands above the noise (the tip does not reach the sample, "
                         "or this is not a tapping trace); nothing was written", file=trace.path, key="data.path")


# --------------------------------------------------------------------------- finishing steps
class FinishingStep(Protocol):
    """One step on the read-outs after their propagation: ``apply(state)`` changes ``state`` in place."""

    name: str

    def apply(self, state: FitState) -> None: ...


@dataclass
class CalibrationAndLimits:
    """The calibration's share (k, Q; when ``uncertainty``) and the model-limited mark:
    :func:`afmid.fit.uncertainty.finish`."""

    uncertainty: bool = True
    name = "calibration and model limits"

    def apply(self, state: FitState) -> None:
        finish_uncertainty(state, self.uncertainty)


@dataclass
class InvolsShare:
    """The deflection sensitivity's calibration share (refits on the scaled record, :mod:`afmid.fit.invols_share`),
    in quadrature with the k and Q share. ``resettle(scaled_prep, params) -> params`` searches the nonlinear
    parameters on the scaled record; ``nonlinear`` the fit's estimates."""

    nonlinear: dict
    resettle: Callable[[Any, dict], dict]
    name = "deflection sensitivity"

    def apply(self, state: FitState) -> None:
        state.force_calibration = math.hypot(state.force_calibration, propagate_invols(
            state.quantities, state.prep, state.library, state.config, state.coef, state.mask, state.params,
            self.nonlinear, read_out, self.resettle))


#: The warning of a fit whose law needs an unphysical parameter (afmid.fit.plausibility.unphysical).
UNPHYSICAL_TEXT = ("model-limited: the model fits the record only with an unphysical {names} (the whole 95 % "
                   "interval outside the physical range): the force the data ask for is not this law with physical "
                   "parameters, so every parameter is biased beyond its error bar (or the calibration is wrong: "
                   "data.invols, data.positive, cantilever.spring_constant, cantilever.tip_radius)")


@dataclass
class ContactLawProbe:
    """A shape probe beside the elastic term (:func:`afmid.fit.contact_probe.check_contact_law`): a contact law the
    model cannot give makes the fit model-limited. ``select_with(extra_terms) -> (library, support)`` reselects
    with the probe's terms added."""

    select_with: Callable[[list[str]], tuple]
    name = "contact-law probe"

    def apply(self, state: FitState) -> None:
        model = state.config.model
        probe = check_contact_law(state.library, state.mask, list(model.terms), model.library, self.select_with)
        if probe is not None and probe.failed:
            mark_model_limited(state.quantities, True)
            state.warn(probe.warning())
            state.model_limited = True


class DriveCalibration:
    """A calibrated drive's declared uncertainty, like k's and Q's (:mod:`afmid.fit.declared_drive`)."""

    name = "drive calibration"

    def apply(self, state: FitState) -> None:
        propagate_drive_calibration(state.quantities, state.prep, state.library, state.system, state.coef, state.mask,
                                    state.params, state.trace, read_out)


@dataclass
class Undetermined:
    """Read-outs whose terms were not selected marked not determined, undecided terms' spread added
    (:func:`afmid.fit.undetermined.mark`; ``n_resamples`` for the forced supports' intervals, 0: flags only)."""

    n_resamples: int
    seed: int | None
    name = "not determined and undecided"

    def apply(self, state: FitState) -> None:
        mark_undetermined(state, self.n_resamples, self.seed)


class Unphysical:
    """A read-out whose whole 95 % interval lies outside its physical range makes the fit model-limited
    (:func:`afmid.fit.plausibility.unphysical`): the other parameters are biased by what it stands for."""

    name = "unphysical parameters"

    def apply(self, state: FitState) -> None:
        impossible = [name for name, q in state.quantities.items() if unphysical(name, q)]
        if impossible:
            mark_model_limited(state.quantities, True)
            state.warn(UNPHYSICAL_TEXT.format(names=", ".join(impossible)))
            state.model_limited = True


# --------------------------------------------------------------------------- the sequence
@dataclass(frozen=True)
class Stages:
    """Where the spread and the error stand on a progress line: (step, of) each, and the error stage's text."""

    spread: tuple[int, int]
    error: tuple[int, int]
    error_text: str = "error and forces"


@dataclass
class Orchestrated:
    """A finished fit of one support: the settled search, the coefficients (all columns, SI), their spread, the
    error, and the read-outs' state after the finishing steps."""

    settled: Settled
    coef: np.ndarray
    spread: Spread
    error: ErrorEstimate
    state: FitState


def orchestrate(config: RunConfig, library: Library, separation: SeparationStrategy, spread: SpreadStrategy,
                error: ErrorStrategy, finishing: list, bar: Progress | None = None,
                stages: Stages | None = None) -> Orchestrated:
    """Run the sequence of the module docstring with these strategies: :class:`Orchestrated`.

    ``finishing``: :class:`FinishingStep` objects, applied in order. ``bar`` and ``stages``: the caller's progress
    line and where the spread and error stages stand on it (None: no stage lines); the line is closed before an
    error of the error strategy propagates (its one line must not land on the progress line).
    """
    settled = separation.settle()
    system, chosen = settled.system, settled.chosen
    coef, _ = regression.subset_fit(regression.combine(system.T_blocks), chosen)
    described = spread.describe()
    if bar is not None and stages is not None and described:
        bar.stage(described, step=stages.spread)
    coefficient_spread = spread.spread(system, coef, chosen)
    if bar is not None and stages is not None:
        bar.stage(stages.error_text, step=stages.error)
    try:
        estimate = error.estimate(settled.prep, system, coef, chosen)
    except AfmidError:
        if bar is not None:
            bar.close()
        raise
    quantities = read_out(library, coef, coefficient_spread.bagging, settled.params, chosen, settled.prep.trace,
                          with_sources=True)
    state = FitState(config, settled.prep, library, system, coef, chosen, settled.params, quantities,
                     settled.warnings, coefficient_spread.inclusion, estimate.cv_error, estimate.noise_floor,
                     estimate.floor_dof)
    separation.propagate(state)
    if spread.error_kind is not None:
        for q in state.quantities.values():
            q["error_kind"] = spread.error_kind
    for step in finishing:
        step.apply(state)
        state.steps.append(step.name)
    return Orchestrated(settled, coef, coefficient_spread, estimate, state)

"""Diagnosis: where a fitted model fails, and which physical effect is missing.

Works from run files (written by ``afmid fit``) so reports can be made later
and compared across runs.

:func:`localize` looks at the residual between the inverted force and the
model force (the model force band-limited to the same drive harmonics as the
inverted one, so that a perfect model leaves only noise). The periods of a
steady trace repeat, so the residual is averaged over periods at equal drive
phase: what survives is the systematic misfit, and its spread from period to
period is the noise it is compared with. The systematic residual is broken down
by region (contact / near / far), by direction (approach / retraction), into a
conservative part (the same at equal separation on approach and retraction)
and a dissipative part (reverses with the direction of motion), by drive
phase and by drive harmonic; its correlation with the separation rate tells
damping-like residuals from others.

:func:`suggest` refits the trace with each catalog effect that the model lacks
and ranks the candidates by an information criterion (BIC, counting the
effect's nonlinear shape parameter, e.g. a decay length, as a fitted
parameter), with the cross-validated error as an independent check. An effect
is suggested only when the evidence is strong (see the constants below), its
own terms are selected and its fitted parameters are physically possible.
Whether the model already explains the data is judged by the reduced
chi-square of the fit (the rows are weighted by their predicted noise, so 1 is
a perfect model) together with the cross-validated error against its noise
floor.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

import afmid.diagnosis.checklist as checklist
from afmid.diagnosis.refit_count import count_refit
import afmid.diagnosis.decide as decide
import afmid.diagnosis.instrument_signature as instrument_signature
import afmid.diagnosis.rival_truth as rival_truth
from afmid.progress import counted
import afmid.fit.plausibility as plausibility
from afmid.config import RunConfig
from afmid.errors import InputError
from afmid.io.files import is_regular_file
from afmid.io.trace import sha256_file
from afmid.diagnosis.candidate_refit import (SEPARATION_WINDOW, fit_searched, search_candidate, search_separation,
                                             separation_estimated)
import afmid.diagnosis.forked_work as forked_work
from afmid.diagnosis.candidate_shapes import ShapeSearch, shape_words
from afmid.diagnosis.base_columns import BaseColumns
# Where the residual sits: afmid.diagnosis.localize.
from afmid.diagnosis.localize import NEAR_RANGE, localize
import afmid.physics.medium as medium
from afmid.physics.effects import EFFECTS
# BIC differences as a person reads them (no -0, no 7e-13): the one formatter of afmid's numbers.
from afmid.quantity_text import format_delta_bic, format_value
# A cross-validated error within FLOOR_FACTOR of its noise floor counts as the noise level (one constant with
# the fit's model-limited mark).
from afmid.fit.uncertainty import FLOOR_FACTOR, floor_threshold, model_limited, quieter_than_its_floor
# The run-file reader lives in afmid.runfile; `from afmid.diagnosis.diagnose import load_run, RunData` keeps working.
from afmid.runfile import RunData, load_run  # noqa: F401

log = logging.getLogger(__name__)

#: An added effect must lower the BIC by at least this much: "very strong" evidence (Kass & Raftery 1995,
#: a Bayes factor above 150). Its nonlinear shape parameters count as fitted parameters (ln n each).
BIC_EVIDENCE = 10.0
#: Two candidates closer than this in BIC are not told apart by the data (Kass & Raftery: below 6 the
#: evidence for one over the other is at most "positive"); the evidence text then names both.
BIC_DISTINCT = 6.0
#: When the current model's cross-validated error stands above its noise floor, an added effect must cut
#: the excess error sqrt(error^2 - floor^2) to at most this fraction (remove >= 36 % of the excess variance).
ERROR_RATIO = 0.8
#: A reduced chi-square above 1 + CHI2_SIGMAS * sqrt(2 / dof) is a significant misfit (the rows are
#: whitened by their predicted noise, so a perfect model gives 1 +- sqrt(2 / dof)).
CHI2_SIGMAS = 5.0
#: A residual counts as "following the separation rate" when |correlation| exceeds this.
RATE_CORRELATION = 0.5
#: Effects that are base contact models: one at a time, never suggested on top of another.
BASE_MODELS = ("dmt", "jkr", "lennard_jones")
#: Search an added effect's nonlinear parameters (decay length, rupture distance) with the quick search of
#: afmid.diagnosis.candidate_shapes.ShapeSearch and refit with them fixed, instead of the fit's own outer search. Measured on the 16
#: hidden-effect variants: the same ranking, parameters within their statistical scatter, 4-5x faster
#: (a diagnosis 2 s instead of 9-10 s).
QUICK_SHAPE = True
#: Quality factors above this mean the lever oscillates in a gas (in liquids Q is ~1-10).
GAS_QUALITY_FACTOR = 30.0
#: Largest plausible viscosity of a gas film, Pa s (air 1.8e-5; every gas is below 1e-4).
GAS_VISCOSITY_MAX = 1e-4


@dataclass
class Trial:
    effect: str
    error_after: float
    noise_floor_after: float
    bic_after: float
    delta_bic: float  # including ln(n) per estimated nonlinear parameter of the added effect
    chi2_after: float
    chi2_limit_after: float
    effect_terms_selected: bool
    quantities: dict
    shape: dict  # the added effect's nonlinear parameters: name -> value (SI)
    implausible: list[str]
    seconds: float
    significant: bool = False
    explains: bool = False  # with the other accepted effects, leaves no significant residual
    conditional_delta_bic: float = math.nan  # BIC change when added on top of the better accepted effects
    evidence: str = ""
    reasons: list[str] = field(default_factory=list)  # why it was not accepted
    separation: float = math.nan  # the rest separation of the refit, m (re-profiled when the run estimated it)
    block_chi2: np.ndarray | None = field(default=None, repr=False)  # per-block chi-square (afmid.diagnosis.decide)
    n_parameters: int = 0  # selected terms + estimated nonlinear parameters of the refit (afmid.diagnosis.decide)
    space: object = field(default=None, repr=False)  # () -> its rival_truth.ModelSpace, computed on first call


@dataclass
class _Base:
    """The current model refitted with the same code and settings as the candidates."""

    error: float
    floor: float
    bic: float
    chi2: float
    chi2_limit: float
    n_rows: int
    floor_dof: float = math.nan  # the noise floor's degrees of freedom (afmid.fit.uncertainty.floor_threshold)


def candidate_effects(current: list[str], medium: str = "air") -> list[str]:
    """The catalog effects to try: those not in the model that exist in the sample's ``medium``."""
    has_base = any(e in BASE_MODELS for e in current)
    return [e.name for e in EFFECTS if e.name not in current and not (has_base and e.name in BASE_MODELS)
            and medium in e.media]


def refit_config(run: RunData, effects: list[str]) -> RunConfig:
    """The run's own config with another effect list, pointing at the run's input file.

    The separation (when the run's estimate is above zero) and the run's own nonlinear parameters (decay lengths of
    effects already in the model) are fixed at the run's values: the candidate
    refits then differ from the run only by the added effect, and are quick.
    """
    config = copy.deepcopy(run.config)
    config.model.effects = effects
    if run.input_path is not None:
        config.data.path = run.input_path
    config.fit.bootstrap = 0
    if config.sample.separation is None and run.separation > 0:  # else (not physical) searched again by each fit
        config.sample.separation = run.separation
    fixed = dict(config.model.parameters)
    for name, est in run.nonlinear.items():
        if name != "d" and name not in fixed and math.isfinite(est["value"]):
            fixed[name] = est["value"]
    config.model.parameters = {**fixed, **medium.fixed_parameters(config.sample, effects)}  # a Debye length of I
    return config


def _fit_quick(config: RunConfig, prepared):
    """The fit of ``config`` without error bars, on the shared preparation ``prepared`` (None: load and prepare).

    Every refit of one diagnosis fits the same trace with the same fit settings
    (:func:`refit_config`), so the trace is prepared once (drive, blocks,
    weak-form rows, noise do not depend on the library).
    """
    from afmid.fit.pipeline import run_fit

    count_refit()
    return run_fit(config, prepared=prepared, uncertainty=False)


def _chi2(result) -> tuple[float, float, int]:
    best = result.selection.best
    n = int(result.system.n_rows)
    dof = max(n - int(best.mask.sum()), 1)
    return best.rss / dof, 1.0 + CHI2_SIGMAS * math.sqrt(2.0 / dof), n


def _implausible(effect: str, quantities: dict, run: RunData) -> list[str]:
    """Reasons why the fitted values of an effect cannot be physical (empty if they can)."""
    # The registry's plausible ranges (afmid.fit.plausibility), as for every fit's read-out.
    verdicts = plausibility.check_plausibility({k: {**q, "effect": effect} for k, q in quantities.items()})
    reasons = [v.finding for v in verdicts.values() if not v.plausible]
    if effect == "squeeze_film":
        Q = run.cantilever.get("quality_factor", math.nan)
        eta = next((q["value"] for k, q in quantities.items() if k.endswith("fluid_viscosity")), math.nan)
        if Q > GAS_QUALITY_FACTOR and math.isfinite(eta) and eta > GAS_VISCOSITY_MAX:
            reasons.append(f"fluid_viscosity = {eta:.3g} Pa*s, but Q = {Q:.0f} means the lever is in a gas "
                           f"(gases: below {GAS_VISCOSITY_MAX:g} Pa*s, air 1.8e-5)")
    return reasons


def suggest(run: RunData, progress: bool = False, trace=None) -> dict:
    """Try each missing catalog effect; return the diagnosis and the ranked suggestions.

    The candidates are refitted on ``trace`` (an :class:`afmid.io.trace.Trace`: the run's own trace, held in
    memory by a fit of the Python front door) or, when it is None, on the run's input file read again.

    Returns (pinned keys first): ``missing_effect`` (the data show physics the
    model lacks: an accepted catalog effect or a significant residual nothing
    in the catalog explains), ``diagnosis`` {region, character,
    explained_by_catalog, ...}, ``suggestions`` (accepted effects, best first,
    each with effect, error_after, evidence) and ``tried`` (every candidate).
    """
    if run.config.model.library is not None:
        return {"missing_effect": False, "suggestions": [], "tried": [],
                "note": "suggestions need a model built from effects (model.effects), not a preset library"}
    if trace is None and (run.input_path is None or not run.input_path.exists()):
        raise InputError("the run's input trace is not available for refitting", file=run.path, key="input_path")
    if trace is None and not is_regular_file(run.input_path):  # a FIFO or a device: never read (it would hang)
        note = f"no suggestions: the stored input {run.input_path} is not a regular file"
        log.warning("%s: %s", run.path, note)
        return {"missing_effect": False, "suggestions": [], "tried": [], "note": note}
    if trace is None and run.input_sha256 and sha256_file(run.input_path) != run.input_sha256:
        # Refits of another trace would be compared with this run's fit: no suggestion can come of that.
        log.warning("%s changed since the run was made (SHA-256 differs); no effects are suggested", run.input_path)
        return {"missing_effect": False, "suggestions": [], "tried": [],
                "note": f"no suggestions: the input trace {run.input_path} changed since the run was made"}
    if run.config.sample.separation is None and not math.isfinite(run.separation):  # no estimate to refit from
        raise InputError("the run holds no estimate of the rest separation: the candidates cannot be refitted; give "
                         "sample.separation", file=run.path, key="sample.separation")
    if run.config.sample.separation is None and not run.separation > 0:
        # The run's model could not place the surface (a missing long-range force moves the estimate far): each
        # candidate's separation is searched over the fit's whole window (candidate_refit.separation_starts).
        log.warning("the run's rest separation estimate (%.3g nm) is not physical: each candidate effect is refitted "
                    "with the separation searched over the fit's whole window", run.separation * 1e9)
    with _one_blas_thread():
        return _diagnose(run, progress, trace)


def track_block_preparation(run: RunData, record, config: RunConfig):
    """The preparation a separation track's run describes: the track's first block of ``record`` (the run's
    single-trace layout holds that block's result), with its periods' rest separations as the track fitted them
    (:func:`afmid.fit.period_separation.with_period_separation`) and its d (``config``'s, from the run).

    The record as a whole under one d is not what the track fitted: while scanning, d(t) follows the topography,
    and one d for the record leaves a residual of the scan itself (docs/lab/2026-11-29-scanning-record.md: the
    2 nm step's force error 13 % of the peak with one d), which a candidate effect would be asked to explain.
    The candidates are refitted on the first block alone, with the track's d and per-period offsets held, as
    a joint fit's candidates are on its first trace; InputError when the stored offsets do not fit the block's
    periods (the record or the fit settings changed)."""
    from afmid.fit.period_separation import with_period_separation
    from afmid.fit.prepare import prepare
    from afmid.fit.separation_track import cut_block
    from afmid.io.trace import check_trace
    from afmid.preprocess.instrument import from_config as instrument_from_config

    block = run.track_block
    checked = check_trace(record, config)
    prepared = prepare(check_trace(cut_block(checked, block["first_sample"], block["stop_sample"]), config),
                       config.fit, instrument_from_config(config))
    offsets = block["period_offsets"]
    if offsets is None:
        return prepared
    if offsets.size != prepared.blocks.n_blocks:
        raise InputError(f"the separation track's first block holds {offsets.size} period offsets, the record's "
                         f"block prepares {prepared.blocks.n_blocks} periods: refit the run", file=run.path,
                         key="model/separation_track/period_offsets")
    return with_period_separation(prepared, offsets)


def _one_blas_thread():
    """Single-threaded BLAS for the refits (threadpoolctl, when installed).

    The refits are many small problems (per-period blocks of ~121 x 6, thin
    matrix products); BLAS threads buy little there and, on a busy machine,
    spin against each other: measured on 2 shared cores, one diagnosis took
    9-17 s of CPU with OpenBLAS threads and 2.8 s with one thread.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _diagnose(run: RunData, progress: bool, trace) -> dict:
    from afmid.fit.prepare import prepare, with_fine_grid
    from afmid.preprocess.instrument import from_config as instrument_from_config
    from afmid.io.trace import load_trace
    from afmid.physics.library import build_library
    from afmid.physics.tips import tip_geometry

    started = time.perf_counter()
    local = localize(run)
    base_config = refit_config(run, run.effects)
    # Every refit below differs from this one only in its library and fixed parameters: one preparation, and its
    # trajectory on the fine grid made once for all the refits' and shape searches' library evaluations.
    record = load_trace(base_config) if trace is None else trace
    if run.track_block is not None:
        prepared = with_fine_grid(track_block_preparation(run, record, base_config))
    else:
        prepared = with_fine_grid(prepare(record, base_config.fit, instrument_from_config(base_config)))
    base_result = _fit_quick(base_config, prepared)
    chi2, limit, n_rows = _chi2(base_result)
    base = _Base(base_result.cv_error, base_result.cv_error_noise_floor, base_result.selection.best.bic,
                 chi2, limit, n_rows, base_result.cv_error_floor_dof)
    if abs(base.error - run.cv_error) > 0.02 * max(run.cv_error, 1e-12):
        log.warning("refitting %s gives error %.4g, the run file says %.4g (made by another afmid version?); "
                    "comparing with the refit", run.path.name, base.error, run.cv_error)
    # The run's own terms' columns at each separation (and shape) a candidate's search visits, evaluated once for
    # all the candidates, their shape searches and the sets' separation searches.
    base_columns = BaseColumns(prepared, build_library(base_config.model, base_config.source,
                                                       tip_geometry(base_config.cantilever)))
    shapes = ShapeSearch(prepared, base_columns)
    # Every refit's BIC and per-block chi-square is a deviance against the base refit's row weights.
    reference_sigma = base_result.prep.row_sigma
    trials: list[Trial] = []
    effects = candidate_effects(run.effects, run.config.sample.medium)
    # The candidates' shape and separation searches are independent (each reads the shared preparation and kept
    # columns): shared with a forked child; each one's fit and everything after it here, in the candidates' order.
    searches = forked_work.each_in_order(functools.partial(_searched_candidate, run, prepared, shapes), effects)
    # strict: the searches run to their end here, so their child is joined now; left suspended, a candidate's
    # re-raised error (a reference cycle through its traceback) keeps them until a garbage collection, which may
    # come in a child forked later (the report's figures) and fail there on a process that is not its own
    for effect, (searched, search_seconds) in zip(counted(effects, "report", "trying effects", "effects", progress,
                                                          named=True), searches, strict=True):  # named, an ETA
        t0 = time.perf_counter()
        config = refit_config(run, run.effects + [effect])
        shape_names = _shape_names(effect, config)
        try:
            if isinstance(searched, Exception):
                raise searched
            result, shape, separation = fit_searched(searched, shape_names, prepared, _fit_quick)
        except Exception as exc:  # one effect that cannot be fitted must not stop the diagnosis
            log.info("refit with %s failed: %s", effect, exc)
            continue
        names = result.library.names
        selected = any(s and n.startswith(effect + ".") for n, s in zip(names, result.selected))
        # The Gaussian BIC of rows weighted by the candidate's own noise, comparable with the base's: its weights'
        # deviance per block (decide.weighting_deviance) times the blocks.
        bic_after = (result.selection.best.bic + math.log(max(n_rows, 2)) * len(shape)
                     + _weights_deviance(result, reference_sigma))
        chi2_after, limit_after, _ = _chi2(result)
        qty = {k: v for k, v in result.quantities.items() if v["effect"] == effect}
        trials.append(Trial(effect, result.cv_error, result.cv_error_noise_floor, bic_after, bic_after - base.bic,
                            chi2_after, limit_after, selected, qty, shape, _implausible(effect, qty, run),
                            search_seconds + time.perf_counter() - t0, separation=separation,
                            block_chi2=decide.block_chi2(result, reference_sigma),
                            n_parameters=int(result.selection.best.mask.sum()) + len(shape),
                            space=functools.cache(functools.partial(rival_truth.model_space, prepared, result,
                                                                    list(shape), separation_estimated(run)))))
    residual_significant = _significant(base.chi2, base.chi2_limit, base.error, base.floor, base.floor_dof)
    for t in trials:
        t.reasons = _rejections(t, base)
        t.significant = not t.reasons
        t.explains = not _significant(t.chi2_after, t.chi2_limit_after, t.error_after, t.noise_floor_after)
    trials.sort(key=lambda t: (not t.significant, t.delta_bic))
    good = [t for t in trials if t.significant]
    final, final_bic = _forward(run, prepared, good, base_columns, reference_sigma)
    good = [t for t in good if t.significant]
    trials.sort(key=lambda t: (not t.significant, t.delta_bic))
    # A catalog shape with physically impossible values (e.g. an attractive "hydration" force) that fits much
    # better than every possible catalog effect: the data want a force the catalog does not have.
    reference = good[0].delta_bic if good else 0.0
    outside = [t for t in trials if t.implausible and _rejections(t, base) == t.implausible
               and t.delta_bic < reference - BIC_EVIDENCE]
    outside.sort(key=lambda t: t.delta_bic)
    if not residual_significant and not good:
        # Nothing stands out of the noise and no possible effect helps: an impossible shape fitting better is the
        # estimator's bias, not a missing force (on a soft lever in liquid, Q 2, the thermal force's work on the tip
        # reads as a negative damping: exponential damping with gamma0 < 0 took 12-29 BIC units on clean traces).
        outside = []
    residual_significant = residual_significant or bool(outside)
    for t in trials:
        t.evidence = _evidence(t, local, base, trials)
    if residual_significant:
        explained = bool(good) and not _significant(*final) and not outside
    else:
        explained = True
    missing = bool(good) or residual_significant
    description = describe_residual(local, run)
    # A residual no sample effect explains, or a quiet one where the detector's shape stands out (a lag the fit
    # absorbed into the force law and the separation).
    quiet_lag = not missing and instrument_signature.detector_stands_out(base_result, prepared.drive.frequency,
                                                                         instrument_from_config(base_config))
    search_instrument = (missing and not (good and explained)) or quiet_lag
    finding = (instrument_signature.undeclared(base_config, prepared, base_result, base.bic, trials, _fit_quick,
                                               BIC_EVIDENCE, BIC_DISTINCT, separation_estimated(run))
               if search_instrument else None)
    # Rivals the per-period evidence does not tell apart from the best candidate: name none of them. Only for a
    # single accepted effect: a set of effects was chosen over each single one by the BIC of their joint refit.
    undecided = decide.rivals(good[0], trials) if len(good) == 1 and not outside else []
    if outside:
        description += "; " + _outside_words(outside[0], good[0] if good else None)
        for t in good:
            t.evidence += f"; but {_outside_words(outside[0], t)}, so `{t.effect}` is at best a partial stand-in"
    summary = {
        "missing_effect": missing,
        "diagnosis": {
            "region": local["region"],
            "character": local["character"],
            "explained_by_catalog": explained,
            "residual_significant": residual_significant,
            "chi2_reduced": base.chi2,
            "chi2_limit": base.chi2_limit,
            "error": base.error,
            "noise_floor": base.floor,
            "snr": local["snr"],
            "rate_correlation": local["rate_correlation"],
            "description": description,
            "outside_catalog": _outside_words(outside[0], good[0] if good else None) if outside else "",
            "verdict": _verdict(good, residual_significant, explained, base, outside, final[2], final_bic - base.bic,
                                final[3]),
            "error_after": final[2] if good else None,
            "delta_bic_after": final_bic - base.bic if good else None,
        },
        "suggestions": [_trial_record(t) for t in good],
        "tried": [_trial_record(t) for t in trials],
        "seconds": time.perf_counter() - started,
    }
    if good:
        summary["compared_with_best"] = {"best": good[0].effect, "rivals": decide.comparisons(good[0], trials)}
    if len(good) == 1 and explained and not undecided and not outside:
        summary["diagnosis"]["verdict"] += decide.parsimony_note(good[0], trials)
    if undecided:
        summary["undecided"] = [_trial_record(t) for t in [good[0]] + undecided]
        summary["suggestions"] = []
        summary["diagnosis"]["verdict"] = decide.verdict(good[0], undecided)
        summary["diagnosis"]["explained_by_catalog"] = False
    summary = summary if finding is None else instrument_signature.name_instrument(summary, finding)
    # Unexplained: what the user should check (calibration, channel, stationarity), never a fix without evidence.
    return checklist.with_what_to_check(summary, run, prepared, {t.effect: t.implausible for t in trials if t.implausible})



def _shape_names(effect: str, config: RunConfig) -> list[str]:
    """The candidate ``effect``'s nonlinear parameters its refit estimates (those ``config`` does not fix)."""
    return [p.name for p in EFFECTS.get(effect).parameters if p.nonlinear and p.name not in config.model.parameters]


def _searched_candidate(run: RunData, prepared, shapes: ShapeSearch, effect: str) -> tuple[object, float]:
    """(the shape and separation search of ``effect``'s refit, :func:`search_candidate`'s (trial config, shape), or
    the exception it raised; its seconds): one item of the candidates' shared work (afmid.diagnosis.forked_work)."""
    started = time.perf_counter()
    config = refit_config(run, run.effects + [effect])
    try:
        searched = search_candidate(run, prepared, config, effect, _shape_names(effect, config), shapes, QUICK_SHAPE)
    except Exception as exc:  # told where the candidate's fit would be, and the diagnosis goes on
        searched = exc
    return searched, time.perf_counter() - started


@dataclass
class _SetFit:
    """A refit with several added effects (their nonlinear parameters fixed at the values found alone)."""

    effects: tuple[str, ...]
    bic: float
    error: float
    state: tuple[float, float, float, float]  # chi2, chi2 limit, error, noise floor
    selected: dict[str, bool]


def _weights_deviance(result, reference_sigma) -> float:
    """What ``result``'s own row weights add to its deviance beyond ``reference_sigma``'s, over all its blocks
    (:func:`afmid.diagnosis.decide.weighting_deviance` per block; 0 without a reference)."""
    if reference_sigma is None:
        return 0.0
    return decide.weighting_deviance(result, reference_sigma) * int(result.system.theta.shape[0])


def _fit_set(run: RunData, prepared, members: list[Trial], base_columns: BaseColumns | None = None,
             reference_sigma: np.ndarray | None = None) -> _SetFit | None:
    config = refit_config(run, run.effects + [m.effect for m in members])
    fixed = {**config.model.parameters}
    for m in members:
        fixed.update(m.shape)
    config.model.parameters = fixed
    if separation_estimated(run) and math.isfinite(members[0].separation):
        config.sample.separation = search_separation(prepared, config, members[0].separation - SEPARATION_WINDOW,
                                                     members[0].separation + SEPARATION_WINDOW, base_columns)
    try:
        result = _fit_quick(config, prepared)
    except Exception as exc:
        log.info("refit with %s failed: %s", [m.effect for m in members], exc)
        return None
    n = int(result.system.n_rows)
    bic = (result.selection.best.bic + math.log(max(n, 2)) * sum(len(m.shape) for m in members)
           + _weights_deviance(result, reference_sigma))
    chi2, limit, _ = _chi2(result)
    names = list(zip(result.library.names, result.selected))
    selected = {m.effect: any(s and name.startswith(m.effect + ".") for name, s in names) for m in members}
    return _SetFit(tuple(m.effect for m in members), bic, result.cv_error,
                   (chi2, limit, result.cv_error, result.cv_error_noise_floor), selected)


#: At most this many accepted candidates enter the search for a pair of missing effects.
PAIR_CANDIDATES = 5


def _forward(run: RunData, prepared, good: list[Trial], base_columns: BaseColumns | None = None,
             reference_sigma: np.ndarray | None = None) -> tuple[tuple[float, float, float, float], float]:
    """Which of the accepted candidates are needed; returns ((chi2, limit, error, floor), BIC) of the final set.

    Forward selection: the best candidate is kept; each further one is refitted
    on top of the ones kept so far and kept only if it still lowers the BIC by
    BIC_EVIDENCE and the cross-validated error (an effect that merely mimics
    part of the top one's signature is dropped; a second missing effect
    survives). When a significant residual remains, every pair of accepted
    candidates is fitted as well (greedy selection can start from an effect
    that imitates two others): a pair that beats the forward choice by
    BIC_EVIDENCE replaces it. Rejected candidates get the reason.
    """
    if not good:
        return (math.nan, math.nan, math.nan, math.nan), math.nan
    top = good[0]
    kept = [top]
    state = (top.chi2_after, top.chi2_limit_after, top.error_after, top.noise_floor_after)
    bic, error = top.bic_after, top.error_after
    verdicts: dict[str, str] = {}
    for t in good[1:]:
        fitted = _fit_set(run, prepared, kept + [t], base_columns, reference_sigma)
        if fitted is None:
            verdicts[t.effect] = "could not be refitted together with " + ", ".join(k.effect for k in kept)
            continue
        gain = fitted.bic - bic
        t.conditional_delta_bic = gain
        if fitted.selected[t.effect] and gain <= -BIC_EVIDENCE and fitted.error < error:
            kept.append(t)
            bic, error, state = fitted.bic, fitted.error, fitted.state
            continue
        why = ("its terms are not selected" if not fitted.selected[t.effect] else
               f"the BIC changes by only {format_delta_bic(gain)}" if gain > -BIC_EVIDENCE else "the cross-validated error does not fall")
        verdicts[t.effect] = (f"added to {', '.join(k.effect for k in kept)} it no longer helps ({why}): it imitates "
                              "part of the same residual")
    # Pairs cost refits only (a pair must still beat the forward choice by BIC_EVIDENCE): tried whenever the
    # error stands above its noise floor at all, not only beyond FLOOR_FACTOR (a meniscus alone can bring a
    # damping + hydration trace to 1.3-1.45x its floor).
    chi2, limit, error_now, floor_now = state
    if (chi2 > limit or (math.isfinite(floor_now) and error_now > floor_now)) and len(good) > 2:
        pool = good[:PAIR_CANDIDATES]
        best = None
        for i in range(len(pool)):
            for j in range(i + 1, len(pool)):
                pair = [pool[i], pool[j]]
                if {p.effect for p in pair} <= {k.effect for k in kept}:
                    continue
                fitted = _fit_set(run, prepared, pair, base_columns, reference_sigma)
                if fitted is None or not all(fitted.selected.values()):
                    continue
                if best is None or fitted.bic < best[1].bic:
                    best = (pair, fitted)
        if best is not None and best[1].bic < bic - BIC_EVIDENCE and best[1].error < error:
            pair, fitted = best
            for k in kept:
                if k not in pair:
                    verdicts[k.effect] = (f"the pair {pair[0].effect} + {pair[1].effect} explains the data better "
                                          f"(BIC {fitted.bic - bic:.0f} lower than with {', '.join(x.effect for x in kept)})")
            for p, other in ((pair[0], pair[1]), (pair[1], pair[0])):
                verdicts.pop(p.effect, None)
                p.conditional_delta_bic = fitted.bic - other.bic_after
            kept, bic, error, state = list(pair), fitted.bic, fitted.error, fitted.state
    for t in good:
        if t not in kept:
            t.significant = False
            t.reasons.append(verdicts.get(t.effect, "not needed once " + ", ".join(k.effect for k in kept)
                                          + " is added"))
    for k in kept:
        k.explains = not _significant(*state)
    good.sort(key=lambda t: (t not in kept, t.delta_bic))
    return state, bic


def _excess(error: float, floor: float) -> float:
    """The part of a cross-validated error not explained by noise (they add in quadrature)."""
    if not (math.isfinite(error) and math.isfinite(floor)):
        return error
    return math.sqrt(max(error**2 - floor**2, 0.0))


def _errors_compared(t: Trial, base: _Base) -> tuple[float, float, float]:
    """(the base's error, the candidate's error, the floor) in one unit: each error over its own noise floor
    (floor 1) where both floors are known, else the raw errors over the base's floor.

    A cross-validated error is normalised by the spread of the inverted force over the harmonics that stand out
    of the noise in its own fit, and its floor in the same way, so errors of fits with other signal harmonics
    or another separation are not comparable, their ratios to their floors are. With the separation re-searched
    per candidate they differ: on a liquid double-layer trace whose [dmt] fit put the surface at -0.86 nm, the
    double layer (refitted at 5.2 nm, its charge and Debye length within 5 % of the truth) took the error from
    0.187 (floor 0.127: 1.47 floors) to 0.228 (floor 0.199: 1.15 floors), and was rejected as "the error does
    not fall". Where the floors agree (the separation fixed) the decisions are those of the raw errors."""
    if all(math.isfinite(f) and f > 0 for f in (base.floor, t.noise_floor_after)):
        return base.error / base.floor, t.error_after / t.noise_floor_after, 1.0
    return base.error, t.error_after, base.floor


def _significant(chi2: float, limit: float, error: float, floor: float, floor_dof: float = math.nan) -> bool:
    """A misfit is significant when the in-sample chi-square OR the out-of-sample error sees it.

    The two are complementary: the chi-square runs over every whitened row and
    dilutes a misfit concentrated on the few harmonics that carry the force; the
    cross-validated error looks only at those, but against a noise floor that is
    itself an estimate (hence FLOOR_FACTOR).
    """
    if quieter_than_its_floor(error, floor, floor_dof):  # a chi-square there is numerical: no diagnosis
        return False
    above_floor = math.isfinite(error) and math.isfinite(floor) and error > FLOOR_FACTOR * floor
    return bool(chi2 > limit or above_floor)


def _rejections(t: Trial, base: _Base) -> list[str]:
    reasons = []
    if quieter_than_its_floor(base.error, base.floor, base.floor_dof):
        reasons.append(f"the model's error {base.error:.3g} is below its noise floor {base.floor:.3g} by more than "
                       "noise explains: nothing is left to explain")
    if not t.effect_terms_selected:
        reasons.append("its terms were not selected")
    if t.delta_bic > -BIC_EVIDENCE:
        reasons.append(f"ΔBIC {format_delta_bic(t.delta_bic)} is not below -{BIC_EVIDENCE:g}")
    error_before, error_after, floor = _errors_compared(t, base)
    if not error_after < error_before:
        reasons.append("the cross-validated error does not fall")
    elif base.error > FLOOR_FACTOR * base.floor:
        before, after = _excess(error_before, floor), _excess(error_after, floor)
        if after > ERROR_RATIO * before:
            reasons.append(f"it removes only {100 * (1 - after / before):.0f} % of the error above the noise")
    reasons += t.implausible
    return reasons


def _trial_record(t: Trial) -> dict:
    return {"effect": t.effect, "error_after": t.error_after, "evidence": t.evidence,
            "delta_bic": t.delta_bic, "noise_floor_after": t.noise_floor_after, "chi2_after": t.chi2_after,
            "terms_selected": t.effect_terms_selected, "significant": t.significant,
            "explains_residual": t.explains, "rejected_because": t.reasons,
            "nonlinear": dict(t.shape), "separation": t.separation, "seconds": t.seconds, "delta_bic_on_top": t.conditional_delta_bic,
            "parameters": {k: {"value": v["value"], "error": v["error"], "unit": v["unit"]}
                           for k, v in t.quantities.items()}}


# --------------------------------------------------------------------------- words
_REGION_WORDS = {"contact": "in contact", "near": f"within {NEAR_RANGE * 1e9:g} nm above contact",
                 "far": f"more than {NEAR_RANGE * 1e9:g} nm from the surface"}
_EFFECT_REGION_WORDS = {"contact": "in contact only", "near": "near the surface, decaying within a few nm",
                        "long_range": "at all separations (long range)", "all": "everywhere"}
_EFFECT_REGIONS = {"contact": {"contact"}, "near": {"contact", "near"}, "long_range": {"contact", "near", "far"},
                   "all": {"contact", "near", "far"}}
_EFFECT_CHARACTERS = {"conservative": {"conservative", "mixed"}, "dissipative": {"dissipative", "mixed"},
                      "hysteretic": {"dissipative", "mixed"}}
_CHARACTER_WORDS = {"conservative": "conservative (the same on approach and retraction)",
                    "dissipative": "dissipative (it reverses with the direction of motion)",
                    "mixed": "partly conservative and partly direction-dependent",
                    "none": "not distinguishable from noise"}


def _region_words(region: str) -> str:
    return _REGION_WORDS[region]


def describe_residual(local: dict, run: RunData) -> str:
    """The systematic residual in plain words (no judgement of significance)."""
    reg = local["by_region"][local["region"]]
    parts = [f"systematic residual {local['rms'] * 1e9:.3g} nN rms ({100 * local['rms'] / max(local['rms_force'], 1e-300):.1f} % "
             f"of the force rms; {local['snr']:.1f} times its noise), {100 * reg['share_of_residual']:.0f} % of it "
             f"{_region_words(local['region'])}"]
    cons, diss = local["conservative_rms"] * 1e9, local["dissipative_rms"] * 1e9
    if local["character"] == "dissipative":
        parts.append(f"it reverses with the direction of motion: dissipative (part that differs between approach and "
                     f"retraction {diss:.3g} nN, part common to both {cons:.3g} nN)")
    elif local["character"] == "conservative":
        sign = "repulsion" if local["conservative_mean"] > 0 else "attraction"
        parts.append(f"it is the same on approach and retraction: conservative, a missing {sign} "
                     f"(common part {cons:.3g} nN, direction-dependent part {diss:.3g} nN)")
    elif local["character"] == "mixed":
        sign = "attraction" if local["conservative_mean"] < 0 else "repulsion"
        parts.append(f"it has a part common to approach and retraction (a missing {sign}, {cons:.3g} nN) and a "
                     f"part that differs between them, i.e. hysteresis or dissipation ({diss:.3g} nN)")
    else:
        parts.append("approach and retraction show no systematic difference from the model beyond the noise")
    # (The residual's dissipated energy is not quoted: the fitted drive absorbs most of a missing dissipation,
    # see energy_check, so it understates it by an unknown factor.)
    for name in ("contact", "near"):
        c = local["by_region"][name]["rate_correlation"]
        if math.isfinite(c) and abs(c) > RATE_CORRELATION and local["by_region"][name]["share_of_residual"] > 0.2:
            kind = "damping-like: it opposes the motion" if c < 0 else "it pushes along the motion"
            parts.append(f"{_region_words(name)} it follows the separation rate (correlation {c:+.2f}, {kind})")
    return "; ".join(parts)


def _match_words(effect: str, local: dict) -> str:
    eff = EFFECTS.get(effect)
    region_ok = local["region"] in _EFFECT_REGIONS.get(eff.region, {"contact", "near", "far"})
    char_ok = local["character"] in _EFFECT_CHARACTERS.get(eff.character, {"conservative", "dissipative", "mixed"})
    where = _EFFECT_REGION_WORDS.get(eff.region, eff.region)
    text = f"`{effect}` is {eff.character} and acts {where}"
    if region_ok and char_ok:
        return text + ", as the residual does"
    misses = []
    if not region_ok:
        misses.append(f"the residual sits mostly {_region_words(local['region'])}")
    if not char_ok:
        misses.append(f"the residual is {_CHARACTER_WORDS.get(local['character'], local['character'])}")
    return text + ", but " + " and ".join(misses)


def _strength(delta: float) -> str:
    d = -delta
    return ("very strong" if d > 10 else "strong" if d > 6 else "positive" if d > 2 else "no") + " evidence"


def _evidence(t: Trial, local: dict, base: _Base, trials: list[Trial]) -> str:
    text = f"{_match_words(t.effect, local)}. Adding it "
    error_before, error_after, floor = _errors_compared(t, base)
    before, after = _excess(error_before, floor), _excess(error_after, floor)
    text += f"changes the cross-validated error from {base.error:.3g} to {t.error_after:.3g} (noise floor {base.floor:.3g}"
    if t.noise_floor_after != base.floor and math.isfinite(t.noise_floor_after):
        text += f" -> {t.noise_floor_after:.3g}"
    if before > 0 and base.error > FLOOR_FACTOR * base.floor:
        text += f"; {100 * (1 - (after / before) ** 2):.0f} % of the error variance above the noise removed"
    text += f") and the BIC by {format_delta_bic(t.delta_bic)} ({_strength(t.delta_bic)}); reduced chi-square {base.chi2:.3g} -> {t.chi2_after:.3g}"
    parts = [f"{k} = {_value_words(v['value'], v['unit'])}" for k, v in t.quantities.items()]
    parts += shape_words(t.effect, t.shape)
    if parts:
        text += "; fitted " + ", ".join(parts)
    if t.significant:
        close = [o for o in trials if o is not t and o.effect_terms_selected and o.delta_bic <= -BIC_EVIDENCE
                 and o.delta_bic - t.delta_bic < BIC_DISTINCT]
        rivals = [o for o in close if not o.implausible]
        if rivals:
            text += ("; the data barely tell it from " + ", ".join(f"`{o.effect}` (ΔBIC {format_delta_bic(o.delta_bic)})" for o in rivals))
        else:
            runner = min((o for o in trials if o is not t and not o.implausible and o.effect_terms_selected
                          and o.delta_bic <= -BIC_EVIDENCE and o.delta_bic >= t.delta_bic),
                         key=lambda o: o.delta_bic, default=None)
            if runner is not None:
                gap = runner.delta_bic - t.delta_bic
                text += (f"; next best `{runner.effect}` (ΔBIC {format_delta_bic(runner.delta_bic)}): {_strength(-gap)} for "
                         f"`{t.effect}` over it")
        for o in close:
            if o.implausible and o.delta_bic - t.delta_bic > -BIC_EVIDENCE:
                text += f"; `{o.effect}` fits about as well (ΔBIC {format_delta_bic(o.delta_bic)}) but is ruled out: {o.implausible[0]}"
        if not t.explains:
            text += "; a significant residual remains after adding it: it explains only part of the misfit"
    elif t.reasons:
        text += "; not suggested: " + "; ".join(t.reasons)
    return text


def _value_words(value: float, unit: str) -> str:
    """A candidate's fitted value in its display unit (afmid.quantity_text: nm, nN, Pa s, zJ); a value the
    refit could not determine (its term was not selected) said in words."""
    if not math.isfinite(value):
        return "not determined (term not selected)"
    return format_value(value, unit)


def _outside_words(t: Trial, top: Trial | None) -> str:
    eff = EFFECTS.get(t.effect)
    shape = ", ".join(shape_words(t.effect, t.shape))
    text = (f"the data prefer the shape of `{t.effect}` ({eff.formula}{'; ' + shape if shape else ''}) with values "
            f"no physical {t.effect} can have ({t.implausible[0]}; ΔBIC {format_delta_bic(t.delta_bic)}")
    text += f", {top.delta_bic - t.delta_bic:.0f} better than `{top.effect}`)" if top else ")"
    return text + ": a force outside the catalog"


def _verdict(good: list[Trial], significant: bool, explained: bool, base: _Base, outside: list[Trial],
             error_after: float = math.nan, delta_bic: float = math.nan, floor_after: float = math.nan) -> str:
    names = " + ".join(t.effect for t in good)
    change = f"error {base.error:.3g} -> {error_after:.3g}"
    if math.isfinite(floor_after) and floor_after > 0 and base.floor > 0 and floor_after != base.floor:
        # Another separation or other signal harmonics: the errors' normalisations differ (_errors_compared).
        change += f", {base.error / base.floor:.3g} -> {error_after / floor_after:.3g} times its noise floor"
    change += f", ΔBIC {format_delta_bic(delta_bic)}"
    if good and explained:
        what = "missing effect" if len(good) == 1 else "missing effects"
        return f"{what}: {names} ({change})"
    if good:
        why = ("a force outside the catalog fits much better" if outside else
               "a significant residual remains after adding it")
        return f"not explained by the catalog: {names} explains part of the residual ({change}), but {why}"
    if significant:
        return "not explained by the catalog: a significant residual that no catalog effect explains"
    if model_limited(base.error, base.floor, base.floor_dof):
        # Flagged by the fit's own threshold, below the alarm (FLOOR_FACTOR or the chi-square): say both.
        return (f"no effect is missing that this record can show: the error {base.error:.3g} stands "
                f"{base.error / base.floor:.3g}x its noise floor {base.floor:.3g}, above this record's 99 % point "
                f"(x{floor_threshold(base.floor_dof):.3g}: the parameters are flagged model-limited) but below the "
                f"alarm (x{FLOOR_FACTOR:g}, reduced chi-square {base.chi2:.3g}), and no catalog effect improves the "
                f"BIC by {BIC_EVIDENCE:g}")
    return (f"no effect is missing: the model explains the data to the noise level (reduced chi-square "
            f"{base.chi2:.3g}, error {base.error:.3g} vs noise floor {base.floor:.3g}) and no catalog effect "
            f"improves the BIC by {BIC_EVIDENCE:g}")

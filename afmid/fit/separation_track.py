"""A slowly varying rest separation d(t), estimated jointly with the force law: the topography track of a record
taken while scanning.

While the tip scans, d(t) = z_piezo(t) - h(x_lat(t)) follows the topography and the amplitude feedback
(afmid.simulate.scan makes such records). One separation for the whole record then mixes periods recorded at
different d into one force curve. Here the record is cut into consecutive blocks of whole drive periods, each
short against the time d takes to change (a block lasts 1 / (2 bandwidth): a piecewise-constant track sampled at
the Nyquist rate of ``bandwidth``), and the blocks are fitted as the traces of a joint fit
(:func:`afmid.fit.joint.fit_traces_jointly`): one force law, a separation (and drive) per block. The track is the
blocks' separations with their 1 sigma (each its own profile's and the common shift's, in quadrature), at the
blocks' middle times.

Within a block d still moves: the feedback moves the piezo every period (sd 8-30 pm within 100-period blocks on a
2 nm step at gain 6000 /s), and a contact of well under a nanometre's indentation turns that into a law biased
soft with every block's d ~400 pm low (docs/lab/2026-11-29-scanning-record.md). Given each period's true d
inside the fit, the same record came out right (d +17 pm at sigma 35 pm, E* 2.06 +- 0.12 GPa for 2). So the
blocks are fitted jointly ``PERIOD_OFFSET_PASSES`` times: each joint fit's law gives each period's d relative to
its block's (:mod:`afmid.fit.period_separation`), and the next fits with those per-period separations, a level per
block (the track: the levels; ``period_offsets``: the periods within). The per-period d comes from all the
period's weak-form rows (``within_block: rows``) or from its mean force alone (``mean_force``). The mean force's
sensitivity to d is the period's mean contact stiffness, ~1.5 N/m on the 240-period feedback records measured:
its offsets erred by 6-9 pm per period against a true sd of 5-8 pm, and the law traded the misassigned contact
for a soft E* and every block's level 42-101 pm low (errors in the regressor flatten the law). The rows find the
offsets to 1-2 pm there: 40 of 40 blocks within 2 sigma over seeds 71-75 of a step and a rough surface, force
error 0.09-1.67 % of the peak. The offsets come from the same rows as the law and the levels, so the last pass
takes them at the joint minimum over all three (:func:`afmid.fit.period_separation.joint_level_step`, linearised
at the previous fit: the alternation alone left the 2 nm step of seed 81 11 pm short of it), and the levels'
sigma gets the offsets' posterior share in quadrature (:func:`offsets_share`; 6 pm beside the profile's 16 pm
there). That minimum is the offsets' marginal likelihood's, with its log-determinant: the fit that holds the
offsets minimises the penalised residual, and offsets fitted to the rows' noise pull that minimum to a higher
level and a stiffer law (+13 pm on flat records, where d does not move); the last fit's rows are shifted by the
log-determinant's step (:func:`afmid.fit.period_separation.with_row_shift`). Each block's sigma is floored at the
record's Cramér-Rao bound of a constant d (:func:`record_bounds`), as the plain fit's is
(docs/lab/2026-11-29-scanning-record.md).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from afmid.config import RunConfig
from afmid.errors import ConfigError
from afmid.fit.joint import JointResult, common_level_variance, fit_traces_jointly, trace_coefficients
from afmid.fit.period_separation import (LevelStep, LinearisedBlock, column_designs, joint_level_step,
                                        mean_force_offsets, ou_prior, row_design, row_offsets, with_period_separation,
                                        with_row_shift)
from afmid.fit.system import library_columns
from afmid.fit.uncertainty import TRACK_LEVEL_ERROR, widen_interval
from afmid.io.onset import crop
from afmid.io.trace import Trace, check_trace

log = logging.getLogger(__name__)

#: The fewest drive periods a block may hold: its own first fit cross-validates over 5 folds and the default
#: selection votes over groups of 6 periods (afmid.fit.selection_strategies), so 30 gives every fold a group.
MIN_BLOCK_PERIODS = 30


@dataclass
class SeparationTrack:
    """The rest separation per block of a record (SI); its run record (afmid.joint_runfile.track_record) is what
    /model/separation_track holds."""

    time: np.ndarray  # s, each block's middle, from the record's first sample
    first_sample: np.ndarray  # index of each block's first sample in the record
    stop_sample: np.ndarray  # one past each block's last sample
    separation: np.ndarray  # m, d of each block
    sigma: np.ndarray  # m, its 1 sigma
    bandwidth: float  # Hz, the track's bandwidth (block duration 1 / (2 bandwidth))
    joint: JointResult  # the joint fit of the blocks (the shared law, each block's forces)
    #: per block, each harmonic block's (period's) rest separation relative to the block's d, m
    period_offsets: list[np.ndarray] = dataclasses.field(default_factory=list)
    within_block: str = "constant"  # how d moved within a block in the fit ("constant", "mean_force" or "rows")
    #: with "rows": the levels, the law and the offsets linearised together at the fit (the levels' covariance
    #: given the offsets and with them marginalised; the joint minimum's step)
    level_step: LevelStep | None = None
    #: per block, the Cramér-Rao bound of a d constant over the whole record at the block's fit (m; NaN: not
    #: computed), the floor of ``sigma`` (:func:`record_bounds`)
    information_bound: np.ndarray | None = None


def block_periods_for(bandwidth: float, drive_frequency: float) -> int:
    """Whole drive periods per block for a track of ``bandwidth`` (Hz): f / (2 bandwidth), rounded down."""
    return int(math.floor(drive_frequency / (2.0 * bandwidth)))


def cut_blocks(trace: Trace, block_periods: int) -> list[Trace]:
    """``trace`` cut into consecutive blocks of ``block_periods`` whole periods (the last block takes the rest of
    the record when that is shorter than a block); a simulation's truth is cut with it, its ``separation``
    attribute set to the mean rest separation of the block when the record has a d(t) track."""
    per_period = trace.sample_rate / trace.drive_frequency
    n_blocks = max(1, int(trace.n_samples // (block_periods * per_period)))
    edges = [round(k * block_periods * per_period) for k in range(n_blocks)] + [trace.n_samples]
    return [cut_block(trace, first, stop) for first, stop in zip(edges[:-1], edges[1:])]


def cut_block(trace: Trace, first: int, stop: int) -> Trace:
    """Samples ``first``..``stop`` of ``trace`` (its own indices) as a block of a track: a simulation's truth
    cut with it, its ``separation`` attribute the block's mean rest separation when the record has a d(t) track."""
    block = crop(trace, first, stop)
    truth = trace.truth
    if truth is not None and truth.tracks:
        tracks = {name: (values[first:stop], unit) for name, (values, unit) in truth.tracks.items()}
        extra = dict(truth.extra)
        if "rest_separation" in tracks:
            extra["separation"] = float(np.mean(tracks["rest_separation"][0]))
        block = dataclasses.replace(block, truth=dataclasses.replace(block.truth, tracks=tracks, extra=extra))
    return block


def fit_separation_track(config: RunConfig, trace: Trace, bandwidth: float, progress=False,
                         uncertainty: bool = True, within_block: str | None = None) -> SeparationTrack:
    """The force law and the track d(t) of ``trace`` (checked, :func:`afmid.io.trace.check_trace`) at
    ``bandwidth`` (Hz). ConfigError naming ``fit.separation_track.bandwidth`` when a block would be shorter than
    the fit needs, or when ``sample.separation`` is given (then there is nothing to track). ``within_block``
    ("constant", "mean_force" or "rows"; None: ``fit.separation_track.within_block``, else "constant"): d held
    per block, or moved per period from each period's mean force or from all its rows (``PERIOD_OFFSET_PASSES``
    joint fits)."""
    key = "fit.separation_track.bandwidth"
    if config.sample.separation is not None:
        raise ConfigError("a separation track estimates d(t); leave sample.separation out", file=config.source,
                          key="sample.separation")
    periods = block_periods_for(bandwidth, trace.drive_frequency)
    if periods < MIN_BLOCK_PERIODS:
        raise ConfigError(f"a bandwidth of {bandwidth:g} Hz gives blocks of {periods} drive periods, need at least "
                          f"{MIN_BLOCK_PERIODS}: lower it", file=config.source, key=key)
    blocks = [check_trace(block, config) for block in cut_blocks(trace, periods)]
    if len(blocks) < 2:
        raise ConfigError(f"the record ({trace.n_periods:.0f} periods) holds one block of {periods} periods: a "
                          "track needs two; raise the bandwidth or fit it with one separation", file=config.source,
                          key=key)
    configs = [config] * len(blocks)
    section = config.fit.separation_track
    within_block = within_block or (section.within_block if section is not None else "constant")
    passes = 1 if within_block == "constant" else PERIOD_OFFSET_PASSES
    joint = fit_traces_jointly(config, configs, blocks, progress, uncertainty=uncertainty and passes == 1)
    offsets = [np.zeros(t.prep.blocks.n_blocks) for t in joint.traces]
    # The blocks' own preparations, before any offset: every pass finds the whole offsets afresh on them from its
    # law. Adding a refit's increments instead can keep the first, soft law's too-large offsets: a correction
    # whose scatter lies below the noise is smoothed to zero (a third pass changed nothing on a step record).
    unshifted = [t.prep for t in joint.traces]
    priors: list[tuple[float, float]] = []
    for fit_pass in range(2, passes + 1):
        offsets, priors = period_offsets(joint, unshifted, within_block)
        last = fit_pass == passes
        shifts = None
        if within_block == "rows" and last and fit_pass > 2:
            # The offsets at the joint minimum over law, levels and offsets (linearised at this fit), not given
            # this fit's law: the alternation reaches that minimum only slowly (step 81 of the 2 nm step: the
            # third fit's levels 11 pm short of it, where the true per-period d given inside the fit ends). The
            # minimum is the offsets' marginal likelihood's: the fit below holds the offsets and minimises the
            # penalised residual, whose minimum the offsets' fit to the noise pulls to a higher level and a
            # stiffer law (+13 pm over 8 flat records); the rows' shift moves it by the log-determinant's step.
            step = joint_level_step(linearised_blocks(joint, unshifted, offsets, priors, derivatives=True))
            offsets, shifts = step.offsets, step.row_shift
            log.info("separation track: the offsets' log-determinant moves the levels by %s pm",
                     np.round(step.log_det_change * 1e12, 1))
        joint = fit_traces_jointly(config, configs, blocks, progress, uncertainty and last,
                                   adjust_prepared=lambda i, prep, shifts=shifts: moved_preparation(
                                       prep, offsets[i], None if shifts is None else shifts[i]))
    first = np.array([b.first_sample - trace.first_sample for b in blocks])
    stop = first + np.array([b.n_samples for b in blocks])
    separation = np.array([t.separation.value for t in joint.traces])
    sigma = np.array([t.separation.sigma for t in joint.traces])
    level_step = None
    if within_block == "rows":
        level_step = joint_level_step(linearised_blocks(joint, unshifted, offsets, priors, derivatives=True))
        sigma = np.sqrt(sigma**2 + offsets_share(level_step))
        log.info("separation track: the offsets add %s pm in quadrature to the levels' sigma; the joint minimum "
                 "(the offsets' marginal likelihood's) lies %s pm from the levels found, its log-determinant's "
                 "part %s pm", np.round(np.sqrt(offsets_share(level_step)) * 1e12, 1),
                 np.round(level_step.level_change * 1e12, 1), np.round(level_step.log_det_change * 1e12, 1))
    floor = record_bounds(config, joint) if uncertainty else np.full(len(blocks), math.nan)
    raised = np.isfinite(floor) & (sigma < floor)
    if np.any(raised):
        log.info("separation track: sigma of block(s) %s raised to the record's information bound (%s pm; theirs "
                 "%s pm)", np.flatnonzero(raised).tolist(), np.round(floor[raised] * 1e12, 1).tolist(),
                 np.round(sigma[raised] * 1e12, 1).tolist())
        sigma = np.where(raised, floor, sigma)
    if uncertainty:
        widen_read_outs(joint, level_added_sigma(joint, sigma))
    return SeparationTrack(0.5 * (first + stop) / trace.sample_rate, first, stop, separation, sigma, bandwidth, joint,
                           offsets, within_block, level_step, floor)


def level_added_sigma(joint: JointResult, sigma: np.ndarray) -> float:
    """The 1 sigma (m) the track adds to the blocks' common level beyond the joint fit's: the root mean square over
    the blocks of sqrt(sigma^2 - joint sigma^2) (``sigma``: the track's per block, m; the joint fit's: its own
    profile's and the common shift's in quadrature), 0 where the track did not raise it.

    The added parts (the offsets' share, the floor at the record's bound of a d constant over the record) are
    taken as common to all the blocks: the floor is one d for the whole record by construction, and a common
    error of the levels is what moves the shared law; taking them as independent per block would divide their
    effect on the law by the number of blocks. The root mean square is not below the mean of the blocks' added
    sigmas, the common level's added sigma were they fully correlated."""
    joint_sigma = np.array([t.separation.sigma if t.separation is not None else math.nan for t in joint.traces])
    added = np.clip(np.asarray(sigma, dtype=float)**2 - joint_sigma**2, 0.0, None)
    added = added[np.isfinite(added)]
    return float(math.sqrt(np.mean(added))) if added.size else 0.0


def widen_read_outs(joint: JointResult, added_sigma: float) -> None:
    """Carry the track's added sigma of the common level ``added_sigma`` (m, :func:`level_added_sigma`) into the
    shared read-outs of ``joint`` (in place): each read-out's larger change with the law refitted at the levels
    moved by +-``added_sigma`` (:func:`afmid.fit.joint.common_level_variance`, the joint fit's own propagation of
    its common shift) added in quadrature to its 1 sigma and its 95 % interval; the values do not change. Each
    read-out keeps that part as :data:`afmid.fit.uncertainty.TRACK_LEVEL_ERROR` (0 when nothing was added)."""
    variance = common_level_variance(joint, added_sigma)
    for name, q in joint.quantities.items():
        share = math.sqrt(variance.get(name, 0.0))
        widen_interval(q, share)
        q[TRACK_LEVEL_ERROR] = share
    if added_sigma > 0:
        log.info("separation track: the levels' added %.1f pm carried into the read-outs (%s)", added_sigma * 1e12,
                 ", ".join(f"{name} +{math.sqrt(v):.3g}" for name, v in variance.items() if v > 0))


def record_bounds(config: RunConfig, joint: JointResult) -> np.ndarray:
    """Per block, the Cramér-Rao bound (m) of a separation constant over the whole record (all the blocks'
    periods), at that block's fit (the joint law, the block's drive and d): the plain fit's floor
    (:func:`afmid.fit.information_bound.fit_bound` on the block, its information scaled by the record's length).
    NaN where the bound does not apply (:func:`afmid.fit.information_bound.bound_applies`) or the fitted law has
    no steady state.

    It floors each block's sigma: the track's model holds the one where the blocks' levels differ by known amounts
    (a d constant over the record, for a flat record), and a block's level cannot be known better than that
    common d; a shared drive only adds information, so the bound with one drive is still below the track's. The
    track's own sigma fell below it on 3 of 8 flat records (14-15 pm against 15.8-16.0 pm)."""
    from afmid.errors import AfmidError
    from afmid.fit.forces import read_out
    from afmid.fit.information_bound import bound_applies, fit_bound
    from afmid.preprocess.instrument import from_config as instrument_from_config

    plain = config.model_copy(update={"fit": config.fit.model_copy(update={"separation_track": None})})
    instrument = instrument_from_config(plain)
    p = len(joint.library)
    coef = np.where(joint.selected, joint.coef, 0.0)
    out = np.full(len(joint.traces), math.nan)
    record_periods = sum(t.prep.blocks.n_blocks for t in joint.traces)
    for i, t in enumerate(joint.traces):
        why_not = bound_applies(t.prep, plain, instrument, t.single.drive_search)
        if why_not is not None or t.separation is None:
            log.info("separation track: no information bound for block %d: %s", i, why_not or "its d is given")
            continue
        mask = trace_coefficients(joint.system, joint.selected, i, p).astype(bool)
        block_coef = trace_coefficients(joint.system, coef, i, p)
        try:
            bound = fit_bound(t.prep, joint.library, plain, t.single.system, block_coef, mask, t.params,
                              {"d": t.separation}, instrument,
                              lambda c, params, prep=t.prep, mask=mask: {
                                  k: q["value"] for k, q in read_out(joint.library, c, None, params, mask,
                                                                     prep.trace).items()})
        except (ArithmeticError, AfmidError, np.linalg.LinAlgError) as exc:
            log.info("separation track: no information bound for block %d: %s", i, exc)
            continue
        # The information grows with the record's length: the block's periods over all the blocks'.
        out[i] = bound.of("d") * math.sqrt(t.prep.blocks.n_blocks / record_periods)
    return out


def offsets_share(step: LevelStep) -> np.ndarray:
    """Each block level's variance (m^2) from the per-period offsets' posterior uncertainty: the marginal
    covariance's diagonal less the conditional one's (:func:`afmid.fit.period_separation.joint_level_step`),
    never negative.

    The joint fit's profile of the levels holds the offsets; they come from the same rows under a prior, so their
    error is correlated with the rows' noise the profile counts, and a common error of a block's offsets moves
    its level and the law together (a misassigned contact is traded for a softer law). Profiling the level with
    the offsets re-derived at each trial level would cost a joint fit per trial point; in the linearised model
    the marginal covariance is the same thing exactly, at the cost of one evaluation of the offsets' design per
    block, and the law of total variance makes its excess over the conditional covariance the offsets' share,
    added in quadrature to the profile's (robust, chi-square-scaled) sigma."""
    return np.maximum(np.diag(step.marginal) - np.diag(step.conditional), 0.0)


def period_offsets(joint: JointResult, preparations: list, within_block: str = "mean_force"
                   ) -> tuple[list[np.ndarray], list[tuple[float, float]]]:
    """Per block, each period's rest separation relative to the block's (m, zero mean) under the joint fit's law
    and the block's level, on ``preparations`` (one per block: the unshifted ones): from the period's mean force
    (``within_block`` "mean_force": :func:`afmid.fit.period_separation.mean_force_offsets`, smoothed) or from all
    the period's weak-form rows with the block's drive ("rows": :func:`afmid.fit.period_separation.row_offsets`);
    and per block the offsets' prior, (sd in m, rho) ((0, 0) for "mean_force", which has none)."""
    p = len(joint.library)
    coef = np.where(joint.selected, joint.coef, 0.0)
    law = coef[:p]
    if within_block == "rows":
        found = [row_offsets(prep, joint.library, law, trace_coefficients(joint.system, coef, i, p)[p:], t.params)
                 for i, (prep, t) in enumerate(zip(preparations, joint.traces))]
        return [offsets for offsets, _ in found], [prior for _, prior in found]
    return ([mean_force_offsets(prep, joint.library, law, t.params) for prep, t in zip(preparations, joint.traces)],
            [(0.0, 0.0)] * len(preparations))


def moved_preparation(prep, offsets: np.ndarray, shift: np.ndarray | None):
    """A block's preparation with its per-period offsets (m) and, when given, the rows' shift of the offsets'
    log-determinant (:func:`afmid.fit.period_separation.with_row_shift`)."""
    moved = with_period_separation(prep, offsets)
    return moved if shift is None else with_row_shift(moved, shift)


#: The step of the offsets' design's derivative in the level, m: the contact's curvature in d (F ~ delta^1.5,
#: the design ~ delta^0.5) changes over hundreds of pm of indentation, so 10 pm is linear and far above
#: :data:`afmid.fit.period_separation.DERIVATIVE_STEP`'s rounding.
LEVEL_SLOPE_STEP = 10e-12


def linearised_blocks(joint: JointResult, preparations: list, offsets: list[np.ndarray],
                      priors: list[tuple[float, float]], derivatives: bool = False) -> list[LinearisedBlock]:
    """Each block of ``joint`` linearised at its fit (:class:`afmid.fit.period_separation.LinearisedBlock`): its
    unshifted preparation moved by its ``offsets`` (m), the law's and the block's drive's selected columns, the
    offsets' design and their OU prior ``priors`` ((sd in m, rho) per block); with ``derivatives`` also the
    design's derivatives in the shared law's selected coefficients and in the level (the offsets'
    log-determinant: twelve evaluations of the columns per block instead of five)."""
    p = len(joint.library)
    coef = np.where(joint.selected, joint.coef, 0.0)
    law = coef[:p]
    out = []
    for i, (prep, t, moved, (sd, rho)) in enumerate(zip(preparations, joint.traces, offsets, priors)):
        chosen = trace_coefficients(joint.system, joint.selected, i, p).astype(bool)
        nuisance = trace_coefficients(joint.system, coef, i, p)[p:]
        moved = np.asarray(moved, dtype=float)
        design, residual = row_design(prep, joint.library, law, nuisance, t.params, moved)
        sigma = prep.row_sigma[None, :, None]
        theta = library_columns(with_period_separation(prep, moved), joint.library, t.params) / sigma
        drive = prep.nuisance / sigma
        shared_designs = level_slope = None
        if derivatives:
            shared_designs = column_designs(prep, joint.library, t.params, moved)[:, :, chosen[:p]]
            up, down = (column_designs(prep, joint.library, t.params, moved + sign * LEVEL_SLOPE_STEP) @ law
                        for sign in (1, -1))
            level_slope = (up - down) / (2 * LEVEL_SLOPE_STEP)
        out.append(LinearisedBlock(residual, moved, theta[:, :, chosen[:p]].reshape(residual.size, -1),
                                   drive[:, :, chosen[p:]].reshape(residual.size, -1), design,
                                   ou_prior(prep.blocks.n_blocks, sd, rho), shared_designs, level_slope))
    return out


#: Joint fits made: the first with d constant per block, then each with the per-period offsets from the previous
#: one's law. The first law is soft (E* 1.1 GPa for 2 on the 2 nm step), its contact stiffness too low, so its
#: offsets come out too large (d +93 pm at sigma 94 pm after two passes, from -405 pm); a third pass starts from
#: a law near the truth.
PERIOD_OFFSET_PASSES = 3


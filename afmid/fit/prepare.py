"""The fit's preparation of a trace: everything about the data that the library does not change.

:func:`prepare` measures (or takes) the drive, cuts the record into periods (per-period Fourier blocks), forms
the weak-form rows and the drive / baseline nuisance columns, estimates the noise of every row, and
reconstructs the trajectory the library is evaluated on (smoothed across periods). The result, a
:class:`Prepared`, is shared by every fit of the same trace (:func:`afmid.fit.pipeline.fit_prepared`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from dataclasses import dataclass

import numpy as np

from afmid.preprocess.baseline import BaselineColumns, remove_drift
from afmid.errors import AfmidError
from afmid.preprocess.instrument import (Instrument, NoiseProbe, RecordedSeries, crossfaded_series, deflection_views,
                                        noise_probe, recorded_series, row_noise_gain, row_noise_gains)
from afmid.preprocess.restoration import restore_trajectory
from afmid.io.trace import Trace
from afmid.physics.library import Library
from afmid.physics.effects import BOLTZMANN
from afmid.preprocess.periods import (
    HarmonicBlocks,
    WeakWindows,
    detrend,
    amplitude_per_block,
    harmonic_blocks,
    ou_smooth_given,
    ou_smooth_variance,
    steadiness,
    weak_windows,
)
from afmid.preprocess.harmonics import estimate_drive
from afmid.preprocess.differentiation import differentiate
from afmid.preprocess.harmonics import transient_limit
from afmid.preprocess.motion import classify as classify_motion
from afmid.fit.thermal_bias import ThermalForce, TrajectorySmoother, corrects_thermal_bias
from afmid.threads import map_in_order

#: Blocks (periods) per chunk when the fine grid is evaluated (the system's columns, the forces): bounds memory
#: for long traces.
CHUNK_BLOCKS = 256

log = logging.getLogger(__name__)


#: Library terms are evaluated on a grid of at least this many points per drive period (see harmonic_blocks).
FINE_POINTS_PER_PERIOD = 2048


# --------------------------------------------------------------------------- preparation
@dataclass
class Prepared:
    """Everything about the data that does not depend on the library or its parameters."""

    trace: Trace
    x: np.ndarray  # m, deflection after detrending (all samples)
    t: np.ndarray  # s
    drive: object  # DriveEstimate
    blocks: HarmonicBlocks  # per-period Fourier fits (trajectory, outputs)
    windows: WeakWindows  # weak-form test functions (regression rows)
    X: np.ndarray  # (B, 2K+1) m, deflection coefficients per period
    Y: np.ndarray  # (W, 2K+1) N s, weak-form left side per window and test function
    nuisance: np.ndarray  # (W, 2K+1, n_nu) drive (and offset / cantilever) columns, weak form
    nuisance_names: list[str]
    row_sigma: np.ndarray  # (2K+1,) N s, predicted noise of each weak-form row
    base_variance: np.ndarray  # (2K+1,) the equation's own noise (thermal force + detector)
    psi_sq: np.ndarray  # (2K+1,) s^2, sum of squared test-function weights (for regressor noise)
    Y_block: np.ndarray  # (B, 2K+1) N, -(m x'' + c x' + k x) per period (outputs)
    nuisance_block: np.ndarray  # (B, 2K+1, n_nu) per-period drive columns (outputs)
    block_sigma: np.ndarray  # (2K+1,) N, noise of Y_block per period
    trajectory_noise: float  # m, rms noise of the trajectory the library is evaluated on
    xdot_used: np.ndarray  # m/s, velocity on the used samples (band-limited)
    X_traj: np.ndarray  # (B, 2K+1) m, smoothed trajectory coefficients (the library's input)
    V_traj: np.ndarray  # (B, 2K+1) m/s, its velocity
    noise_rms: float  # m, detector noise estimated from the block fits
    steadiness: float  # relative change of the amplitude over the record (afmid.preprocess.harmonics.amplitude_change)
    #: the change above which the record is a transient (afmid.preprocess.harmonics.transient_limit: larger than
    #: 2 % where the lever's thermal motion moves the amplitude more, a soft lever in liquid)
    transient_limit: float
    removed: dict  # detrend info
    form: str = "weak"
    strong: tuple | None = None  # (x, xdot) on the used samples from the differentiator (strong form)
    motion: object = None  # afmid.preprocess.motion.Motion: periodic, period doubling or non-periodic (None: not judged)
    #: m, the tip restored for the per-sample forces behind a declared detector (afmid.preprocess.restoration): the
    #: smoothed, Wiener-shrunk trajectory instead of ``x``, whose inverted noise is multiplied by |1/G| (None: x)
    x_restored: np.ndarray | None = None
    #: the calibrated drive moved into Y and Y_block, its columns out of the regression
    #: (:func:`afmid.fit.declared_drive.with_declared_drive`; None: the drive is fitted)
    declared_drive: object = None
    declared_drive_rows: np.ndarray | None = None  # (W, 2K+1, 2) the weak-form rows of its cos and sin
    #: the trajectory on the fine grid kept for repeated library evaluations (:func:`with_fine_grid`; None: made
    #: afresh by every :func:`fine_chunks` pass)
    fine_grid: "FineGrid | None" = None
    #: the lever's thermal force as the fit's configuration has it (``fit.thermal_noise``, ``fit.temperature``):
    #: its bias of the weak-form regression is taken out of the factors (:mod:`afmid.fit.thermal_bias`); None
    #: without a thermal force, or in the strong form
    thermal_force: ThermalForce | None = None
    #: the preparation's instrument-free part, kept for preparations of this record with another instrument
    #: (:func:`with_instrument`); None: not kept
    before_instrument: "BeforeInstrument | None" = None


@dataclass
class BeforeInstrument:
    """What :func:`prepare` makes of a record before any instrument is undone: the detrended samples, the drive,
    the blocks and weak-form windows. None of it depends on the declared instrument, so a preparation of the same
    record with another instrument declared (:func:`with_instrument`: the diagnosis's search for an undeclared
    detector or second mode refits the record with ~100 of them) starts from it; so do the instrument-free parts
    of the views and of the rows' noise probe, made on first use."""

    settings: tuple  # the fit settings it was made with (:func:`_before_instrument_settings`)
    t: np.ndarray  # s
    x: np.ndarray  # m, detrended (and without the drift when detrending linearly)
    removed: dict  # detrend info
    drive: object  # DriveEstimate
    blocks: HarmonicBlocks
    windows: WeakWindows
    _recorded: RecordedSeries | None = None
    _probe: NoiseProbe | None = None
    _tip_side: "TipSide | None" = None

    def recorded(self) -> RecordedSeries:
        """The instrument-free part of the views of ``x`` (:func:`afmid.preprocess.instrument.recorded_series`)."""
        if self._recorded is None:
            self._recorded = recorded_series(self.x, self.blocks)
        return self._recorded

    def probe(self) -> NoiseProbe:
        """The rows' noise probe on these blocks (:func:`afmid.preprocess.instrument.noise_probe`)."""
        if self._probe is None:
            self._probe = noise_probe(self.blocks)
        return self._probe

    def tip_side(self, key) -> "TipSide | None":
        """The :class:`TipSide` kept under ``key`` (:meth:`TipSide.key_of`), or None."""
        kept = self._tip_side
        return kept if key is not None and kept is not None and kept.key == key else None

    def keep_tip_side(self, tip_side: "TipSide") -> None:
        """Keep ``tip_side`` for the next preparation with its key: one at a time (a search tries one detector with
        many modes, or many detectors one after another)."""
        self._tip_side = tip_side

    def forget_tip_side(self) -> None:
        """Let the kept :class:`TipSide` go (its fine grid and kept columns: up to ~0.2 GB on a long record)."""
        self._tip_side = None


@dataclass(frozen=True)
class TipSide:
    """What :func:`prepare` makes of the tip's view alone: the deflection's block coefficients, the nuisance columns,
    the noise level, the trajectory the library is evaluated on (and its fine grid, :class:`FineGrid`). The tip's
    view depends on the declared detector, not on the higher modes (they change only the equation's view and the
    rows' noise), so the second-mode hypotheses of the diagnosis's instrument search share it: kept in
    :class:`BeforeInstrument` under :meth:`key_of` by :func:`with_instrument`. Its arrays are shared by the
    preparations made from it (never written into)."""

    key: tuple
    x: np.ndarray  # m, the tip's view of the samples
    X: np.ndarray  # (B, 2K+1) m
    nuisance_block: np.ndarray  # (B, 2K+1, n_nu)
    nuisance: np.ndarray | None  # (W, 2K+1, n_nu) weak form
    noise_rms: float  # m
    trajectory_noise: float  # m
    xdot_used: np.ndarray  # m/s
    X_traj: np.ndarray  # (B, 2K+1) m
    V_traj: np.ndarray  # (B, 2K+1) m/s
    motion: object
    x_restored: np.ndarray | None  # m
    steadiness: float
    transient_limit: float
    thermal_force: "ThermalForce | None"
    fine_grid: "FineGrid | None"

    @staticmethod
    def key_of(instrument, fit) -> tuple | None:
        """What the tip side depends on beyond the record: whether any instrument is declared, the detector, the
        fit settings; None in the strong form (its rows are made from the tip's samples: not kept)."""
        if fit.form != "weak":
            return None
        ideal = instrument is None or instrument.ideal
        return ideal, None if instrument is None else instrument.detector, fit.model_dump_json()


def _before_instrument_settings(fit) -> tuple:
    """The fit settings :class:`BeforeInstrument` depends on."""
    return fit.detrend, fit.oversample, fit.periods_per_block, fit.max_harmonic


def before_instrument(trace: Trace, fit, drive=None, layouts: dict | None = None) -> BeforeInstrument:
    """The part of :func:`prepare` (same arguments) that no instrument changes."""
    t = trace.times
    x, removed = detrend(trace.deflection, t, fit.detrend)
    if trace.time is not None:
        steps = np.diff(t)
        if np.max(np.abs(steps - steps.mean())) > 1e-3 * steps.mean():
            raise AfmidError("the time column is not uniformly sampled (gaps or jitter); resample or crop it first",
                             file=trace.path, key="data.time_column")
    if drive is None:
        drive = trace.drive_for(fit.detrend) or estimate_drive(x, t, trace.drive_frequency)  # measured on loading
    spp = trace.sample_rate / drive.frequency
    oversample = fit.oversample or max(1, int(math.ceil(FINE_POINTS_PER_PERIOD / spp)))
    layout = (x.size, trace.sample_rate, drive.frequency, float(t[0]), fit.periods_per_block, fit.max_harmonic,
              oversample)
    if layouts is not None and layout in layouts:
        blocks, windows = layouts[layout]
    else:
        blocks = harmonic_blocks(x.size, trace.sample_rate, drive.frequency, t0=float(t[0]),
                                 periods_per_block=fit.periods_per_block, max_harmonic=fit.max_harmonic,
                                 oversample=oversample)
        windows = weak_windows(blocks)
        if layouts is not None:
            layouts.clear()  # one layout at a time: a map's pixels come in runs of one drive frequency
            layouts[layout] = blocks, windows
    if fit.detrend == "linear":  # the trajectory without the drift; the regression's columns take the rest
        x, removed["drift"] = remove_drift(x, t, blocks)
    return BeforeInstrument(_before_instrument_settings(fit), t, x, removed, drive, blocks, windows)


def with_instrument(prep: "Prepared", fit, instrument) -> "Prepared":
    """``prep``'s record prepared again with ``instrument`` declared (fit settings ``fit``): the same as
    :func:`prepare` of ``prep.trace`` with the drive ``prep`` was cut at, the instrument-free part
    (:class:`BeforeInstrument`) reused when ``prep`` holds one made with the same settings, and with it the tip
    side (:class:`TipSide`) of the last instrument prepared with the same detector: the same values as a fresh
    preparation, the trajectory's fine grid made once for all its fits."""
    shared = prep.before_instrument
    if shared is None or shared.settings != _before_instrument_settings(fit):
        return prepare(prep.trace, fit, instrument, drive=prep.drive)
    return _prepare(prep.trace, fit, instrument, shared, reuse_tip_side=True)


def prepare(trace: Trace, fit, instrument=None, drive=None, layouts: dict | None = None) -> Prepared:
    """Everything about the data that the library does not change: drive, blocks, weak-form rows, noise.

    ``instrument`` (:class:`afmid.preprocess.instrument.Instrument`, None: ideal) is undone per harmonic first
    (:func:`afmid.preprocess.instrument.deflection_views`): the library sees the tip, the equation its single-mode twin.

    Per-sample work runs chunk by chunk (:data:`afmid.preprocess.periods.CHUNK_BLOCKS` periods): the only arrays as
    long as the trace are the deflection, its times and the velocity kept for the per-sample forces.

    ``drive`` (:class:`afmid.preprocess.harmonics.DriveEstimate`, None: the one measured on loading, else measured
    here) sets the drive frequency the record is cut at. ``layouts``: a dict in which the blocks and test
    functions are kept, keyed by everything they are made from (samples, rate, drive frequency, start time,
    harmonics, fine grid), so records of one layout share them (the pixels of a map fitted at one drive
    frequency); they are not modified by the fit.
    """
    return _prepare(trace, fit, instrument, before_instrument(trace, fit, drive, layouts))


def _prepare(trace: Trace, fit, instrument, shared: BeforeInstrument, reuse_tip_side: bool = False) -> Prepared:
    """:func:`prepare` from ``shared``. ``reuse_tip_side``: what depends only on the tip's view (:class:`TipSide`)
    is taken from ``shared`` when made there for the same detector and fit settings, and kept there otherwise."""
    t, x, drive, blocks, windows = shared.t, shared.x, shared.drive, shared.blocks, shared.windows
    removed = dict(shared.removed)
    ideal = instrument is None or instrument.ideal
    key = TipSide.key_of(instrument, fit) if reuse_tip_side else None
    known = shared.tip_side(key) if reuse_tip_side else None
    # With the tip side known only the equation's view is needed (the tip's, behind a detector, is not made again).
    views = deflection_views(x, blocks, instrument, trace.cantilever, None if ideal else shared.recorded(),
                             equation_only=known is not None)
    x_equation = views.equation
    x = views.tip if known is None else known.x
    cl = trace.cantilever
    k, w0, Q = cl.spring_constant, cl.omega0, cl.quality_factor
    m, c = cl.mass, cl.damping
    fixed = fit.cantilever == "fixed"

    columns = BaselineColumns(drive.omega, float(t[0]), float(t[-1]), fit.baseline == "free", fit.detrend == "linear")
    names = columns.names
    n_drive = len(names)
    weak = fit.form == "weak"
    # Rows of the weak form: -integral of (m psi'' - c psi' + k psi) x = integral of psi (F_ts - F_drive);
    # with a free cantilever k x + c x' move to the right-hand side with free coefficients.
    operator = m * windows.ddpsi + ((k * windows.psi - c * windows.dpsi) if fixed else 0.0)
    rows = blocks.n_coef
    # One pass over the samples, chunk by chunk: per-period Fourier coefficients of the deflection and the
    # drive columns, and the weak-form integrals of the windows starting in the chunk (they reach one period
    # into the next chunk). The drive columns and the rotations to global phase are made once per chunk. With
    # the tip side known, only the equation's rows Y (each chunk's the same operations as in the full pass).
    W = windows.n_windows
    if known is None:
        X = np.empty((blocks.n_blocks, rows, 1))
        nuisance_block = np.empty((blocks.n_blocks, rows, n_drive))
        nuisance = np.empty((W, rows, n_drive + (0 if fixed else 2))) if weak else None
    if weak:
        Y = np.empty((W, rows))
        minus_dpsi = -windows.dpsi
    chunks = list(blocks.chunks())

    def project_chunk(bounds: tuple[int, int]) -> None:  # into its own rows (chunks shared among threads)
        b0, b1 = bounds
        lo = blocks.start + b0 * blocks.L
        n_block = (b1 - b0) * blocks.L
        hi = lo + n_block + (blocks.L + 1 if weak else 0)
        xs = x[lo:hi, None]
        cols = columns(t[lo:hi]) if known is None else None
        xe = xs if x_equation is x else x_equation[lo:hi, None]
        turn = blocks.rotation(b0, b1)
        if known is None:
            X[b0:b1] = blocks.project_blocks(xs[:n_block], b0, turn)
            nuisance_block[b0:b1] = blocks.project_blocks(cols[:n_block], b0, turn)
        w1 = min(b1, W)
        if weak and w1 > b0:
            Y[b0:w1] = -windows.integrate_samples(operator, xe, b0, w1 - b0, turn)[..., 0]
            if known is not None:
                return
            nuisance[b0:w1, :, :n_drive] = windows.integrate_samples(windows.psi, cols, b0, w1 - b0, turn)
            if not fixed:
                nuisance[b0:w1, :, n_drive:n_drive + 1] = windows.integrate_samples(windows.psi, xs, b0, w1 - b0, turn)
                nuisance[b0:w1, :, n_drive + 1:] = windows.integrate_samples(minus_dpsi, xs, b0, w1 - b0, turn)

    if weak or known is None:
        _map_chunks(project_chunk, chunks)
    if known is not None:
        X = known.X[..., None]

    # The trajectory, the outputs and the noise level.
    X_eq = views.equation_coefficients(X)
    Y_block = -(m * blocks.derivative(X_eq, 2) + c * blocks.derivative(X_eq, 1) + k * X_eq)[..., 0]
    used = blocks.used
    if known is None:
        V = blocks.derivative(X, 1)
        n_used = blocks.n_blocks * blocks.L
        dof = max(n_used - blocks.n_blocks * blocks.n_coef, 1)
        rss = views.residual_sum_squares if views.tip_gain is not None else _fit_residual_sum_squares(x, blocks, X)
        noise_rms = float(math.sqrt(rss / dof))
        noise_rms = max(noise_rms, 1e-9 * drive.amplitude)  # noise-free input: keep weights finite
        if not fixed:
            nuisance_block = np.concatenate([nuisance_block, X, V], axis=2)
    else:
        noise_rms, nuisance_block, nuisance = known.noise_rms, known.nuisance_block, known.nuisance
    if not fixed:
        names += ["stiffness", "damping"]
    thermal = 2 * BOLTZMANN * fit.temperature * c / blocks.dt if fit.thermal_noise else 0.0
    strong = None
    if weak:
        # Predicted noise per row: detector noise through the operator, thermal force noise through psi.
        psi_sq = _pair_mean(np.sum(windows.psi**2, axis=1))
        detector_variance = noise_rms**2 * _pair_mean(np.sum(operator**2, axis=1))
        # a declared instrument: the rows' noise through the views' gains over each row's band (measured)
        # behind higher modes the thermal force (on the first mode, as the simulator has it) reaches the
        # equation through the modes' gain H_1 / H too: 1.5-2.8 at harmonics 3-5 for f2 = 6.27 f0
        thermal_modes = bool(thermal and instrument is not None and instrument.higher_modes)
        band_gain = modes_gain = None
        if thermal_modes and instrument.detector is None:  # one instrument for both: the probe through it once
            band_gain, modes_gain = row_noise_gains(instrument, trace.cantilever, blocks, [operator, windows.psi],
                                                    shared.probe())
        else:
            band_gain = None if ideal else row_noise_gain(instrument, trace.cantilever, blocks, operator, shared.probe())
            modes_gain = (row_noise_gain(Instrument(None, instrument.higher_modes), trace.cantilever, blocks,
                                         windows.psi, shared.probe()) if thermal_modes else None)
        if band_gain is not None:
            detector_variance = detector_variance * band_gain
        base_variance = detector_variance + thermal * psi_sq * (1.0 if modes_gain is None else modes_gain)
    else:
        # Rows: the equation at every used sample, derivatives from a registered differentiator.
        xs, v, a = differentiate(x, trace.sample_rate, drive.frequency, fit.differentiation,
                                 fit.differentiation_options)
        shape = (blocks.n_blocks, blocks.L)
        Y = -(m * a + ((c * v + k * xs) if fixed else 0.0))[used].reshape(shape)
        cols = [columns(t)] + ([] if fixed else [xs[:, None], v[:, None]])
        nuisance = np.column_stack(cols)[used].reshape(shape + (-1,))
        psi_sq = np.zeros(blocks.L)
        base_variance = np.full(blocks.L, float(np.var(Y - Y.mean(axis=0))))  # uniform weights
        strong = (xs[used], v[used])
    n = blocks.harmonics * drive.omega
    H2 = (1 - (n / w0) ** 2) ** 2 + (n / (Q * w0)) ** 2
    if views.tip_gain is not None:
        H2 = H2 * views.noise_gain(blocks.harmonics)
    thermal_gain = 1.0 if views.equation_gain is None else np.abs(views.equation_gain[blocks.harmonics]) ** 2
    block_sigma = np.sqrt(blocks.noise_variance_factor() * (thermal * thermal_gain + k**2 * H2 * noise_rms**2))
    if known is None:
        known = _tip_side(key, trace, fit, blocks, drive, x, X, nuisance_block, nuisance, noise_rms, views)
        if key is not None:
            shared.keep_tip_side(known)
    return Prepared(
        trace=trace, x=x, t=t, drive=drive, blocks=blocks, windows=windows, X=known.X,
        Y=Y, nuisance=nuisance, nuisance_names=names, row_sigma=np.sqrt(base_variance),
        base_variance=base_variance, psi_sq=psi_sq,
        Y_block=Y_block, nuisance_block=nuisance_block, block_sigma=block_sigma,
        trajectory_noise=known.trajectory_noise, xdot_used=known.xdot_used, X_traj=known.X_traj,
        V_traj=known.V_traj, noise_rms=noise_rms, steadiness=known.steadiness, transient_limit=known.transient_limit,
        removed=removed, form=fit.form, strong=strong, motion=known.motion, x_restored=known.x_restored,
        thermal_force=known.thermal_force if weak else None, before_instrument=shared,
        fine_grid=known.fine_grid if key is not None else None,
    )


def _tip_side(key, trace: Trace, fit, blocks: HarmonicBlocks, drive, x: np.ndarray, X: np.ndarray,
              nuisance_block: np.ndarray, nuisance: np.ndarray | None, noise_rms: float, views) -> "TipSide":
    """The trajectory the library is evaluated on and what else :func:`_prepare` makes of the tip's view alone."""
    cl = trace.cantilever
    k, w0, Q = cl.spring_constant, cl.omega0, cl.quality_factor
    rows = blocks.n_coef
    thermal = 2 * BOLTZMANN * fit.temperature * cl.damping / blocks.dt if fit.thermal_noise else 0.0
    # The library is evaluated on a trajectory smoothed across periods: detector noise is independent from
    # period to period while the real motion wanders slowly (thermal correlation time Q / pi periods), and
    # noise in the regressors biases stiff terms low (errors in variables).
    rho = math.exp(-math.pi * blocks.L * blocks.dt * drive.frequency / Q)
    noise_var = blocks.noise_variance_factor() * noise_rms**2
    if views.tip_gain is not None:  # an undone detector amplifies the noise of each harmonic by |1 / G|
        noise_var = noise_var * np.abs(views.tip_gain[blocks.harmonics]) ** 2
    thermal_variance = BOLTZMANN * fit.temperature / k if fit.thermal_noise else 0.0  # m^2, k_B T / k
    motion = classify_motion(X[..., 0], noise_var, thermal_variance)
    if fit.smooth_periods is not None:
        X_traj = smooth_across_blocks(X, fit.smooth_periods)
        residual_var = smoothing_variance_factor(blocks.n_blocks, fit.smooth_periods)
        smoother = TrajectorySmoother("savgol", blocks.n_blocks, window=fit.smooth_periods,
                                      across_blocks=functools.partial(smooth_across_blocks, window=fit.smooth_periods))
    elif motion is not None and motion.non_periodic:  # no one orbit to smooth towards: each period as it is
        X_traj, residual_var = X, 1.0
        smoother = TrajectorySmoother("none", blocks.n_blocks)
    else:
        signal_var = ou_smooth_variance(X[..., 0], noise_var)
        X_s, post_var = ou_smooth_given(X[..., 0], noise_var, signal_var, rho)
        smoother = TrajectorySmoother("ou", blocks.n_blocks, noise_var=noise_var * np.ones(rows),
                                      signal_var=signal_var, rho=rho)
        if views.amplifies_noise:  # a declared detector: the amplified noise kept out of the trajectory
            X_s = restore_trajectory(X_s, noise_var, blocks.harmonics)
        X_traj = X_s[..., None]
        residual_var = float(np.mean(post_var.sum(axis=1) / noise_var.sum()))
    if views.amplifies_noise:  # the trajectory's noise relative to the recorded samples' (noise_rms): amplified
        residual_var *= float(noise_var.sum() / (blocks.noise_variance_factor() * noise_rms**2).sum())
    V_traj = blocks.derivative(X_traj, 1)
    X_traj_kept, V_traj_kept = X_traj[..., 0], V_traj[..., 0]
    small = 3 * 8 * blocks.n_blocks * blocks.L * blocks.oversample <= FINE_GRID_MAX_BYTES
    return TipSide(
        key=key, x=x, X=X[..., 0], nuisance_block=nuisance_block, nuisance=nuisance, noise_rms=noise_rms,
        trajectory_noise=noise_rms * math.sqrt(residual_var),
        xdot_used=blocks.synthesize(V_traj)[:, 0],  # chunk by chunk into one array
        X_traj=X_traj_kept, V_traj=V_traj_kept, motion=motion,
        x_restored=crossfaded_series(blocks, X_traj, x.size) if views.amplifies_noise else None,
        steadiness=steadiness(X),
        transient_limit=transient_limit(float(np.mean(amplitude_per_block(X))), thermal_variance),
        thermal_force=(ThermalForce(k, w0, Q, fit.temperature, smoother)
                       if thermal and fit.form == "weak" and corrects_thermal_bias(fit.thermal_bias, Q) else None),
        fine_grid=FineGrid(X_traj_kept, V_traj_kept, {}, KeptColumns()) if key is not None and small else None,
    )


def _release_free_memory() -> None:
    """Hand the heap pages freed by a chunked pass back to the OS (glibc keeps freed chunk-sized temporaries
    resident: ~0.2 GB after a pass over a 1e7-sample trace). A no-op elsewhere. Called only after passes of more
    than one chunk: after a short trace's pass (a map pixel, a batch item) the next trace reuses those pages at
    once, and trimming them cost ~2,900 page faults (~5 ms) per 10^4-sample pixel."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        _MALLOC_TRIM = False
        try:
            import ctypes
            import sys

            if sys.platform.startswith("linux"):
                _MALLOC_TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            pass
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM = None


#: Largest piece np.sum is applied to in :func:`pairwise_sum` (samples).
PAIRWISE_LEAF = 1 << 17


def pairwise_sum(values, n: int, first: int = 0) -> float:
    """The sum of ``values(lo, hi)`` (a float64 array for elements lo .. hi - 1) over 0 .. n - 1, rounded
    exactly as ``np.sum`` over all n at once: NumPy sums pairwise, halving the range (at multiples of 8)
    down to 128 elements, so pieces of that same tree summed by np.sum give the same bits, without the
    array of n ever existing."""
    if n <= max(PAIRWISE_LEAF, 128):  # NumPy's own blocks (128) are not split
        return np.sum(values(first, first + n))
    half = n // 2
    half -= half % 8
    return pairwise_sum(values, half, first) + pairwise_sum(values, n - half, first + half)


def _fit_residual_sum_squares(x: np.ndarray, blocks: HarmonicBlocks, X: np.ndarray) -> float:
    """sum((x - series)^2) over the used samples, chunk by chunk (same bits as over the whole residual)."""
    L, start = blocks.L, blocks.start

    def squares(lo: int, hi: int) -> np.ndarray:
        b0 = lo // L // 8 * 8  # whole BLAS panels: the chunk's synthesis rounds like the whole trace's
        b1 = min(-(-hi // L), blocks.n_blocks)
        series = blocks.synthesize_blocks(X[b0:b1], b0)[lo - b0 * L:hi - b0 * L, 0]
        return (x[start + lo:start + hi] - series) ** 2

    return float(pairwise_sum(squares, blocks.n_blocks * L))


def _pair_mean(v: np.ndarray) -> np.ndarray:
    """Average the cos and sin rows of each harmonic (the rotation to global phase mixes them)."""
    out = v.copy()
    out[1::2] = out[2::2] = 0.5 * (v[1::2] + v[2::2])
    return out


def smoothing_variance_factor(n_blocks: int, window: int) -> float:
    """Noise variance left after :func:`smooth_across_blocks` (1 = no smoothing)."""
    impulse = np.zeros((n_blocks, 1))
    impulse[n_blocks // 2] = 1.0
    return float(np.sum(smooth_across_blocks(impulse, window) ** 2))


def with_regressor_noise(prep: Prepared, library: Library, params: dict, coef: np.ndarray) -> Prepared:
    """Row noise including the noise that the library columns inherit from the trajectory.

    The force law is evaluated on a reconstructed trajectory with rms error
    sigma_traj; the model force then errs by about k_ts(t) * sigma_traj, where
    k_ts = dF/dx is the local tip-sample stiffness. Near resonance this dwarfs
    the equation's own noise on the first harmonics (k/Q is small), so without
    it those rows would get weights they do not deserve and bias the contact
    terms (errors in variables).
    """
    import dataclasses

    eps = max(prep.trajectory_noise, 1e-15)
    p = len(library)
    keep = np.flatnonzero(coef[:p] != 0)  # only the terms of the model enter its stiffness
    model = dataclasses.replace(library, terms=[library.terms[j] for j in keep])

    # A generated kernel (afmid.kernels.termgen) takes the central difference in one pass without the columns;
    # without one (state gates), the columns at x +- eps: the same up to rounding (its docstring).
    kernel = model.term_kernel(params) if keep.size else None

    def squared_stiffness(_, x, v, t):  # (sum of squares, samples) of one chunk
        if kernel is not None:
            total = kernel.stiffness_squares(coef[keep], x, v, t, float(params["d"]), float(params["a0"]), eps)
            return total, x.size
        f_hi = _model_force(model, x + eps, v, t, params) @ coef[keep]
        f_lo = _model_force(model, x - eps, v, t, params) @ coef[keep]
        return float(np.sum(((f_hi - f_lo) / (2 * eps)) ** 2)), f_hi.size

    if keep.size:
        model.compile(params)  # once, before the chunks' threads share it
    kept_grid = prep.fine_grid is not None and prep.fine_grid.holds(prep)
    if keep.size and not kept_grid and not model.states and not model.reads_velocity():
        # The model's columns do not read the velocity: the trajectory's x alone is synthesised (half the GEMM of
        # the pass); the kernel is handed x in the velocity's place, a value no term reads (the same bits).
        def on_chunk(bounds):
            b0, b1 = bounds
            (x,) = prep.blocks.synthesize_fine_rows(prep.X_traj[b0:b1], first=b0)
            return squared_stiffness(b0, x, x, prep.blocks.fine_times(b0, b1))

        parts = _map_chunks(on_chunk, _fine_chunk_bounds(prep.blocks.n_blocks, 0))
    else:
        parts = map_fine_chunks(prep, squared_stiffness) if keep.size else []
    total, count = 0.0, 0
    for chunk_total, chunk_count in parts:
        total += chunk_total  # in chunk order: the same sum whatever the threads
        count += chunk_count
    stiffness_sq = total / max(count, 1)
    variance = prep.base_variance + prep.psi_sq * stiffness_sq * prep.trajectory_noise**2
    return dataclasses.replace(prep, row_sigma=np.sqrt(variance))




def _model_force(model: Library, x: np.ndarray, v: np.ndarray, t: np.ndarray, params: dict) -> np.ndarray:
    """The model's columns (N, k) along fine-grid rows (n, L U): one pass without the variables array when the
    model has no state gates (the same bits as ``model.evaluate`` on the raveled rows)."""
    return model.evaluate_rows(x, v, t, params)


def fine_chunks(prep: Prepared, overlap: int = 0):
    """Yield (first block, x, xdot, t) on the fine grid, (n, L U) each, chunk by chunk.

    ``overlap`` extra blocks are included at the end of each chunk (windows need the next block). With a
    :class:`FineGrid` of this trajectory at hand (:func:`with_fine_grid`) the chunks come from it (the same
    arrays, made once: callers do not write into them).
    """
    grid = prep.fine_grid
    bounds = _fine_chunk_bounds(prep.blocks.n_blocks, overlap)
    if grid is not None and grid.holds(prep):
        if bounds not in grid.chunks:  # keyed by the blocks: a trace of one chunk has the same one for any overlap
            grid.chunks[bounds] = list(_fine_chunks(prep, bounds))
        yield from grid.chunks[bounds]
        return
    yield from _fine_chunks(prep, bounds)
    if len(bounds) > 1:
        _release_free_memory()


def map_fine_chunks(prep: Prepared, work, overlap: int = 0) -> list:
    """``work(first block, x, xdot, t)`` on each chunk of :func:`fine_chunks`, in chunk order, the chunks shared among
    :func:`afmid.threads.trace_threads` threads (:func:`afmid.threads.map_in_order`): each thread synthesises the
    chunks it works on, so at most that many chunks of the fine grid exist at a time. The same results as one
    thread, in chunk order; ``work`` must only write into its own chunk's part of any shared output (and a
    library it evaluates should be compiled first, :meth:`afmid.physics.library.Library.compile`)."""
    grid = prep.fine_grid
    if grid is not None and grid.holds(prep):  # kept chunks: made once (here, in order), then shared out
        return map_in_order(lambda chunk: work(*chunk), list(fine_chunks(prep, overlap)))

    def on_chunk(bounds):
        (chunk,) = _fine_chunks(prep, (bounds,))
        return work(*chunk)

    return _map_chunks(on_chunk, _fine_chunk_bounds(prep.blocks.n_blocks, overlap))


def _map_chunks(work, bounds) -> list:
    """:func:`afmid.threads.map_in_order` over chunk ``bounds``, then the freed pages handed back when there was
    more than one chunk (:func:`_release_free_memory` says why not after one)."""
    out = map_in_order(work, bounds)
    if len(bounds) > 1:
        _release_free_memory()
    return out


def _fine_chunk_bounds(n_blocks: int, overlap: int) -> tuple[tuple[int, int], ...]:
    return tuple((b0, min(b0 + CHUNK_BLOCKS + overlap, n_blocks))
                 for b0 in range(0, n_blocks - overlap if overlap else n_blocks, CHUNK_BLOCKS))


def _fine_chunks(prep: Prepared, bounds: tuple[tuple[int, int], ...]):
    for b0, b1 in bounds:
        x, v = prep.blocks.synthesize_fine_rows(prep.X_traj[b0:b1], prep.V_traj[b0:b1], first=b0)
        yield b0, x, v, prep.blocks.fine_times(b0, b1)


#: Largest trajectory (bytes of x, xdot and t on the fine grid) that :func:`with_fine_grid` keeps in memory.
FINE_GRID_MAX_BYTES = 64 << 20


@dataclass
class FineGrid:
    """The fine-grid chunks of one trajectory (``X_traj``, ``V_traj`` of a :class:`Prepared`), made on first use
    and kept: a search that evaluates the library at many separations on one trace synthesises the trajectory
    once instead of once per evaluation (the trajectory does not depend on the library's parameters)."""

    X_traj: np.ndarray
    V_traj: np.ndarray
    chunks: dict  # the chunks' (first, stop) blocks -> [(first block, x, xdot, t)]
    #: the library's columns on this trajectory kept across fits (:class:`KeptColumns`); None: not kept
    columns: "KeptColumns | None" = None

    def holds(self, prep: Prepared) -> bool:
        """Whether this grid is ``prep``'s trajectory (a copy of ``prep`` with another trajectory is not)."""
        return self.X_traj is prep.X_traj and self.V_traj is prep.V_traj


#: Largest total of library columns (bytes) a :class:`KeptColumns` keeps.
KEPT_COLUMNS_MAX_BYTES = 128 << 20


@dataclass
class KeptColumns:
    """Library columns (weak-form integrals, :func:`afmid.fit.system.library_columns`) evaluated on one trajectory,
    kept per library and parameter set for the other fits on that trajectory. The second-mode hypotheses of the
    diagnosis's instrument search share their trajectory (:class:`TipSide`) and differ only in the equation's rows
    and their noise, so their fits evaluate the same columns at the same separations (the run's separation, a
    separation search's grid). Kept until ``max_bytes`` are held (the first evaluations: a search's grid comes
    first); the arrays are read-only."""

    max_bytes: int = KEPT_COLUMNS_MAX_BYTES
    values: dict = dataclasses.field(default_factory=dict)
    nbytes: int = 0
    hits: int = 0

    @staticmethod
    def key(library: Library, params: dict) -> tuple | None:
        """What the columns depend on beyond the trajectory: the terms, states, tip, the nonlinear parameters'
        defaults and the parameters (None when one of them cannot be a key)."""
        key = (tuple(library.terms), library.states, library.tip, tuple(sorted(library.nonlinear.items())),
               tuple(sorted(params.items())))
        try:
            hash(key)
        except TypeError:
            return None
        return key

    def get(self, key: tuple | None) -> np.ndarray | None:
        found = None if key is None else self.values.get(key)
        self.hits += found is not None
        return found

    def keep(self, key: tuple | None, theta: np.ndarray) -> None:
        if key is None or key in self.values or self.nbytes + theta.nbytes > self.max_bytes:
            return
        theta.flags.writeable = False  # shared by the fits that find it: a write would change theirs
        self.values[key] = theta
        self.nbytes += theta.nbytes


def kept_columns(prep: Prepared) -> KeptColumns | None:
    """The columns kept for ``prep``'s trajectory (:class:`KeptColumns`), or None when none are."""
    grid = prep.fine_grid
    return grid.columns if grid is not None and grid.holds(prep) else None


def with_fine_grid(prep: Prepared, max_bytes: int = FINE_GRID_MAX_BYTES) -> Prepared:
    """``prep`` with its trajectory's fine grid kept across library evaluations (:class:`FineGrid`), when the grid
    fits in ``max_bytes``; else ``prep`` itself (long records are evaluated chunk by chunk as before). The same
    values either way: only the synthesis is not repeated."""
    blocks = prep.blocks
    if prep.fine_grid is not None and prep.fine_grid.holds(prep):
        return prep  # kept already (its chunks stay)
    if 3 * 8 * blocks.n_blocks * blocks.L * blocks.oversample > max_bytes:
        return prep
    import dataclasses

    return dataclasses.replace(prep, fine_grid=FineGrid(prep.X_traj, prep.V_traj, {}))


def smooth_across_blocks(coef: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic) smoothing of each Fourier coefficient over ``window`` consecutive blocks."""
    from scipy.signal import savgol_filter

    window = min(window, coef.shape[0] - (1 - coef.shape[0] % 2))
    if window < 5:
        return coef
    return savgol_filter(coef, window, 2, axis=0, mode="interp")

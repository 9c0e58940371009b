"""The fit stage: from a deflection trace to a sparse, physically named force law.

Pipeline (each step a plain function; the CLI only wires them):
load (:func:`afmid.io.load_trace`) -> :func:`prepare` (drive frequency, blocks of
one period, Fourier coefficients, noise level, the model-free force) ->
:func:`build_system` (library columns projected like the data, whitened, factored)
-> :func:`afmid.regression.select` (sparsity path + BIC / CV) -> nonlinear
parameters (separation, decay lengths) by an outer search -> bagging for error
bars -> physical read-out -> per-sample and per-period forces -> :func:`afmid.runfile.write_run`.

:func:`run_fit` is load + :func:`prepare` + :func:`fit_prepared`. Fits of many
libraries or parameter sets on one trace (the diagnosis, force maps) prepare
it once and pass it (``run_fit(config, prepared=...)`` or :func:`fit_prepared`);
:func:`build_system`, :func:`residual_sum_squares` and :func:`library_parameters`
serve searches of their own on a prepared trace. The pieces live beside this
module: :mod:`afmid.fit_selection` (selection settings), :mod:`afmid.fit_search`
(1-D searches and search ranges of the nonlinear parameters),
:mod:`afmid.fit_forces` (error metric, read-out, forces).

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
from dataclasses import dataclass, field

import numpy as np

from .config import RunConfig
from .errors import AfmidError, ConfigError, InputError
from .instrument import deflection_views, from_config as instrument_from_config
from .io import Trace, load_trace
from .library import Library, build_library
from .physics import BOLTZMANN
from .preprocess import (HarmonicBlocks, WeakWindows, detrend, differentiate, estimate_drive, harmonic_blocks,
                         ou_smooth,
                         steadiness, weak_windows)
from . import regression
from .fit_forces import (CHUNK_BLOCKS, force_cv_error, per_sample_forces, period_curves, read_out,
                         signal_rows)
from .fit_search import NonlinearEstimate, search_1d, search_range
from .profile import GroupedProfile, ProfileResult, robust_profile
from .fit_selection import SelectionSettings
from .drive_search import DriveSearch, settle_drive_frequency
from .baseline import BaselineColumns, remove_drift
from .motion import classify as classify_motion, fit_warning as motion_warning
from .uncertainty import finish as finish_uncertainty
# Kept importable from afmid.fit, where they were defined before (bench/bench_fit.py uses term_penalties).
from .fit_forces import PERIOD_CHUNK, SIGNAL_SNR  # noqa: F401
from .fit_selection import EXHAUSTIVE_MAX_TERMS, term_penalties  # noqa: F401
# The run-file writer lives in afmid.runfile; `from afmid.fit import write_run` keeps working.
from .runfile import PERIOD_UNITS, write_run  # noqa: F401

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
    steadiness: float
    removed: dict  # detrend info
    form: str = "weak"
    strong: tuple | None = None  # (x, xdot) on the used samples from the differentiator (strong form)
    motion: object = None  # afmid.motion.Motion: periodic, period doubling or non-periodic (None: not judged)


def prepare(trace: Trace, fit, instrument=None) -> Prepared:
    """Everything about the data that the library does not change: drive, blocks, weak-form rows, noise.

    ``instrument`` (:class:`afmid.instrument.Instrument`, None: ideal) is undone per harmonic first
    (:func:`afmid.instrument.deflection_views`): the library sees the tip, the equation its single-mode twin.

    Per-sample work runs chunk by chunk (:data:`afmid.preprocess.CHUNK_BLOCKS` periods): the only arrays as
    long as the trace are the deflection, its times and the velocity kept for the per-sample forces.
    """
    t = trace.times
    x, removed = detrend(trace.deflection, t, fit.detrend)
    if trace.time is not None:
        steps = np.diff(t)
        if np.max(np.abs(steps - steps.mean())) > 1e-3 * steps.mean():
            raise AfmidError("the time column is not uniformly sampled (gaps or jitter); resample or crop it first",
                             file=trace.path, key="data.time_column")
    drive = trace.drive_for(fit.detrend) or estimate_drive(x, t, trace.drive_frequency)  # measured on loading
    spp = trace.sample_rate / drive.frequency
    oversample = fit.oversample or max(1, int(math.ceil(FINE_POINTS_PER_PERIOD / spp)))
    blocks = harmonic_blocks(x.size, trace.sample_rate, drive.frequency, t0=float(t[0]),
                             periods_per_block=fit.periods_per_block, max_harmonic=fit.max_harmonic,
                             oversample=oversample)
    if fit.detrend == "linear":  # the trajectory without the drift; the regression's columns take the rest
        x, removed["drift"] = remove_drift(x, t, blocks)
    views = deflection_views(x, blocks, instrument, trace.cantilever)
    x, x_equation = views.tip, views.equation
    windows = weak_windows(blocks)
    cl = trace.cantilever
    k, w0, Q = cl.spring_constant, cl.omega0, cl.quality_factor
    m, c = k / w0**2, k / (Q * w0)
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
    # into the next chunk). The drive columns and the rotations to global phase are made once per chunk.
    X = np.empty((blocks.n_blocks, rows, 1))
    nuisance_block = np.empty((blocks.n_blocks, rows, n_drive))
    W = windows.n_windows
    if weak:
        Y = np.empty((W, rows))
        nuisance = np.empty((W, rows, n_drive + (0 if fixed else 2)))
        minus_dpsi = -windows.dpsi
    for b0, b1 in blocks.chunks():
        lo = blocks.start + b0 * blocks.L
        n_block = (b1 - b0) * blocks.L
        hi = lo + n_block + (blocks.L + 1 if weak else 0)
        xs, cols = x[lo:hi, None], columns(t[lo:hi])
        xe = xs if x_equation is x else x_equation[lo:hi, None]
        turn = blocks.rotation(b0, b1)
        X[b0:b1] = blocks.project_blocks(xs[:n_block], b0, turn)
        nuisance_block[b0:b1] = blocks.project_blocks(cols[:n_block], b0, turn)
        w1 = min(b1, W)
        if weak and w1 > b0:
            Y[b0:w1] = -windows.integrate_samples(operator, xe, b0, w1 - b0, turn)[..., 0]
            nuisance[b0:w1, :, :n_drive] = windows.integrate_samples(windows.psi, cols, b0, w1 - b0, turn)
            if not fixed:
                nuisance[b0:w1, :, n_drive:n_drive + 1] = windows.integrate_samples(windows.psi, xs, b0, w1 - b0, turn)
                nuisance[b0:w1, :, n_drive + 1:] = windows.integrate_samples(minus_dpsi, xs, b0, w1 - b0, turn)
    del xs, xe, cols
    _release_free_memory()

    # The trajectory, the outputs and the noise level.
    V = blocks.derivative(X, 1)
    X_eq = views.equation_coefficients(X)
    Y_block = -(m * blocks.derivative(X_eq, 2) + c * blocks.derivative(X_eq, 1) + k * X_eq)[..., 0]
    used = blocks.used
    n_used = blocks.n_blocks * blocks.L
    dof = max(n_used - blocks.n_blocks * blocks.n_coef, 1)
    rss = views.residual_sum_squares if views.tip_gain is not None else _fit_residual_sum_squares(x, blocks, X)
    noise_rms = float(math.sqrt(rss / dof))
    noise_rms = max(noise_rms, 1e-9 * drive.amplitude)  # noise-free input: keep weights finite
    if not fixed:
        nuisance_block = np.concatenate([nuisance_block, X, V], axis=2)
        names += ["stiffness", "damping"]
    thermal = 2 * BOLTZMANN * fit.temperature * c / blocks.dt if fit.thermal_noise else 0.0
    strong = None
    if weak:
        # Predicted noise per row: detector noise through the operator, thermal force noise through psi.
        psi_sq = _pair_mean(np.sum(windows.psi**2, axis=1))
        detector_variance = noise_rms**2 * _pair_mean(np.sum(operator**2, axis=1))
        if views.tip_gain is not None:  # the declared instrument's inverse amplifies the noise per harmonic
            detector_variance = detector_variance * views.noise_gain(blocks.harmonics)
        base_variance = detector_variance + thermal * psi_sq
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
    block_sigma = np.sqrt(blocks.noise_variance_factor() * (thermal + k**2 * H2 * noise_rms**2))

    # The library is evaluated on a trajectory smoothed across periods: detector noise is independent from
    # period to period while the real motion wanders slowly (thermal correlation time Q / pi periods), and
    # noise in the regressors biases stiff terms low (errors in variables).
    rho = math.exp(-math.pi * blocks.L * blocks.dt * drive.frequency / Q)
    noise_var = blocks.noise_variance_factor() * noise_rms**2
    if views.tip_gain is not None:  # an undone detector amplifies the noise of each harmonic by |1 / G|
        noise_var = noise_var * np.abs(views.tip_gain[blocks.harmonics]) ** 2
    motion = classify_motion(X[..., 0], noise_var, BOLTZMANN * fit.temperature / k if fit.thermal_noise else 0.0)
    if fit.smooth_periods is not None:
        X_traj = smooth_across_blocks(X, fit.smooth_periods)
        residual_var = smoothing_variance_factor(blocks.n_blocks, fit.smooth_periods)
    elif motion is not None and motion.non_periodic:  # no one orbit to smooth towards: each period as it is
        X_traj, residual_var = X, 1.0
    else:
        X_s, post_var = ou_smooth(X[..., 0], noise_var, rho)
        X_traj = X_s[..., None]
        residual_var = float(np.mean(post_var.sum(axis=1) / noise_var.sum()))
    V_traj = blocks.derivative(X_traj, 1)
    return Prepared(
        trace=trace, x=x, t=t, drive=drive, blocks=blocks, windows=windows, X=X[..., 0],
        Y=Y, nuisance=nuisance, nuisance_names=names, row_sigma=np.sqrt(base_variance),
        base_variance=base_variance, psi_sq=psi_sq,
        Y_block=Y_block, nuisance_block=nuisance_block, block_sigma=block_sigma,
        trajectory_noise=noise_rms * math.sqrt(residual_var),
        xdot_used=blocks.synthesize(V_traj)[:, 0],  # chunk by chunk into one array
        X_traj=X_traj[..., 0], V_traj=V_traj[..., 0], noise_rms=noise_rms, steadiness=steadiness(X), removed=removed,
        form=fit.form, strong=strong, motion=motion,
    )


def _release_free_memory() -> None:
    """Hand the heap pages freed by a chunked pass back to the OS (glibc keeps freed chunk-sized temporaries
    resident: ~0.2 GB after a pass over a 1e7-sample trace). A no-op elsewhere."""
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
    total, count = 0.0, 0
    for _, x, v, t in (fine_chunks(prep) if keep.size else ()):
        f_hi = model.evaluate(x.ravel() + eps, v.ravel(), t.ravel(), params) @ coef[keep]
        f_lo = model.evaluate(x.ravel() - eps, v.ravel(), t.ravel(), params) @ coef[keep]
        total += float(np.sum(((f_hi - f_lo) / (2 * eps)) ** 2))
        count += f_hi.size
    stiffness_sq = total / max(count, 1)
    variance = prep.base_variance + prep.psi_sq * stiffness_sq * prep.trajectory_noise**2
    return dataclasses.replace(prep, row_sigma=np.sqrt(variance))




def fine_chunks(prep: Prepared, overlap: int = 0):
    """Yield (first block, x, xdot, t) on the fine grid, (n, L U) each, chunk by chunk.

    ``overlap`` extra blocks are included at the end of each chunk (windows need the next block).
    """
    B = prep.blocks.n_blocks
    for b0 in range(0, B - overlap if overlap else B, CHUNK_BLOCKS):
        b1 = min(b0 + CHUNK_BLOCKS + overlap, B)
        x, v = prep.blocks.synthesize_fine_rows(prep.X_traj[b0:b1], prep.V_traj[b0:b1], first=b0)
        yield b0, x, v, prep.blocks.fine_times(b0, b1)
    _release_free_memory()


def smooth_across_blocks(coef: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic) smoothing of each Fourier coefficient over ``window`` consecutive blocks."""
    from scipy.signal import savgol_filter

    window = min(window, coef.shape[0] - (1 - coef.shape[0] % 2))
    if window < 5:
        return coef
    return savgol_filter(coef, window, 2, axis=0, mode="interp")


# --------------------------------------------------------------------------- system
@dataclass
class System:
    params: dict  # d, a0, R, w and nonlinear parameters used
    theta: np.ndarray  # (W, rows, p) library columns in the regression's form (weak-form integrals)
    T_blocks: np.ndarray  # per-block factors of the whitened [Theta N | Y]
    protected: np.ndarray  # bool (p + n_nu)
    names: list[str]

    @property
    def n_rows(self) -> int:
        """Whitened equations behind the factors: blocks x Fourier coefficients."""
        return int(self.theta.shape[0] * self.theta.shape[1])


def build_system(prep: Prepared, library: Library, params: dict, theta: np.ndarray | None = None) -> System:
    """Library columns in the regression's form, whitened and factored per window (chunk by chunk).

    ``theta`` reuses the columns of an earlier system at the same parameters (only the row weights changed).
    """
    if theta is None:
        theta = _library_columns(prep, library, params)
    T_blocks = np.concatenate([
        regression.factor_blocks(
            np.concatenate([theta[i:i + CHUNK_BLOCKS], prep.nuisance[i:i + CHUNK_BLOCKS]], axis=2)
            / prep.row_sigma[None, :, None],
            prep.Y[i:i + CHUNK_BLOCKS] / prep.row_sigma[None, :])
        for i in range(0, theta.shape[0], CHUNK_BLOCKS)
    ])
    protected = np.zeros(theta.shape[2] + prep.nuisance.shape[2], dtype=bool)
    protected[theta.shape[2]:] = True
    return System(dict(params), theta, T_blocks, protected, library.names + prep.nuisance_names)


def _library_columns(prep: Prepared, library: Library, params: dict) -> np.ndarray:
    """The library's columns in the regression's form: weak-form integrals (windows, rows, p) or samples."""
    if prep.form == "strong":
        xs, v = prep.strong
        theta = library.evaluate(xs, v, prep.t[prep.blocks.used], params).reshape(prep.blocks.n_blocks, prep.blocks.L, -1)
        _check_finite(theta.reshape(-1, theta.shape[-1]), library, params)
        return theta
    parts = []
    for b0, x, v, t in fine_chunks(prep, overlap=1):
        # Hysteresis states scanned once: the library columns and the switching cells both use them.
        states = library.states_along(x.ravel(), v.ravel(), t.ravel(), params) if library.states else None
        fine = library.evaluate(x.ravel(), v.ravel(), t.ravel(), params, state_values=states).reshape(x.shape + (-1,))
        average_switching_cells(library, params, x, v, t, fine, states)
        _check_finite(fine.reshape(-1, fine.shape[-1]), library, params)
        parts.append(prep.windows.integrate_fine(fine, b0))
    return np.concatenate(parts, axis=0)


#: Sub-samples per fine-grid cell in which a gated term switches on or off.
SWITCH_SUBSAMPLES = 32


def average_switching_cells(library: Library, params: dict, x: np.ndarray, v: np.ndarray, t: np.ndarray,
                            fine: np.ndarray, states: np.ndarray | None = None) -> None:
    """Replace (in place) the library values on fine-grid samples whose cell holds a switching gate by cell averages.

    ``x`` (m), ``v`` (m/s), ``t`` (s) are (n, M) rows of the fine grid, each
    contiguous in time with step h; ``fine`` is (n, M, p). A gated term is
    exactly zero where its gate is false, so a term that is zero on one sample
    and not on the next switched between them. The weak form integrates with
    the rectangle rule, which would put the switch on a sample: the integral of
    a step (the in-contact adhesion constant, a meniscus) then jumps as the
    separation moves the switch across samples, the residual becomes a
    staircase in the separation and its profile is useless. Both samples take
    instead the average of the terms over their cell, from sub-samples on a
    cubic Hermite interpolation of (x, xdot): the integral becomes continuous in
    the switch time, with error O(h^2). State gates (hysteresis) are scanned
    through the cell from the state of the sample before it (``states``:
    their values along the rows, (n_states, n * M), as the library scans them).
    """
    zero = fine == 0.0
    switch = (zero[:, 1:, :] != zero[:, :-1, :]).any(axis=2)  # between samples j and j + 1
    flagged = np.zeros(x.shape, dtype=bool)
    flagged[:, :-1] |= switch
    flagged[:, 1:] |= switch
    flagged[:, 0] = flagged[:, -1] = False  # the cell needs both neighbours
    rows, cols = np.nonzero(flagged)
    if rows.size == 0:
        return
    h = float(t[0, 1] - t[0, 0])
    u = (np.arange(SWITCH_SUBSAMPLES) + 0.5) / SWITCH_SUBSAMPLES - 0.5  # offsets within the cell, in cells
    left = u < 0  # the left half of the cell lies between samples j - 1 and j
    a = cols[:, None] - left[None, :].astype(int)  # first sample of the interval holding each sub-sample
    s = np.where(left, 1.0 + u, u)[None, :]
    r = rows[:, None]
    xa, xb, va, vb = x[r, a], x[r, a + 1], v[r, a], v[r, a + 1]
    s2, s3 = s * s, s * s * s
    xs = (2 * s3 - 3 * s2 + 1) * xa + (s3 - 2 * s2 + s) * h * va + (3 * s2 - 2 * s3) * xb + (s3 - s2) * h * vb
    vs = (6 * s2 - 6 * s) * (xa - xb) / h + (3 * s2 - 4 * s + 1) * va + (3 * s2 - 2 * s) * vb
    ts = t[rows, cols][:, None] + u[None, :] * h
    states = None
    sub_states = None
    if library.states:  # scanned through the cell from the state of the sample before it
        if states is None:
            states = library.states_along(x.ravel(), v.ravel(), t.ravel(), params)
        along = states.reshape(-1, *x.shape)
        sub_states = library.states_from(along[:, rows, cols - 1], xs, vs, ts, params)
    sub = library.evaluate(xs.ravel(), vs.ravel(), ts.ravel(), params, state_values=sub_states)
    fine[rows, cols, :] = sub.reshape(rows.size, SWITCH_SUBSAMPLES, -1).mean(axis=1)


def _check_finite(columns: np.ndarray, library: Library, params: dict) -> None:
    if np.isfinite(columns.sum(axis=0)).all():  # cheap: a sum is finite only if every term is (barring overflow)
        return
    finite = np.isfinite(columns).all(axis=0)
    if not finite.all():
        bad = [library.terms[j].name for j in np.flatnonzero(~finite)]
        raise AfmidError(
            f"library terms {bad} are not finite along the trajectory at separation {params['d'] * 1e9:.3f} nm "
            "(a term singular in contact? gate it, e.g. [z > a0] * ...)",
            key="model",
        )


def residual_sum_squares(system: System, mask: np.ndarray | None = None) -> float:
    """Weighted residual sum of squares (dimensionless: rows are whitened) of the least-squares fit of ``system``
    on the columns ``mask`` selects (None: all columns, library and nuisance)."""
    T = regression.combine(system.T_blocks)
    mask = np.ones(T.shape[1] - 1, dtype=bool) if mask is None else mask
    return regression.subset_fit(T, mask)[1]


# --------------------------------------------------------------------------- nonlinear search
def profile_parameter(prep: "Prepared", library: Library, params: dict, name: str, bounds: tuple[float, float],
                      mask: np.ndarray | None, jackknife: bool = True) -> ProfileResult:
    """Profile the weighted residual over one nonlinear parameter (the others held): :class:`ProfileResult`.

    ``mask`` selects the columns (None: all). The minimum, its chi-square
    interval and the block jackknife of the minimum (``jackknife``: the
    honest sigma; off for quick refits) are :func:`afmid.profile.robust_profile`'s.
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
    from .config import ModelConfig

    physics = build_library(ModelConfig(effects=list(library.effects)), config.source)
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
    force_direct: np.ndarray  # N per input sample, model-free (band-limited)
    periods: dict[str, np.ndarray]
    warnings: list[str] = field(default_factory=list)
    drive_search: DriveSearch | None = None  # the drive frequency searched by the regression (transient records)
    force_calibration_uncertainty: float = 0.0  # relative, 1 sigma: the force's share of the k / Q calibration
    model_limited: bool = False  # cv_error above its noise floor: parameters biased beyond their error bars

    @property
    def selected(self) -> np.ndarray:
        return self.selection.best.mask

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

    The sample's a0, the measured drive frequency ``w`` (rad/s), the tip radius
    ``R`` when the cantilever has one, and the library's nonlinear parameters at
    their defaults or fixed values. The rest separation ``d`` is not included:
    the outer search (or ``sample.separation``) sets it.
    """
    params = {"a0": config.sample.a0, "w": prep.drive.omega}
    if prep.trace.cantilever.tip_radius is not None:
        params["R"] = prep.trace.cantilever.tip_radius
    params.update(library.nonlinear)
    return params


def first_contact(prep: Prepared, a0: float) -> float:
    """Separation at which the lowest turning point just touches (z_min = a0), m."""
    x_max = float(np.max(prep.blocks.synthesize(prep.X[..., None])[:, 0]))
    return x_max + a0


def estimate_nonlinear(prep, library, config, params, progress=None, physics=None) -> dict[str, NonlinearEstimate]:
    """Coarse outer search over the rest separation and the library's decay lengths.

    The objective is the residual of the profile library (:func:`profile_library`: the run's catalog
    effects, all their terms; ``physics`` = its (library, extra parameters) when already built);
    :func:`run_fit` then refines each on its profile.
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
            span = search_range(library, name)
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
            best, grid, values = search_1d(objective, lo_r, hi_r, n_grid, log_scale)
            if name in zero_allowed and objective(0.0) <= min(objective(best), float(np.min(values))):
                best = 0.0
            params[name] = best
            estimates[name] = NonlinearEstimate(name, best, math.nan, unit, True, grid, values,
                                                (0.0 if name in zero_allowed else lo, hi))
            if progress:
                progress.update(1)
    return estimates


def run_fit(config: RunConfig, progress: bool = False, trace: Trace | None = None, uncertainty: bool = True,
            prepared: Prepared | None = None) -> FitResult:
    """Fit the trace named by ``config`` (or ``trace``) and return everything the run file holds.

    ``uncertainty=False`` skips the error bars (bootstrap, profile widths of the
    nonlinear parameters and their propagation): for quick comparative refits.
    ``prepared`` is :func:`prepare` of the trace with ``config.fit`` done once
    and shared by fits of other libraries or parameters on the same trace (it
    is never modified); its trace is the one fitted.
    """
    if prepared is not None:
        if trace is not None and trace is not prepared.trace:
            raise ValueError("run_fit: `trace` is not the trace `prepared` was made from")
        trace = prepared.trace
    elif trace is None:
        trace = load_trace(config)
    library = build_library(config.model, config.source)
    if len(library) == 0:
        raise ConfigError("the library is empty: list effects, a preset or terms", file=config.source, key="model")
    prep = prepared if prepared is not None else prepare(trace, config.fit, instrument_from_config(config))
    return fit_prepared(prep, library, config, progress=progress, uncertainty=uncertainty)


def fit_prepared(prep: Prepared, library: Library, config: RunConfig, progress: bool = False,
                 uncertainty: bool = True) -> FitResult:
    """Fit ``library`` to a prepared trace (:func:`prepare` with ``config.fit``): the fit after the preparation.

    ``config`` gives the sample (a0, a fixed separation), fixed model parameters
    and the fit settings; ``config.model`` is not read (``library`` is fitted).
    ``prep`` is not modified, so one preparation serves fits of many libraries
    and parameter sets. ``uncertainty`` as in :func:`run_fit`.
    """
    from tqdm import tqdm

    fit = config.fit
    trace = prep.trace
    # Defects were detected and reported when the trace was loaded (afmid.defects); keep them with the run.
    warnings = [f"{f.severity}: {f.message}" for f in trace.findings if f.severity != "error"]
    if prep.motion is not None and prep.motion.non_periodic:
        warnings.append(motion_warning(prep.motion, prep.noise_rms))
    params = library_parameters(prep, config, library)
    bar = tqdm(total=4, desc="fit", disable=not progress, leave=False)
    physics, extra = profile_library(library, config)
    nonlinear = estimate_nonlinear(prep, library, config, params, physics=(physics, extra))

    def factors_at(p: Prepared):  # the profile library's columns at the current parameters, held
        trial = dict(params, **extra)
        theta = _library_columns(p, physics, trial)
        return lambda q: build_system(q, physics, trial, theta=theta).T_blocks

    def estimate_again(p: Prepared) -> None:
        nonlinear.update(estimate_nonlinear(p, library, config, params, physics=(physics, extra)))

    prep, drive_search = settle_drive_frequency(prep, fit.drive_frequency, fit.seed, factors_at,
                                                estimate_again if nonlinear else None)
    bar.update(1)
    settings = SelectionSettings.for_library(fit, library, len(prep.nuisance_names))
    system = build_system(prep, library, params)
    selection = settings.select(system)
    chosen = selection.best.mask
    # Second pass: weights that include the regressors' own noise, then select again.
    coef0, _ = regression.subset_fit(regression.combine(system.T_blocks), chosen)
    prep = with_regressor_noise(prep, library, params, coef0)
    system = build_system(prep, library, params, theta=system.theta)  # same columns, new row weights
    selection = settings.select(system)
    chosen = selection.best.mask
    # Refine the nonlinear parameters on the profile of the chosen support, then re-select once; the
    # profile's width is their uncertainty (propagated into the read-out below).
    if nonlinear:
        def profile(name, est, mask):
            # A preset is profiled with all the terms of its catalog effects.
            return profile_parameter(prep, physics, dict(params, **extra), name, est.bounds,
                                     mask if physics is library else None, jackknife=uncertainty)

        profiled = {}
        for name, est in nonlinear.items():
            found = profile(name, est, chosen)
            params[name] = found.value
            profiled[name] = found.sigma
        support = chosen
        system = build_system(prep, library, params)
        selection = settings.select(system)
        chosen = selection.best.mask
        for name, est in nonlinear.items():
            est.value = params[name]
            if uncertainty:
                # The profile of the final support (the first one's when the support did not change).
                same = np.array_equal(chosen, support) or physics is not library
                est.sigma = profiled[name] if same else profile(name, est, chosen).sigma
    bar.update(1)
    T = regression.combine(system.T_blocks)
    coef, _ = regression.subset_fit(T, chosen)
    bagging = None
    coef_std = np.zeros_like(coef)
    ci_low, ci_high = coef.copy(), coef.copy()
    inclusion = chosen.astype(float)
    for name, est in nonlinear.items():
        est.value = params[name]
    if fit.bootstrap > 0 and uncertainty:
        rng = np.random.default_rng(fit.seed)
        bagging = settings.bag(system, chosen, fit.bootstrap, rng)
        coef_std = bagging.coef_samples.std(axis=0, ddof=1)
        ci_low, ci_high = np.percentile(bagging.coef_samples, [2.5, 97.5], axis=0)
        inclusion = bagging.inclusion
    bar.update(1)
    rows = signal_rows(prep, system, coef)
    cv_error, per_fold, noise_floor = force_cv_error(prep, system, chosen, rows, fit.folds)
    try:
        refuse_unusable(trace, library, coef[:len(library)], cv_error)
    except AfmidError:
        bar.close()  # the error line must not land on the progress bar's line
        raise
    quantities = read_out(library, coef, bagging, params, chosen, trace)
    if uncertainty:
        propagate_nonlinear(quantities, nonlinear, prep, library, params, chosen, trace)
    force_calibration, limited = finish_uncertainty(quantities, warnings, prep, library, system, coef, chosen, params,
                                                    trace, config, cv_error, noise_floor, read_out, uncertainty)
    force_estimate, force_direct = per_sample_forces(prep, library, system, coef, rows)
    periods = period_curves(prep, library, system, coef, params, rows, fit.phase_points)
    bar.update(1)
    bar.close()
    for name, est in nonlinear.items():
        log.debug("estimated %s = %.4g ± %.2g %s", name, est.value, est.sigma, est.unit)
    return FitResult(config, prep, library, system, selection, coef, coef_std, ci_low, ci_high, inclusion, bagging,
                     nonlinear, quantities, cv_error, per_fold, noise_floor, rows, force_estimate, force_direct, periods,
                     warnings, drive_search, force_calibration, limited)


def refuse_unusable(trace: Trace, library: Library, coef: np.ndarray, cv_error: float) -> None:
    """Stop (InputError, nothing written) when the fit has no result afmid can stand behind.

    A NaN error metric means no drive harmonic of the model-free force stood out of the noise on the
    held-out periods: there was no tip-sample force to identify, and the coefficients only describe noise.
    """
    bad = [name for name, c in zip(library.names, coef) if not math.isfinite(c)]
    if bad:
        raise InputError(f"the fit's coefficients are not finite for {', '.join(bad)}: the library columns are "
                         "degenerate on this trace; nothing was written", file=trace.path, key="model")
    if not math.isfinite(cv_error):
        raise InputError("the fit has no usable result: its cross-validated error is NaN because no harmonic of "
                         "the model-free tip-sample force stands above the noise (the tip does not reach the sample, "
                         "or this is not a tapping trace); nothing was written", file=trace.path, key="data.path")


def propagate_nonlinear(quantities: dict, nonlinear: dict, prep, library, params, mask, trace) -> None:
    """Add the uncertainty of estimated nonlinear parameters (separation, decay lengths) to the quantities.

    The bootstrap holds them fixed; refitting at +-1 sigma of each and reading
    out again gives the sensitivity, added in quadrature to the error and to
    both halves of the 95 % interval (in place).
    """
    extra = {k: 0.0 for k in quantities}
    for name, est in nonlinear.items():
        if not math.isfinite(est.sigma) or est.sigma <= 0:
            continue
        shifted = []
        for sign in (1, -1):
            trial = dict(params, **{name: params[name] + sign * est.sigma})
            try:
                system = build_system(prep, library, trial)
            except AfmidError:
                break
            coef, _ = regression.subset_fit(regression.combine(system.T_blocks), mask)
            shifted.append(read_out(library, coef, None, trial, mask, trace))
        if len(shifted) == 2:
            for k in quantities:
                delta = 0.5 * (shifted[0].get(k, {}).get("value", math.nan) - shifted[1].get(k, {}).get("value", math.nan))
                if math.isfinite(delta):
                    extra[k] += delta**2
    for k, q in quantities.items():
        if extra[k] > 0:
            q["error"] = math.sqrt((q["error"] if math.isfinite(q["error"]) else 0.0) ** 2 + extra[k])
            half = 1.96 * math.sqrt(extra[k])
            lo, hi = q["ci_low"], q["ci_high"]
            if math.isfinite(lo) and math.isfinite(hi):
                q["ci_low"] = q["value"] - math.hypot(q["value"] - lo, half)
                q["ci_high"] = q["value"] + math.hypot(hi - q["value"], half)
            else:
                q["ci_low"], q["ci_high"] = q["value"] - half, q["value"] + half


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

        from .config import validation_error

        if isinstance(exc, ValidationError):
            err = validation_error(exc, config.source)
            raise ConfigError(err.message.replace("unknown effect", "--add: unknown effect"), file=config.source,
                              key="model.effects") from None
        raise

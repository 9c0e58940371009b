"""What a fit says about the force: the error metric, the read-out of physical quantities, and the forces
per input sample and per period.

Everything here works on a finished fit (a prepared trace, its system, the
chosen coefficients); :func:`afmid.fit.pipeline.fit_prepared` calls these in turn.
Forces in N, positive repulsive.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

import afmid.fit.regression as regression
from afmid.io.trace import Trace, create_dataset, write_dataset
from afmid.physics.library import Library
from afmid.physics.effects import EFFECTS
from afmid.physics.tips import shaped_effect
from afmid.fit.inband_noise import excess_variance
from afmid.fit.prepare import CHUNK_BLOCKS
from afmid.threads import map_in_order

if TYPE_CHECKING:  # annotations only
    from afmid.fit.prepare import Prepared
    from afmid.fit.system import System

#: A harmonic counts as signal in the error metric when its mean exceeds this many noise sigmas per block.
SIGNAL_SNR = 1.0


# --------------------------------------------------------------------------- error metric
def inverted_force_coefficients(prep: Prepared, system: System, coef: np.ndarray, blocks: slice = slice(None)
                               ) -> np.ndarray:
    """The inverted force F_ts per period (B, 2K+1): the drive minus (m x'' + c x' + k x) (``blocks``: of those).

    The drive is the fitted one (``coef``'s drive columns: then F_ts depends on the force model) or, with a
    calibrated drive (:mod:`afmid.fit.declared_drive`), the declared one already in ``Y_block``."""
    p = system.theta.shape[2]
    Y = prep.Y_block[blocks]
    if "stiffness" in prep.nuisance_names:  # free cantilever: the identified k, c replace the calibrated ones
        Y = -(prep.trace.cantilever.mass * prep.blocks.derivative(prep.X[blocks, :, None], 2))[..., 0]
    return Y - np.einsum("bkm,m->bk", prep.nuisance_block[blocks], coef[p:])


def signal_rows(prep: Prepared, system: System, coef: np.ndarray) -> np.ndarray:
    """Rows whose mean inverted force stands above the per-block noise."""
    F = inverted_force_coefficients(prep, system, coef)
    mean = np.abs(F.mean(axis=0))
    harmonics = prep.blocks.harmonics
    # coloured detector noise: each harmonic's noise raised by its rows' measured excess (the same deflection
    # noise at that harmonic, through the weak form's operator instead of the per-period one)
    rows = mean > SIGNAL_SNR * prep.block_sigma * np.sqrt(row_noise_excess(prep))
    # Keep cos/sin of a harmonic together.
    for n in np.unique(harmonics[rows]):
        rows[harmonics == n] = True
    return rows


def at_numerical_floor(prep: Prepared) -> bool:
    """The record is noise-free: its noise level is the preparation's floor (1e-9 of the amplitude)."""
    return bool(prep.noise_rms <= 1e-9 * prep.drive.amplitude * (1.0 + 1e-9))


def row_noise_excess(prep: Prepared) -> np.ndarray:
    """The factor (>= 1) by which each weak-form row's noise variance, as measured across the record's periods,
    exceeds ``prep.row_sigma``'s prediction (:func:`afmid.fit.inband_noise.excess_variance`; ones for white
    noise)."""
    return excess_variance(prep.Y, prep.row_sigma**2, prep.blocks.harmonics, noise_free=at_numerical_floor(prep))


def _power(F: np.ndarray, harmonics: np.ndarray) -> np.ndarray:
    """Mean-square value of series with coefficients F (..., 2K+1) (Parseval)."""
    w = np.where(harmonics == 0, 1.0, 0.5)
    return np.sum(w * F**2, axis=-1)


class CrossValidatedError(NamedTuple):
    """The cross-validated force error (:func:`force_cv_error`): relative RMS, each fold's, the noise floor (the
    error a right model shows at this noise) and the floor's effective degrees of freedom (the per-fit threshold
    of afmid.fit.uncertainty.floor_threshold; NaN: not known, the one factor applies)."""

    error: float
    folds: np.ndarray
    floor: float
    floor_dof: float


class FoldErrors:
    """The cross-validated force error summed over held-out folds (:func:`force_cv_error`; the joint fit's
    per-trace error uses the same sums): per fold the misfit |F_free - F_model|^2, the signal |F_free - mean|^2
    and the expected noise (N^2, Parseval over the drive harmonics), over the rows where the held-out average
    stands 3 sigma above its noise (cos and sin of a harmonic together)."""

    def __init__(self, harmonics: np.ndarray):
        self.harmonics = harmonics
        self.misfit = self.signal = self.noise = 0.0
        self.noise_squares = 0.0  # sum over the rows of (their noise term)^2: the floor's degrees of freedom
        self.per_fold: list[float] = []

    def add(self, free: np.ndarray, model: np.ndarray, sigma: np.ndarray, held_out: np.ndarray,
            rows: np.ndarray) -> None:
        """One held-out fold: ``free`` and ``model`` its averaged force coefficients (N), ``sigma`` the noise of
        their difference, ``held_out`` that of ``free`` alone, ``rows`` the signal rows of the fit."""
        harmonics = self.harmonics
        keep = rows & (np.abs(free) > 3 * held_out)
        for n in np.unique(harmonics[keep]):  # cos and sin of a harmonic together
            keep[harmonics == n] = True
        h = harmonics[keep]
        ac = np.where(h == 0, 0.0, free[keep])
        misfit, signal = _power((free - model)[keep], h), _power(ac, h)
        self.per_fold.append(math.sqrt(misfit / signal) if signal > 0 else math.nan)
        self.misfit += misfit
        self.signal += signal
        self.noise += _power(sigma[keep], h)
        self.noise_squares += float(np.sum((np.where(h == 0, 1.0, 0.5) * sigma[keep] ** 2) ** 2))

    @property
    def floor_dof(self) -> float:
        """The effective degrees of freedom of error^2 / floor^2 for a right model (Satterthwaite): the misfit is
        sum_i w_i r_i^2 with r_i ~ N(0, sigma_i^2) per kept row, so (sum w sigma^2)^2 / sum (w sigma^2)^2
        (NaN where no row was kept)."""
        return self.noise**2 / self.noise_squares if self.noise_squares > 0 else math.nan

    def result(self) -> "CrossValidatedError":
        """(error, error of each fold, noise floor, the floor's degrees of freedom); NaN where no held-out row
        carried signal."""
        if self.signal <= 0:
            return CrossValidatedError(math.nan, np.asarray(self.per_fold), math.nan, math.nan)
        return CrossValidatedError(math.sqrt(self.misfit / self.signal), np.asarray(self.per_fold),
                                   math.sqrt(self.noise / self.signal), self.floor_dof)


def force_cv_error(prep: Prepared, system: System, mask: np.ndarray, rows: np.ndarray,
                   folds: int) -> CrossValidatedError:
    """Normalised cross-validated force error over held-out periods (0 = perfect, 1 = a constant force).

    For each fold of contiguous periods the model is refitted on the other
    periods. On the held-out periods, averaged like the paper averages periods,
    the model force is compared with the inverted force
    F_ts = drive - (m x'' + c x' + k x) on the drive harmonics where that
    average stands 3 sigma above its noise:
    error^2 = sum |F_free - F_model|^2 / sum |F_free - mean(F_free)|^2
    (Parseval over harmonics, summed over folds). Returns the error, the error
    of each fold, and the noise floor: the error a perfect model would show,
    i.e. the expected noise in that same sum: the held-out periods' noise plus
    that of the model fitted on the other periods (docs/diagnosis.md, "The noise
    floor and its threshold"), and the floor's effective degrees of freedom.
    """
    if prep.form == "strong":
        return _time_domain_cv_error(prep, system, mask, folds)
    errors = FoldErrors(prep.blocks.harmonics)
    p = system.theta.shape[2]
    excess = row_noise_excess(prep)  # coloured detector noise: the rows' noise as measured, not as predicted
    for test in regression.fold_slices(system.T_blocks.shape[0], folds):
        train = regression.training_blocks(system.T_blocks.shape[0], test)
        trained = regression.combine(system.T_blocks[train])
        coef, _ = regression.subset_fit(trained, mask)
        free = (prep.Y[test] - np.einsum("bkm,m->bk", prep.nuisance[test], coef[p:])).mean(axis=0)
        model = np.einsum("bkm,m->bk", system.theta[test], coef[:p]).mean(axis=0)
        # The error's noise: the held-out periods' own, plus the noise of the model fitted on the other periods.
        columns = np.concatenate([system.theta[test].mean(axis=0), prep.nuisance[test].mean(axis=0)], axis=1)
        held_out = prep.row_sigma / math.sqrt(test.size) * np.sqrt(excess)  # x 1.0 exactly for white noise
        sigma = np.sqrt(held_out**2 + excess * prediction_variance(trained, mask, columns))
        errors.add(free, model, sigma, held_out, rows)
    return errors.result()


def prediction_variance(trained: np.ndarray, mask: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Variance of ``columns @ coef`` (one value per row of ``columns``, (rows, all columns)) when coef is the
    least-squares fit on the ``mask`` columns of the whitened factor ``trained`` ([columns | y], unit noise).

    Columns are scaled to unit norm and singular values below 1e-12 of the largest dropped, as the subset fit
    does (SI columns differ by tens of orders of magnitude).
    """
    active = np.flatnonzero(mask)
    if active.size == 0:
        return np.zeros(columns.shape[0])
    A = trained[:, active]
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = 1.0
    _, s, vt = np.linalg.svd(A / norms, full_matrices=False)
    keep = s > 1e-12 * s[0]
    projected = ((columns[:, active] / norms) @ vt[keep].T) / s[keep]
    return np.sum(projected**2, axis=1)


def _time_domain_cv_error(prep: Prepared, system: System, mask: np.ndarray, folds: int):
    """The strong form's error: per-sample force on held-out periods (no noise floor is predicted)."""
    p = system.theta.shape[2]
    num = den = 0.0
    per_fold = []
    for test in regression.fold_slices(system.T_blocks.shape[0], folds):
        train = regression.training_blocks(system.T_blocks.shape[0], test, gap=0)
        coef, _ = regression.subset_fit(regression.combine(system.T_blocks[train]), mask)
        free = prep.Y[test] - np.einsum("bkm,m->bk", prep.nuisance[test], coef[p:])
        model = np.einsum("bkm,m->bk", system.theta[test], coef[:p])
        n_f, d_f = float(np.sum((free - model) ** 2)), float(np.sum((free - free.mean()) ** 2))
        per_fold.append(math.sqrt(n_f / d_f) if d_f > 0 else math.nan)
        num += n_f
        den += d_f
    return CrossValidatedError(math.sqrt(num / den) if den > 0 else math.nan, np.asarray(per_fold), math.nan, math.nan)


# --------------------------------------------------------------------------- read-out
def read_out(library: Library, coef, bagging, params: dict, mask, trace: Trace,
             with_sources: bool = False) -> dict[str, dict]:
    """Physical quantities of each effect from its terms' coefficients, with bootstrap intervals.

    ``with_sources``: also record each read-out's ``sources`` (the selected terms it is computed from, by a probe
    of one extra read-out per selected term). Only the final fit's read-outs need them (the plausibility check
    counts the independent terms behind implausible values); the read-outs of resamples and propagations, made
    many times per fit, leave them out."""
    out: dict[str, dict] = {}
    ctx = dict(params)
    if "R" not in ctx:
        ctx["R"] = math.nan
    for effect_name in library.effects:
        effect = shaped_effect(EFFECTS.get(effect_name), library.tip)  # E* read out with the tip's contact law
        index = {t.label: j for j, t in enumerate(library.terms) if t.effect == effect_name}
        if not index:
            continue

        def quantities(c):
            values = {label: (c[j] if mask[j] else 0.0) for label, j in index.items()}
            values.update({t.label: 0.0 for t in effect.terms if t.label not in values})
            with np.errstate(all="ignore"):
                try:
                    return effect.readout(values, ctx)
                except (ZeroDivisionError, ValueError):
                    return {q.name: math.nan for q in effect.quantities}

        central = quantities(coef)
        samples = [quantities(c) for c in bagging.coef_samples] if bagging is not None else []
        sources = _sources(quantities, central, coef, index, mask) if with_sources else None
        for q in effect.quantities:
            value = float(central.get(q.name, math.nan))
            arr = np.array([s.get(q.name, math.nan) for s in samples], dtype=float)
            arr = arr[np.isfinite(arr)]
            err = float(arr.std(ddof=1)) if arr.size > 2 else math.nan
            lo, hi = (np.percentile(arr, [2.5, 97.5]) if arr.size > 2 else (math.nan, math.nan))
            key = q.name if q.name not in out else f"{effect_name}.{q.name}"
            out[key] = {"value": value, "error": err, "ci_low": float(lo), "ci_high": float(hi), "unit": q.unit,
                        "effect": effect_name, "doc": q.doc, "tip_radius": float(ctx["R"])}
            if sources is not None:
                out[key]["sources"] = sources.get(q.name, ())
    return out


def _sources(quantities, central: dict, coef, index: dict[str, int], mask) -> dict[str, tuple[str, ...]]:
    """For each read-out of an effect, the selected terms whose coefficient it is computed from (labels, sorted):
    each selected coefficient is moved by 0.1 % and the read-outs that change depend on it. Read-outs of the same
    single coefficient (H, the adhesion and the surface energy of DMT's van der Waals term) are one piece of
    evidence, not several (afmid.fit.plausibility.spring_constant_cause counts the terms)."""
    out: dict[str, set[str]] = {}
    for label, j in index.items():
        if not mask[j] or not np.isfinite(coef[j]) or coef[j] == 0:
            continue
        moved = np.array(coef, dtype=float, copy=True)
        moved[j] *= 1.001
        for name, value in quantities(moved).items():
            before = central.get(name, math.nan)
            if np.isfinite(value) and np.isfinite(before) and value != before:
                out.setdefault(name, set()).add(label)
    return {name: tuple(sorted(labels)) for name, labels in out.items()}


# --------------------------------------------------------------------------- forces
def per_sample_forces(prep: Prepared, library: Library, system: System, coef: np.ndarray, rows: np.ndarray):
    """Model force on every used sample and the band-limited inverted force (N; NaN elsewhere)."""
    n = prep.x.size
    estimate = model_force_samples(prep, library, system, coef)
    L = prep.blocks.L
    used = prep.blocks.used
    inverted = np.full(n, np.nan)

    def synthesize(bounds: tuple[int, int]) -> None:  # one chunk of blocks, into its own samples
        b0, b1 = bounds
        F = inverted_force_coefficients(prep, system, coef, slice(b0, b1)) * rows[None, :]
        inverted[used.start + b0 * L:used.start + b1 * L] = prep.blocks.synthesize_blocks(F[..., None], b0)[:, 0]

    map_in_order(synthesize, prep.blocks.chunks())
    return estimate, inverted


def estimated_peak(force_estimate: np.ndarray) -> tuple[np.ndarray, float]:
    """(the samples where ``force_estimate`` (N) is estimated, its largest |value| there, N; 0 if none): what the
    force's relative uncertainties are an RMS over and relative to."""
    used = np.isfinite(force_estimate)
    if not used.any():
        return used, 0.0
    values = force_estimate[used]
    return used, float(np.max(np.abs(values, out=values)))  # in place: one temporary as long as the trace, not two


def model_force_samples(prep: Prepared, library: Library, system: System, coef: np.ndarray) -> np.ndarray:
    """The model force (N) with coefficients ``coef`` on every used sample (NaN elsewhere), at the parameters
    of ``system``."""
    estimate = np.full(prep.x.size, np.nan)
    p = system.theta.shape[2]

    def fill(where, cols):
        estimate[where] = cols @ coef[:p]

    map_library_pieces(prep, library, system, fill)
    return estimate


def model_force_spread(prep: Prepared, library: Library, system: System, coef_samples: np.ndarray) -> np.ndarray:
    """The standard deviation (N) of the model force over the rows of ``coef_samples`` (resampled coefficient
    vectors, e.g. the bootstrap's) on every used sample (NaN elsewhere), at the parameters of ``system``."""
    spread = np.full(prep.x.size, np.nan)
    p = system.theta.shape[2]
    samples = np.asarray(coef_samples, dtype=float)[:, :p]
    if samples.shape[0] < 2:
        return spread

    def fill(where, cols):
        spread[where] = (cols @ samples.T).std(axis=1, ddof=1)

    map_library_pieces(prep, library, system, fill)
    return spread


def map_library_pieces(prep: Prepared, library: Library, system: System, work) -> list:
    """``work(slice of the input samples, the library's columns there)`` over every used sample, piece by piece,
    the pieces shared among :func:`afmid.threads.trace_threads` threads (results in the pieces' order; ``work``
    writes only into its own slice of any shared output)."""
    used = prep.blocks.used
    # Behind a declared detector, the restored tip (the inverted samples carry the noise times |1/G|).
    x_used = (prep.x if prep.x_restored is None else prep.x_restored)[used]
    t_used = prep.t[used]
    L = prep.blocks.L
    # Pieces of CHUNK_BLOCKS periods (hysteresis states are scanned along each): small enough that the threads'
    # pieces in flight add little to the peak memory (~13 MB each at 200 samples per period; pieces of 2,048
    # periods took ~0.1 GB each) and that their temporaries are reused from the heap instead of being mapped
    # afresh (page faults); the library is compiled once for all of them (a compilation costs ~3 ms).
    step = CHUNK_BLOCKS * L
    library.compile(system.params)  # once, before the threads share it

    def on_piece(i: int):
        sl = slice(i, i + step)
        cols = library.evaluate_rows(x_used[sl], prep.xdot_used[sl], t_used[sl], system.params)
        return work(slice(used.start + i, used.start + i + cols.shape[0]), cols)

    return map_in_order(on_piece, range(0, x_used.size, step))


#: Periods per chunk in :func:`period_curves` and when its curves are evaluated (bounds the temporaries). A
#: multiple of 8, and every evaluation starts at a multiple of it: the BLAS products then round the same way
#: whenever a curve is evaluated (the summaries, the mapping, the run file agree to the bit).
PERIOD_CHUNK = 2048
#: Periods per piece of the per-period summaries in :func:`period_curves`: a divisor of :data:`PERIOD_CHUNK` (its
#: pieces start where the curves' do, so they round alike). Smaller than the curves' pieces so that two threads'
#: temporaries (~10 MB each at 256 phase points) stay small and are reused from the heap, not mapped afresh: at
#: 2,048 periods each piece took ~0.1 GB, and mapping it cost ~0.4 s of page faults at 5e4 periods.
SUMMARY_CHUNK = 256


def period_curves(prep: Prepared, library: Library, system: System, coef, params, rows, n_phase: int,
                  keep_curves: bool = False) -> "PeriodCurves":
    """Per-period curves on a common phase grid and per-period summaries (SI), chunk by chunk of periods.

    Returns a read-only mapping name -> array (:class:`PeriodCurves`): the summaries are computed here, the
    curves (periods x phase points each) when asked for or written. ``keep_curves``: a record of one piece
    (at most :data:`SUMMARY_CHUNK` periods) keeps the curves the summaries were made from (deflection, velocity,
    the model and inverted forces; <= 2 MB at 256 phase points), so that a caller reading them right away (a map
    pixel's residual signature, afmid.maps.residual) does not evaluate them again (the same values).
    """
    curves = PeriodCurves(prep, library, system, coef, params, rows, n_phase)
    B = prep.blocks.n_blocks
    period = 2 * np.pi / prep.drive.omega
    dt = period / n_phase
    d, a0 = params["d"], params["a0"]
    held = {name: np.empty(B) for name in PeriodCurves.SUMMARIES}
    # Hysteresis gates are scanned along the evaluated points: in one piece, as the states need (and kept).
    step = B if library.states else min(SUMMARY_CHUNK, PERIOD_CHUNK)
    library.compile(params)  # once, before the chunks' threads share it

    def summarise(b0: int) -> None:  # one chunk of periods, into its rows of `held`
        b1 = min(b0 + step, B)
        x, v, f_inverted = (curves.curve(name, b0, b1) for name in ("deflection", "velocity", "force_inverted"))
        f = curves.model_force(x, v, b0, b1)
        if library.states:
            held["force_model"] = f
        if keep_curves and b0 == 0 and b1 == B:
            curves.kept.update(deflection=x, velocity=v, force_inverted=f_inverted, force_model=f)
        z = d - x
        zdot = -v
        contact = z <= a0
        out = {
            "peak_force": f.max(axis=1),
            "adhesion_force": np.maximum(-f.min(axis=1), 0.0),
            "max_indentation": np.maximum(a0 - z, 0.0).max(axis=1),
            "contact_time": contact.mean(axis=1) * period,
            # energy taken from the tip per period: -closed integral of F dz
            "dissipated_energy": -np.sum(f * zdot, axis=1) * dt,
            "dissipated_energy_inverted": -np.sum(f_inverted * zdot, axis=1) * dt,
            # (1/T) integral of (force toward the sample) * x dt
            "virial": -np.mean(f * x, axis=1),
            "virial_inverted": -np.mean(f_inverted * x, axis=1),
            "period_error": np.sqrt(np.mean((f_inverted - f) ** 2, axis=1)),
        }
        for name, value in out.items():
            held[name][b0:b1] = value

    map_in_order(summarise, range(0, B, step))
    held["amplitude"] = np.hypot(prep.X[:, 1], prep.X[:, 2])
    curves.held.update(held)
    return curves


class PeriodCurves(Mapping):
    """The outputs of :func:`period_curves`: a read-only mapping name -> array, in the run file's order.

    The per-period summaries are held. The curves on the phase grid
    (deflection, velocity, acceleration, separation, the model and inverted
    forces: (periods, phase points) each, 0.1 GB apiece at 5e4 periods) are
    evaluated from the coefficients the fit keeps anyway when asked for, and
    chunk by chunk when written (:meth:`write`): the values are the same
    either way. (With hysteresis states the model force is held: its gates are
    scanned through all periods at once.)
    """

    NAMES = ("phase", "period_start_time", "deflection", "velocity", "acceleration", "separation", "force_model",
             "force_inverted", "peak_force", "adhesion_force", "max_indentation", "contact_time", "dissipated_energy",
             "dissipated_energy_inverted", "virial", "virial_inverted", "amplitude", "period_error")
    CURVES = ("deflection", "velocity", "acceleration", "separation", "force_model", "force_inverted")
    SUMMARIES = ("peak_force", "adhesion_force", "max_indentation", "contact_time", "dissipated_energy",
                 "dissipated_energy_inverted", "virial", "virial_inverted", "period_error")

    def __init__(self, prep: Prepared, library: Library, system: System, coef, params, rows, n_phase: int):
        self.prep, self.library, self.system = prep, library, system
        self.coef, self.params, self.rows = coef, params, rows
        self.phase = 2 * np.pi * np.arange(n_phase) / n_phase
        # Each block shows the drive period whose start lies nearest the block's start: the series is evaluated
        # at most half a period outside its block (floor reached up to a whole period back, and a start that
        # rounding put a hair below a period boundary showed the period before it: 430 pm off on a transient
        # whose blocks were cut 3e-3 off the drive frequency, 190 pm with the nearest period).
        self.cycles = np.round(prep.blocks.block_times() * prep.drive.omega / (2 * np.pi))
        start = (2 * np.pi * self.cycles + self.phase[0]) / prep.drive.omega  # = times(...)[:, 0]
        self.held = {"phase": self.phase, "period_start_time": start}
        #: whole curves (name -> (periods, phase points)) kept by period_curves(keep_curves=True); read, not written
        self.kept: dict[str, np.ndarray] = {}

    @property
    def shape(self) -> tuple[int, int]:
        """(periods, phase points) of the curves."""
        return self.prep.blocks.n_blocks, self.phase.size

    def times(self, first: int, stop: int | None) -> np.ndarray:
        """Times (s) of the phase grid of periods ``first`` .. ``stop - 1``."""
        return (2 * np.pi * self.cycles[first:stop, None] + self.phase[None, :]) / self.prep.drive.omega

    def model_force(self, x: np.ndarray, v: np.ndarray, first: int, stop: int) -> np.ndarray:
        """The model force (N) on the phase grid of periods ``first`` .. ``stop - 1`` at deflection x, velocity v."""
        cols = self.library.evaluate_rows(x, v, self.times(first, stop), self.params)
        return (cols @ self.coef[:self.system.theta.shape[2]]).reshape(x.shape)

    def curve(self, name: str, first: int, stop: int) -> np.ndarray:
        """One of :attr:`CURVES` for periods ``first`` .. ``stop - 1``: (stop - first, phase points)."""
        if name in self.kept:
            return self.kept[name][first:stop]
        blocks, X = self.prep.blocks, self.prep.X[first:stop, :, None]
        if name == "force_inverted":
            F = inverted_force_coefficients(self.prep, self.system, self.coef, slice(first, stop)) * self.rows[None, :]
            return self.at_drive_phase(F[..., None], first, stop)
        if name == "separation":
            return self.params["d"] - self.curve("deflection", first, stop)
        if name == "force_model":
            return self.model_force(self.curve("deflection", first, stop), self.curve("velocity", first, stop),
                                    first, stop)
        order = ("deflection", "velocity", "acceleration").index(name)
        return self.at_drive_phase(blocks.derivative(X, order) if order else X, first, stop)

    def at_drive_phase(self, series: np.ndarray, first: int, stop: int) -> np.ndarray:
        """Block series (stop - first, 2K+1, 1) on the phase grid of the drive's periods ``first`` .. ``stop - 1``."""
        blocks = self.prep.blocks
        return blocks.evaluate_in_periods(series, self.phase, self.cycles[first:stop], self.prep.drive.omega)[..., 0]

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self.held:
            return self.held[name]
        if name not in self.CURVES:
            raise KeyError(name)
        out = np.empty(self.shape)
        for b0, values in self.pieces(name):
            out[b0:b0 + values.shape[0]] = values
        return out

    def pieces(self, name: str):
        """(first period, values) of a curve, :data:`PERIOD_CHUNK` periods at a time."""
        for b0 in range(0, self.shape[0], PERIOD_CHUNK):
            yield b0, self.curve(name, b0, min(b0 + PERIOD_CHUNK, self.shape[0]))

    def __iter__(self):
        return iter(self.NAMES)

    def __len__(self) -> int:
        return len(self.NAMES)

    def write(self, group, units: dict[str, str]) -> None:
        """Write every array into ``group`` as :func:`write_dataset` would, the curves chunk by chunk."""
        for name in self.NAMES:
            if name in self.held:
                write_dataset(group, name, self.held[name], units[name])
                continue
            ds = create_dataset(group, name, self.shape, np.float64, units[name])
            rows = ds.chunks[0] if ds.chunks else self.shape[0]
            # Written in whole HDF5 chunks (each compressed once); the rows past the last whole one wait for
            # the next piece.
            pending, first = np.empty((0, self.shape[1])), 0
            for b0, values in self.pieces(name):
                pending = np.concatenate([pending, values]) if pending.size else values
                stop = b0 + values.shape[0]
                cut = stop if stop == self.shape[0] else first + (stop - first) // rows * rows
                if cut > first:
                    ds[first:cut] = pending[:cut - first]
                    pending, first = pending[cut - first:], cut

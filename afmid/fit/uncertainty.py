"""Honest error bars: the calibration's share and the model's limits.

Two things the bootstrap of periods cannot see:

- **Calibration.** The equation of motion is written with the declared spring
  constant k and quality factor Q. A relative 1-sigma uncertainty of either
  (``cantilever.spring_constant_uncertainty``, ``cantilever.quality_factor_uncertainty``)
  moves every read-out. For a fixed trace the left side
  Y = -(m x'' + c x' + k x), m = k / w0^2, c = k / (Q w0), is proportional to k,
  so every force coefficient (and the force itself) scales with k; Q enters
  only the damping term c x', whose change -dc * x' the regression shares out
  among the selected terms (mostly the dissipative ones). Both are linear in the
  coefficients, so the sensitivity is the read-out of the refit with k or Q
  moved by +-1 sigma (a least-squares solve on the fit's own columns, no library
  evaluation). The calibration part is kept beside the statistical part and
  added in quadrature to the error (1 sigma) and to both halves of the 95 %
  interval.
- **Model limits.** A fit whose cross-validated error stands above its noise
  floor (by more than :data:`FLOOR_FACTOR`) fails to explain the data: its
  parameters are biased by whatever is missing, by an amount no error bar
  holds. They are marked ``model_limited``.

Conventions: every ``error`` is 1 sigma; every ``ci_low``/``ci_high`` a 95 %
interval (:data:`ERROR_LABEL`, :data:`INTERVAL_LABEL`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import afmid.fit.regression as regression

if TYPE_CHECKING:  # annotations only
    from afmid.fit.fit_state import FitState

#: The most a cross-validated error may stand above its noise floor and still count as the noise level
#: (:func:`floor_threshold` is the fit's own threshold, at most this). For a right model (error)^2 / (floor)^2 is a
#: chi-square over its effective degrees of freedom nu divided by nu (the floor is the expected noise in the
#: error's own sum: fit_forces.force_cv_error), nu = 12-40 on steady traces (10 pm at 50 samples/period .. 1 pm at
#: 200). Measured on 28 clean traces with detector noise, separation not given: error / floor mean 1.05, sd 0.14,
#: max 1.36 (scripts/floor_study.py). 1.45 is the one-sided 99 % quantile of sqrt(chi2_nu / nu) at nu = 13.5, the
#: fewest seen (docs/diagnosis.md, "The noise floor and its threshold"). Above it the model misses something; the
#: diagnosis looks for it and the fit marks its parameters model-limited.
FLOOR_FACTOR = 1.45

#: What every ``error`` in afmid's outputs is.
ERROR_LABEL = "1 sigma"
#: The key of a read-out's part of its 1 sigma (its unit) from a separation track's widening of its blocks' d
#: sigmas beyond the joint fit's (afmid.fit.separation_track), kept beside ``error`` like the statistical /
#: calibration split and stored as the run file's attribute of that name.
TRACK_LEVEL_ERROR = "error_separation_track"
#: What every ``ci_low`` .. ``ci_high`` interval in afmid's outputs is.
INTERVAL_LABEL = "95 %"
#: The attributes that say so on every stored value with an error and an interval.
ERROR_ATTRS = {"error_kind": ERROR_LABEL, "interval": INTERVAL_LABEL}

#: What a fit's intervals hold when no calibration uncertainty is declared: said once by ``afmid fit`` and the
#: report, and stored as the run file's ``intervals`` attribute (:func:`intervals_kind`).
STATISTICAL_ONLY_TEXT = ("the intervals are statistical only (noise), not calibration: declare "
                         "cantilever.spring_constant_uncertainty, cantilever.quality_factor_uncertainty, "
                         "data.invols_uncertainty to include it")
#: The run file's ``intervals`` attribute: without and with a declared calibration uncertainty.
INTERVALS_STATISTICAL = "statistical only (noise)"
INTERVALS_WITH_CALIBRATION = "statistical and calibration"

#: Warning text of a model-limited fit (the numbers are filled in).
MODEL_LIMITED_TEXT = ("model-limited: the cross-validated error {error:.3g} stands above its noise floor {floor:.3g} "
                      "(x{ratio:.2g}, above x{threshold:.3g}{why}): the model misses part of the force, so its "
                      "parameters are biased by more than their error bars, which cover the noise and a declared "
                      "calibration uncertainty only")


#: The one-sided quantile of a right model's error / floor at which a fit counts as model-limited
#: (:func:`floor_threshold`): about 1 right model in 100 is flagged by chance.
FLOOR_QUANTILE = 0.99


def floor_threshold(floor_dof: float = math.nan) -> float:
    """The ratio cv_error / noise floor above which a fit is model-limited, for a floor with ``floor_dof``
    effective degrees of freedom (afmid.fit.forces.FoldErrors.floor_dof): the :data:`FLOOR_QUANTILE` point of
    sqrt(chi2_nu / nu), never above :data:`FLOOR_FACTOR` (which it is at nu = 13.5, the fewest seen); NaN or
    fewer than one degree of freedom: :data:`FLOOR_FACTOR`. A record with many degrees of freedom locates its
    floor well, so a smaller excess is already significant (nu 32: 1.29)."""
    if not (math.isfinite(floor_dof) and floor_dof >= 1.0):
        return FLOOR_FACTOR
    from scipy.stats import chi2

    return min(FLOOR_FACTOR, math.sqrt(float(chi2.ppf(FLOOR_QUANTILE, floor_dof)) / floor_dof))


def model_limited(cv_error: float, noise_floor: float, floor_dof: float = math.nan) -> bool:
    """True when the fit's error stands above its noise floor by more than :func:`floor_threshold`."""
    return bool(math.isfinite(cv_error) and math.isfinite(noise_floor)
                and cv_error > floor_threshold(floor_dof) * noise_floor)


def at_noise_floor(cv_error: float, noise_floor: float) -> bool:
    """True when the fit's error is at or below its noise floor: nothing is left for a missing effect to
    explain (a misfit the chi-square still sees there is numerical, e.g. the Gibbs ringing of the
    model-free force at a step on noise-free data), so the diagnosis names none."""
    return bool(math.isfinite(cv_error) and math.isfinite(noise_floor) and cv_error <= noise_floor)


def quieter_than_its_floor(cv_error: float, noise_floor: float, floor_dof: float = math.nan) -> bool:
    """True when the fit's error lies below its noise floor by more than a right model's error falls there by
    chance: below the one-sided (1 - :data:`FLOOR_QUANTILE`) point of sqrt(chi2_nu / nu) at the floor's ``floor_dof``
    = nu degrees of freedom (0.57 at nu 13.5, 0.71 at nu 30). Such a record carries less noise than its noise model
    says (noise-free: a misfit the chi-square sees there is numerical; thermal noise only: the floor about twice the
    real scatter), so the diagnosis names nothing there. An error within a right model's spread of its floor (both
    sides) is the noise level by chance, and a gain over the whole record's rows still measures a misfit there.
    Without nu (NaN or below one degree of freedom): :func:`at_noise_floor` (the floor itself)."""
    if not (math.isfinite(floor_dof) and floor_dof >= 1.0):
        return at_noise_floor(cv_error, noise_floor)
    from scipy.stats import chi2

    lowest = math.sqrt(float(chi2.ppf(1.0 - FLOOR_QUANTILE, floor_dof)) / floor_dof)
    return bool(math.isfinite(cv_error) and math.isfinite(noise_floor) and cv_error < lowest * noise_floor)


def model_limited_warning(cv_error: float, noise_floor: float, floor_dof: float = math.nan) -> str:
    """The warning line of a model-limited fit."""
    threshold = floor_threshold(floor_dof)
    why = (f", which a right model exceeds 1 time in {round(1 / (1 - FLOOR_QUANTILE))} at this record's "
           f"{floor_dof:.0f} degrees of freedom" if threshold < FLOOR_FACTOR else "")
    return MODEL_LIMITED_TEXT.format(error=cv_error, floor=noise_floor, ratio=cv_error / noise_floor,
                                     threshold=threshold, why=why)


def mark_model_limited(quantities: dict, limited: bool) -> None:
    """Set each quantity's ``model_limited`` flag (in place)."""
    for q in quantities.values():
        q["model_limited"] = bool(limited)


@dataclass
class Calibration:
    """Relative 1-sigma uncertainties of the cantilever's calibration (0 = exact)."""

    spring_constant: float = 0.0
    quality_factor: float = 0.0

    @classmethod
    def from_config(cls, cantilever) -> "Calibration":
        """From ``cantilever.spring_constant_uncertainty`` / ``quality_factor_uncertainty`` (None = 0)."""
        return cls(float(cantilever.spring_constant_uncertainty or 0.0),
                   float(cantilever.quality_factor_uncertainty or 0.0))

    @property
    def declared(self) -> bool:
        return self.spring_constant > 0 or self.quality_factor > 0


def calibration_declared(config) -> bool:
    """True when a run config (:class:`afmid.config.RunConfig`) declares any calibration uncertainty (k, Q or the
    deflection sensitivity) that the fit propagates into its intervals."""
    cl = config.cantilever
    return bool(cl.spring_constant_uncertainty or cl.quality_factor_uncertainty or config.data.invols_uncertainty)


def intervals_kind(config) -> str:
    """What the intervals of a fit with ``config`` hold: :data:`INTERVALS_STATISTICAL` or
    :data:`INTERVALS_WITH_CALIBRATION` (a joint fit of ``data.paths`` does not propagate the calibration:
    afmid.fit.joint warns so; its intervals are statistical)."""
    joint = bool(getattr(config.data, "paths", None))
    return INTERVALS_WITH_CALIBRATION if calibration_declared(config) and not joint else INTERVALS_STATISTICAL


def damping_integrals(prep) -> np.ndarray:
    """The damping part of the left side per row (W, rows): Y = -(mass and spring parts) - c * D.

    Weak form: the integral of psi x' is that of -psi' x (the windows vanish at both ends), so
    D = integral of -psi' x over each window and test function; strong form: D = x' on the used samples.
    """
    if prep.form == "strong":
        _, v = prep.strong
        return v.reshape(prep.Y.shape)
    blocks, windows = prep.blocks, prep.windows
    D = np.zeros(prep.Y.shape)
    minus_dpsi = -windows.dpsi
    W = windows.n_windows
    for b0, b1 in blocks.chunks():
        w1 = min(b1, W)
        if w1 <= b0:
            continue
        lo = blocks.start + b0 * blocks.L
        hi = lo + (b1 - b0) * blocks.L + blocks.L + 1
        xs = prep.x[lo:hi, None]
        D[b0:w1] = windows.integrate_samples(minus_dpsi, xs, b0, w1 - b0, blocks.rotation(b0, b1))[..., 0]
    return D


def coefficient_shift(prep, system, delta_Y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The change of the least-squares coefficients (support ``mask``, the fit's row weights) when Y
    changes by ``delta_Y`` (W, rows): the solution is linear in Y."""
    A = np.concatenate([system.theta, prep.nuisance], axis=2) / prep.row_sigma[None, :, None]
    b = delta_Y / prep.row_sigma[None, :]
    step = 2048
    T = regression.combine(np.concatenate([regression.factor_blocks(A[i:i + step], b[i:i + step])
                                           for i in range(0, A.shape[0], step)]))
    return regression.subset_fit(T, mask)[0]


def propagate_calibration(quantities: dict, prep, library, system, coef: np.ndarray, mask: np.ndarray,
                          params: dict, trace, calibration: Calibration, read_out, fixed_cantilever: bool = True
                          ) -> float:
    """Add the calibration's share to every quantity (in place); returns the force's relative calibration
    uncertainty (1 sigma, rms over the weak-form rows of the model force).

    Each quantity gains ``error_statistical`` (its error so far), ``error_calibration`` (1 sigma, k and Q in
    quadrature, each the half-difference of the read-outs at +-1 sigma) and ``error`` = both in quadrature;
    its 95 % interval widens by 1.96 ``error_calibration`` in quadrature on each side. ``read_out`` is
    :func:`afmid.fit.forces.read_out`. With a free cantilever (``fit.cantilever: free``) k x and c x' have free
    coefficients of their own: only the mass k / w0^2 scales the equation, and Q does not enter.
    """
    for q in quantities.values():
        q["error_statistical"] = q["error"]
        q["error_calibration"] = 0.0
    p = len(library)
    force_variance = 0.0
    model_rows = np.einsum("wrp,p->wr", system.theta, coef[:p]) if calibration.declared else None
    norm = float(np.sqrt(np.mean(model_rows**2))) if model_rows is not None else 0.0
    shifts = []
    if calibration.spring_constant > 0:
        s = calibration.spring_constant
        # Y scales with k exactly: so does every coefficient (the relative row weights barely move).
        shifts.append((coef * (1 + s), coef * (1 - s)))
        force_variance += s**2
    if calibration.quality_factor > 0 and fixed_cantilever:
        s = calibration.quality_factor
        c = trace.cantilever.damping  # io.cantilever.lever_damping, the one formula
        D = damping_integrals(prep)
        pair = []
        for sign in (1, -1):
            dc = c * (1 / (1 + sign * s) - 1)  # c = k / (Q w0) with Q -> Q (1 +- s)
            pair.append(coef + coefficient_shift(prep, system, -dc * D, mask))
        shifts.append(tuple(pair))
        if norm > 0:
            dF = np.einsum("wrp,p->wr", system.theta, 0.5 * (pair[0] - pair[1])[:p])
            force_variance += float(np.mean(dF**2)) / norm**2
    variance = shift_variance(quantities, shifts, lambda c: read_out(library, c, None, params, mask, trace))
    for k, q in quantities.items():
        if variance[k] <= 0:
            continue
        cal = math.sqrt(variance[k])
        q["error_calibration"] = cal
        widen_interval(q, cal)
    return math.sqrt(force_variance)


def finish(state: FitState, uncertainty: bool = True) -> None:
    """The fit's last step on its error bars (in place on ``state``, an :class:`afmid.fit.fit_state.FitState`): the
    calibration's share (when ``uncertainty``; ``state.force_calibration`` becomes the force's relative calibration
    uncertainty, 1 sigma) and the model-limited mark (always: ``state.model_limited``, each quantity's flag and a
    warning line)."""
    # The read-out's module is loaded here, not with this one: the report and the batch summary read this module's
    # labels and thresholds without loading the fit's numerics.
    from afmid.fit.forces import read_out, row_noise_excess
    from afmid.fit.inband_noise import measured_noise_words

    if uncertainty:
        state.force_calibration = propagate_calibration(
            state.quantities, state.prep, state.library, state.system, state.coef, state.mask, state.params,
            state.trace, Calibration.from_config(state.config.cantilever), read_out,
            fixed_cantilever=state.config.fit.cantilever == "fixed")
    state.model_limited = model_limited(state.cv_error, state.noise_floor, state.floor_dof)
    mark_model_limited(state.quantities, state.model_limited)
    if state.model_limited:
        state.warn(model_limited_warning(state.cv_error, state.noise_floor, state.floor_dof))
    if state.prep.form != "strong":
        words = measured_noise_words(row_noise_excess(state.prep), state.prep.blocks.harmonics)
        if words:
            state.warn(words)


def error_beyond_split(q: dict) -> float:
    """The part of read-out ``q``'s 1 sigma that its statistical / calibration / separation-track split does not
    hold (the quantity's unit; 0 when the parts make it up to 1 %): the widenings added after the split, the
    separation's interval of a model-limited fit (the profile weighed against the misfit) and a declared drive's
    calibration. Without it the split's parts, 1000x smaller than the 1 sigma they are said to make up, misread as
    the error."""
    error = q.get("error", math.nan)
    stat, cal = q.get("error_statistical", math.nan), q.get("error_calibration", 0.0)
    track = q.get(TRACK_LEVEL_ERROR, 0.0)
    if not (math.isfinite(error) and math.isfinite(stat) and math.isfinite(cal) and math.isfinite(track)):
        return 0.0
    rest = math.sqrt(max(error**2 - stat**2 - cal**2 - track**2, 0.0))
    return rest if rest > 0.01 * error else 0.0


def statistical_error(q: dict) -> float:
    """Read-out ``q``'s statistical part of its 1 sigma (its unit): the stored ``error_statistical``, else what
    the 1 sigma holds beyond its calibration and :data:`TRACK_LEVEL_ERROR` parts in quadrature (a separation
    track's read-outs store no statistical part: their joint fit's error is the noise's alone, and the track's
    share was added to it in quadrature). Without either part this is the 1 sigma itself."""
    if "error_statistical" in q:
        return q["error_statistical"]
    error = q.get("error", math.nan)
    added = math.hypot(q.get("error_calibration", 0.0), q.get(TRACK_LEVEL_ERROR, 0.0))
    if not math.isfinite(error) or not math.isfinite(added) or added == 0:
        return error
    return math.sqrt(max(error**2 - added**2, 0.0))


def one_sigma_parts(q: dict) -> dict[str, float]:
    """Read-out ``q``'s 1 sigma split into named parts that add up to it in quadrature (each in its unit), in the
    order the texts name them: ``statistical`` (:func:`statistical_error`), ``calibration`` and ``separation
    track`` (:data:`TRACK_LEVEL_ERROR`) where they are > 0, ``rest`` (:func:`error_beyond_split`) where the parts
    do not make up the 1 sigma. Empty when there is no calibration nor track part (the 1 sigma is statistical
    alone, nothing to split) or the 1 sigma is not finite."""
    cal, track = q.get("error_calibration", 0.0), q.get(TRACK_LEVEL_ERROR, 0.0)
    if not math.isfinite(q.get("error", math.nan)) or not (cal > 0 or track > 0):
        return {}
    parts = {"statistical": statistical_error(q)}
    if cal > 0:
        parts["calibration"] = cal
    if track > 0:
        parts["separation track"] = track
    rest = error_beyond_split(q)
    if rest > 0:
        parts["rest"] = rest
    return parts


def shift_variance(quantities: dict, shifts: list, read_out_at) -> dict[str, float]:
    """Per read-out, the sum over ``shifts`` (pairs of coefficient vectors at +-1 sigma of a calibration) of the
    squared half-difference of the read-outs ``read_out_at(coefficients)`` (units of each quantity, squared)."""
    variance = dict.fromkeys(quantities, 0.0)
    for plus, minus in shifts:
        add_half_difference(variance, read_out_at(plus), read_out_at(minus))
    return variance


def add_half_difference(variance: dict[str, float], up: dict, down: dict) -> None:
    """Add to ``variance[k]`` (in place, for each of its keys) the squared half-difference of read-out ``k``
    between two read-outs at +-1 sigma of one input (``up``, ``down``: read-out dicts); a quantity missing or
    not finite in either adds nothing."""
    for k in variance:
        delta = 0.5 * (up.get(k, {}).get("value", math.nan) - down.get(k, {}).get("value", math.nan))
        if math.isfinite(delta):
            variance[k] += delta**2


def add_largest_shift(variance: dict[str, float], quantities: dict, shifted: list[dict]) -> None:
    """Add to ``variance[k]`` (in place) the square of the largest change of read-out ``k`` from its value in
    ``quantities`` among the read-outs ``shifted`` at +-1 sigma of a nonlinear input (one side alone when the
    other could not be fitted). For a read-out linear in the input this is the half-difference of the two
    sides; where it is not, the half-difference can miss the change entirely: measured on the poor instrument
    (seed 206, separation 8.80 +- 0.60 nm, truth 8.0): E* 9.04 GPa at the estimate, 1.93 at -1 sigma, 0 at +1
    sigma (the tip no longer touches), half-difference 0.97, reported 9.0 +- 1.6 for a truth of 1.5. A side
    where the read-out is not finite adds nothing."""
    for k in variance:
        central = quantities.get(k, {}).get("value", math.nan)
        changes = [abs(side.get(k, {}).get("value", math.nan) - central) for side in shifted]
        changes = [c for c in changes if math.isfinite(c)]
        if changes:
            variance[k] += max(changes) ** 2


#: The half-width of a 95 % interval in sigmas, as every widening of afmid's intervals uses it (two-sided normal,
#: 1.95996 rounded as the intervals are stated): one constant, so two widenings of the same interval agree.
Z95 = 1.96


def widen_interval(q: dict, sigma: float) -> None:
    """Add an independent 1-sigma error component ``sigma`` (the quantity's unit) to read-out ``q`` in place:
    in quadrature to its 1-sigma ``error`` and, as 1.96 sigma, to each side of its 95 % interval (an interval
    that is not finite becomes value +- 1.96 sigma). Used for every component added after the fit's own error
    (calibration, the separation's sigma, the spread between models)."""
    if not math.isfinite(sigma) or sigma <= 0:
        return
    q["error"] = math.hypot(q["error"] if math.isfinite(q["error"]) else 0.0, sigma)
    half = Z95 * sigma
    lo, hi, value = q["ci_low"], q["ci_high"], q["value"]
    if math.isfinite(lo) and math.isfinite(hi):
        q["ci_low"], q["ci_high"] = value - math.hypot(value - lo, half), value + math.hypot(hi - value, half)
    else:
        q["ci_low"], q["ci_high"] = value - half, value + half

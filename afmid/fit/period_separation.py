"""A rest separation that moves from period to period inside a trace: the library evaluated at d + delta_b.

Under an amplitude feedback the piezo moves every drive period, so within a block of a separation track
(:mod:`afmid.fit.separation_track`) d(t) is not constant (measured on a 2 nm step at gain 6000 /s: sd 8-30 pm
within 100-period blocks, against an indentation of well under a nanometre). The library's terms depend on the
separation only through z = d - x, and each harmonic block (about one period) of a preparation is synthesised
from its own Fourier coefficients, so a per-period rest separation d + delta_b is the library evaluated on the
trajectory x - delta_b: its constant coefficient moved by -delta_b. The equation of motion's own rows
(m x'' + c x' + k x, from the recorded samples) are untouched: moving the piezo moves the sample, not the lever.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from afmid.fit.prepare import Prepared
from afmid.fit.system import library_columns
from afmid.preprocess.periods import ou_smooth_given


def block_means(prep: Prepared, per_sample: np.ndarray) -> np.ndarray:
    """The mean of ``per_sample`` (one value per sample of ``prep``'s trace) over each of its harmonic blocks."""
    blocks = prep.blocks
    used = np.asarray(per_sample, dtype=float)[blocks.used]
    return used.reshape(blocks.n_blocks, blocks.L).mean(axis=1)


def with_period_separation(prep: Prepared, offsets: np.ndarray) -> Prepared:
    """``prep`` with the library evaluated at the rest separation d + ``offsets[b]`` (m) in harmonic block b
    (the trajectory's constant coefficient moved by -offsets[b]; its velocity and the equation's rows unchanged).
    ValueError when ``offsets`` does not hold one value per block."""
    offsets = np.asarray(offsets, dtype=float)
    if offsets.shape != (prep.blocks.n_blocks,):
        raise ValueError(f"need one separation offset per harmonic block ({prep.blocks.n_blocks}), got "
                         f"{offsets.shape}")
    trajectory = prep.X_traj.copy()
    trajectory[:, 0] -= offsets
    # A kept fine grid belongs to the old trajectory (FineGrid.holds compares the arrays): dropped with it.
    return dataclasses.replace(prep, X_traj=trajectory, fine_grid=None)


#: The offsets tried per period when matching its mean force, m: +-SCAN_HALF_WIDTH in SCAN_STEP steps (the
#: feedback moved d by at most 108 pm within a 100-period block on the 2 nm step measured; 300 pm leaves room).
SCAN_HALF_WIDTH = 300e-12
SCAN_STEP = 5e-12


def period_mean_forces(prep: Prepared, library, coef: np.ndarray, params: dict, offsets: np.ndarray) -> np.ndarray:
    """The law's tip-sample force (N, ``coef`` on ``library``'s columns) averaged over each harmonic block's
    trajectory, at the rest separation params["d"] + each of ``offsets`` (m): (n_blocks, len(offsets))."""
    blocks = prep.blocks
    first = np.arange(blocks.n_blocks)
    x, v = blocks.synthesize_fine_rows(prep.X_traj, prep.V_traj, first=0)
    t = blocks.fine_times(0, blocks.n_blocks)
    out = np.empty((blocks.n_blocks, len(offsets)))
    for j, offset in enumerate(offsets):
        shifted = dict(params, d=float(params["d"]) + float(offset))
        force = library.evaluate_rows(x, v, t, shifted) @ coef
        out[:, j] = force.reshape(first.size, -1).mean(axis=1)
    return out


def mean_force_offsets(prep: Prepared, library, coef: np.ndarray, params: dict, smooth: bool = True
                       ) -> np.ndarray:
    """Each harmonic block's rest separation relative to params["d"] (m), from its mean force.

    A period's constant Fourier row of the equation of motion is its mean tip-sample force, measured without the
    drive (which has none): <F_ts>_b = -<m x'' + c x' + k x>_b (prep.Y_block[:, 0], N). Given the law, the
    rest separation at which the law's force averaged over that period's trajectory is this mean is the
    period's d: found on a grid of offsets (linear interpolation between the two bracketing ones; a period whose
    mean force the grid does not bracket gets the grid's end). Returned minus their mean: the trace's level
    stays params["d"] (the joint fit's to estimate). With ``smooth`` the period-to-period noise is smoothed away
    (:func:`smooth_offsets`; its variance: prep.block_sigma[0] over the mean force's slope in d, squared)."""
    grid = np.arange(-SCAN_HALF_WIDTH, SCAN_HALF_WIDTH + 0.5 * SCAN_STEP, SCAN_STEP)
    model = period_mean_forces(prep, library, coef, params, grid)  # falls with the offset (less contact)
    measured = prep.Y_block[:, 0]
    offsets = np.empty(model.shape[0])
    for b, (curve, target) in enumerate(zip(model, measured)):
        # Made non-increasing (an attractive dip at the far end could turn it up), then reversed: np.interp
        # needs increasing abscissae.
        falling = np.minimum.accumulate(curve)
        offsets[b] = np.interp(target, falling[::-1], grid[::-1])
    offsets -= offsets.mean()
    centre = grid.size // 2  # the offset 0
    slope = np.mean(model[:, centre - 1] - model[:, centre + 1]) / (2 * SCAN_STEP)  # N/m, the mean contact stiffness
    if smooth and slope > 0 and offsets.size > 2:
        offsets = smooth_offsets(offsets, (float(prep.block_sigma[0]) / slope) ** 2)
    return offsets - offsets.mean()


def smooth_offsets(offsets: np.ndarray, noise_var: float) -> np.ndarray:
    """Per-period offsets (m) with their noise (``noise_var``, m^2, independent per period) smoothed away: the
    feedback moves d on its loop's time (tens of periods), so the offsets are an Ornstein-Uhlenbeck process seen
    in white noise (:func:`afmid.preprocess.periods.ou_smooth_given`, a Kalman smoother), its variance the
    scatter's excess over the noise and its period-to-period correlation the lag-1 autocovariance over that
    variance (an OU process's rho; clipped to [0, 0.999]). Unchanged when the scatter is all noise."""
    signal_var = float(np.var(offsets)) - noise_var
    if signal_var <= 0:
        return np.zeros_like(offsets)  # nothing beyond the noise: the block's d holds for every period
    centred = offsets - offsets.mean()
    rho = float(np.clip(np.mean(centred[1:] * centred[:-1]) / signal_var, 0.0, 0.999))
    smoothed, _ = ou_smooth_given(centred[:, None], np.array([noise_var]), np.array([signal_var]), rho)
    return smoothed[:, 0]


#: The step of the offsets' numerical derivative, m: a few pm, far below the indentation (~1 nm on the records
#: measured), so the law's curvature over it is negligible, and far above the arithmetic's rounding.
DERIVATIVE_STEP = 2e-12
#: Gauss-Newton steps of :func:`row_offsets` (the second on the trajectory shifted by the first's offsets:
#: F ~ delta^1.5 bends over the tens of pm the feedback moves d).
ROW_OFFSET_STEPS = 2
#: The Ornstein-Uhlenbeck prior's candidates, searched by the marginal likelihood: the offsets' sd (m) and their
#: period-to-period correlation (the feedback loop's time, tens of periods, gives 0.9-0.99).
PRIOR_SD = np.array([0.5, 1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 100]) * 1e-12
PRIOR_RHO = np.array([0.0, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995])


def row_design(prep: Prepared, library, law: np.ndarray, nuisance_coef: np.ndarray, params: dict,
               offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weak-form rows linearised in the per-period offsets at ``offsets`` (m): the whitened design G
    (rows, n) in 1/m, and r, the rows' whitened residual under the law (``law`` on ``library``'s columns,
    ``nuisance_coef`` on the preparation's drive columns) at ``offsets`` (rows,), dimensionless.

    A window spans two periods (:func:`afmid.preprocess.periods.weak_windows`) and sees each through the same
    harmonics (weighted by the window's envelope), so one window cannot tell its two periods apart: G has about
    one direction per window, and neighbouring periods are separated only by a prior (:func:`row_offsets`). The
    derivatives come from moving the even and the odd periods apart (four evaluations of the columns); the row
    noise is the fit's (``row_sigma``, independent rows). G summed over its columns is the rows' derivative in
    the block's level: moving every period by the same amount moves the level."""
    residual = (prep.Y - library_columns(with_period_separation(prep, offsets), library, params) @ law
                - prep.nuisance @ nuisance_coef) / prep.row_sigma[None, :]
    return column_designs(prep, library, params, offsets) @ law, residual.ravel()


def column_designs(prep: Prepared, library, params: dict, offsets: np.ndarray) -> np.ndarray:
    """Each library column's whitened rows differentiated in the per-period offsets at ``offsets`` (m): (rows, n,
    p), 1/m per unit coefficient; the design of a law is this times its coefficients (:func:`row_design`). Four
    evaluations of the columns (the even and the odd periods moved apart, each up and down)."""
    n = prep.blocks.n_blocks
    parity = np.arange(n) % 2
    windows, harmonic_rows = prep.Y.shape
    if windows > n:
        raise ValueError(f"{windows} weak-form windows over {n} periods: a window spans more than two periods")
    design = None
    for odd in (0, 1):
        step = DERIVATIVE_STEP * (parity == odd)
        up = library_columns(with_period_separation(prep, offsets + step), library, params)
        down = library_columns(with_period_separation(prep, offsets - step), library, params)
        slope = (up - down) / (2 * DERIVATIVE_STEP) / prep.row_sigma[None, :, None]  # (windows, rows, p)
        if design is None:
            design = np.zeros((windows, harmonic_rows, n, slope.shape[2]))
        for w in range(windows):  # window w spans periods w and w + 1
            for b in (w, w + 1):
                if b < n and parity[b] == odd:
                    design[w, :, b] = slope[w]
    return design.reshape(windows * harmonic_rows, n, -1)


def row_information(prep: Prepared, library, law: np.ndarray, nuisance_coef: np.ndarray, params: dict,
                    offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weak-form rows' information on the per-period offsets linearised at ``offsets`` (m): the whitened
    design's G^T G (1/m^2, (n, n)) and G^T r (1/m, (n,)) (:func:`row_design`)."""
    whitened, residual = row_design(prep, library, law, nuisance_coef, params, offsets)
    return whitened.T @ whitened, whitened.T @ residual


def ou_prior(n: int, sd: float, rho: float) -> np.ndarray:
    """The covariance (m^2) of n periods of an Ornstein-Uhlenbeck process of sd ``sd`` (m), lag-1 correlation rho."""
    lags = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    return sd**2 * rho**lags


def marginal_log_likelihood(information: np.ndarray, score: np.ndarray, prior: np.ndarray) -> float:
    """log p(rows | prior) up to a constant for rows = G x + e, x ~ N(0, prior), e ~ N(0, 1) whitened, from
    G^T G and G^T r: -1/2 log det(1 + prior G^T G) + 1/2 score^T (prior^-1 + G^T G)^-1 score."""
    n = score.size
    system = np.eye(n) + prior @ information
    sign, logdet = np.linalg.slogdet(system)
    if sign <= 0:
        return -np.inf
    return float(-0.5 * logdet + 0.5 * score @ np.linalg.solve(system, prior @ score))


def row_offsets(prep: Prepared, library, law: np.ndarray, nuisance_coef: np.ndarray, params: dict
                ) -> tuple[np.ndarray, tuple[float, float]]:
    """Each harmonic block's (period's) rest separation relative to params["d"] (m, zero mean) from all the
    weak-form rows of the equation of motion under the law, and the prior chosen ((sd in m, rho)).

    The period's mean force (:func:`mean_force_offsets`) is one of those rows; on a contact of well under a
    nanometre its sensitivity to d is low (mean contact stiffness ~1.5 N/m on the 2 nm step and rough records
    measured: a period's noise ~10 pm against the feedback's 5-30 pm of motion), while the contact's harmonics
    carry the same d in every row. The rows cannot tell neighbouring periods apart (:func:`row_information`), so
    the offsets are the posterior mean under an Ornstein-Uhlenbeck prior (the feedback moves d smoothly) whose
    sd and correlation maximise the rows' marginal likelihood (:data:`PRIOR_SD`, :data:`PRIOR_RHO`), linearised
    at the previous step's offsets (Gauss-Newton, :data:`ROW_OFFSET_STEPS`)."""
    n = prep.blocks.n_blocks
    offsets = np.zeros(n)
    chosen = (0.0, 0.0)
    for _ in range(ROW_OFFSET_STEPS):
        information, score = row_information(prep, library, law, nuisance_coef, params, offsets)
        # The rows' evidence for the total offsets (not the step): G^T r + G^T G x0.
        total = score + information @ offsets
        best = -np.inf
        for sd in PRIOR_SD:
            for rho in PRIOR_RHO:
                value = marginal_log_likelihood(information, total, ou_prior(n, sd, rho))
                if value > best:
                    best, chosen = value, (float(sd), float(rho))
        prior = ou_prior(n, *chosen)
        offsets = prior @ np.linalg.solve(np.eye(n) + information @ prior, total)
    return offsets - offsets.mean(), chosen


@dataclasses.dataclass
class LinearisedBlock:
    """One block of a separation track linearised at its fit (whitened rows, unit noise): the rows' residual
    ``residual`` (rows,) at the offsets ``offsets`` (m, (n,)); the selected law columns ``shared`` (rows, p_s),
    shared with the other blocks; the block's own selected drive columns ``own`` (rows, m); the offsets' design
    ``design`` (rows, n) in 1/m (:func:`row_design`; its row sums are the level's column); and the offsets'
    Ornstein-Uhlenbeck prior ``prior`` (n, n), m^2 (:func:`ou_prior`, before its mean is taken out). With
    ``shared_designs`` (rows, n, p_s: ``design``'s derivative in each shared coefficient, 1/m per unit) and
    ``level_slope`` (rows, n: its derivative in the level, 1/m^2) :func:`joint_level_step` also takes the
    offsets' log-determinant into the levels and the law (the marginal likelihood's minimum, not the penalised
    fit's); without them it does not."""

    residual: np.ndarray
    offsets: np.ndarray
    shared: np.ndarray
    own: np.ndarray
    design: np.ndarray
    prior: np.ndarray
    shared_designs: np.ndarray | None = None
    level_slope: np.ndarray | None = None


@dataclasses.dataclass
class LevelStep:
    """What :func:`joint_level_step` returns: the levels' covariance given the offsets (``conditional``, m^2, as
    the joint fit's profile sees it) and with them marginalised (``marginal``); the linearised joint minimum's
    change of each level (``level_change``, m), the shared law's (``shared_change``) and the offsets there
    (``offsets``, per block, m, zero mean). Of
    ``level_change``, ``log_det_change`` (m) is the offsets' log-determinant's part (zero when the blocks carry
    no design derivatives), and ``row_shift`` (per block, whitened rows) is what moves a fit that holds the
    offsets by that part: the model's columns times the step it makes in the law, the block's drive and level."""

    conditional: np.ndarray
    marginal: np.ndarray
    level_change: np.ndarray
    offsets: list[np.ndarray]
    log_det_change: np.ndarray | None = None
    row_shift: list[np.ndarray] | None = None
    shared_change: np.ndarray | None = None  # the shared law's coefficients' step (their units)


def centred_prior(prior: np.ndarray) -> np.ndarray:
    """``prior`` (m^2) of offsets whose mean is taken out (the block's level carries it): C prior C, C the
    centring matrix."""
    n = prior.shape[0]
    centring = np.eye(n) - 1.0 / n
    return centring @ prior @ centring


def joint_level_step(blocks: list[LinearisedBlock]) -> LevelStep:
    """The blocks' levels, the shared law and each block's drive, linearised together with the per-period offsets.

    Each block's whitened rows are r = S c + O n + l d + G x + e (S: the shared law's columns, O: its drive's, l =
    G 1: its level's, G: its offsets', e ~ N(0, 1)), the offsets x ~ N(0, P) with P the centred OU prior. The
    joint fit refits c, n and d with x held at the offsets found from the previous law, so its profile's
    covariance of d is the conditional (A^T A)^-1 over A = [S O l]. The offsets come from the same rows, and their
    error is common to a block: integrating x out gives the rows' covariance 1 + G P G^T, weight
    W = 1 - G P (1 + G^T G P)^-1 G^T, and the marginal covariance (A^T W A)^-1, which exceeds the conditional by
    the offsets' posterior uncertainty propagated into the levels (the law of total variance, exact for this
    linear Gaussian model). The same weight gives the joint minimum over (c, n, d, x): the generalised least
    squares step of (c, n, d) on the rows with the offsets put back, r + G x0, and x at its posterior mean given
    that step. The alternation (offsets from one law, the law from those offsets) reaches that minimum only in
    the limit of many passes; one step of this solve lands there for the linear model.

    That minimum is the penalised one, min over x of |r - G x|^2 + x^T P^-1 x. The level's and the law's
    likelihood with the offsets integrated out adds log det(1 + P G^T G), and G grows with the contact (a deeper
    or stiffer one moves the rows more per pm): offsets fitted to the rows' noise lower the penalised residual
    more where G is larger, so its minimum slides along the level-law valley towards a higher level and a stiffer
    law (+14.5 pm on a flat record whose d does not move, where the log-determinant's gradient predicted 11 pm;
    docs/lab/2026-11-29-scanning-record.md). With the blocks' design derivatives the step includes the
    log-determinant's gradient, 2 tr((1 + P G^T G)^-1 P G^T dG), linearised (a Newton step on the marginal
    objective whose curvature is the marginal information).

    Every column is scaled to unit norm before the solve (the law's coefficients and the offsets differ by
    orders of magnitude)."""
    widths = [b.own.shape[1] + 1 for b in blocks]
    n_shared = blocks[0].shared.shape[1]
    size = n_shared + sum(widths)
    conditional_info, marginal_info = np.zeros((size, size)), np.zeros((size, size))
    marginal_score = np.zeros(size)
    log_det_gradient = np.zeros(size)
    start = n_shared
    index, weighted = [], []
    for block, width in zip(blocks, widths):
        level = block.design.sum(axis=1)
        columns = np.column_stack([block.shared, block.own, level])
        where = np.r_[np.arange(n_shared), start + np.arange(width)]
        prior = centred_prior(block.prior)
        gain = prior @ np.linalg.solve(np.eye(prior.shape[0]) + block.design.T @ block.design @ prior,
                                       block.design.T)  # P (1 + G^T G P)^-1 G^T: rows -> offsets
        if block.shared_designs is not None and block.level_slope is not None:
            # d log det(1 + P G^T G) = 2 tr((1 + P G^T G)^-1 P G^T dG) = 2 sum(gain^T * dG)
            log_det_gradient[:n_shared] += 2 * np.einsum("nr,rnk->k", gain, block.shared_designs)
            log_det_gradient[where[-1]] += 2 * np.sum(gain.T * block.level_slope)
        restored = block.residual + block.design @ block.offsets  # the rows with the offsets put back
        weighted_columns = columns - block.design @ (gain @ columns)  # W A
        conditional_info[np.ix_(where, where)] += columns.T @ columns
        marginal_info[np.ix_(where, where)] += columns.T @ weighted_columns
        marginal_score[where] += weighted_columns.T @ restored
        index.append(where)
        weighted.append((gain, restored, columns))
        start += width
    scale = 1.0 / np.sqrt(np.maximum(np.diag(conditional_info), np.finfo(float).tiny))
    levels = np.array([where[-1] for where in index])

    def covariance(info: np.ndarray) -> np.ndarray:
        inverse = np.linalg.pinv(info * np.outer(scale, scale), hermitian=True) * np.outer(scale, scale)
        return inverse

    conditional = covariance(conditional_info)
    marginal = covariance(marginal_info)
    log_det_step = -0.5 * marginal @ log_det_gradient
    step = marginal @ marginal_score + log_det_step
    offsets, row_shift = [], []
    for where, (gain, restored, columns) in zip(index, weighted):
        found = gain @ (restored - columns @ step[where])
        offsets.append(found - found.mean())
        row_shift.append(columns @ log_det_step[where])
    return LevelStep(conditional[np.ix_(levels, levels)], marginal[np.ix_(levels, levels)], step[levels], offsets,
                     log_det_step[levels], row_shift, step[:n_shared])


def with_row_shift(prep: Prepared, shift: np.ndarray) -> Prepared:
    """``prep`` with its weak-form rows moved by ``shift`` (whitened, (windows * rows,), :attr:`LevelStep.row_shift`):
    the fit of the law, the drive and the level on them, the offsets held, lands where the offsets' marginal
    likelihood has its minimum instead of the penalised residual's (a shift along the model's own columns: the
    linear term the log-determinant adds to the objective, in the rows' form). Its size is that of the step,
    ~1 sigma of the level: |shift|^2 is ~1 against a residual of ~21000 on a 60-period block, so the residual's
    noise statistics (cross-validated error, chi-square) do not see it."""
    shift = np.asarray(shift, dtype=float).reshape(prep.Y.shape)
    return dataclasses.replace(prep, Y=prep.Y + shift * prep.row_sigma[None, :])

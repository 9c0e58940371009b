"""A drifting deflection baseline (``fit.detrend: linear``), estimated with the force law.

A deflection baseline that drifts linearly in time, x_measured = x + a + b t,
enters the equation of motion through k x (and c x'): the weak-form rows gain
-k a integral(psi) - k b integral(psi t) - c b integral(psi). A constant of
0.25 nm on a 40 N/m lever is a 10 nN mean force, so the drift must not be
guessed from the raw oscillation: a straight line fitted to the oscillation's
samples has a slope of amplitude / duration from the partial period alone
(-0.5 nm over 50 periods of a 15 nm oscillation, where there is no drift).

Here the drift is a nuisance column of the regression, (t - t_mid) / half the
duration (with ``fit.baseline: free`` also a constant), projected and
integrated like the drive columns and never selected away: the fit estimates
it jointly with the force law. The trajectory the library is evaluated on must not carry
the drift either (it moves the contact point): before the blocks are fitted,
the slope of the per-period mean deflection (the DC Fourier coefficient of
each period, which no oscillation or partial period leaks into) is removed; a
change of the mean force over the record (a settling amplitude) would bias
that slope, and what is left over is absorbed by the regression's slope
column in the equation.
"""

from __future__ import annotations

import numpy as np

#: Names of the baseline's nuisance columns (offset: N, drift: N per half duration).
OFFSET, DRIFT = "offset", "drift"


class BaselineColumns:
    """The regression's nuisance columns at sample times ``t``: cos, sin of the drive and the baseline's.

    ``offset``: a constant (``fit.baseline: free``: a force or deflection offset); ``drift``: (t - t_mid) /
    half, with t_mid and half the record's centre and half duration (s), so the column is of order 1. The
    drift alone adds no constant: the baseline at the record's centre stays the declared zero of the
    deflection, so the mean force (the rows of harmonic 0) still informs the fit, as without drift.
    """

    def __init__(self, omega: float, t_first: float, t_last: float, offset: bool, drift: bool):
        self.omega = omega
        self.offset = offset
        self.drift = drift
        self.t_mid = 0.5 * (t_first + t_last)
        self.half = max(0.5 * (t_last - t_first), 1e-300)

    @property
    def names(self) -> list[str]:
        return ["drive_cos", "drive_sin"] + ([OFFSET] if self.offset else []) + ([DRIFT] if self.drift else [])

    def __call__(self, t: np.ndarray) -> np.ndarray:
        cols = [np.cos(self.omega * t), np.sin(self.omega * t)]
        if self.offset:
            cols.append(np.ones_like(t))
        if self.drift:
            cols.append((t - self.t_mid) / self.half)
        return np.column_stack(cols)


def period_mean_slope(x: np.ndarray, t: np.ndarray, blocks) -> float:
    """Slope (m/s) of the per-period mean deflection against time: the DC Fourier coefficient of each block
    (:class:`afmid.preprocess.periods.HarmonicBlocks`), fitted by a straight line over the blocks."""
    if blocks.n_blocks < 3:
        return 0.0
    dc = np.empty(blocks.n_blocks)
    for b0, b1 in blocks.chunks():
        lo = blocks.start + b0 * blocks.L
        piece = x[lo:lo + (b1 - b0) * blocks.L, None]
        dc[b0:b1] = blocks.project_blocks(piece, b0, blocks.rotation(b0, b1))[:, 0, 0]
    centres = blocks.block_times() + 0.5 * blocks.L * blocks.dt
    slope, _ = np.polyfit(centres - centres.mean(), dc, 1)
    return float(slope)


def remove_drift(x: np.ndarray, t: np.ndarray, blocks) -> tuple[np.ndarray, float]:
    """``x`` with the per-period mean's linear drift removed (about the record's centre) and the slope, m/s."""
    slope = period_mean_slope(x, t, blocks)
    centre = 0.5 * (t[0] + t[-1])
    return x - slope * (t - centre), slope

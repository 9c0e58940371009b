"""Preprocessing: segmentation, filtering and differentiation.

Steady tapping motion is periodic in the drive, so afmid works period by period.
:func:`afmid.preprocess.harmonics.estimate_drive` measures the actual drive frequency from
the data (the nominal value is not trusted), :func:`harmonic_blocks` cuts the trace into
blocks of about one period and fits each with a truncated Fourier series in the
drive harmonics (a least-squares projection, exact for a non-integer number of
samples per period). Derivatives of a Fourier series are exact, so the second
derivative of noisy data is never formed by finite differences; the regression
applies the *same* projection to every library column (a weak form with
Fourier test functions), so truncating harmonics does not bias the fit.

Time-domain differentiators (for transients and for the model-free force per
sample) are declared in :data:`afmid.preprocess.differentiation.DIFFERENTIATORS`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from afmid.errors import InputError
from afmid.preprocess.harmonics import (
    amplitude_change,
    apply_rows,
    block_layout,
    fourier_design,
    harmonic_cos_sin,
    highest_harmonic,
    least_squares_projector,
    noise_variance_factor,
    rotate_to_global,
    rotation,
)
from afmid.threads import map_in_order

log = logging.getLogger(__name__)


def detrend(x: np.ndarray, t: np.ndarray, mode: str) -> tuple[np.ndarray, dict]:
    """Remove an offset (``offset``). Returns the corrected trace and what was removed (m). ``linear`` changes
    nothing here: :func:`afmid.fit.prepare.prepare` estimates the drift (:mod:`afmid.preprocess.baseline`)."""
    if mode == "none":
        return x, {}
    if mode == "offset":
        offset = float(x.mean())
        return x - offset, {"offset": offset}
    if mode == "linear":
        # Not a line through the oscillation (its partial period alone makes a fake ramp): the fit estimates
        # the drift with the force law (afmid.preprocess.baseline) once the periods are known.
        return x, {}
    raise ValueError(mode)


# --------------------------------------------------------------------------- harmonic blocks
#: Blocks (or windows) per chunk when per-sample data are projected, integrated or synthesised: bounds the
#: temporaries on long traces. A multiple of 8: every chunk's BLAS product then rounds exactly like one
#: product over all blocks (OpenBLAS works on panels of 4-8 columns), so chunking changes no result.
CHUNK_BLOCKS = 2048

@dataclass
class HarmonicBlocks:
    """Least-squares Fourier fits of consecutive blocks of ``L`` samples (about one period each).

    Coefficient layout per block: ``[c0, a1, b1, ..., aK, bK]`` for
    ``c0 + sum(a_n cos(n w t) + b_n sin(n w t))`` in *global* time t, so blocks
    of a steady motion have equal coefficients up to noise.
    """

    omega: float  # rad/s
    dt: float  # s
    L: int  # samples per block
    K: int  # highest harmonic
    start: int  # index of the first sample used
    n_blocks: int
    t0: float  # time of sample 0, s
    design: np.ndarray  # (L, 2K+1) local basis
    projector: np.ndarray  # (2K+1, L) pseudo-inverse of the local basis
    oversample: int = 1  # fine-grid points per sample for evaluating library terms
    design_fine: np.ndarray | None = None  # (L * oversample, 2K+1)

    @property
    def n_coef(self) -> int:
        return 2 * self.K + 1

    @property
    def harmonics(self) -> np.ndarray:
        """Harmonic number of each coefficient row (0, 1, 1, 2, 2, ...)."""
        return np.concatenate([[0], np.repeat(np.arange(1, self.K + 1), 2)])

    @property
    def used(self) -> slice:
        return slice(self.start, self.start + self.n_blocks * self.L)

    def block_times(self) -> np.ndarray:
        """Start time of each block, s."""
        return self.t0 + (self.start + self.L * np.arange(self.n_blocks)) * self.dt

    def _rotations(self) -> tuple[np.ndarray, np.ndarray]:
        theta = np.outer(self.block_times(), np.arange(1, self.K + 1)) * self.omega  # (n_blocks, K)
        return np.cos(theta), np.sin(theta)

    def to_global(self, local: np.ndarray) -> np.ndarray:
        """Rotate local-time coefficients (n_blocks, 2K+1, m) to global time."""
        return rotate_to_global(local, self.block_times(), self.omega)

    def to_local(self, coef: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`to_global`."""
        c, s = self._rotations()
        out = coef.copy()
        a, b = coef[:, 1::2, :], coef[:, 2::2, :]
        out[:, 1::2, :] = c[..., None] * a + s[..., None] * b
        out[:, 2::2, :] = -s[..., None] * a + c[..., None] * b
        return out

    def chunks(self, size: int | None = None) -> list[tuple[int, int]]:
        """Block ranges (first, stop) of at most ``size`` blocks (default :data:`CHUNK_BLOCKS`, a multiple of 8)."""
        size = size or CHUNK_BLOCKS
        return [(b, min(b + size, self.n_blocks)) for b in range(0, self.n_blocks, size)]

    def project(self, columns: np.ndarray) -> np.ndarray:
        """Fourier coefficients (n_blocks, 2K+1, m) of sample columns (N,) or (N, m), global phase."""
        cols = columns[self.used]
        if cols.ndim == 1:
            cols = cols[:, None]
        out = np.empty((self.n_blocks, self.n_coef, cols.shape[1]))
        for b0, b1 in self.chunks():
            out[b0:b1] = self.project_blocks(cols[b0 * self.L:b1 * self.L], b0)
        return out

    def project_blocks(self, cols: np.ndarray, first: int = 0, turn=None) -> np.ndarray:
        """Coefficients (n, 2K+1, m) of blocks ``first`` .. ``first + n - 1`` from their samples (n L, m).

        ``turn``: :meth:`rotation` of these blocks, if at hand."""
        blocks = cols.reshape(-1, self.L, cols.shape[1])
        local = apply_rows(self.projector, blocks)
        return rotate_to_global(local, self.block_times()[first:first + blocks.shape[0]], self.omega, turn)

    def rotation(self, first: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:func:`rotation` of blocks ``first`` .. ``stop - 1`` (the same for the weak-form windows starting there)."""
        return rotation(self.block_times()[first:stop], self.omega, self.K)

    def fine_times(self, first: int = 0, stop: int | None = None) -> np.ndarray:
        """Times (n, L * oversample) of the fine grid of blocks ``first`` .. ``stop - 1``, s."""
        local = np.arange(self.L * self.oversample) * (self.dt / self.oversample)
        return self.block_times()[first:stop, None] + local[None, :]

    def synthesize_fine(self, coef: np.ndarray, first: int = 0) -> np.ndarray:
        """The series (n, L * oversample, m) on the fine grid of blocks ``first`` .. ``first + n - 1``."""
        n, k, m = coef.shape
        rows = self.synthesize_fine_rows(*(coef[:, :, j] for j in range(m)), first=first)
        return np.stack(rows, axis=2)

    def synthesize_fine_rows(self, *coefs: np.ndarray, first: int = 0) -> list[np.ndarray]:
        """Several series (each (n, 2K+1), global phase) on the fine grid of blocks ``first`` ..: (n, L U) each.

        One BLAS product for all of them ((m n, 2K+1) by (2K+1, L U)); a stacked
        product per block (121 x 1 columns) runs ~3x slower.
        """
        n = coefs[0].shape[0]
        times = self.block_times()[first:first + n]
        c, s = rotation(times, -self.omega, self.K)  # once for all the series (the same blocks)
        turn = (np.tile(c, (len(coefs), 1)), np.tile(s, (len(coefs), 1)))
        local = rotate_to_global(np.concatenate(coefs, axis=0)[..., None], np.tile(times, len(coefs)), -self.omega,
                                 turn)
        values = local[..., 0] @ self.design_fine.T
        return [values[i * n:(i + 1) * n] for i in range(len(coefs))]

    def derivative(self, coef: np.ndarray, order: int = 1) -> np.ndarray:
        """Coefficients of the ``order``-th time derivative (exact for the series)."""
        n = np.arange(1, self.K + 1)[None, :, None] * self.omega
        out = coef.copy() if order == 0 else coef
        for _ in range(order):  # each order written once into a fresh array (copies of the halves cost 3 passes)
            out, a, b = np.empty_like(out), out[:, 1::2, :], out[:, 2::2, :]
            np.multiply(n, b, out=out[:, 1::2, :])
            np.multiply(-n, a, out=out[:, 2::2, :])  # -n * a, as (-n) * a
            out[:, 0, :] = 0.0
        return out

    def synthesize(self, coef: np.ndarray) -> np.ndarray:
        """Samples (n_blocks * L, m) of the series, on the used samples."""
        out = np.empty((self.n_blocks * self.L, coef.shape[2]))

        def synthesize(bounds: tuple[int, int]) -> None:  # one chunk, into its own samples (chunks share threads)
            b0, b1 = bounds
            out[b0 * self.L:b1 * self.L] = self.synthesize_blocks(coef[b0:b1], b0)

        map_in_order(synthesize, self.chunks())
        return out

    def synthesize_blocks(self, coef: np.ndarray, first: int = 0) -> np.ndarray:
        """Samples (n L, m) of the series of blocks ``first`` .. ``first + n - 1`` (coef (n, 2K+1, m))."""
        c, s = self.rotation(first, first + coef.shape[0])  # to local time, as to_local
        local = coef.copy()
        a, b = coef[:, 1::2, :], coef[:, 2::2, :]
        local[:, 1::2, :] = c[..., None] * a + s[..., None] * b
        local[:, 2::2, :] = -s[..., None] * a + c[..., None] * b
        return apply_rows(self.design, local).reshape(-1, coef.shape[2])

    def evaluate(self, coef: np.ndarray, phase: np.ndarray) -> np.ndarray:
        """Series at drive phases ``phase`` (rad, 0 = t where w t is a multiple of 2 pi): (n_blocks, P, m)."""
        basis = self._phase_basis(np.asarray(phase, dtype=float))
        b, k, m = coef.shape
        flat = np.ascontiguousarray(coef.transpose(0, 2, 1)).reshape(b * m, k)
        return (flat @ basis.T).reshape(b, m, -1).transpose(0, 2, 1)  # one BLAS product (einsum is not BLAS)

    def _phase_basis(self, phase: np.ndarray) -> np.ndarray:
        """``fourier_design(phase, 1, K)``, the last one kept: a fit's force curves evaluate every curve (deflection,
        velocity, force, ...) on the same phase grid, and the basis was ~5 % of a map pixel's time. The same bits."""
        key = (phase.shape, phase.tobytes())
        last = self.__dict__.get("_last_phase_basis")
        if last is None or last[0] != key:
            last = (key, fourier_design(phase, 1.0, self.K))
            self.__dict__["_last_phase_basis"] = last
        return last[1]

    def evaluate_in_periods(self, coef: np.ndarray, phase: np.ndarray, cycles: np.ndarray, drive_omega: float
                            ) -> np.ndarray:
        """Series (n, 2K+1, m) at the times (2 pi ``cycles``_i + ``phase``) / ``drive_omega`` (s): (n, P, m).

        The series turn with these blocks' frequency ``omega``. When the drive's ``drive_omega`` (rad/s) differs
        from it (the fit's drive is the nominal or a searched frequency, the blocks were cut at the one measured
        on loading), the drive's period i starts at a different phase of the series in every period: evaluating
        at ``phase`` alone lets the per-period curves drift against the samples by 2 pi (omega / drive_omega - 1)
        per period (2e-4 rad per period measured at a 3.4e-5 relative difference). Equal frequencies give
        :meth:`evaluate` at ``phase`` bit for bit.
        """
        ratio = self.omega / drive_omega
        cycles = np.asarray(cycles, dtype=float)
        if ratio == 1.0 and np.all(np.mod(cycles, 1.0) == 0.0):
            # Whole periods at the blocks' own frequency all start at phase 0 of the series: the rotation by 0
            # (cos 1, sin 0) would give the coefficients back, the same bits; skipped (~1 ms a map pixel).
            return self.evaluate(coef, phase)
        # The series' phase at each period's start, reduced mod 2 pi before the harmonic numbers multiply it.
        start_phase = 2.0 * np.pi * np.mod(cycles * ratio, 1.0)
        local = rotate_to_global(coef, start_phase / self.omega, -self.omega)
        return self.evaluate(local, phase * ratio)

    def noise_variance_factor(self) -> np.ndarray:
        """diag(P P^T): variance of each coefficient per unit white-noise variance of the samples."""
        return noise_variance_factor(self.projector)


@dataclass
class WeakWindows:
    """Weak-form test functions: sin^4 windows of two periods (hop one period) times drive harmonics.

    psi_n(t) = w(s) {1, cos(n w t), sin(n w t)} with w(s) = sin^4(pi s / T_w) on
    s in [0, T_w]. w, w' and w'' vanish at both ends, so integrating the equation of
    motion against psi moves every derivative onto psi exactly, for any motion:
    no derivative of noisy data, and no assumption that a period repeats. (sin^4
    rather than a Hann window: smooth to third order at the ends, so the
    trapezoid quadrature stays spectrally accurate.)
    Matrices hold the local test functions (and derivatives) times the
    quadrature weight dt, on the 2L + 1 samples of a window.
    """

    omega: float
    dt: float
    L: int  # samples per period block (hop)
    K: int
    start: int  # sample index of window 0
    n_windows: int
    t0: float
    psi: np.ndarray  # (2K+1, 2L+1) psi * dt
    dpsi: np.ndarray  # (2K+1, 2L+1) psi' * dt
    ddpsi: np.ndarray  # (2K+1, 2L+1) psi'' * dt
    #: (2 (2K+1), L U) psi * dt / U on the fine grid of two blocks, as two C-contiguous halves stacked: the rows
    #: over the first block, then the rows over the second (the layout of the weak form's one matrix product)
    psi_halves: np.ndarray

    def __post_init__(self) -> None:
        self._turns: dict = {}  # (first, count) -> rotation of those windows (see rotation())

    @property
    def psi_fine(self) -> np.ndarray:
        """(2K+1, 2 L U) psi * dt / U on the fine grid of two blocks (made from :attr:`psi_halves` on each call)."""
        rows = self.psi_halves.shape[0] // 2
        return np.concatenate([self.psi_halves[:rows], self.psi_halves[rows:]], axis=1)

    def start_times(self) -> np.ndarray:
        return self.t0 + (self.start + self.L * np.arange(self.n_windows)) * self.dt

    def windows(self, samples: np.ndarray) -> np.ndarray:
        """(n_windows, 2L+1, m) views of sample columns (N,) or (N, m); zero past the end (where w = 0)."""
        cols = samples[:, None] if samples.ndim == 1 else samples
        idx = self.start + self.L * np.arange(self.n_windows)[:, None] + np.arange(2 * self.L + 1)[None, :]
        padded = np.concatenate([cols, np.zeros((1, cols.shape[1]))])
        return padded[np.minimum(idx, cols.shape[0])]

    def integrate(self, matrix: np.ndarray, samples: np.ndarray) -> np.ndarray:
        """Global-phase integrals (n_windows, 2K+1, m) of sample columns against ``matrix`` rows."""
        cols = samples[:, None] if samples.ndim == 1 else samples
        out = np.empty((self.n_windows, matrix.shape[0], cols.shape[1]))
        for w0, w1 in self.chunks():
            lo, hi = self.sample_range(w0, w1)
            out[w0:w1] = self.integrate_samples(matrix, cols[lo:hi], w0, w1 - w0)
        return out

    def chunks(self, size: int | None = None) -> list[tuple[int, int]]:
        """Window ranges (first, stop) of at most ``size`` windows (default :data:`CHUNK_BLOCKS`)."""
        size = size or CHUNK_BLOCKS
        return [(w, min(w + size, self.n_windows)) for w in range(0, self.n_windows, size)]

    def sample_range(self, first: int, stop: int) -> tuple[int, int]:
        """Samples [lo, hi) that windows ``first`` .. ``stop - 1`` span (hi may pass the end of the trace)."""
        return self.start + self.L * first, self.start + self.L * (stop + 1) + 1

    def integrate_samples(self, matrix: np.ndarray, cols: np.ndarray, first: int, count: int | None = None,
                          turn=None) -> np.ndarray:
        """:meth:`integrate` over windows ``first`` .. ``first + count - 1`` (default: up to the last window).

        ``cols`` (n, m) are the samples from ``sample_range(first, ...)[0]`` on, as far as the trace goes
        (samples past its end count as zero: the windows vanish there). ``turn``: the rotation of these
        windows (:meth:`HarmonicBlocks.rotation` of the blocks they start at), if at hand.
        """
        if count is None:
            count = self.n_windows - first
        L, m = self.L, cols.shape[1]
        need = L * (count + 1) + 1
        if cols.shape[0] >= need:
            padded = np.ascontiguousarray(cols[:need])
        else:
            padded = np.zeros((need, m))
            padded[:cols.shape[0]] = cols
        # The windows' samples laid out as apply_rows lays out its blocks, (2L+1, count m), in one copy.
        step, item = padded.strides
        windows = np.lib.stride_tricks.as_strided(padded, (2 * L + 1, count, m), (step, L * step, item),
                                                  writeable=False)
        flat = np.ascontiguousarray(windows).reshape(2 * L + 1, count * m)
        local = (matrix @ flat).reshape(matrix.shape[0], count, m).transpose(1, 0, 2)
        return rotate_to_global(local, self.start_times()[first:first + count], self.omega, turn)

    def integrate_fine(self, fine: np.ndarray, first: int = 0) -> np.ndarray:
        """Integrals over windows ``first``, ``first + 1``, ... of fine-grid block columns (n, L U, m).

        ``fine`` holds blocks ``first`` .. ``first + n - 1``; window b spans
        blocks b and b + 1, so n blocks give n - 1 windows: its integral is the
        first half of the test functions applied to block b plus the second half
        applied to block b + 1 (no copies of the blocks).
        """
        n = min(fine.shape[0] - 1, self.n_windows - first)
        return self.integrate_fine_columns(np.ascontiguousarray(fine[: n + 1].transpose(1, 0, 2)), first)

    def integrate_fine_columns(self, columns: np.ndarray, first: int = 0, support: np.ndarray | None = None
                               ) -> np.ndarray:
        """:meth:`integrate_fine` of columns already laid out sample-major: ``columns`` (L U, n + 1, m),
        C-contiguous, holds blocks ``first`` .. ``first + n`` (``fine.transpose(1, 0, 2)``), giving windows
        ``first`` .. ``first + n - 1`` (or up to the last window). The same bits as :meth:`integrate_fine`.

        ``support`` (L U, m) bool (:func:`fine_support`; None: every sample): the fine-grid samples where each
        column may be non-zero in some block. A column non-zero on fewer than :data:`NARROW_SUPPORT` of them (a
        contact-only term) is integrated over its support only: the same sum without its exact zeros, so equal to
        rounding (the products' summation order changes; ~4x fewer operations for a term in contact 10 % of
        the period)."""
        half, n_blocks, m = columns.shape
        n = min(n_blocks - 1, self.n_windows - first)
        if n + 1 < n_blocks:
            columns = np.ascontiguousarray(columns[:, : n + 1])
        rows = self.psi_halves.shape[0] // 2
        narrow = [] if support is None else np.flatnonzero(support.sum(axis=0) < NARROW_SUPPORT * half).tolist()
        if narrow:
            both = np.empty((2, rows, n + 1, m))
            wide = [j for j in range(m) if j not in narrow]
            if wide:
                both[..., wide] = (self.psi_halves @ columns[:, :, wide].reshape(half, -1)).reshape(
                    2, rows, n + 1, len(wide))
            for j in narrow:
                on = np.flatnonzero(support[:, j])
                if on.size and on[-1] - on[0] + 1 == on.size:
                    # One run of samples (contact once per period): the test functions' columns as a view (the
                    # same product as the gathered copy, the same bits; the 1.4 MB copy was ~0.35 ms a build).
                    run = slice(int(on[0]), int(on[-1]) + 1)
                    part = self.psi_halves[:, run] @ np.ascontiguousarray(columns[run, :, j])
                else:
                    part = self.psi_halves[:, on] @ columns[on, :, j]
                both[..., j] = part.reshape(2, rows, n + 1)
        else:
            # One GEMM for both halves and all blocks: (2 rows, LU) @ (LU, (n + 1) m). A batched matmul over
            # blocks with few columns (m ~ 3-20 terms) runs ~10x slower.
            both = (self.psi_halves @ columns.reshape(half, -1)).reshape(2, rows, n + 1, m)
        local = (both[0, :, :n] + both[1, :, 1:]).transpose(1, 0, 2)
        return rotate_to_global(local, self.start_times()[first : first + n], self.omega, self.rotation(first, n))

    def rotation(self, first: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        """:func:`rotation` of windows ``first`` .. ``first + count - 1``, made once and kept: every library
        evaluation of a fit turns its integrals by the same angles (2 K n cos/sin each time)."""
        key = (first, count)
        if key not in self._turns:
            self._turns[key] = rotation(self.start_times()[first:first + count], self.omega, self.K)
        return self._turns[key]


#: Share of a block's fine-grid samples below which a column is integrated over its non-zero samples only.
NARROW_SUPPORT = 0.5


def fine_support(columns: np.ndarray) -> np.ndarray:
    """(L U, m) bool: the fine-grid samples of a block where each column of ``columns`` (L U, blocks, m) is
    non-zero in at least one block (NaN counts as non-zero)."""
    half, _, m = columns.shape
    nonzero = (columns != 0.0).reshape(half, -1)
    # One column at a time over a strided view: ~10x faster than any() over the middle axis (a per-element loop).
    return np.stack([nonzero[:, j::m].any(axis=1) for j in range(m)], axis=1)


def weak_windows(blocks: "HarmonicBlocks") -> WeakWindows:
    """Test functions matching ``blocks`` (same hop, harmonics and fine grid)."""
    L, K, dt, w = blocks.L, blocks.K, blocks.dt, blocks.omega
    T_w = 2 * L * dt

    def family(s: np.ndarray, weight: float, derivatives: bool = True, out: np.ndarray | None = None):
        # Rows: the window, then window x (cos, sin) of each harmonic, interleaved; the same element-wise
        # arithmetic as one row at a time, on (K, samples) arrays at once.
        # Written into one array in place: the fine family is ~4 MB, and each temporary (stacked, concatenated,
        # scaled) was a pass through memory: 2.5x the time of the same arithmetic in place (bench_selection).
        a = np.pi / T_w
        sn_ = np.sin(a * s)
        win = sn_**4
        n = np.arange(1, K + 1)[:, None] * w
        psi = np.empty((2 * K + 1, s.size)) if out is None else out
        psi[0] = win
        harmonic_cos_sin(w * s, K, out_cos=psi[1::2], out_sin=psi[2::2])
        phi = psi[1:].copy() if derivatives else None
        psi[1:] *= win
        psi *= weight
        if not derivatives:
            return psi, None, None
        c, sn = phi[0::2], phi[1::2]
        cs_ = np.cos(a * s)
        dwin = 4 * a * sn_**3 * cs_
        ddwin = 4 * a**2 * (3 * sn_**2 * cs_**2 - sn_**4)
        dphi, ddphi = np.empty_like(phi), np.empty_like(phi)
        dphi[0::2], dphi[1::2] = -n * sn, n * c
        ddphi[0::2], ddphi[1::2] = -n ** 2 * c, -n ** 2 * sn
        dpsi = np.concatenate([dwin[None], dwin * phi + win * dphi]) * weight
        ddpsi = np.concatenate([ddwin[None], ddwin * phi + 2 * dwin * dphi + win * ddphi]) * weight
        return psi, dpsi, ddpsi

    s = np.arange(2 * L + 1) * dt
    psi, dpsi, ddpsi = family(s, dt)
    U = blocks.oversample
    s_fine = np.arange(2 * L * U) * (dt / U)
    # Each half of the two blocks written in place (the arithmetic is element by element: the same values as
    # the family over both blocks at once, without the 4 MB copy that cut it into halves, ~2 ms a map pixel).
    rows = 2 * K + 1
    psi_halves = np.empty((2 * rows, L * U))
    family(s_fine[:L * U], dt / U, derivatives=False, out=psi_halves[:rows])
    family(s_fine[L * U:], dt / U, derivatives=False, out=psi_halves[rows:])
    n_windows = blocks.n_blocks - 1
    return WeakWindows(w, dt, L, K, blocks.start, n_windows, blocks.t0, psi, dpsi, ddpsi, psi_halves)


def harmonic_blocks(
    n_samples: int, sample_rate: float, frequency: float, t0: float = 0.0,
    periods_per_block: int = 1, max_harmonic: int = 60, oversample: int = 1,
) -> HarmonicBlocks:
    """Blocks of ``round(periods_per_block * samples_per_period)`` samples, and their LS Fourier projector."""
    spp = sample_rate / frequency
    L, n_blocks, start = block_layout(n_samples, periods_per_block * spp)
    if n_blocks < 3:
        raise InputError(f"only {n_blocks} whole blocks of {L} samples; need at least 3 drive periods", key="data.path")
    K = highest_harmonic(spp, max_harmonic)
    if K < 2:
        raise InputError(f"{spp:.1f} samples per period cannot resolve any harmonic beyond the drive", key="data.sample_rate")
    dt = 1.0 / sample_rate
    omega = 2 * np.pi * frequency
    design = fourier_design(np.arange(L) * dt, omega, K)
    projector = least_squares_projector(design)
    # Library terms are evaluated on this fine grid of the smooth reconstructed trajectory: terms with
    # kinks or steps (contact onset, adhesion) have slowly decaying harmonics, and on the sample grid
    # their edges would be quantised to a sample (a phase error of up to n w dt / 2 at harmonic n).
    design_fine = fourier_design(np.arange(L * oversample) * (dt / oversample), omega, K)
    return HarmonicBlocks(omega, dt, L, K, start, n_blocks, t0, design, projector, oversample, design_fine)


def ou_smooth(coef: np.ndarray, noise_var: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel smoothing of per-block Fourier coefficients across blocks.

    Each coefficient is modelled as an Ornstein-Uhlenbeck process around its
    mean (correlation ``rho`` from one block to the next: the thermal amplitude
    and phase fluctuations of the cantilever) observed with white noise of
    variance ``noise_var`` (detector noise through the projection). The process
    variance is estimated from the block-to-block scatter. Returns the smoothed
    coefficients (B, n) and their posterior variance (B, n).
    """
    return ou_smooth_given(coef, noise_var, ou_smooth_variance(coef, noise_var), rho)


def ou_smooth_variance(coef: np.ndarray, noise_var: np.ndarray) -> np.ndarray:
    """The process variance :func:`ou_smooth` estimates from the block-to-block scatter of ``coef`` (B, n)."""
    return np.maximum(coef.var(axis=0) - noise_var, 1e-6 * noise_var)


def ou_smooth_given(coef: np.ndarray, noise_var: np.ndarray, signal_var: np.ndarray, rho: float,
                    mean: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ou_smooth` with the process variance ``signal_var`` (n,) given: linear in ``coef`` (for fixed
    variances), so it also smooths a perturbation of the coefficients as the trajectory's smoother does
    (:mod:`afmid.fit.thermal_bias`). ``mean`` (n,): the mean taken out and put back (None: ``coef``'s)."""
    B, n = coef.shape
    mean = coef.mean(axis=0) if mean is None else mean
    q = signal_var * (1 - rho**2)
    m_f = np.empty((B, n))
    p_f = np.empty((B, n))
    m, P = np.zeros(n), signal_var.copy()
    obs = coef - mean
    if B >= OU_NUMBA_MIN_BLOCKS:  # the same arithmetic compiled (the loop below costs ~25 us per block)
        m_s, p_s = np.empty((B, n)), np.empty((B, n))
        _ou_kernel()(obs, noise_var * np.ones(n), signal_var, q, rho, rho**2, m_f, p_f, m_s, p_s)
        return m_s + mean, p_s
    for b in range(B):
        if b:
            m, P = rho * m, rho**2 * P + q
        gain = P / (P + noise_var)
        m = m + gain * (obs[b] - m)
        P = (1 - gain) * P
        m_f[b], p_f[b] = m, P
    m_s, p_s = m_f.copy(), p_f.copy()
    for b in range(B - 2, -1, -1):
        p_pred = rho**2 * p_f[b] + q
        g = rho * p_f[b] / p_pred
        m_s[b] = m_f[b] + g * (m_s[b + 1] - rho * m_f[b])
        p_s[b] = p_f[b] + g**2 * (p_s[b + 1] - p_pred)
    return m_s + mean, p_s


#: From this many blocks on :func:`ou_smooth` runs compiled (numba), below as NumPy (no compilation).
OU_NUMBA_MIN_BLOCKS = 2000
_OU_KERNEL = None


def _ou_loops(obs, noise_var, signal_var, q, rho, rho2, m_f, p_f, m_s, p_s):  # pragma: no cover - compiled
    """The filter and smoother loops of :func:`ou_smooth`, element by element in the same operation order."""
    B, n = obs.shape
    for b in range(B):
        for j in range(n):
            if b:
                m = rho * m_f[b - 1, j]
                P = rho2 * p_f[b - 1, j] + q[j]
            else:
                m = 0.0
                P = signal_var[j]
            gain = P / (P + noise_var[j])
            m_f[b, j] = m + gain * (obs[b, j] - m)
            p_f[b, j] = (1 - gain) * P
    m_s[B - 1] = m_f[B - 1]
    p_s[B - 1] = p_f[B - 1]
    for b in range(B - 2, -1, -1):
        for j in range(n):
            p_pred = rho2 * p_f[b, j] + q[j]
            g = rho * p_f[b, j] / p_pred
            m_s[b, j] = m_f[b, j] + g * (m_s[b + 1, j] - rho * m_f[b, j])
            p_s[b, j] = p_f[b, j] + g * g * (p_s[b + 1, j] - p_pred)


def _ou_kernel():
    global _OU_KERNEL
    if _OU_KERNEL is None:
        from numba import njit

        _OU_KERNEL = njit(cache=True)(_ou_loops)
    return _OU_KERNEL


def amplitude_per_block(coef_x: np.ndarray) -> np.ndarray:
    """First-harmonic amplitude of each block (m) from deflection coefficients (n_blocks, 2K+1[, 1])."""
    c = coef_x[..., 0] if coef_x.ndim == 3 else coef_x
    return np.hypot(c[:, 1], c[:, 2])


def steadiness(coef_x: np.ndarray) -> float:
    """Relative amplitude change across the trace from a linear fit (0 = steady)."""
    return amplitude_change(amplitude_per_block(coef_x))

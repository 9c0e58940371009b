"""The thermal force's bias of the weak-form regression, and its removal from the per-window factors.

A weak-form row is the equation of motion integrated against a test function psi over one window (two
periods): ``Y = A coef + e``, whose equation error ``e = -integral psi(t) xi(t) dt`` is the window's thermal
force xi (plus detector noise, independent of the motion). The library columns ``A_l = integral psi f_l(x, v)``
are evaluated on the trajectory, and the trajectory inside the window is moved by that same xi: the free
lever's response to it, ``delta x(t) = integral_{s<t} h(t - s) xi(s) ds`` (h: displacement per unit impulse,
``m h'' + c h' + k h = delta(t)``). With ``E[xi(t) xi(s)] = 2 c k_B T delta(t - s)`` (c = k / (Q w0)):

    E[A_l e] = -2 c k_B T integral psi(t) [df_l/dx(t) G(t) + df_l/dv(t) G'(t)] dt,
    G(t) = integral_{s<t} psi(s) h(t - s) ds,   G'(t) = integral_{s<t} psi(s) h'(t - s) ds

(for Gaussian thermal motion the derivatives are those averaged over it: Stein's lemma, below). The
least-squares estimate is then biased by
``(A^T W A)^-1 E[A^T W e]``: h'(0+) = 1 / m > 0, so a damping term (df/dv > 0) reads low in liquid (Q 2-4),
where c k_B T is large; in air (k 40 N/m, 300 kHz, Q 250) c is 15-19x smaller than on those levers.

:func:`thermal_bias_rows` evaluates ``E[A_l e]`` per window and test function (the same integrals as the
library columns, with the test functions replaced by the kernels ``psi(t) G(t)``, ``psi(t) G'(t)``, and the
terms by their derivatives along the trajectory; G as the fit sees the motion: through its per-period Fourier
fits and its smoother across periods); :func:`remove_thermal_bias` takes ``b = E[A^T W e]`` out of the normal
equations: every window's data moved by the same ``A_w v`` in the span of the columns (``A^T W A v = -b``), so
every subset of the columns solves its corrected normal equations, the full model's residual stays, and every
use of the factors (selection, cross-validation, bootstrap over windows) sees the corrected equations.

Assumes: the thermal force white, on the first mode (higher modes and a declared detector's restoration are
not followed); the lever's response that of the free lever (in contact the sample's stiffness and damping
change it for part of each period: on the Q 2 lever of scripts/liquid_velocity_bias.py, the response
linearised about the fitted contact moved eta by 0.04 %); the thermal motion Gaussian, so that
E[f(x) e] = E[f'(x)] Cov(x, e) holds beyond first order (Stein's lemma): the derivatives are taken on the
trajectory as it is (one draw of the motion), which is what makes the average over windows right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

import afmid.fit.regression as regression
from afmid.io.cantilever import lever_damping, lever_mass
from afmid.physics.effects import BOLTZMANN
from afmid.physics.library import Library
from afmid.preprocess.harmonics import rotate_to_global
from afmid.preprocess.periods import NARROW_SUPPORT, fine_support, ou_smooth_given

#: Relative step of the central differences of the terms (of the amplitude, and of the amplitude times w).
DERIVATIVE_STEP = 1e-4

#: ``fit.thermal_bias: auto`` corrects levers of this quality factor or lower. The bias scales with the lever's
#: damping c = k / (Q w0): measured (scripts/liquid_velocity_bias.py) eta -2.5 % on a Q 4 lever and
#: -5.3 % on a Q 2 lever in liquid (1000-period records), while on air levers (k 40 N/m, 300 kHz, Q 250;
#: c 15-19x smaller) the correction moves E* by -0.08 %, H by +0.9 % and eta by +0.01 %, below their
#: statistical errors, at 2.4x the fit's CPU (a map pixel 35 -> 58 ms). Liquid levers have Q 1-10, air levers
#: 100-600 (shared/notes: real experiments).
AUTO_MAX_QUALITY_FACTOR = 20.0


def corrects_thermal_bias(setting: str | bool, quality_factor: float) -> bool:
    """Whether the fit takes the thermal force's bias out (``fit.thermal_bias``: true, false, or "auto": at a
    quality factor <= :data:`AUTO_MAX_QUALITY_FACTOR`)."""
    if setting == "auto":
        return quality_factor <= AUTO_MAX_QUALITY_FACTOR
    return setting is True


@dataclass(frozen=True, eq=False)  # equality below: the variances are arrays
class TrajectorySmoother:
    """How the fit's trajectory is made from the per-period coefficients (:func:`afmid.fit.prepare.prepare`), as a
    linear filter across periods: ``ou`` (:func:`afmid.preprocess.periods.ou_smooth_given` with the variances
    it used), ``savgol`` (``fit.smooth_periods``) or ``none`` (each period as it is)."""

    kind: str
    n_blocks: int  # periods of the trace (the OU smoother's mean is over all of them)
    noise_var: np.ndarray | None = None  # (2K+1,) m^2
    signal_var: np.ndarray | None = None  # (2K+1,) m^2
    rho: float = 0.0
    window: int = 0  # savgol: periods
    #: savgol: the filter across periods itself, (blocks, n) -> (blocks, n)
    #: (:func:`afmid.fit.prepare.smooth_across_blocks` with ``window``)
    across_blocks: Callable | None = None

    def __eq__(self, other) -> bool:
        """The same filter: kind, periods, variances, rho and window (the savgol function is the window's)."""
        if not isinstance(other, TrajectorySmoother):
            return NotImplemented
        same = ((self.kind, self.n_blocks, self.rho, self.window)
                == (other.kind, other.n_blocks, other.rho, other.window))
        return same and all(
            (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))
            for a, b in ((self.noise_var, other.noise_var), (self.signal_var, other.signal_var)))

    __hash__ = None  # arrays inside

    def smooth(self, seq: np.ndarray) -> np.ndarray:
        """The filter applied to a perturbation ``seq`` (blocks, 2K+1, m) of the coefficients (zero outside)."""
        if self.kind == "none":
            return seq
        blocks, rows, m = seq.shape
        if self.kind == "savgol":
            return self.across_blocks(seq.reshape(blocks, -1)).reshape(seq.shape)

        def paired(v):  # the rows of a harmonic alike, so the filter does not depend on the window's phase
            out = v.copy()
            out[1::2] = out[2::2] = 0.5 * (v[1::2] + v[2::2])
            return np.repeat(out, m)

        flat = seq.reshape(blocks, -1)
        smoothed, _ = ou_smooth_given(flat, paired(self.noise_var), paired(self.signal_var), self.rho,
                                      mean=flat.sum(axis=0) / self.n_blocks)
        return smoothed.reshape(seq.shape)


@dataclass(frozen=True)
class ThermalForce:
    """The lever's thermal force as the fit knows it (its configuration): ``fit.temperature`` and the calibrated
    lever, and the filter that makes the trajectory the library is evaluated on; present only where
    ``fit.thermal_noise`` is on."""

    spring_constant: float  # N/m
    omega0: float  # rad/s
    quality_factor: float  # 1
    temperature: float  # K
    smoother: TrajectorySmoother

    @property
    def mass(self) -> float:
        """kg, the effective mass k / w0^2 (afmid.io.cantilever.lever_mass)."""
        return lever_mass(self.spring_constant, self.omega0)

    @property
    def damping(self) -> float:
        """N s/m, c = k / (Q w0) (afmid.io.cantilever.lever_damping)."""
        return lever_damping(self.spring_constant, self.omega0, self.quality_factor)

    @property
    def strength(self) -> float:
        """N^2 s, 2 c k_B T: the thermal force's white spectrum, E[xi(t) xi(s)] = strength * delta(t - s)."""
        return 2.0 * self.damping * BOLTZMANN * self.temperature


def lever_response(force: ThermalForce, t: np.ndarray) -> np.ndarray:
    """The free lever's displacement per unit impulse h(t) (m / (N s)) at times ``t`` >= 0:
    ``m h'' + c h' + k h = delta(t)``, h(0) = 0, h'(0+) = 1 / m. Under- and overdamped."""
    m, c, k = force.mass, force.damping, force.spring_constant
    root = np.sqrt(complex(c * c - 4 * m * k)) / (2 * m)
    s1, s2 = -c / (2 * m) + root, -c / (2 * m) - root
    if abs(s1 - s2) < 1e-9 * abs(s1):  # critically damped: h = t e^{st} / m
        return t * np.exp(s1.real * t) / m
    return ((np.exp(s1 * t) - np.exp(s2 * t)) / (m * (s1 - s2))).real


#: Periods after a window over which the lever's ringing from its thermal force is followed (e^-pi n / Q: 1e-4
#: after 2.9 Q periods). Capped for air (Q 250: 733 periods): on a 300-period trace of tests/configs/dmt.yaml, b
#: with 64 periods differs from b with all 296 by < 1e-4 of itself (16: 7e-4).
MAX_RINGING_PERIODS = 64


def window_responses(psi: np.ndarray, force: ThermalForce, span: int, dt: float) -> np.ndarray:
    """G_j(u) = sum_{s <= u} psi_j(s) ds h(u - s) (rows, ``span``), m / N: the free lever's motion at the data's
    samples u (step ``dt``, s) from the start of a window on, per unit of the window's thermal force projected on
    its test function j (``psi``: (rows, 2 L + 1), psi times the quadrature weight ``dt``). Causal convolutions."""
    size = 1 << int(math.ceil(math.log2(span + psi.shape[1])))
    h = lever_response(force, np.arange(span) * dt)
    return np.fft.irfft(np.fft.rfft(psi, size, axis=1) * np.fft.rfft(h, size), size, axis=1)[:, :span]


@dataclass(frozen=True)
class BiasKernels:
    """The kernels psi(t) G(t) (position) and psi(t) G'(t) (velocity) of one window's test functions, on the fine
    grid of its two blocks, in the layout of :attr:`afmid.preprocess.periods.WeakWindows.psi_halves`: (2 rows,
    L U), the rows over the first block, then over the second. G_j(t) = E[delta x_traj(t) integral psi_j xi] /
    (2 c k_B T): the trajectory's response (as the fit reconstructs it: per-period Fourier fits, smoothed across
    periods) to the window's thermal force. Rows (3K + 1): the mean row with itself, then per harmonic the cos
    row with itself (K), the sin row with itself (K), and the two cross products summed (K): what the rotation
    to global phase needs (:func:`rotate_bias`)."""

    position: np.ndarray
    velocity: np.ndarray
    harmonics: int  # the highest harmonic kept (:data:`KERNEL_TAIL`); rows above it are left at 0


#: The kernels' harmonics are kept up to where the rest holds less than this share of the rows' weighted sum
#: of |kernel| (weights 1 / sigma^2 of the rows), judged on the kernels of the lever's motion before the fit's
#: per-period fits and smoother (which only take from the high harmonics: the cut errs on the side of more):
#: the kernels fall off as the lever's response does and the rows' weights as the detector noise through the
#: operator grows. On the 50-period traces of scripts/liquid_velocity_bias.py (K 60) this keeps 33 (Q 4) and
#: 41 (Q 2) harmonics, and the bias b differs from all 60's by 2e-5 and 3e-5 of itself; 12 in air
#: (tests/configs/dmt.yaml, Q 250).
KERNEL_TAIL = 1e-4


def bias_kernels(windows, blocks, force: ThermalForce, row_variance: np.ndarray) -> BiasKernels:
    """:class:`BiasKernels` of the weak form's test functions (``windows``, on ``blocks``); ``row_variance``
    (2K+1,) the rows' noise variance (the weights 1 / sigma^2 that decide how many harmonics are kept)."""
    L, dt = blocks.L, blocks.dt
    K = blocks.K
    ringing = int(min(MAX_RINGING_PERIODS, math.ceil(force.quality_factor / math.pi * math.log(1e4)),
                      max(blocks.n_blocks - 2, 0)))
    span = (ringing + 2) * L  # the window's two blocks and the ringing after them, on the data's samples
    # The harmonics needed, from the motion itself in the window on the data's samples (psi holds the weight dt).
    in_window = window_responses(windows.psi, force, 2 * L + 1, dt)
    kept = max(_harmonics_needed(_pairs(windows.psi, in_window, K), row_variance),
               _harmonics_needed(_pairs(windows.psi, np.gradient(in_window, dt, axis=1), K), row_variance))
    functions = 2 * kept + 1  # the test functions of those harmonics: the first rows
    G = window_responses(windows.psi[:functions], force, span, dt)
    # ... as the fit sees the motion: per-period Fourier coefficients (n, 2K+1, functions), in the window's frame
    per_period = G[:functions].reshape(functions * (ringing + 2), L) @ blocks.projector.T
    local = per_period.reshape(functions, ringing + 2, -1).transpose(1, 2, 0)
    starts = np.arange(ringing + 2) * L * dt
    framed = rotate_to_global(local, starts, blocks.omega)
    # smoothed across periods, the window in the middle of zeros before it (the smoother looks both ways)
    seq = np.concatenate([np.zeros((ringing,) + framed.shape[1:]), framed])
    smoothed = force.smoother.smooth(seq)[ringing:ringing + 2]
    back = rotate_to_global(smoothed, starts[:2], -blocks.omega)  # to each block's own phase
    fine = blocks.design_fine  # (L U, 2K+1)
    position = np.concatenate([fine @ back[0], fine @ back[1]]).T  # (functions, 2 L U)
    speed = blocks.derivative(back, 1)
    velocity = np.concatenate([fine @ speed[0], fine @ speed[1]]).T
    psi_fine = windows.psi_fine[:functions]
    return BiasKernels(_halves(_pairs(psi_fine, position, kept)), _halves(_pairs(psi_fine, velocity, kept)), kept)


def _pairs(psi: np.ndarray, conv: np.ndarray, K: int) -> np.ndarray:
    """The kernel rows (3K+1, n) of :class:`BiasKernels` from test functions ``psi`` and their responses ``conv``
    (rows 0, cos 1, sin 1, ... up to harmonic K, on one grid)."""
    rows = 2 * K + 1
    cos, sin = slice(1, rows, 2), slice(2, rows, 2)
    out = np.empty((3 * K + 1, conv.shape[1]))
    out[0] = psi[0] * conv[0]
    out[1:K + 1] = psi[cos] * conv[cos]
    out[K + 1:2 * K + 1] = psi[sin] * conv[sin]
    out[2 * K + 1:] = psi[cos] * conv[sin] + psi[sin] * conv[cos]
    return out


def _halves(kernel: np.ndarray) -> np.ndarray:
    """(rows, 2 L U) -> the halves' layout (2 rows, L U): the rows over the first block, then over the second."""
    half = kernel.shape[1] // 2
    return np.ascontiguousarray(np.concatenate([kernel[:, :half], kernel[:, half:]], axis=0))


def _harmonics_needed(kernel: np.ndarray, row_variance: np.ndarray) -> int:
    """The highest harmonic whose kernel rows (3K+1, n; :func:`_pairs`) the bias needs: beyond it the rows'
    weighted sum of |kernel| is below :data:`KERNEL_TAIL` of the whole."""
    K = (kernel.shape[0] - 1) // 3
    size = np.abs(kernel).sum(axis=1)
    per_harmonic = np.empty(K + 1)
    per_harmonic[0] = size[0] / row_variance[0]
    per_harmonic[1:] = (size[1:K + 1] + size[K + 1:2 * K + 1] + size[2 * K + 1:]) / row_variance[1::2]
    total = per_harmonic.sum()
    if total == 0:
        return 0
    beyond = np.concatenate([np.cumsum(per_harmonic[::-1])[::-1][1:], [0.0]])  # the sum above each harmonic
    return int(np.flatnonzero(beyond <= KERNEL_TAIL * total)[0])


def rotate_bias(local: np.ndarray, turn: tuple[np.ndarray, np.ndarray], rows: int) -> np.ndarray:
    """E[A e] per global-phase row (n, ``rows`` = 2K+1, p) from the local pair products ``local`` (n, 3k+1, p) of
    the first k harmonics (rows as in :class:`BiasKernels`; the rows above them 0), with the windows' rotation
    ``turn`` (cos, sin (n, K) of n w t0; :func:`afmid.preprocess.harmonics.rotate_to_global` turns a row pair
    (a, b) into (c a - s b, s a + c b))."""
    n, rows3, p = local.shape
    K = (rows3 - 1) // 3
    c, s = turn[0][:n, :K, None], turn[1][:n, :K, None]
    same_cos, same_sin, cross = local[:, 1:K + 1], local[:, K + 1:2 * K + 1], local[:, 2 * K + 1:]
    out = np.zeros((n, rows, p))
    out[:, 0] = local[:, 0]
    out[:, 1:2 * K + 1:2] = c * c * same_cos - c * s * cross + s * s * same_sin
    out[:, 2:2 * K + 2:2] = s * s * same_cos + c * s * cross + c * c * same_sin
    return out


def thermal_bias_rows(chunks, windows, blocks, library: Library, params: dict, force: ThermalForce,
                      amplitude: float, omega: float, row_variance: np.ndarray) -> np.ndarray:
    """E[A_l e] (W, 2K+1, p), in the units of the columns times N s, of every window and test function.

    ``chunks``: the fine-grid trajectory chunk by chunk, (first block, x, xdot, t) with one block of overlap
    (:func:`afmid.fit.prepare.fine_chunks`); ``windows``: the weak form's
    :class:`afmid.preprocess.periods.WeakWindows`. The terms' derivatives are central differences with steps
    :data:`DERIVATIVE_STEP` times ``amplitude`` (m) and ``amplitude * omega`` (m/s). ``row_variance`` (2K+1,):
    the rows' noise (decides the harmonics the kernels keep, :data:`KERNEL_TAIL`).
    """
    kernels = _kernels_of(windows, blocks, force, row_variance)
    dx, dv = DERIVATIVE_STEP * amplitude, DERIVATIVE_STEP * amplitude * omega
    reads_velocity = library.reads_velocity()
    library.compile(params)
    parts = []
    for b0, x, v, t in chunks:
        n = min(x.shape[0] - 1, windows.n_windows - b0)
        if n <= 0:
            continue
        f_x = (library.evaluate_rows(x + dx, v, t, params) - library.evaluate_rows(x - dx, v, t, params)) / (2 * dx)
        local = _integrate(kernels.position, f_x, x.shape, n)
        if reads_velocity:
            f_v = (library.evaluate_rows(x, v + dv, t, params) - library.evaluate_rows(x, v - dv, t, params)) / (2 * dv)
            local += _integrate(kernels.velocity, f_v, x.shape, n)
        parts.append(rotate_bias(local, windows.rotation(b0, n), blocks.n_coef))
    return -force.strength * np.concatenate(parts, axis=0)


def _kernels_of(windows, blocks, force: ThermalForce, row_variance: np.ndarray) -> BiasKernels:
    """:func:`bias_kernels`, made once per trace's preparation and kept (one at a time: the fit evaluates its
    library many times on one trace)."""
    held = _KERNELS.get("last")
    if held is not None and held[0] is windows and held[1] is force and held[2] is row_variance:
        return held[3]
    kernels = bias_kernels(windows, blocks, force, row_variance)
    _KERNELS["last"] = (windows, force, row_variance, kernels)
    return kernels


_KERNELS: dict = {}


def _integrate(kernel_halves: np.ndarray, values: np.ndarray, shape: tuple, n: int) -> np.ndarray:
    """Window integrals (n, rows, p) of fine-grid values ((blocks L U, p), blocks of ``shape`` (blocks, L U))
    against kernels in the halves' layout: window b is the first half applied to block b plus the second half
    applied to block b + 1. A column that is zero on most samples of every block (a contact term's derivative)
    is integrated over its non-zero samples only (as the library columns are:
    :meth:`afmid.preprocess.periods.WeakWindows.integrate_fine_columns`)."""
    blocks, half = shape
    p = values.shape[-1]
    columns = np.ascontiguousarray(values.reshape(blocks, half, p)[: n + 1].transpose(1, 0, 2))
    rows = kernel_halves.shape[0] // 2
    support = fine_support(columns)
    both = np.empty((2, rows, n + 1, p))
    for j in range(p):
        on = np.flatnonzero(support[:, j])
        if on.size >= NARROW_SUPPORT * half:
            both[..., j] = (kernel_halves @ columns[:, :, j]).reshape(2, rows, n + 1)
        elif on.size:
            run = slice(int(on[0]), int(on[-1]) + 1)  # one run per period (contact once per period), else gathered
            part = (kernel_halves[:, run] @ columns[run, :, j] if on[-1] - on[0] + 1 == on.size
                    else kernel_halves[:, on] @ columns[on, :, j])
            both[..., j] = part.reshape(2, rows, n + 1)
        else:
            both[..., j] = 0.0
    return (both[0, :, :n] + both[1, :, 1:]).transpose(1, 0, 2)


def remove_thermal_bias(T_blocks: np.ndarray, bias: np.ndarray, row_sigma: np.ndarray) -> np.ndarray:
    """The per-window factors ``T_blocks`` (W, q, q) of the whitened ``[A | y]`` with E[A^T W e] taken out of
    their normal equations: the data of every window moved by the same ``A_w v`` inside the span of the columns,
    ``z_w <- z_w + R_w v`` with ``A^T W A v = -b`` (A^T W A = R^T R of all windows combined; b = sum over windows
    and rows of ``bias`` / sigma_r^2, ``bias`` (W, rows, p) for the first p columns; the others, the drive's, are
    not random; with ``fit.cantilever: free`` the lever's own stiffness and damping columns are, and are not
    corrected). Every subset S of the columns then solves ``A_S^T W A_S c = A_S^T W y - b_S`` (the rows S of
    ``A^T W A v``), and the full model's residual is unchanged. One shift for all windows, not one per window:
    a window's own R is near-singular for collinear terms (the powers of a Lennard-Jones library), and per-window
    shifts ``R_w^-T b_w`` differ from window to window by far more than the bias, which the residual then counts.
    The columns are scaled to unit norm for the solve (SI columns span many orders of magnitude); directions the
    columns do not determine (zero singular values) are left alone."""
    q = T_blocks.shape[1]
    p = bias.shape[2]
    b = np.zeros(q - 1)
    b[:p] = np.einsum("wrp,r->p", bias, 1.0 / row_sigma**2)
    R = regression.combine(T_blocks)[:q - 1, :q - 1]
    scale = np.linalg.norm(R, axis=0)
    scale[scale == 0] = 1.0
    S = R / scale  # R^T R v = -b  <=>  S^T S (scale v) = -b / scale
    v = -(np.linalg.pinv(S) @ (np.linalg.pinv(S.T) @ (b / scale))) / scale
    out = T_blocks.copy()
    out[:, :q - 1, q - 1] += T_blocks[:, :q - 1, :q - 1] @ v
    return out

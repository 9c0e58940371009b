"""The analysis the signal checks share: per-period harmonics, noise and the model-free force shape.

Times in samples (it also runs on files without a sample rate). The
oscillation frequency (cycles per sample) comes from the spectrum
(:func:`afmid.preprocess.harmonics.measure_frequency`) or, for a loaded trace, from the
drive the fit uses; then a least-squares Fourier fit of every drive period on
the engine the fit uses (:mod:`afmid.preprocess.harmonics`: harmonics up to 0.45 x samples
per period, at most :data:`MAX_HARMONIC`) gives per-period amplitude, phase and
mean, the period-averaged harmonics with their noise, and the model-free
tip-sample force shape from the harmonics above the noise (the equation of
motion per harmonic, ``F_n / k = (n^2 r^2 - 1 - i n r / Q) X_n`` for n >= 2,
``r = f / f0``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from afmid.preprocess.motion import classify as classify_motion
from afmid.preprocess.harmonics import (
    MIN_PERIODS,
    changes_like_a_transient,
    block_layout,
    fourier_design,
    highest_harmonic,
    least_squares_projector,
    measure_frequency,
    noise_variance_factor,
    rotate_to_global,
    settled_start,
)

#: Fewer samples per period than this and no signal check is meaningful (near Nyquist).
MIN_ANALYSABLE_SPP = 4.0
#: Highest harmonic analysed (afmid.preprocess.harmonics.highest_harmonic), no more than fit.max_harmonic's default:
#: harmonics the fit does not use need no checking.
MAX_HARMONIC = 60
#: A harmonic "stands above the noise" above this many standard deviations (per cos/sin coefficient).
DETECT_SIGMA = 5.0
#: The interaction is put at the negative turning point (the sign flipped) only when its shape is this many times
#: larger there: on records with strong contact and few harmonics above the noise the ratio reaches 2.4-2.7 with
#: the right sign (a transient into tapping, d 6.5 nm, A0 10 nm), against 4-7 for a flipped trace.
FLIP_RATIO = 3.0


@dataclass
class Analysis:
    """What the signal analysis measured. Times in samples; lengths in the trace's units."""

    n: int
    cycles_per_sample: float  # oscillation frequency / sample rate
    spp: float  # samples per period
    K: int  # highest harmonic fitted
    L: int  # samples per block (about one period)
    start: int  # first sample of block 0
    amplitude: float  # first-harmonic amplitude (mean over periods)
    mean: float  # mean deflection
    noise_rms: float  # residual of the per-period harmonic fits
    block_amplitude: np.ndarray  # (B,)
    block_phase: np.ndarray  # (B,) rad, unwrapped, x ~ A cos(w t + phase)
    block_mean: np.ndarray  # (B,)
    coef: np.ndarray  # (2K+1,) period-averaged [c0, a1, b1, a2, b2, ...] against cos/sin(n w t), t in samples
    coef_sigma: np.ndarray  # (2K+1,) noise standard deviation of coef
    above_noise: list[int]  # harmonics >= 2 standing DETECT_SIGMA above the noise
    force_range: float = 0.0  # range of the model-free force / k (lengths units), 0 without interaction
    contact: str = "none"  # 'contact', 'attractive' (never touches), 'none' (no interaction detected)
    flipped: bool = False  # the interaction is at the negative deflection peaks
    motion: object = None  # afmid.preprocess.motion.Motion of the per-period coefficients (None: too few periods)

    @property
    def n_blocks(self) -> int:
        return int(self.block_amplitude.size)

    @property
    def periods(self) -> float:
        return self.n / self.spp

    def harmonic_amplitudes(self) -> np.ndarray:
        """|X_n| for n = 0..K (n = 0: |mean|)."""
        return np.concatenate([[abs(self.coef[0])], np.hypot(self.coef[1::2], self.coef[2::2])])

    def harmonic_sigma(self) -> np.ndarray:
        """Noise standard deviation of one cos/sin coefficient of harmonic n = 0..K."""
        s = self.coef_sigma
        return np.concatenate([[s[0]], np.sqrt(0.5 * (s[1::2] ** 2 + s[2::2] ** 2))])


#: Samples per chunk in :func:`analyse` (bounds its temporaries on long traces).
ANALYSE_CHUNK_SAMPLES = 1 << 19


def _series(coef: np.ndarray, phase: np.ndarray, harmonics, weights=None, derivative_weights=None,
            basis: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """sum over n of w_n (a_n cos(n phase) + b_n sin(n phase)) + v_n d/dphase(...), for n in ``harmonics``.

    ``basis``: (cos, sin) of ``np.outer(phase, 1..N)`` for N >= max(harmonics), made once for several series on
    the same phases (its columns n - 1 are the values this computes for n: the same products, the same bits)."""
    n = np.asarray(list(harmonics), dtype=int)
    if n.size == 0:
        return np.zeros_like(phase)
    a, b = coef[2 * n - 1], coef[2 * n]
    w = np.ones(n.size) if weights is None else np.asarray(weights, dtype=float)
    v = np.zeros(n.size) if derivative_weights is None else np.asarray(derivative_weights, dtype=float)
    if basis is None:
        arg = np.outer(phase, n)
        cos, sin = np.cos(arg), np.sin(arg)
    else:
        # C order, as np.cos(np.outer(...)) lays them out (a gathered copy comes out in Fortran order, which
        # would take the other BLAS product and round differently)
        cos, sin = np.ascontiguousarray(basis[0][:, n - 1]), np.ascontiguousarray(basis[1][:, n - 1])
    return cos @ (w * a + v * n * b) + sin @ (w * b - v * n * a)


def analyse(
    x: np.ndarray, resonance_ratio: float | None = None, quality_factor: float | None = None,
    cycles_per_sample: float | None = None, thermal_variance: float = 0.0,
) -> Analysis | None:
    """Measure the oscillation, per-period amplitude/phase/mean, harmonics, noise and the force shape.

    ``resonance_ratio`` is f / f0 (1 if unknown: tapping drives near resonance),
    ``quality_factor`` Q (infinite if unknown; it matters little for n >= 2),
    ``thermal_variance`` the lever's thermal deflection variance k_B T / k, m^2 (0 if unknown), for the
    motion's classification (:func:`afmid.preprocess.motion.classify`).
    Returns None when there is no oscillation to analyse or it has fewer than
    :data:`MIN_ANALYSABLE_SPP` samples per period or fewer than 3 periods.
    """
    x = np.asarray(x, dtype=np.float64)
    f = cycles_per_sample if cycles_per_sample is not None else measure_frequency(x)
    if f is None or f <= 0:
        return None
    spp = 1.0 / f
    if spp < MIN_ANALYSABLE_SPP:
        return None
    L, B, start = block_layout(x.size, spp)
    if B < MIN_PERIODS:
        return None
    K = max(1, highest_harmonic(spp, MAX_HARMONIC))
    omega = 2.0 * math.pi * f
    design = fourier_design(np.arange(L, dtype=float), omega, K)  # time in samples: omega in rad per sample
    projector = least_squares_projector(design)
    used = slice(start, start + B * L)
    starts = start + L * np.arange(B)
    # Slow drift would leak into every harmonic (a sawtooth's 1/n spectrum per period) and pass for a
    # tip-sample force: remove the trend through the per-period means (kept for the offset and drift checks).
    means = x[used].reshape(B, L) @ projector[0]
    local = np.empty((B, design.shape[1]))
    rss = 0.0
    step = max(8, ANALYSE_CHUNK_SAMPLES // L // 8 * 8)  # blocks per chunk (whole BLAS panels: same rounding)
    for b0 in range(0, B, step):
        b1 = min(b0 + step, B)
        lo, hi = start + b0 * L, start + b1 * L
        trend = np.interp(np.arange(lo, hi), starts + 0.5 * (L - 1), means)
        blocks = (x[lo:hi] - trend).reshape(b1 - b0, L)
        local[b0:b1] = blocks @ projector.T
        resid = blocks - local[b0:b1] @ design.T
        rss += float(np.sum(resid**2))
    glob = rotate_to_global(local[..., None], starts, omega)[..., 0]
    glob[:, 0] += means
    dof = B * (L - design.shape[1])
    noise = float(np.sqrt(rss / dof)) if dof > 0 else float("nan")
    amp = np.hypot(glob[:, 1], glob[:, 2])
    phase = np.unwrap(np.arctan2(-glob[:, 2], glob[:, 1]))
    steady = not changes_like_a_transient(amp, thermal_variance)
    averaged = glob if steady else aligned_periods(glob, phase, settled_start(amp, thermal_variance))
    coef = averaged.mean(axis=0)
    # Noise of the averages: white noise through the projector, or the scatter between periods if larger
    # (non-white noise, period-to-period variation of the motion).
    white = noise * np.sqrt(noise_variance_factor(projector)) if math.isfinite(noise) else np.zeros(2 * K + 1)
    sigma = np.maximum(white, averaged.std(axis=0)) / math.sqrt(averaged.shape[0])
    out = Analysis(
        n=x.size, cycles_per_sample=f, spp=spp, K=K, L=L, start=start,
        amplitude=float(np.hypot(coef[1], coef[2])), mean=float(x.mean()), noise_rms=noise,
        block_amplitude=amp, block_phase=phase, block_mean=glob[:, 0].copy(), coef=coef, coef_sigma=sigma,
        above_noise=[], motion=classify_motion(glob, white**2, thermal_variance),
    )
    _interaction(out, 1.0 if resonance_ratio is None else resonance_ratio, quality_factor)
    return out


def aligned_periods(glob: np.ndarray, phase: np.ndarray, first: int) -> np.ndarray:
    """The per-period coefficients (B, 2K+1) of a record that is not steady, from block ``first`` on (its settled
    end, :func:`afmid.preprocess.harmonics.settled_start`), each period turned to the phase of the last one.

    Averaged over a transient, periods of another amplitude (before the tip
    reached the sample) and another phase (the free response and the drive
    beat; the frequency measured from such a record is off the drive) blur the
    harmonics and can put the interaction on the wrong turning point.
    """
    part = glob[first:]
    K = (glob.shape[1] - 1) // 2
    n = np.arange(1, K + 1)
    turn = np.exp(-1j * np.outer(phase[first:] - phase[-1], n))  # (b, K): shift each period to the last one's phase
    c = (part[:, 1::2] - 1j * part[:, 2::2]) * turn  # x ~ Re[(a - i b) exp(i n theta)]
    aligned = part.copy()
    aligned[:, 1::2], aligned[:, 2::2] = c.real, -c.imag
    return aligned


#: Points of the phase grid on which :func:`_interaction` evaluates the force shape.
PHASE_POINTS = 1024


@functools.lru_cache(maxsize=8)
def _phase_basis(K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The phase grid (rad) of :func:`_interaction` and the cos and sin of every harmonic 1..``K`` on it (phase
    points x K), read-only. The same for every trace of one sampling (K follows the samples per period): made once
    per process, not per trace (~1-2 ms of CPU a map pixel)."""
    phase = np.linspace(0.0, 2 * np.pi, PHASE_POINTS, endpoint=False)
    arg = np.outer(phase, np.arange(1, K + 1))
    out = (phase, np.cos(arg), np.sin(arg))
    for values in out:
        values.flags.writeable = False
    return out


def _interaction(a: Analysis, r: float, Q: float | None) -> None:
    """Model-free force shape from the harmonics >= 2: is there contact, and on which side?"""
    amps, sig = a.harmonic_amplitudes(), a.harmonic_sigma()
    floor = np.maximum(sig, 1e-12 * max(a.amplitude, 1e-300))
    a.above_noise = [n for n in range(2, a.K + 1) if amps[n] > DETECT_SIGMA * floor[n]]
    if not a.above_noise:
        a.contact = "none"
        return
    include = a.above_noise  # a harmonic at 3 sigma weighted by n^2 would swamp the shape with noise
    damping = 0.0 if not Q else r / Q
    # F / k = sum_n (n^2 r^2 - 1) x_n - (r / Q) dx_n/dphase  (equation of motion per harmonic, n >= 2)
    n = np.asarray(include, dtype=float)
    phase, cos, sin = _phase_basis(a.K)
    basis = (cos, sin)
    g = _series(a.coef, phase, include, n * n * r * r - 1, np.full(n.size, -damping), basis=basis)
    noise = math.sqrt(sum(((n * n * r * r - 1) ** 2 + (n * damping) ** 2) * sig[n] ** 2 for n in include))
    x = a.coef[0] + _series(a.coef, phase, range(1, a.K + 1), basis=basis)
    a.force_range = float(g.max() - g.min())

    def near(turn: int, width: float) -> np.ndarray:
        return np.abs(np.angle(np.exp(1j * (phase - phase[turn])))) <= width

    # The interaction is localised at one turning point: the one where the force shape is largest.
    # (Even harmonics look the same from both turning points: only odd ones tell the sides apart.)
    top, bottom = int(np.argmax(x)), int(np.argmin(x))
    size_top = float(np.max(np.abs(g[near(top, np.pi / 4)])))
    size_bottom = float(np.max(np.abs(g[near(bottom, np.pi / 4)])))
    odd = any(n % 2 for n in include)
    a.flipped = bool(odd and size_bottom > FLIP_RATIO * size_top)
    turn, sign = (bottom, -1.0) if a.flipped else (top, 1.0)
    # Contact: the force rises (repulsion) towards the closest approach; attraction only: it is lowest there.
    force = sign * g
    rise = float(force[turn] - force[near(turn, np.pi / 2)].min())
    a.contact = "contact" if rise > max(3.0 * noise, 0.1 * a.force_range) else "attractive"

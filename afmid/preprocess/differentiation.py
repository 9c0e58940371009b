"""Strong-form differentiators (``fit.form: strong``): time-domain filters that turn the deflection into (x
smoothed, dx/dt, d2x/dt2), SI, declared once each in :data:`DIFFERENTIATORS` (``fit.differentiation``; their
options in ``fit.differentiation_options``). The weak form (the default) needs none of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from afmid.registry import Registry


# --------------------------------------------------------------------------- differentiators
@dataclass(frozen=True)
class Differentiator:
    """A time-domain filter + differentiator: x -> (x smoothed, dx/dt, d2x/dt2), SI."""

    name: str
    title: str
    when: str  # when to use it
    references: tuple[str, ...]
    apply: Callable[[np.ndarray, float, float, dict], tuple[np.ndarray, np.ndarray, np.ndarray]]
    #: fit.differentiation_options it reads: name -> (what is expected, test of a value)
    options: dict = field(default_factory=dict)

    def check_options(self, options: dict) -> str | None:
        """Why ``options`` (fit.differentiation_options) do not suit this differentiator, or None."""
        from afmid.registry import closest

        for name, value in options.items():
            key = f"fit.differentiation_options.{name}"
            if name not in self.options:
                valid = ", ".join(self.options) if self.options else "none"
                hint = closest(str(name), list(self.options))
                return (f"{key}: the {self.name} differentiator has no option {name!r}"
                        f"{f' (did you mean {hint!r}?)' if hint else ''}; its options: {valid}")
            expected, accepts = self.options[name]
            if not (math.isfinite(value) and accepts(value)):
                return f"{key}: must be {expected}, got {value!r}"
        return None


def _check_differentiator(d: Differentiator) -> None:
    if not d.when:
        raise ValueError("document when to use it")


DIFFERENTIATORS: Registry[Differentiator] = Registry("differentiator", _check_differentiator)


def _central(x, fs, f, opts):
    dt = 1.0 / fs
    v = np.gradient(x, dt, edge_order=2)
    a = np.gradient(v, dt, edge_order=2)
    return x, v, a


def _savgol(x, fs, f, opts):
    from scipy.signal import savgol_filter

    spp = fs / f
    window = int(opts.get("window") or max(5, int(round(spp / 10)) | 1))
    window += 1 - window % 2
    order = int(opts.get("order", 4))
    if window <= order:
        window = order + 2 - order % 2 + 1
    dt = 1.0 / fs
    xs = savgol_filter(x, window, order, deriv=0, mode="interp")
    v = savgol_filter(x, window, order, deriv=1, delta=dt, mode="interp")
    a = savgol_filter(x, window, order, deriv=2, delta=dt, mode="interp")
    return xs, v, a


def _spectral(x, fs, f, opts):
    """Fourier differentiation keeping drive harmonics that stand above the noise floor."""
    n = x.size
    X = np.fft.rfft(x)
    freqs = np.fft.rfftfreq(n, 1.0 / fs)
    power = np.abs(X) ** 2
    floor = np.median(power[freqs > 0.6 * fs / 2]) if n > 16 else 0.0
    harmonic = np.round(freqs / f)
    near = np.abs(freqs - harmonic * f) <= 1.5 * fs / n
    snr = float(opts.get("snr", 10.0))
    keep = (freqs == 0) | (near & (power > snr * floor))
    X = np.where(keep, X, 0)
    w = 2j * np.pi * freqs
    return np.fft.irfft(X, n), np.fft.irfft(w * X, n), np.fft.irfft(w * w * X, n)


def _spline(x, fs, f, opts):
    from scipy.interpolate import make_smoothing_spline

    t = np.arange(x.size) / fs
    lam = opts.get("lam")
    spline = make_smoothing_spline(t, x, lam=lam)
    return spline(t), spline(t, 1), spline(t, 2)


def _period_average(x, fs, f, opts):
    """Average all periods on a phase grid (the paper's approach), differentiate spectrally, tile back."""
    spp = fs / f
    m = int(2 ** np.ceil(np.log2(max(64, spp))))
    t = np.arange(x.size) / fs
    phase = (f * t) % 1.0
    idx = np.minimum((phase * m).astype(int), m - 1)
    sums = np.bincount(idx, weights=x, minlength=m)
    counts = np.bincount(idx, minlength=m)
    mean = sums / np.maximum(counts, 1)
    X = np.fft.rfft(mean)
    k = np.arange(X.size)
    kmax = int(min(X.size - 1, spp * 0.45))
    X[kmax + 1:] = 0
    w = 2j * np.pi * f * k
    grid = np.arange(m) / m
    series = [np.fft.irfft(X * w**p, m) for p in range(3)]
    return tuple(np.interp(phase, grid, s, period=1.0) for s in series)


DIFFERENTIATORS.register(Differentiator(
    "central", "second-order central finite differences",
    "only for nearly noise-free data sampled far above the drive (> 500 samples per period)",
    ("Fornberg, Math. Comp. 51, 699 (1988)",), _central))
DIFFERENTIATORS.register(Differentiator(
    "savgol", "Savitzky-Golay local polynomial smoothing and differentiation",
    "transients and general traces; window ~ 1/10 period (fit.differentiation_options.window)",
    ("Savitzky, Golay, Anal. Chem. 36, 1627 (1964)", "scipy.signal.savgol_filter"), _savgol,
    {"window": ("a whole number of samples >= 3", lambda v: v == int(v) and v >= 3),
     "order": ("a whole polynomial order from 1 to 10", lambda v: v == int(v) and 1 <= v <= 10)}))
DIFFERENTIATORS.register(Differentiator(
    "spectral", "Fourier differentiation keeping the drive harmonics above the noise floor",
    "steady-state traces (periodic in the drive); best noise rejection for the per-sample force",
    ("Trefethen, Spectral Methods in MATLAB (2000)",), _spectral,
    {"snr": ("a power ratio > 0", lambda v: v > 0)}))
DIFFERENTIATORS.register(Differentiator(
    "spline", "smoothing spline with generalized cross-validation",
    "irregular or transient motion when no periodicity can be assumed",
    ("Wahba, Spline Models for Observational Data (1990)", "scipy.interpolate.make_smoothing_spline"), _spline,
    {"lam": ("a smoothing weight > 0 (leave it out for generalized cross-validation)", lambda v: v > 0)}))
DIFFERENTIATORS.register(Differentiator(
    "period_average", "average all periods on a phase grid, then differentiate spectrally",
    "strictly steady traces when period-to-period variation is of no interest (as in the paper)",
    ("Chandrashekar et al., Nanoscale Adv. (2022)",), _period_average))


def differentiate(x: np.ndarray, fs: float, f_drive: float, method: str, options: dict | None = None):
    """Apply a registered differentiator; returns (x smoothed, dx/dt, d2x/dt2)."""
    return DIFFERENTIATORS.get(method).apply(x, fs, f_drive, options or {})

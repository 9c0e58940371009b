"""Noise-aware (Wiener-type) restoration of the tip trajectory behind a declared detector.

Undoing a detector low-pass per harmonic (:func:`afmid.preprocess.instrument.deflection_views`) multiplies the detector
noise of harmonic n by |1 / G(n f)|: 36 at harmonic 60 for a 2-pole Butterworth at 10 f, ~100 for a 4-pole
filter at 8 f. The weak-form rows stay unbiased (each row's noise variance carries the same factor, so the
regression weighs them right), but the library is a nonlinear function of the trajectory it is evaluated on:
noise in that trajectory biases the stiff contact terms and, with the separation unknown, the separation
(errors in variables). There the trajectory must be the best estimate of the tip, not the inverse of the data:
per drive harmonic, the mean over the periods is shrunk by the Wiener gain

    g_j = S_j / (S_j + V_j),   S_j = max(mean_j^2 - V_j, 0),   V_j = noise variance of the mean

(S_j the signal power, estimated from the mean itself, V_j the noise variance of coefficient j per period over
the number of periods). Harmonics well above the noise keep g ~ 1; those the detector has buried in noise go
to 0 instead of carrying the amplified noise. The period-to-period deviations are already smoothed against the
same noise (:func:`afmid.preprocess.periods.ou_smooth`) and are left as they are.
"""

from __future__ import annotations

import numpy as np


def restore_trajectory(smoothed: np.ndarray, noise_var: np.ndarray, pair_rows: np.ndarray) -> np.ndarray:
    """Per-period coefficients (B, n) ``smoothed`` with their across-period mean shrunk by the Wiener gain.

    ``noise_var`` (n,): each coefficient's noise variance in one period (m^2); ``pair_rows`` (n,): the harmonic
    number of each coefficient: the cosine and sine of a harmonic share one gain (the power of the pair), so
    the shrinkage does not rotate the harmonic's phase.
    """
    B = smoothed.shape[0]
    mean = smoothed.mean(axis=0)
    variance = noise_var / B
    harmonics = np.unique(pair_rows)
    power = np.zeros(harmonics.size)
    noise = np.zeros(harmonics.size)
    index = np.searchsorted(harmonics, pair_rows)
    np.add.at(power, index, mean * mean)
    np.add.at(noise, index, variance)
    signal = np.maximum(power - noise, 0.0)
    gain = np.divide(signal, signal + noise, out=np.ones(harmonics.size), where=(signal + noise) > 0)
    return smoothed + (gain[index] - 1.0) * mean

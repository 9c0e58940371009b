"""The weak form's fine-grid test functions (afmid.preprocess.periods.weak_windows), written as two halves in place.

Each half is the family over its block's samples, element by element the arithmetic of the family over both
blocks at once; checked against the defining formula psi_n(s) = sin^4(pi s / T_w) {1, cos(n w s), sin(n w s)}
dt / U on the 2 L U fine samples. Tolerance: the harmonics come from one angle addition of two directly
evaluated cos/sin (afmid.preprocess.harmonics.harmonic_cos_sin, a few units in the last place of 1) and the
argument n w s itself is rounded to ~n w s eps (< 1e-13 rad here): 1e-12 of the largest weight dt / U.
"""

from __future__ import annotations

import numpy as np

from afmid.preprocess.periods import harmonic_blocks, weak_windows


def test_fine_halves_are_the_test_functions_on_both_blocks():
    blocks = harmonic_blocks(40 * 128, 38.4e6, 300_002.7, max_harmonic=57, oversample=16)
    windows = weak_windows(blocks)
    L, K, U, dt, w = blocks.L, blocks.K, blocks.oversample, blocks.dt, blocks.omega
    s = np.arange(2 * L * U) * (dt / U)
    window = np.sin(np.pi * s / (2 * L * dt)) ** 4
    n = np.arange(1, K + 1)[:, None]
    expected = np.empty((2 * K + 1, s.size))
    expected[0] = window
    expected[1::2] = window * np.cos(n * w * s)
    expected[2::2] = window * np.sin(n * w * s)
    expected *= dt / U
    rows = 2 * K + 1
    assert windows.psi_halves.shape == (2 * rows, L * U) and windows.psi_halves.flags.c_contiguous
    np.testing.assert_allclose(windows.psi_halves[:rows], expected[:, :L * U], rtol=0, atol=1e-12 * dt / U)
    np.testing.assert_allclose(windows.psi_halves[rows:], expected[:, L * U:], rtol=0, atol=1e-12 * dt / U)
    assert np.array_equal(windows.psi_fine, np.concatenate([windows.psi_halves[:rows], windows.psi_halves[rows:]],
                                                           axis=1))

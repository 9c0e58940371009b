"""A tapping-like trajectory as rows (the layout the library kernels evaluate), shared by the kernel tests."""

from __future__ import annotations

import numpy as np


def tapping_rows(rows: int = 5, n: int = 700, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, v, t) of shape (rows, n), m, m/s, s: a 9.75 nm, 300 kHz oscillation with 1 pm of noise, sampled at 1 GHz,
    that crosses into contact (z <= a0) at a rest separation of 9.8 nm."""
    rng = np.random.default_rng(seed)
    t = np.arange(rows * n).reshape(rows, n) * 1e-9
    w = 2 * np.pi * 3e5
    x = 9.75e-9 * np.cos(w * t) + 1e-12 * rng.standard_normal(t.shape)
    v = -9.75e-9 * w * np.sin(w * t)
    return x, v, t

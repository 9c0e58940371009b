"""A gated term integrated over its non-zero samples only (afmid.preprocess.periods.WeakWindows.integrate_fine_columns
with ``support``) against the integral over every sample of the fine grid.

The two sums hold the same products (the left-out ones are exact zeros) in another order, so they differ by
rounding only. The tolerance is the dot product's rounding bound, not a number picked after a run: each of the
two computations errs by at most gamma_n sum_k |psi_k f_k| (gamma_n = n eps, n = the L U products of a half
window, +4 for adding the two halves and the rotation to global phase, whose rotated pair mixes the cosine and
sine rows' bounds), so they differ by at most twice that. A support that misses one non-zero sample must break
the bound (the test can fail).

Traces: configs/lennard_jones.yaml with the dmt library at 8 periods, simulator seeds 1 and 2, three separations
in contact (the contact term non-zero on 5-20 % of the period) and one out of contact (all zeros).
"""

from __future__ import annotations

import numpy as np
import pytest

from repo_paths import REPO_ROOT

pytestmark = [pytest.mark.numerics, pytest.mark.blas_sensitive]

EPS = np.finfo(float).eps


def _columns(seed: int, depth: float):
    """(windows, columns (L U, blocks, p) sample-major as the fit lays them out, first block) of the dmt library
    on a simulated trace, at the rest separation ``depth`` (m) below first contact."""
    from afmid.config import load_config
    from afmid.fit.pipeline import first_contact, library_parameters
    from afmid.fit.prepare import prepare
    from afmid.fit.prepare import fine_chunks
    from afmid.fit.system import average_switching_cells
    from afmid.physics.library import build_library
    from afmid.simulate.driver import simulate

    cfg = load_config(REPO_ROOT / "configs" / "lennard_jones.yaml",
                      ["simulate.periods=8", "model.effects=[dmt]", f"simulate.seed={seed}"])
    prepared = prepare(simulate(cfg), cfg.fit)
    library = build_library(cfg.model, cfg.source)
    params = dict(library_parameters(prepared, cfg, library),
                  d=first_contact(prepared, cfg.sample.a0) - depth)
    b0, x, v, t = next(iter(fine_chunks(prepared, overlap=1)))
    columns = np.empty((x.shape[1], x.shape[0], len(library)))
    fine = columns.transpose(1, 0, 2)
    library.evaluate_into(x, v, t, params, fine)
    average_switching_cells(library, params, x, v, t, fine)
    return prepared.windows, columns, b0


def _rounding_bound(windows, columns: np.ndarray, first: int) -> np.ndarray:
    """Twice the rounding bound of one computation, per output (windows, 2K+1, p); see the module docstring."""
    half, blocks, m = columns.shape
    n = min(blocks - 1, windows.n_windows - first)
    rows = windows.psi_fine.shape[0]
    absolute = (np.abs(windows.psi_halves) @ np.abs(columns[:, :n + 1]).reshape(half, -1)).reshape(
        2, rows, n + 1, m)
    local = (absolute[0, :, :n] + absolute[1, :, 1:]).transpose(1, 0, 2)
    pair = local.copy()
    pair[:, 1::2] += local[:, 2::2]  # the rotation mixes each harmonic's cosine and sine rows
    pair[:, 2::2] = pair[:, 1::2]
    return 2 * (half + 4) * EPS * pair


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("depth", [0.1e-9, 0.5e-9, 1.5e-9, -2.0e-9])
def test_integral_over_the_support_equals_the_full_integral_to_rounding(seed, depth):
    from afmid.preprocess.periods import NARROW_SUPPORT, fine_support

    windows, columns, first = _columns(seed, depth)
    support = fine_support(columns)
    narrow = support.sum(axis=0) < NARROW_SUPPORT * columns.shape[0]
    assert narrow.any(), "the contact term must take the support path"
    full = windows.integrate_fine_columns(columns, first)
    on_support = windows.integrate_fine_columns(columns, first, support)
    bound = _rounding_bound(windows, columns, first)
    assert np.all(np.abs(on_support - full) <= bound)
    if depth < 0:  # out of contact: the contact term is zero everywhere, so is its integral
        assert not support[:, narrow].any() and np.all(on_support[..., narrow] == 0.0)
        return
    # A support that misses one non-zero sample of the contact term: the integrals differ beyond rounding.
    j = int(np.flatnonzero(narrow)[0])
    missing = support.copy()
    missing[np.flatnonzero(support[:, j])[len(np.flatnonzero(support[:, j])) // 2], j] = False
    short = windows.integrate_fine_columns(columns, first, missing)
    assert np.any(np.abs(short - full) > bound)


def test_support_counts_a_sample_non_zero_in_any_block_and_nan():
    from afmid.preprocess.periods import fine_support

    columns = np.zeros((6, 3, 2))
    columns[1, 2, 0] = 1e-30
    columns[4, 0, 1] = np.nan
    columns[5, 1, 1] = -2.0
    expected = np.zeros((6, 2), bool)
    expected[1, 0] = expected[4, 1] = expected[5, 1] = True
    np.testing.assert_array_equal(fine_support(columns), expected)

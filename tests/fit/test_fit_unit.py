"""Fast unit tests of the fit's pieces (no simulation, no full fit).

Each numba kernel is checked against its plain-NumPy twin, the factor algebra
of :mod:`afmid.fit.regression` against ``np.linalg.lstsq`` on the stacked rows, the
preprocessing (drive estimate, Fourier blocks, weak-form test functions)
against signals whose answer is known in closed form, and the library builder
against the presets, the effect catalog and custom terms.
"""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest

import afmid.terms.expr as expr
import afmid.fit.regression as regression
from afmid.config import ModelConfig
from afmid.errors import ConfigError
from afmid.kernels.hysteresis import scan_hysteresis, scan_hysteresis_numpy
from afmid.kernels.sparse import subset_lstsq, stlsq_factor, stlsq_factor_numpy, subset_rss, subset_rss_numpy
from afmid.physics.library import build_library, trajectory_variables
from afmid.physics.presets import PRESETS
from afmid.physics.effects import EFFECTS
from afmid.preprocess.periods import harmonic_blocks, weak_windows
from afmid.preprocess.harmonics import estimate_drive
from afmid.terms.units import parse_unit
from library_twin import evaluate_numpy

# floating-point results compared; blas_sensitive: make test-kernels runs these again (BLAS/LAPACK on the path)
pytestmark = [pytest.mark.numerics, pytest.mark.blas_sensitive]

F_DRIVE = 300e3  # Hz
SPP = 200  # samples per period
FS = F_DRIVE * SPP
A0_CONTACT = 0.165e-9  # m


# --------------------------------------------------------------------------- helpers
def sparse_problem(rng, rows=240, p=9, support=(0, 3, 5), noise=1e-3, spread=True):
    """A least-squares problem y = A c + noise with a sparse c.

    Columns get scales spanning many decades (as SI library columns do) when
    ``spread``; the last two columns play the protected drive columns.
    """
    A = rng.standard_normal((rows, p))
    scales = 10.0 ** rng.uniform(-12, 12, p) if spread else np.ones(p)
    A *= scales
    c = np.zeros(p)
    c[list(support)] = rng.uniform(0.5, 2.0, len(support)) * rng.choice([-1, 1], len(support)) / scales[list(support)]
    c[-2:] = rng.uniform(0.5, 2.0, 2) / scales[-2:]
    y = A @ c + noise * rng.standard_normal(rows)
    protected = np.zeros(p, dtype=bool)
    protected[-2:] = True
    return A, y, c, protected


def factor(A, y):
    """Upper-triangular factor (q, q) of [A | y]."""
    return np.linalg.qr(np.column_stack([A, y]), mode="r")


def blocks_of(A, y, n_blocks):
    r = A.shape[0] // n_blocks
    return A[: r * n_blocks].reshape(n_blocks, r, -1), y[: r * n_blocks].reshape(n_blocks, r)


# --------------------------------------------------------------------------- sparse kernels
@pytest.mark.parametrize("seed", range(6))
def test_stlsq_factor_matches_numpy_twin(seed):
    rng = np.random.default_rng(seed)
    A, y, _, protected = sparse_problem(rng, noise=10.0 ** rng.uniform(-6, -1))
    T = np.ascontiguousarray(factor(A, y))
    p = A.shape[1]
    scale = np.linalg.norm(T[:, :p], axis=0)
    initial = np.ones(p, dtype=np.bool_)
    base = math.sqrt(float(np.sum(T[:, p] ** 2)))
    for lam in (0.0, 1e-6, 1e-4, 1e-3, 1e-2, 0.1, 0.3, 1.0):
        mask_nb, coef_nb, rss_nb = stlsq_factor(T, scale, lam * base, protected, initial, 20)
        mask_np, coef_np, rss_np = stlsq_factor_numpy(T, scale, lam * base, protected, initial.copy(), 20)
        np.testing.assert_array_equal(mask_nb, mask_np, err_msg=f"threshold {lam}")
        # compare on unit-norm columns: SI coefficients differ by ~24 decades
        np.testing.assert_allclose(coef_nb * scale, coef_np * scale, rtol=1e-9,
                                   atol=1e-12 * np.abs(coef_np * scale).max())
        assert rss_nb == pytest.approx(rss_np, rel=1e-8, abs=1e-20)
        assert np.all(mask_nb[protected]), "protected columns are never dropped"


def test_stlsq_factor_recovers_clear_support():
    rng = np.random.default_rng(42)
    A, y, c, protected = sparse_problem(rng, noise=1e-6)
    T = np.ascontiguousarray(factor(A, y))
    p = A.shape[1]
    scale = np.linalg.norm(T[:, :p], axis=0)
    mask, coef, _ = stlsq_factor(T, scale, 1e-3 * math.sqrt(float(np.sum(T[:, p] ** 2))), protected,
                                 np.ones(p, dtype=np.bool_), 20)
    np.testing.assert_array_equal(mask, c != 0)
    np.testing.assert_allclose(coef, c, rtol=1e-4)


@pytest.mark.parametrize("seed", range(4))
def test_subset_fit_equals_lstsq_on_stacked_rows(seed):
    rng = np.random.default_rng(100 + seed)
    A, y, _, protected = sparse_problem(rng, rows=300, noise=0.1)
    Ab, yb = blocks_of(A, y, 12)
    T = regression.combine(regression.factor_blocks(Ab, yb))
    A_st, y_st = Ab.reshape(-1, A.shape[1]), yb.reshape(-1)
    for _ in range(5):
        mask = rng.random(A.shape[1]) < 0.6
        mask |= protected
        coef, rss = regression.subset_fit(T, mask)
        # reference on unit-norm columns (the columns span 24 decades; lstsq's cut-off is relative)
        norms = np.linalg.norm(A_st[:, mask], axis=0)
        ref, *_ = np.linalg.lstsq(A_st[:, mask] / norms, y_st, rcond=None)
        ref /= norms
        np.testing.assert_allclose(coef[mask], ref, rtol=1e-8)
        assert np.all(coef[~mask] == 0.0)
        assert rss == pytest.approx(float(np.sum((y_st - A_st[:, mask] @ ref) ** 2)), rel=1e-8)
    # the empty support: the whole signal is residual
    coef, rss = regression.subset_fit(T, np.zeros(A.shape[1], dtype=bool))
    assert np.all(coef == 0) and rss == pytest.approx(float(np.sum(y_st**2)), rel=1e-10)


def test_combine_gives_the_gram_of_the_stacked_rows():
    rng = np.random.default_rng(7)
    A, y, _, _ = sparse_problem(rng, rows=200, spread=False)
    Ab, yb = blocks_of(A, y, 10)
    M = np.concatenate([Ab, yb[..., None]], axis=2)  # (B, r, q)
    T_blocks = regression.factor_blocks(Ab, yb)
    for b in range(len(M)):  # each block factor carries its block's Gram
        np.testing.assert_allclose(T_blocks[b].T @ T_blocks[b], M[b].T @ M[b], rtol=1e-10, atol=1e-10)
    T = regression.combine(T_blocks)
    stacked = M.reshape(-1, M.shape[2])
    np.testing.assert_allclose(T.T @ T, stacked.T @ stacked, rtol=1e-10, atol=1e-9)
    # bootstrap weights: multiplicity m_b counts block b m_b times
    mult = rng.integers(0, 4, len(M)).astype(float)
    Tw = regression.combine(T_blocks, mult)
    gram = sum(m * (Mb.T @ Mb) for m, Mb in zip(mult, M))
    np.testing.assert_allclose(Tw.T @ Tw, gram, rtol=1e-10, atol=1e-9)


def test_factor_blocks_pads_short_blocks():
    rng = np.random.default_rng(8)
    A = rng.standard_normal((5, 3, 6))  # fewer rows per block than columns
    y = rng.standard_normal((5, 3))
    T_blocks = regression.factor_blocks(A, y)
    assert T_blocks.shape == (5, 7, 7)
    M = np.concatenate([A, y[..., None]], axis=2)
    for b in range(5):
        np.testing.assert_allclose(T_blocks[b].T @ T_blocks[b], M[b].T @ M[b], atol=1e-12)


def test_exhaustive_path_contains_the_true_support_and_bic_picks_it():
    rng = np.random.default_rng(3)
    A, y, c, protected = sparse_problem(rng, rows=400, p=9, support=(1, 4, 6), noise=0.05)
    Ab, yb = blocks_of(A, y, 20)
    T_blocks = regression.factor_blocks(Ab, yb)
    T = regression.combine(T_blocks)
    cands = regression.exhaustive_path(T, protected)
    assert len(cands) == 2 ** int((~protected).sum())
    assert all(np.all(cand.mask[protected]) for cand in cands)
    truth = c != 0
    matches = [cand for cand in cands if np.array_equal(cand.mask, truth)]
    assert len(matches) == 1
    same_size = [cand.rss for cand in cands if cand.n_free == matches[0].n_free]
    assert matches[0].rss == min(same_size)
    sel = regression.select(T_blocks, protected, "exhaustive", "bic", n_rows=Ab.shape[0] * Ab.shape[1])
    np.testing.assert_array_equal(sel.best.mask, truth)
    with pytest.raises(ValueError, match="too large"):
        regression.exhaustive_path(T, np.zeros(9, dtype=bool), max_free=4)


# --------------------------------------------------------------------------- all subsets in one kernel call
def _kernel_rss(T, protected):
    from afmid.kernels.sparse import SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT

    return subset_rss(np.ascontiguousarray(T), protected.astype(np.bool_), SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT)


def _subset_masks(protected):
    """Mask of each bitmask over the free columns (bit i = the i-th free column), as the kernel indexes them."""
    free = np.flatnonzero(~protected)
    for sub in range(1 << free.size):
        mask = protected.copy()
        mask[free[(sub >> np.arange(free.size)) & 1 == 1]] = True
        yield sub, mask


def _per_subset_path(T, protected):
    """The exhaustive path fitted subset by subset with ``subset_fit`` (the reference implementation)."""
    free = np.flatnonzero(~protected)
    cands = []
    for k in range(free.size + 1):
        for subset in itertools.combinations(free, k):
            mask = protected.copy()
            mask[list(subset)] = True
            coef, rss = regression.subset_fit(T, mask)
            cands.append(regression.Candidate(mask, coef, rss, k))
    return cands


def _realistic_problem(library, seed, periods=12, rel_noise=1e-3):
    """Blocks of a per-sample regression on a seed library evaluated in SI units along a tapping
    trajectory (columns span 50-80 decades: z^-8 ~ 1e70, delta^2.5 ~ 1e-22), plus the drive cos/sin
    (protected); the force is a DMT (``viscoelastic_table2``) or Lennard-Jones (``lj_table1``) law."""
    rng = np.random.default_rng(seed)
    lib = build_library(ModelConfig(library=library))
    x, v, t = _tapping_trajectory(seed, periods)
    d = 8.5e-9 if library != "lj_table1" else float(x.max()) + 0.3e-9
    params = {"d": d, "a0": A0_CONTACT, "R": 10e-9, "w": 2 * np.pi * F_DRIVE, **lib.nonlinear}
    theta = evaluate_numpy(lib, x, v, t, params)
    w = 2 * np.pi * F_DRIVE
    A = np.column_stack([theta, np.cos(w * t), np.sin(w * t)])
    if library == "lj_table1":
        H, R, sigma = 5e-20, 10e-9, 0.3e-9
        c = {"z^-2": -H * R / 6, "z^-8": H * R * sigma**6 / 180}
    else:
        c = {"z^-2": -1e-19 * 10e-9 / 6, "delta^1.5": 4 / 3 * 1e9 * math.sqrt(10e-9),
             "[z<=a0] (bridging)": -1e-19 * 10e-9 / (6 * A0_CONTACT**2)}
    coef = np.array([c.get(name, 0.0) for name in lib.names] + [2e-9, -1e-9])
    y = A @ coef
    y = y + rel_noise * np.abs(y).max() * rng.standard_normal(y.size)
    protected = np.r_[np.zeros(len(lib), bool), True, True]
    Ab, yb = blocks_of(A, y, periods)
    return regression.factor_blocks(Ab, yb), protected, y.size, lib


def _degenerate_problems(rng):
    """Badly scaled problems with the degeneracies the kernel hands to ``subset_lstsq``."""
    A, y, c, protected = sparse_problem(rng, rows=300, p=10, support=(1, 4, 6), noise=1e-3)
    out = {"spread 1e+-12": (A, y, protected)}
    B = A.copy()
    B[:, 3] = 1e7 * B[:, 2]  # an exact (scaled) duplicate: rank-deficient subsets
    out["duplicate column"] = (B, y, protected)
    B = A.copy()
    B[:, 3] = 1e7 * B[:, 2] * (1 + 1e-9 * rng.standard_normal(A.shape[0]))  # condition ~1e9
    out["near duplicate"] = (B, y, protected)
    B = A.copy()
    B[:, 5] = 0.0
    out["zero column"] = (B, y, protected)
    out["noise-free"] = (A, A @ c, protected)
    out["fewer rows than columns"] = (A[:7], y[:7], protected)
    out["no protected column"] = (A[:, :8], y, np.zeros(8, dtype=bool))
    return out


def _padded_factor(A, y):
    T = factor(A, y)
    return np.vstack([T, np.zeros((T.shape[1] - T.shape[0], T.shape[1]))]) if T.shape[0] < T.shape[1] else T


@pytest.mark.parametrize("library", ["viscoelastic_table2", "lj_table1"])
@pytest.mark.parametrize("seed", range(2))
def test_subset_rss_matches_per_subset_fits_on_library_matrices(library, seed):
    T_blocks, protected, _, lib = _realistic_problem(library, seed)
    T = regression.combine(T_blocks)
    norms = np.linalg.norm(T[:, :-1], axis=0)
    assert norms.max() / norms.min() > 1e40, "SI library columns span many decades"
    rss, exact = _kernel_rss(T, protected)
    assert rss.shape == (1 << len(lib),)
    ref = np.array([subset_lstsq(T, mask)[1] for _, mask in _subset_masks(protected)])
    np.testing.assert_allclose(rss, ref, rtol=1e-9, atol=0)
    assert np.array_equal(rss[exact], ref[exact]), "subsets refitted by subset_lstsq are bit for bit its result"
    twin, exact_twin = subset_rss_numpy(T, protected)
    np.testing.assert_array_equal(exact, exact_twin)
    np.testing.assert_allclose(rss, twin, rtol=1e-9, atol=0)


@pytest.mark.parametrize("seed", range(4))
def test_subset_rss_matches_numpy_twin(seed):
    rng = np.random.default_rng(200 + seed)
    A, y, _, protected = sparse_problem(rng, rows=200, p=11, support=(0, 2, 7), noise=10.0 ** rng.uniform(-6, -1))
    T = np.ascontiguousarray(factor(A, y))
    rss, exact = _kernel_rss(T, protected)
    twin, exact_twin = subset_rss_numpy(T, protected)
    np.testing.assert_array_equal(exact, exact_twin)
    np.testing.assert_allclose(rss, twin, rtol=1e-9, atol=0)
    # the empty support (protected columns only) and the full one
    assert rss[0] == pytest.approx(regression.subset_fit(T, protected)[1], rel=1e-9)
    assert rss[-1] == pytest.approx(regression.subset_fit(T, np.ones(A.shape[1], dtype=bool))[1], rel=1e-9)


def test_subset_rss_degenerate_subsets_are_those_of_subset_fit():
    rng = np.random.default_rng(11)
    for name, (A, y, protected) in _degenerate_problems(rng).items():
        T = _padded_factor(A, y)
        rss, exact = _kernel_rss(T, protected)
        masks = dict(_subset_masks(protected))
        ref = np.array([subset_lstsq(T, masks[sub])[1] for sub in range(rss.size)])
        assert np.array_equal(rss[exact], ref[exact]), name
        np.testing.assert_allclose(rss[~exact], ref[~exact], rtol=1e-9, atol=0, err_msg=name)
        twin, exact_twin = subset_rss_numpy(T, protected)
        np.testing.assert_array_equal(exact, exact_twin, err_msg=name)
        np.testing.assert_allclose(rss[~exact], twin[~exact], rtol=1e-9, atol=0, err_msg=name)
        scale = float(np.sum(y**2))
        if name in ("near duplicate", "zero column", "noise-free", "fewer rows than columns"):
            # the SVD cut-off is not borderline here: NumPy's lstsq (the twin's fallback) agrees
            np.testing.assert_allclose(rss[exact], twin[exact], rtol=1e-6, atol=1e-12 * scale, err_msg=name)
        if name in ("duplicate column", "zero column", "noise-free", "fewer rows than columns"):
            assert exact.any(), f"{name}: rank-deficient subsets go to subset_lstsq"
        if name == "spread 1e+-12":
            assert not exact.any()
        if name == "duplicate column":  # both copies in: rank-deficient, refitted
            both = [sub for sub, mask in masks.items() if mask[2] and mask[3]]
            assert exact[both].all()


def _reference_select(T_blocks, protected, criterion, n_rows, folds, penalty):
    """``regression.select(..., "exhaustive")`` as it was: every subset a Candidate fitted by subset_fit."""
    cands = _per_subset_path(regression.combine(T_blocks), protected)
    regression.score_candidates(cands, n_rows, penalty)
    ranked = sorted(cands, key=lambda c: c.bic)[: regression.CV_CANDIDATES]
    ranked += [c for c in cands if c.n_free == 0 and c not in ranked]
    cands = sorted(ranked, key=lambda c: (c.n_free, c.bic))
    regression.cross_validate(T_blocks, cands, folds)
    if criterion == "cv":
        best = min(cands, key=lambda c: c.cv_rss)
        ok = [c for c in cands if c.cv_rss <= best.cv_rss + best.cv_rss_se]
        chosen = min(ok, key=lambda c: (c.n_free, c.cv_rss))
    else:
        chosen = min(cands, key=lambda c: getattr(c, criterion))
    return cands, next(i for i, c in enumerate(cands) if c is chosen)


def _reference_bag(T_blocks, protected, chosen_mask, names, criterion, n_boot, rng, n_rows, penalty):
    B = T_blocks.shape[0]
    key = "bic" if criterion in ("bic", "cv") else "aicc"
    counts, samples, supports = np.zeros(T_blocks.shape[-1] - 1), [], {}
    for _ in range(n_boot):
        mult = rng.multinomial(B, np.full(B, 1.0 / B)).astype(float)
        T = regression.combine(T_blocks, mult)
        cands = _per_subset_path(T, protected)
        regression.score_candidates(cands, int(B * (n_rows / B)), penalty)
        pick = min(cands, key=lambda c: getattr(c, key))
        counts += pick.mask
        support = tuple(n for n, m, prot in zip(names, pick.mask, protected) if m and not prot)
        supports[support] = supports.get(support, 0) + 1
        samples.append(regression.subset_fit(T, chosen_mask)[0])
    return counts / n_boot, np.array(samples), supports


@functools.cache
def _selection_problems():
    out = {}
    for library in ("viscoelastic_table2", "lj_table1"):
        T_blocks, protected, n_rows, lib = _realistic_problem(library, 5, rel_noise=3e-2)
        penalty = np.where([t.effect is None for t in lib.terms] + [False, False], 2 * math.log(10), 0.0)
        out[library] = (T_blocks, protected, n_rows, penalty, lib.names + ["cos", "sin"])
    rng = np.random.default_rng(12)
    for name, (A, y, protected) in _degenerate_problems(rng).items():
        if name == "fewer rows than columns":
            continue
        Ab, yb = blocks_of(A, y, 10)
        names = [f"c{j}" for j in range(A.shape[1])]
        out[name] = (regression.factor_blocks(Ab, yb), protected, Ab.shape[0] * Ab.shape[1], None, names)
    return out


SELECTION_PROBLEMS = ["viscoelastic_table2", "lj_table1", "spread 1e+-12", "duplicate column", "near duplicate",
                      "zero column", "noise-free", "no protected column"]


@pytest.mark.parametrize("problem", SELECTION_PROBLEMS)
def test_exhaustive_select_and_bag_equal_the_per_subset_path(problem):
    """select / bag with the one-call kernel give exactly what fitting every subset gave (same choice,
    same Candidate values bit for bit, same bootstrap)."""
    T_blocks, protected, n_rows, penalty, names = _selection_problems()[problem]
    for criterion in ("bic", "aicc", "cv"):
        sel = regression.select(T_blocks, protected, "exhaustive", criterion, n_rows=n_rows, folds=5, penalty=penalty)
        ref, chosen = _reference_select(T_blocks, protected, criterion, n_rows, 5, penalty)
        assert sel.chosen == chosen
        assert len(sel.candidates) == len(ref)
        for c, r in zip(sel.candidates, ref):
            assert np.array_equal(c.mask, r.mask) and c.n_free == r.n_free
            assert (c.rss, c.bic, c.aicc, c.cv_rss, c.cv_rss_se) == (r.rss, r.bic, r.aicc, r.cv_rss, r.cv_rss_se)
            assert np.array_equal(c.coef, r.coef)
    chosen_mask = sel.best.mask
    for criterion in ("bic", "aicc"):
        bag = regression.bag(T_blocks, protected, chosen_mask, names, "exhaustive", criterion,
                             regression.default_thresholds(), 6, np.random.default_rng(3), n_rows, penalty)
        inclusion, samples, supports = _reference_bag(T_blocks, protected, chosen_mask, names, criterion, 6,
                                                      np.random.default_rng(3), n_rows, penalty)
        assert np.array_equal(bag.inclusion, inclusion)
        assert np.array_equal(bag.coef_samples, samples)
        assert bag.supports == supports


def test_exhaustive_path_equals_the_per_subset_path():
    T_blocks, protected, _, _, _ = _selection_problems()["lj_table1"]
    T = regression.combine(T_blocks)
    cands = regression.exhaustive_path(T, protected)
    ref = _per_subset_path(T, protected)
    assert len(cands) == len(ref) == 1 << 10
    for c, r in zip(cands, ref):  # same order (by size, then itertools.combinations), masks, sizes
        assert np.array_equal(c.mask, r.mask) and c.n_free == r.n_free
        assert c.rss == pytest.approx(r.rss, rel=1e-9)
    for c, r in zip(cands[::37], ref[::37]):  # coefficients (fitted on first access) are subset_fit's
        assert np.array_equal(c.coef, r.coef)
    T[:] = 0.0  # the path keeps its own copy of the factor for the lazy coefficients
    assert np.array_equal(cands[-1].coef, ref[-1].coef)


# --------------------------------------------------------------------------- hysteresis kernel
def _gate_signals(rng, n=5000, neck=0.4e-9):
    """on/off conditions of a contact gate along a noisy tapping trajectory (on: z <= a0, off: z > a0 + neck)."""
    t = np.arange(n) / FS
    z = A0_CONTACT + 1.0e-9 + 2e-9 * np.cos(2 * np.pi * F_DRIVE * t) + 0.3e-9 * rng.standard_normal(n)
    on = (z <= A0_CONTACT).astype(float)
    off = (z > A0_CONTACT + neck).astype(float)
    return on, off


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("initial", [0.0, 1.0])
def test_scan_hysteresis_matches_numpy_twin(seed, initial):
    rng = np.random.default_rng(seed)
    for neck in (0.0, 0.2e-9, 1.0e-9):
        on, off = _gate_signals(rng, neck=neck)
        out = np.empty_like(on)
        final = scan_hysteresis(on, off, initial, out)
        ref = scan_hysteresis_numpy(on, off, initial)
        np.testing.assert_array_equal(out, ref)
        assert final == ref[-1]
        assert 0 < out.mean() < 1  # the gate does switch on this trajectory
        # scanning in two chunks, carrying the state, gives the same result
        k = on.size // 3
        first, second = np.empty(k), np.empty(on.size - k)
        state = scan_hysteresis(on[:k], off[:k], initial, first)
        scan_hysteresis(on[k:], off[k:], state, second)
        np.testing.assert_array_equal(np.concatenate([first, second]), out)


def test_scan_hysteresis_holds_state_between_conditions():
    on = np.array([0, 1, 0, 0, 0, 1, 0, 0], dtype=float)
    off = np.array([0, 0, 0, 1, 0, 0, 0, 1], dtype=float)
    out = np.empty(8)
    scan_hysteresis(on, off, 0.0, out)
    assert out.tolist() == [0, 1, 1, 0, 0, 1, 1, 0]
    np.testing.assert_array_equal(scan_hysteresis_numpy(on, off, 0.0), out)


# --------------------------------------------------------------------------- preprocessing
@pytest.mark.parametrize("detune", [-4e-4, 1.3e-4, 7e-4])
def test_estimate_drive_recovers_detuned_frequency(detune):
    rng = np.random.default_rng(1)
    f = F_DRIVE * (1 + detune)
    t = np.arange(50 * SPP) / FS
    w = 2 * np.pi * f
    amplitude, phase = 9.3e-9, 0.7
    x = (amplitude * np.cos(w * t + phase) + 0.4e-9 * np.cos(2 * w * t - 0.3) + 0.1e-9 * np.sin(3 * w * t)
         + 0.2e-9 + 1e-12 * rng.standard_normal(t.size))
    est = estimate_drive(x, t, F_DRIVE)
    assert abs(est.frequency - f) / f < 1e-6
    assert est.nominal == F_DRIVE
    assert est.amplitude == pytest.approx(amplitude, rel=1e-3)
    assert math.remainder(est.phase - phase, 2 * math.pi) == pytest.approx(0.0, abs=1e-3)
    assert est.offset == pytest.approx(0.2e-9, abs=1e-12)


def test_harmonic_blocks_derivative_of_a_fourier_series():
    rng = np.random.default_rng(5)
    f = F_DRIVE * (1 + 2e-4)  # the blocks hold a non-integer number of samples per period
    n = 20 * SPP + 37
    blocks = harmonic_blocks(n, FS, f, max_harmonic=12)
    w = 2 * np.pi * f
    t = np.arange(n) / FS
    harm = np.arange(1, 9)
    a, b = rng.standard_normal(8) * 1e-9 / harm**2, rng.standard_normal(8) * 1e-9 / harm**2
    c0 = 0.3e-9
    x = c0 + sum(a[k] * np.cos(harm[k] * w * t) + b[k] * np.sin(harm[k] * w * t) for k in range(8))
    v = sum(harm[k] * w * (-a[k] * np.sin(harm[k] * w * t) + b[k] * np.cos(harm[k] * w * t)) for k in range(8))
    acc = sum(-((harm[k] * w) ** 2) * (a[k] * np.cos(harm[k] * w * t) + b[k] * np.sin(harm[k] * w * t))
              for k in range(8))
    X = blocks.project(x)
    # global-phase coefficients: every block holds the same series
    np.testing.assert_allclose(X[:, 0, 0], c0, rtol=1e-9)
    np.testing.assert_allclose(X[:, 1:17:2, 0], np.broadcast_to(a, (blocks.n_blocks, 8)), atol=1e-9 * 1e-9)
    np.testing.assert_allclose(X[:, 2:17:2, 0], np.broadcast_to(b, (blocks.n_blocks, 8)), atol=1e-9 * 1e-9)
    np.testing.assert_allclose(blocks.to_global(blocks.to_local(X)), X, rtol=1e-12, atol=1e-24)
    used = blocks.used
    np.testing.assert_allclose(blocks.synthesize(X)[:, 0], x[used], atol=1e-9 * np.abs(x).max())
    np.testing.assert_allclose(blocks.synthesize(blocks.derivative(X, 1))[:, 0], v[used], atol=1e-9 * np.abs(v).max())
    np.testing.assert_allclose(blocks.synthesize(blocks.derivative(X, 2))[:, 0], acc[used],
                               atol=1e-9 * np.abs(acc).max())
    np.testing.assert_allclose(blocks.derivative(blocks.derivative(X, 1), 1), blocks.derivative(X, 2),
                               rtol=1e-12, atol=1e-30)


@pytest.mark.parametrize("spp, tol", [(200, 1e-6), (100, 5e-6), (50, 3e-5)])
def test_weak_windows_integrate_by_parts_for_non_periodic_motion(spp, tol):
    """Integral of psi x'' = integral of psi'' x (and psi x' = -psi' x) for a decaying, detuned sinusoid.

    The identity is exact for the integrals; the sampled sums (trapezoid rule)
    hold it to 7e-8 at 200 samples per period, 1.4e-6 at 100 and 8e-6 at 50
    (measured: the quadrature error falls as ~h^4, not spectrally).
    """
    fs = F_DRIVE * spp
    n = 12 * spp
    blocks = harmonic_blocks(n, fs, F_DRIVE, max_harmonic=60)
    win = weak_windows(blocks)
    t = np.arange(n) / fs
    wd, tau, phi = 2 * np.pi * F_DRIVE * 1.13, 4.0 / F_DRIVE, 0.4  # not a drive harmonic, decays within the trace
    amp = 5e-9
    x = amp * np.exp(-t / tau) * np.sin(wd * t + phi)
    x1 = amp * np.exp(-t / tau) * (wd * np.cos(wd * t + phi) - np.sin(wd * t + phi) / tau)
    x2 = amp * np.exp(-t / tau) * ((1 / tau**2 - wd**2) * np.sin(wd * t + phi) - 2 * wd / tau * np.cos(wd * t + phi))
    lhs2 = win.integrate(win.psi, x2)[..., 0]
    rhs2 = win.integrate(win.ddpsi, x)[..., 0]
    lhs1 = win.integrate(win.psi, x1)[..., 0]
    rhs1 = -win.integrate(win.dpsi, x)[..., 0]
    for lhs, rhs in ((lhs2, rhs2), (lhs1, rhs1)):
        assert np.linalg.norm(lhs - rhs) < tol * np.linalg.norm(lhs)
        # row by row on the rows that carry the signal (the low harmonics)
        rows = np.abs(lhs) > 1e-2 * np.abs(lhs).max()
        assert rows.sum() > 10
        np.testing.assert_allclose(lhs[rows], rhs[rows], rtol=10 * tol)
    # the constant test function of the first window integrates the window itself
    s = np.arange(2 * blocks.L + 1) * blocks.dt
    np.testing.assert_allclose(win.psi[0] / blocks.dt, np.sin(np.pi * s / (2 * blocks.L * blocks.dt)) ** 4, atol=1e-14)


# --------------------------------------------------------------------------- library
def test_build_library_presets():
    for preset in PRESETS:
        lib = build_library(ModelConfig(library=preset.name))
        assert lib.names == [entry.name for entry in preset.terms], preset.name
        assert lib.effects == preset.effects
        assert lib.source == preset.name
        for term, entry in zip(lib.terms, preset.terms):
            assert term.expression == entry.expression
            assert term.roles == entry.roles
            assert parse_unit(term.coefficient_unit) * parse_unit(term.unit) == parse_unit("N"), term.name
            if entry.effect is None:
                assert term.effect is None and term.label is None  # a distractor (gets the prior penalty)
            else:
                assert (term.effect, term.label) == (entry.effect, entry.label)
                assert term.effect in preset.effects
    # the seed tables' true terms are labelled with the effects the read-out needs
    labels = {t.name: (t.effect, t.label) for t in build_library(ModelConfig(library="lj_table1")).terms}
    assert labels["z^-2"] == ("lennard_jones", "attraction") and labels["z^-8"] == ("lennard_jones", "repulsion")
    assert sum(e is not None for e, _ in labels.values()) == 2
    table3 = build_library(ModelConfig(library="exponential_table3"))
    default_length = EFFECTS.get("exponential_damping").parameter("damping_length").default
    assert table3.nonlinear == {"damping_length": default_length}
    fixed = build_library(ModelConfig(library="exponential_table3", parameters={"damping_length": 2e-9}))
    assert fixed.nonlinear == {"damping_length": 2e-9}


@pytest.mark.parametrize("effects", [["dmt"], ["jkr"], ["lennard_jones"], ["dmt", "viscoelastic"],
                                     ["dmt", "exponential_damping"], ["capillary", "hydration", "electrostatic"]])
def test_build_library_effects(effects):
    lib = build_library(ModelConfig(effects=effects))
    expected = [f"{e}.{t.label}" for e in effects for t in EFFECTS.get(e).terms]
    assert lib.names == expected
    assert lib.effects == tuple(effects)
    assert lib.source == "effects"
    for term in lib.terms:
        effect = EFFECTS.get(term.effect)
        assert term.label in [t.label for t in effect.terms]
        assert parse_unit(term.coefficient_unit) * parse_unit(term.unit) == parse_unit("N")
    nonlinear = {p.name: p.default for e in effects for p in EFFECTS.get(e).parameters if p.nonlinear}
    used = set().union(*(expr.free_names(t.expression) for t in lib.terms))
    used |= {n for g in lib.states for n in expr.free_names(f"[{g.on}] * [{g.off}]")}
    assert lib.nonlinear == {k: v for k, v in nonlinear.items() if k in used}
    for gate in lib.states:  # a state gate is kept only if a term reads it
        assert any(gate.name in t.expression for t in lib.terms)


def test_build_library_rejects_unknown_preset_and_parameter():
    with pytest.raises(ConfigError) as err:
        build_library(ModelConfig(library="lj_tabel1"))
    assert err.value.key == "model.library" and "lj_table1" in err.value.message
    with pytest.raises(ConfigError) as err:
        build_library(ModelConfig(effects=["dmt"], parameters={"damping_length": 1e-9}))
    assert err.value.key == "model.parameters.damping_length"


def test_custom_terms_parse_and_append():
    terms = ["z^-4", "[z <= a0] * delta^2", "zdot * exp(-z / damping_length)", "max(z, a0)^-3 * R"]
    lib = build_library(ModelConfig(effects=["dmt", "exponential_damping"], terms=terms))
    custom = lib.terms[-len(terms):]
    assert [t.name for t in custom] == terms
    assert [t.effect for t in custom] == [None] * len(terms)
    assert [t.unit for t in custom] == [str(parse_unit(u)) for u in ("m^-4", "m^2", "m/s", "m^-2")]
    for t in custom:
        assert parse_unit(t.coefficient_unit) * parse_unit(t.unit) == parse_unit("N")
    # a custom term equal to an effect's term is one column, not two
    dup = build_library(ModelConfig(effects=["viscoelastic"], terms=["delta^0.5 * deltadot"]))
    assert len(dup) == 1


@pytest.mark.parametrize("bad", [
    "z^^2",  # syntax
    "z * foo",  # unknown name
    "z +",  # incomplete
    "exp(-z / 1e-9)",  # non-dimensionless argument
    "z + zdot",  # adding metres to metres per second
    "[z <= a0",  # unclosed gate
])
def test_bad_custom_term_names_its_index(bad):
    with pytest.raises(ConfigError) as err:
        build_library(ModelConfig(effects=["dmt"], terms=["z^-4", bad]), source="run.yaml")
    assert err.value.key == "model.terms[1]", err.value.format()
    assert err.value.file == "run.yaml"
    assert "model.terms[1]" in str(err.value)


# --------------------------------------------------------------------------- expression VM vs NumPy
def _tapping_trajectory(seed=0, periods=4):
    """A realistic tapping trajectory (deflection, velocity, time) with contact: A = 9.4 nm, d = 8.5 nm."""
    rng = np.random.default_rng(seed)
    t = np.arange(periods * SPP) / FS
    w = 2 * np.pi * F_DRIVE
    x = 9.4e-9 * np.cos(w * t) + 0.15e-9 * np.cos(2 * w * t + 0.3) + 0.05e-9 * np.cos(3 * w * t)
    v = -9.4e-9 * w * np.sin(w * t) - 0.3e-9 * w * np.sin(2 * w * t + 0.3) - 0.15e-9 * w * np.sin(3 * w * t)
    x = x + 1e-12 * rng.standard_normal(t.size)
    return x, v, t


LIBRARIES = [{"library": name} for name in PRESETS.names()] + [
    {"effects": ["dmt", "viscoelastic", "exponential_damping"]},
    {"effects": ["jkr"], "parameters": {"neck_length": 0.5e-9}},
    {"effects": ["capillary", "hydration", "electrostatic", "squeeze_film"]},
    {"effects": ["dmt", "exponential_damping"],
     "terms": ["max(z, a0)^-3", "[z > a0] * z^-1 * exp(-z / damping_length)", "sqrt(abs(zdot)) * z", "delta^2.5"]},
]


@pytest.mark.parametrize("spec", LIBRARIES, ids=lambda s: s.get("library") or "+".join(s["effects"]))
def test_vm_matches_numpy_on_library_terms(spec):
    from afmid.kernels.vm import eval_set

    lib = build_library(ModelConfig(**spec))
    x, v, t = _tapping_trajectory()
    # contact models indent by ~1 nm; the Lennard-Jones table (z^1.5, z^2) needs z > 0: closest approach 0.15 nm
    d = 8.5e-9 if spec.get("library") != "lj_table1" else float(x.max()) + 0.15e-9
    params = {"d": d, "a0": A0_CONTACT, "R": 10e-9, "w": 2 * np.pi * F_DRIVE, **lib.nonlinear}
    vm = lib.evaluate(x, v, t, params)
    ref = evaluate_numpy(lib, x, v, t, params)
    assert vm.shape == (x.size, len(lib))
    assert np.all(np.isfinite(ref))
    for j, name in enumerate(lib.names):
        col, col_ref = vm[:, j], ref[:, j]
        np.testing.assert_allclose(col, col_ref, rtol=1e-12, atol=1e-300, err_msg=name)
        assert np.array_equal(col == 0, col_ref == 0), f"{name}: gates differ"
    # the raw kernel on the compiled program set, without the Library wrapper (no state gates here)
    if not lib.states:
        program_set, _ = lib.compile(params)
        variables = np.ascontiguousarray(trajectory_variables(x, v, t, params["d"], params["a0"]))
        out = np.empty((x.size, len(lib)))
        eval_set(program_set.code, program_set.code_offsets, program_set.consts, program_set.const_offsets,
                 variables, out)
        np.testing.assert_array_equal(out, vm)
        for j, term in enumerate(lib.terms):
            np.testing.assert_allclose(expr.evaluate_numpy(term.expression, variables, params), ref[:, j],
                                       rtol=1e-15, atol=0)


def test_trajectory_variables_contact_conventions():
    x, v, t = _tapping_trajectory()
    d = 8.5e-9
    var = trajectory_variables(x, v, t, d, A0_CONTACT)
    z, zdot, delta, deltadot = var[0], var[1], var[2], var[3]
    np.testing.assert_allclose(z, d - x)
    np.testing.assert_allclose(zdot, -v)
    contact = z <= A0_CONTACT
    assert 0 < contact.mean() < 0.5
    np.testing.assert_allclose(delta[contact], A0_CONTACT - z[contact])
    assert np.all(delta[~contact] == 0) and np.all(deltadot[~contact] == 0)
    np.testing.assert_allclose(deltadot[contact], v[contact])


# --------------------------------------------------------------------------- selection constraint
def test_term_roles_of_the_catalog_and_the_seed_tables():
    """Roles are declared on the registry's terms and the tables' columns, checked, and become rule masks."""
    from afmid.physics.effect_tags import SELECTION_RULES, TERM_ROLES

    roles = {f"{e.name}.{t.label}": t.roles for e in EFFECTS for t in e.terms}
    assert {r for rs in roles.values() for r in rs} <= set(TERM_ROLES)
    assert {r for rule in SELECTION_RULES for r in rule.if_all + rule.then_any} <= set(TERM_ROLES)
    assert roles["dmt.hertz"] == roles["jkr.hertz"] == ("elastic_contact",)
    assert roles["viscoelastic.kelvin_voigt"] == ("contact_only",)
    assert roles["jkr.adhesion"] == ("contact_only", "contact_adhesion") and roles["jkr.vdw"] == ("attractive_tail",)
    assert roles["dmt.vdw"] == () and roles["exponential_damping.surface_damping"] == ()  # act out of contact too
    table2 = build_library(ModelConfig(library="viscoelastic_table2"))
    (needs,), elastic = table2.selection_rules(2)[0]
    assert [n for n, m in zip(table2.names, needs) if m] == ["delta^0.5*deltadot", "delta*deltadot^2",
                                                               "[z<=a0] (bridging)"]
    assert [n for n, m in zip(table2.names, elastic) if m] == ["delta^2", "delta^2.5", "delta^1.5"]
    assert needs.size == len(table2) + 2 and not needs[-2:].any() and not elastic[-2:].any()
    (tail, elastic2), adhesion = table2.selection_rules()[1]
    assert [n for n, m in zip(table2.names, tail) if m] == ["z^-2", "z^-3"]
    assert [n for n, m in zip(table2.names, adhesion) if m] == ["[z<=a0] (bridging)"]
    assert build_library(ModelConfig(library="lj_table1")).selection_rules() == []
    assert build_library(ModelConfig(effects=["dmt"])).selection_rules() == []  # the tail is tied to the adhesion
    assert len(build_library(ModelConfig(effects=["jkr", "viscoelastic"])).selection_rules()) == 2


@pytest.mark.parametrize("method", ["exhaustive", "stlsq"])
def test_selection_rules_exclude_unphysical_supports(method):
    """Data that a viscous column alone explains best: under the rule 'contact-only needs elastic' the chosen
    support carries an elastic column too, and every candidate kept satisfies it, in the bootstrap as well;
    a two-condition rule (tail and elastic need adhesion) applies only when both are present."""
    rng = np.random.default_rng(3)
    B, r = 30, 40
    cols = rng.normal(size=(5, B, r))  # elastic, viscous, tail, adhesion, drive
    y = 2.0 * cols[1] + 1.0 * cols[2] + 0.5 * cols[4] + 0.05 * rng.normal(size=(B, r))
    T_blocks = regression.factor_blocks(np.stack(list(cols), axis=2), y)
    protected = np.array([False, False, False, False, True])
    col = {name: np.arange(5) == i for i, name in enumerate(("elastic", "viscous", "tail", "adhesion", "drive"))}
    rules = [([col["viscous"]], col["elastic"]), ([col["tail"], col["elastic"]], col["adhesion"])]
    free = regression.select(T_blocks, protected, method, "bic", n_rows=B * r)
    assert list(free.best.mask) == [False, True, True, False, True]  # unconstrained: viscous + tail
    held = regression.select(T_blocks, protected, method, "bic", n_rows=B * r, rules=rules)
    assert held.best.mask[1] and held.best.mask[0]  # viscous needs the elastic column ...
    assert not held.best.mask[2] or held.best.mask[3]  # ... and with the tail, the adhesion
    assert all(regression.satisfies(c.mask, rules) for c in held.candidates)
    assert regression.satisfies(col["tail"] | col["drive"], rules)  # a tail alone (no contact) is fine
    assert not regression.satisfies(col["tail"] | col["elastic"], rules)
    bagging = regression.bag(T_blocks, protected, held.best.mask, ["e", "v", "t", "a", "d"], method, "bic",
                             regression.default_thresholds(), 20, np.random.default_rng(0), B * r, rules=rules)
    assert all(("v" not in s or "e" in s) and not ("t" in s and "e" in s and "a" not in s) for s in bagging.supports)


# --------------------------------------------------------------------------- long traces: chunked = whole
def _long_trace(periods=40, seed=3, detune=2.3e-4):
    """A synthetic tapping deflection (Trace) with harmonics, detector noise and a slow thermal-like wander."""
    from afmid.io.trace import Cantilever, Trace

    rng = np.random.default_rng(seed)
    n = periods * SPP + 37  # partial periods at the ends
    t = np.arange(n) / FS
    w = 2 * np.pi * F_DRIVE * (1 + detune)
    wander = 1 + 1e-3 * np.sin(2 * np.pi * t / t[-1])
    x = (9.4e-9 * wander * np.cos(w * t) + 0.15e-9 * np.cos(2 * w * t + 0.3) + 0.05e-9 * np.cos(3 * w * t)
         + 1e-12 * rng.standard_normal(n))
    return Trace(deflection=x, sample_rate=FS, cantilever=Cantilever(40.0, 300e3, 250.0, 10e-9),
                 drive_frequency=F_DRIVE)


#: Relative size of a rounding-level change of the input trace: one product of the chunked computations sums
#: over at most SPP samples (one period), and a different GEMM kernel or blocking reorders those sums. Its
#: forward error is bounded by gamma_SPP * |A||B| (Higham, Accuracy and Stability, 3.5), the same as the error
#: a relative perturbation of SPP * u of the input produces; we emulate that perturbation to learn how much
#: each output field moves under rounding (through cancellations, the noise estimate, the Kalman smoother).
ROUNDING_PERTURBATION = SPP * np.finfo(float).eps


def _rounding_scales(trace, cfg):
    """Per Prepared field: max |change| when the deflection is perturbed at rounding level (see above)."""
    import dataclasses

    import afmid.fit.pipeline as fit_mod
    from afmid.io.trace import Trace

    rng = np.random.default_rng(12345)
    nudged = Trace(**{**{f.name: getattr(trace, f.name) for f in dataclasses.fields(trace)},
                      "deflection": trace.deflection * (1 + ROUNDING_PERTURBATION * rng.uniform(-1, 1, trace.n_samples))})
    a, b = fit_mod.prepare(trace, cfg), fit_mod.prepare(nudged, cfg)
    scales = {}
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray) and va.dtype.kind == "f":
            scales[f.name] = float(np.max(np.abs(va - vb), initial=0.0))
        elif isinstance(va, float):
            scales[f.name] = abs(va - vb)
    return scales


def _assert_equal_to_rounding(a, b, scales, where=""):
    """Two Prepared objects from different chunkings agree to rounding: each float field within 16x the change a
    rounding-level perturbation of the input makes (``scales``), plus 16 * SPP ulps of the field's magnitude for
    fields the perturbation cannot reach (formed from the times or the design alone); everything else exactly."""
    import dataclasses

    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray) and va.dtype.kind == "f":
            atol = 16 * scales.get(f.name, 0.0) + 16 * ROUNDING_PERTURBATION * float(np.max(np.abs(va), initial=0.0))
            np.testing.assert_allclose(va, vb, rtol=0, atol=atol, err_msg=f"{where}{f.name}")
        elif isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb, err_msg=f"{where}{f.name}")
        elif isinstance(va, float):
            atol = 16 * scales.get(f.name, 0.0) + 16 * ROUNDING_PERTURBATION * abs(va)
            assert abs(va - vb) <= atol, f"{where}{f.name}: {va!r} != {vb!r} (tolerance {atol:.3g})"


def _assert_products_agree(a, b, inner, where=""):
    """Two evaluations of the same products in different blocking: within gamma_inner of the terms' magnitude
    (bounded here by ``inner`` ulps of the largest |value| times 4, since the terms are of the output's order)."""
    scale = float(np.max(np.abs(a), initial=0.0))
    np.testing.assert_allclose(a, b, rtol=0, atol=4 * inner * np.finfo(float).eps * scale, err_msg=where)


@pytest.mark.parametrize("form", ["weak", "strong"])
@pytest.mark.parametrize("cantilever, baseline", [("fixed", "zero"), ("free", "free")])
def test_prepare_in_chunks_equals_one_piece(monkeypatch, form, cantilever, baseline):
    """Chunks of 8 periods (and pairwise-sum leaves of 256 samples) give one piece's result to rounding.

    Not bit for bit: which BLAS kernel runs (and so the order of each sum) depends on the CPU and on the shape
    of each product, so chunking changes the last bits on some CPUs (measured on AVX-512: up to 1e-9 relative in
    fields formed by cancellation). The tolerances are derived from the arithmetic (see ROUNDING_PERTURBATION).
    """
    import afmid.fit.prepare as fit_mod
    import afmid.preprocess.periods as pre
    from afmid.config import FitConfig

    trace = _long_trace()
    cfg = FitConfig(form=form, cantilever=cantilever, baseline=baseline)
    whole = fit_mod.prepare(trace, cfg)
    scales = _rounding_scales(trace, cfg)
    monkeypatch.setattr(pre, "CHUNK_BLOCKS", 8)
    monkeypatch.setattr(fit_mod, "PAIRWISE_LEAF", 256)
    chunked = fit_mod.prepare(trace, cfg)
    _assert_equal_to_rounding(whole, chunked, scales)
    # the chunked building blocks against their one-piece formulas
    blocks, windows, x = whole.blocks, whole.windows, whole.x
    cols = x[blocks.used].reshape(blocks.n_blocks, blocks.L, 1)
    _assert_products_agree(blocks.project(x), blocks.to_global(pre.apply_rows(blocks.projector, cols)), blocks.L,
                           "project ")
    X = blocks.project(x)
    _assert_products_agree(blocks.synthesize(X), pre.apply_rows(blocks.design, blocks.to_local(X)).reshape(-1, 1),
                           X.shape[1], "synthesize ")
    local = pre.apply_rows(windows.psi, windows.windows(x))
    _assert_products_agree(windows.integrate(windows.psi, x),
                           pre.rotate_to_global(local, windows.start_times(), windows.omega), windows.psi.shape[-1],
                           "integrate ")


def test_pairwise_sum_rounds_like_numpy():
    from afmid.fit.prepare import pairwise_sum

    rng = np.random.default_rng(0)
    for n in (1, 7, 129, 1000, 123_457):
        a = rng.standard_normal(n) ** 2 * 1e-20
        for leaf in (128, 256, 4096):
            import afmid.fit.prepare as prepare_module

            old, prepare_module.PAIRWISE_LEAF = prepare_module.PAIRWISE_LEAF, leaf
            try:
                assert pairwise_sum(lambda lo, hi: a[lo:hi], n) == np.sum(a), (n, leaf)
            finally:
                prepare_module.PAIRWISE_LEAF = old


def test_fine_grid_synthesis_as_one_product():
    """Several series on the fine grid from one BLAS product equal the per-block products (to rounding)."""
    trace = _long_trace(periods=12)
    blocks = harmonic_blocks(trace.n_samples, FS, F_DRIVE * (1 + 2.3e-4), oversample=11)
    X = blocks.project(trace.deflection)
    V = blocks.derivative(X, 1)
    x, v = blocks.synthesize_fine_rows(X[2:9, :, 0], V[2:9, :, 0], first=2)
    from afmid.preprocess.periods import rotate_to_global

    for series, coef in ((x, X), (v, V)):
        ref = np.matmul(blocks.design_fine, rotate_to_global(coef[2:9], blocks.block_times()[2:9], -blocks.omega))
        np.testing.assert_allclose(series, ref[..., 0], rtol=0, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_allclose(blocks.synthesize_fine(X[2:9], 2)[..., 0], x, rtol=0, atol=1e-13 * np.abs(x).max())


def test_ou_smooth_compiled_equals_numpy(monkeypatch):
    import afmid.preprocess.periods as pre

    rng = np.random.default_rng(1)
    coef = rng.standard_normal((300, 9)) * np.linspace(1, 1e-3, 9) + 0.2
    noise_var = np.abs(rng.standard_normal(9)) * 0.1
    monkeypatch.setattr(pre, "OU_NUMBA_MIN_BLOCKS", 10**9)
    m_np, p_np = pre.ou_smooth(coef, noise_var, 0.98)
    monkeypatch.setattr(pre, "OU_NUMBA_MIN_BLOCKS", 1)
    m_nb, p_nb = pre.ou_smooth(coef, noise_var, 0.98)
    np.testing.assert_array_equal(m_nb, m_np)
    np.testing.assert_array_equal(p_nb, p_np)


def test_period_curves_are_evaluated_in_chunks_and_written_as_whole_arrays(monkeypatch, tmp_path):
    """The lazily evaluated curves equal the eager formulas, in any chunking (to rounding), and the file holds them."""
    import dataclasses

    import h5py

    import afmid.fit.pipeline as fit_mod
    from afmid.runfile import PERIOD_UNITS
    import afmid.fit.forces as forces
    from afmid.config import FitConfig
    from afmid.io.trace import write_dataset

    trace = _long_trace(periods=30)
    prep = fit_mod.prepare(trace, FitConfig())
    lib = build_library(ModelConfig(effects=["dmt"]))
    params = {"d": 8.5e-9, "a0": A0_CONTACT, "R": 10e-9, "w": prep.drive.omega, **lib.nonlinear}
    system = fit_mod.build_system(prep, lib, params)
    coef, _ = regression.subset_fit(regression.combine(system.T_blocks), np.ones(system.protected.size, bool))
    rows = forces.signal_rows(prep, system, coef)
    whole = dict(fit_mod.period_curves(prep, lib, system, coef, params, rows, 64))  # evaluated in one chunk
    monkeypatch.setattr(forces, "PERIOD_CHUNK", 8)
    chunked = fit_mod.period_curves(prep, lib, system, coef, params, rows, 64)
    assert list(whole) == list(chunked) == list(PERIOD_UNITS)
    # the eager formulas of the curves
    blocks, phase = prep.blocks, whole["phase"]
    Xc = prep.X[..., None]
    harmonics = [f(n * phase) for n in range(1, blocks.K + 1) for f in (np.cos, np.sin)]
    basis = np.stack([np.ones_like(phase)] + harmonics, 1)
    np.testing.assert_allclose(whole["deflection"], prep.X @ basis.T, rtol=0, atol=1e-14 * np.abs(prep.X).sum(1).max())
    np.testing.assert_allclose(whole["acceleration"], blocks.derivative(Xc, 2)[..., 0] @ basis.T, rtol=1e-12,
                               atol=1e-12 * np.abs(whole["acceleration"]).max())
    times = whole["period_start_time"][:, None] + phase[None, :] / prep.drive.omega
    f_model = (lib.evaluate(whole["deflection"].ravel(), whole["velocity"].ravel(), times.ravel(), params)
               @ coef[:len(lib)]).reshape(whole["deflection"].shape)
    np.testing.assert_allclose(whole["force_model"], f_model, rtol=1e-9, atol=1e-9 * np.abs(f_model).max())
    assert np.all(whole["peak_force"] == whole["force_model"].max(axis=1))
    # Chunked and whole evaluations are different BLAS products (row blocks of different sizes): they agree to
    # rounding, not bit for bit on every CPU. Each curve's tolerance: 16x how much it moves when its inputs (the
    # period coefficients) are perturbed at rounding level (ROUNDING_PERTURBATION), plus 16 * SPP ulps of its size.
    rng = np.random.default_rng(7)
    nudge = {name: getattr(prep, name) * (1 + ROUNDING_PERTURBATION * rng.uniform(-1, 1, getattr(prep, name).shape))
             for name in ("X", "X_traj", "V_traj", "Y_block")}
    nudged = dict(fit_mod.period_curves(dataclasses.replace(prep, **nudge), lib, system, coef, params, rows, 64))
    chunked_values = dict(chunked)
    tolerance = {name: 16 * float(np.max(np.abs(nudged[name] - whole[name]), initial=0.0))
                 + 16 * ROUNDING_PERTURBATION * float(np.max(np.abs(whole[name]), initial=0.0)) for name in whole}
    for name in whole:
        np.testing.assert_allclose(chunked_values[name], whole[name], rtol=0, atol=tolerance[name], err_msg=name)
    with h5py.File(tmp_path / "streamed.h5", "w") as h5:
        chunked.write(h5.create_group("periods"), PERIOD_UNITS)
        small = h5.create_group("small_chunks")  # HDF5 chunks of 3 periods: pieces of 8 written as 6 + 2 + ...
        monkeypatch.setattr(forces, "create_dataset", lambda g, n, shape, dtype, units: g.create_dataset(
            n, shape=shape, dtype=dtype, chunks=(3, shape[1]), compression="gzip"))
        chunked.write(small, PERIOD_UNITS)
        for name in forces.PeriodCurves.CURVES:  # the same chunked evaluation, stored in other HDF5 chunks: same bits
            np.testing.assert_array_equal(small[name][()], chunked_values[name], err_msg=name)
    with h5py.File(tmp_path / "eager.h5", "w") as h5:
        g = h5.create_group("periods")
        for name, arr in whole.items():
            write_dataset(g, name, arr, PERIOD_UNITS[name])
    with h5py.File(tmp_path / "streamed.h5") as a, h5py.File(tmp_path / "eager.h5") as b:
        for name in whole:
            da, db = a["periods"][name], b["periods"][name]
            np.testing.assert_array_equal(da[()], chunked_values[name], err_msg=name)  # the file holds what was computed
            np.testing.assert_allclose(da[()], db[()], rtol=0, atol=tolerance[name], err_msg=name)
            assert (da.chunks, da.compression, da.shuffle, dict(da.attrs)) == (db.chunks, db.compression, db.shuffle,
                                                                              dict(db.attrs)), name

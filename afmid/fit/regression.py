"""Sparse regression: sparsity path, model selection, cross-validation and bagging.

The problem arrives as per-block triangular factors ``T_b`` of the weighted
``[A_b | y_b]`` (see :mod:`afmid.kernels.sparse`): blocks are drive periods, so
cross-validation holds out periods and bagging resamples periods. Columns are
scaled to unit norm inside the thresholding (SI columns span ~40 orders of
magnitude); protected columns (the drive, a free offset) are never dropped.

Selection methods:
- ``stlsq``: sequentially thresholded least squares over a threshold path
  (Brunton et al. 2016, as in the paper);
- ``lasso``: supports along a LASSO path (coordinate descent on scaled columns),
  each refitted by least squares;
- ``exhaustive``: every subset (libraries of up to 16 free terms). The residuals of all
  subsets come from one numba call (:func:`afmid.kernels.sparse.subset_rss`); only the
  subsets that can matter (the best few by the criterion, and any within rounding of
  them) are then refitted one by one (:func:`subset_fit`) into :class:`Candidate` objects,
  so the selection and the bootstrap equal those of fitting every subset on its own.
The candidate supports are ranked by an information criterion (BIC by default)
or by the cross-validated error over held-out periods.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from afmid.kernels.sparse import (SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT, stlsq_factor, subset_lstsq_or_twin,
                                  subset_rss)


# --------------------------------------------------------------------------- factors
def factor_blocks(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-block R factors (B, q, q) of ``[A_b | y_b]``; A is (B, r, p), y is (B, r)."""
    M = np.concatenate([A, y[..., None]], axis=-1)
    B, r, q = M.shape
    if r < q:
        M = np.concatenate([M, np.zeros((B, q - r, q))], axis=1)
    return np.linalg.qr(M, mode="r")[:, :q, :]


def combine(T_blocks: np.ndarray, multiplicity: np.ndarray | None = None) -> np.ndarray:
    """One factor for several blocks (weighted by ``multiplicity``, e.g. bootstrap counts)."""
    q = T_blocks.shape[-1]
    stacked = T_blocks if multiplicity is None else T_blocks * np.sqrt(multiplicity)[:, None, None]
    R = np.linalg.qr(stacked.reshape(-1, q), mode="r")
    if R.shape[0] < q:
        R = np.vstack([R, np.zeros((q - R.shape[0], q))])
    return R


def combine_each(T_stacks: np.ndarray) -> np.ndarray:
    """:func:`combine` of each of several equal-sized sets of block factors, ``T_stacks`` (sets, blocks, q, q) ->
    (sets, q, q), in one LAPACK call over the stack: the same routine on the same matrices, so the same bits as
    one :func:`combine` per set, without NumPy's per-call overhead (~40 us, paid ~100 times per map pixel by its
    separation profile's groups and jackknife)."""
    sets, blocks, rows, q = T_stacks.shape
    if blocks * rows < q:  # combine() pads a short factor with zero rows; rare enough to do one by one
        return np.stack([combine(T) for T in T_stacks])
    return np.linalg.qr(T_stacks.reshape(sets, blocks * rows, q), mode="r")


def subset_fit(T: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares coefficients on the columns in ``mask`` and the residual sum of squares."""
    coef, rss = subset_lstsq_or_twin(np.ascontiguousarray(T), mask.astype(np.bool_))
    return coef, float(rss)


def block_rss(T_blocks: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Residual sum of squares of each block for coefficients ``coef``."""
    p = T_blocks.shape[-1] - 1
    resid = T_blocks[:, :, :p] @ coef - T_blocks[:, :, p]
    return np.sum(resid**2, axis=1)


# --------------------------------------------------------------------------- candidates
@dataclass(eq=False)
class Candidate:
    mask: np.ndarray  # active columns (including protected)
    coef: np.ndarray
    rss: float
    n_free: int  # active non-protected terms
    bic: float = math.nan
    aicc: float = math.nan
    cv_rss: float = math.nan
    cv_rss_se: float = math.nan


class _LazyCandidate(Candidate):
    """A :class:`Candidate` of the exhaustive path whose coefficients are fitted on first access."""

    def __init__(self, T: np.ndarray, mask: np.ndarray, rss: float, n_free: int):
        self.mask, self.rss, self.n_free = mask, rss, n_free
        self.bic = self.aicc = self.cv_rss = self.cv_rss_se = math.nan
        self._T = T

    def __getattr__(self, name: str):
        if name != "coef" or "_T" not in self.__dict__:
            raise AttributeError(name)
        self.coef = subset_fit(self._T, self.mask)[0]
        return self.coef


def information_criteria(rss: float, n_rows: int, k: int) -> tuple[float, float]:
    """BIC and AICc for a Gaussian model with unknown scale (rss from whitened rows)."""
    rss = max(rss, 1e-300)
    base = n_rows * math.log(rss / n_rows)
    bic = base + k * math.log(n_rows)
    aicc = base + 2 * k + (2 * k * (k + 1) / max(n_rows - k - 1, 1))
    return bic, aicc


def _unique(cands: list[Candidate]) -> list[Candidate]:
    seen: dict[bytes, Candidate] = {}
    for c in cands:
        seen.setdefault(c.mask.tobytes(), c)
    return sorted(seen.values(), key=lambda c: c.n_free)


def stlsq_path(T: np.ndarray, protected: np.ndarray, thresholds: np.ndarray, max_iter: int = 20) -> list[Candidate]:
    """Distinct supports of STLSQ over relative thresholds (fractions of the non-drive signal norm)."""
    p = T.shape[1] - 1
    scale = np.linalg.norm(T[:, :p], axis=0)
    scale[scale == 0] = 1.0
    _, base_rss = subset_fit(T, protected)
    signal = math.sqrt(base_rss)
    full = np.ones(p, dtype=np.bool_)
    cands = []
    for lam in thresholds:
        mask, coef, rss = stlsq_factor(np.ascontiguousarray(T), scale, lam * signal, protected, full, max_iter)
        cands.append(Candidate(mask.copy(), coef.copy(), float(rss), int((mask & ~protected).sum())))
    coef, rss = subset_fit(T, protected)
    cands.append(Candidate(protected.copy(), coef, rss, 0))
    return _unique(cands)


def lasso_path(T: np.ndarray, protected: np.ndarray, n_alphas: int = 40) -> list[Candidate]:
    """Supports along a LASSO path (cyclic coordinate descent on unit-norm columns), refitted by LS."""
    p = T.shape[1] - 1
    scale = np.linalg.norm(T[:, :p], axis=0)
    scale[scale == 0] = 1.0
    X = T[:, :p] / scale
    y = T[:, p]
    G = X.T @ X
    g = X.T @ y
    free = ~protected
    alpha_max = np.max(np.abs(g[free])) if free.any() else 0.0
    cands = []
    beta = np.zeros(p)
    for alpha in alpha_max * np.logspace(0, -6, n_alphas):
        for _ in range(500):
            beta_old = beta.copy()
            for j in range(p):
                if G[j, j] == 0:
                    continue
                rho = g[j] - G[j] @ beta + G[j, j] * beta[j]
                if protected[j]:
                    beta[j] = rho / G[j, j]
                else:
                    beta[j] = np.sign(rho) * max(abs(rho) - alpha, 0.0) / G[j, j]
            if np.max(np.abs(beta - beta_old)) < 1e-10 * (1 + np.max(np.abs(beta))):
                break
        mask = (beta != 0) | protected
        coef, rss = subset_fit(T, mask)
        cands.append(Candidate(mask, coef, rss, int((mask & free).sum())))
    return _unique(cands)


def exhaustive_path(T: np.ndarray, protected: np.ndarray, max_free: int = 16) -> list[Candidate]:
    """Every subset of the free terms (the protected columns always in), by size, then in
    ``itertools.combinations`` order. The residuals of all subsets come from one kernel call
    (:func:`afmid.kernels.sparse.subset_rss`); each candidate's coefficients are fitted when first read."""
    free = np.flatnonzero(~protected)
    T = np.array(T, dtype=float, order="C")  # private copy: the lazy coefficients read it later
    rss = _all_subsets_rss(T, protected, max_free)
    cands = []
    for k in range(free.size + 1):
        for subset in itertools.combinations(range(free.size), k):
            mask = protected.copy()
            mask[free[list(subset)]] = True
            cands.append(_LazyCandidate(T, mask, float(rss[sum(1 << i for i in subset)]), k))
    return cands


def _all_subsets_rss(T: np.ndarray, protected: np.ndarray, max_free: int = 16) -> np.ndarray:
    """Residual sum of squares of every subset of the free terms, indexed by bitmask over the free columns."""
    n_free = int((~protected).sum())
    if n_free > max_free:
        raise ValueError(f"exhaustive search over {n_free} terms is too large (max {max_free})")
    rss, _ = subset_rss(np.ascontiguousarray(T, dtype=float), np.ascontiguousarray(protected, dtype=np.bool_),
                        SUBSET_RSS_MAX_ERROR, SUBSET_RSS_MIN_PIVOT)
    return rss


#: Screening tolerance of the exhaustive search, as a relative error of the residual sum of squares: a
#: subset whose screened criterion is within ``2 n_rows x this`` of the cut is refitted exactly
#: (:func:`subset_fit`) before it is ranked, so the ranking is that of the per-subset fits. The
#: kernel's residuals agree with :func:`subset_fit` to ~1e-10 or better (it refits the others itself).
_SCREEN_RSS_REL = 1e-8


class _SubsetCriteria:
    """BIC / AICc of every subset of the free terms of one problem, vectorised over bitmasks.

    Mirrors :func:`information_criteria` + :func:`score_candidates` (to rounding); used to screen the
    exhaustive path without building a :class:`Candidate` per subset."""

    def __init__(self, protected: np.ndarray, n_rows: int, penalty: np.ndarray | None,
                 rules: list | None = None):
        self.protected = np.asarray(protected, dtype=bool)
        self.free = np.flatnonzero(~self.protected)
        nf = self.free.size
        bits = (np.arange(1 << nf)[:, None] >> np.arange(nf)) & 1  # (2^nf, nf)
        self.n_free = bits.sum(axis=1)
        k = self.n_free + int(self.protected.sum())
        extra = np.zeros(1 << nf)
        if penalty is not None:
            extra = bits @ np.asarray(penalty, dtype=float)[self.free] + float(penalty[self.protected].sum())
        self.n_rows = n_rows
        self.allowed = np.ones(1 << nf, dtype=bool)
        for conditions, then in rules or ():
            applies = np.ones(1 << nf, dtype=bool)
            for c in conditions:
                applies &= (bits @ np.asarray(c, dtype=float)[self.free]) > 0
            self.allowed &= ~applies | ((bits @ np.asarray(then, dtype=float)[self.free]) > 0)
        extra = np.where(self.allowed, extra, np.inf)
        self.offset = {"bic": k * math.log(n_rows) + extra,
                       "aicc": 2 * k + (2 * k * (k + 1) / np.maximum(n_rows - k - 1, 1)) + extra}
        self.tol = 2.0 * n_rows * _SCREEN_RSS_REL

    def values(self, rss: np.ndarray, key: str) -> np.ndarray:
        return self.n_rows * np.log(np.maximum(rss, 1e-300) / self.n_rows) + self.offset[key]

    def mask(self, sub: int) -> np.ndarray:
        mask = self.protected.copy()
        mask[self.free[(sub >> np.arange(self.free.size)) & 1 == 1]] = True
        return mask

    def exact(self, T: np.ndarray, subs, penalty: np.ndarray | None) -> list[Candidate]:
        """Candidates of the subsets ``subs`` fitted by :func:`subset_fit` and scored, in the order of
        :func:`exhaustive_path` (size, then ``itertools.combinations`` order)."""
        order = sorted((int(self.n_free[s]), [i for i in range(self.free.size) if (s >> i) & 1], int(s)) for s in subs)
        cands = []
        for n_free, _, sub in order:
            mask = self.mask(sub)
            coef, rss = subset_fit(T, mask)
            cands.append(Candidate(mask, coef, rss, n_free))
        score_candidates(cands, self.n_rows, penalty)
        return cands


def _exhaustive_ranked(T: np.ndarray, rss: np.ndarray, protected: np.ndarray, n_rows: int,
                       penalty: np.ndarray | None, n_best: int,
                       rules: list | None = None) -> list[Candidate]:
    """The candidates of the exhaustive path (residuals ``rss`` of all subsets, by bitmask) that
    :func:`select` can keep: the ``n_best`` lowest BIC and the protected-only support, plus any within
    rounding of the cut; fitted by :func:`subset_fit` and scored, in path order. Ranked on these, the
    candidates come out as ranked on all of :func:`exhaustive_path` with exact fits."""
    crit = _SubsetCriteria(protected, n_rows, penalty, rules)
    bic = crit.values(rss, "bic")
    n_best = min(n_best, int(crit.allowed.sum()))
    cut = np.partition(bic, n_best - 1)[n_best - 1]
    keep = set(np.flatnonzero((bic <= cut + crit.tol + 1e-12 * abs(cut)) & crit.allowed).tolist()) | {0}
    return crit.exact(T, keep, penalty)


PATHS = {"stlsq": stlsq_path, "lasso": lasso_path, "exhaustive": exhaustive_path}


@dataclass
class Selection:
    candidates: list[Candidate]
    chosen: int  # index into candidates
    criterion: str
    #: per column, the fraction of period groups whose own selection used it (None: selected on the whole record)
    votes: np.ndarray | None = None

    @property
    def best(self) -> Candidate:
        return self.candidates[self.chosen]


def candidates_for(T: np.ndarray, protected: np.ndarray, method: str, thresholds: np.ndarray) -> list[Candidate]:
    if method == "stlsq":
        return stlsq_path(T, protected, thresholds)
    return PATHS[method](T, protected)


def select(
    T_blocks: np.ndarray,
    protected: np.ndarray,
    method: str = "stlsq",
    criterion: str = "bic",
    thresholds: np.ndarray | None = None,
    n_rows: int | None = None,
    folds: int = 5,
    penalty: np.ndarray | None = None,
    rules: list | None = None,
) -> Selection:
    """Sparsity path on all blocks, scored by BIC/AICc and cross-validation over held-out blocks.

    ``penalty`` (per column) is added to the information criteria of every
    candidate that uses the column: ``2 ln(prior odds against the term)``, so a
    term with weak physical motivation needs that much more evidence.
    ``rules`` = [(condition masks, then mask), ...]: a support that uses a
    column of every condition mask but none of the then mask is not a
    candidate (e.g. a contact adhesion or damping without an elastic contact
    law; :meth:`afmid.physics.library.Library.selection_rules`).
    """
    if thresholds is None:
        thresholds = default_thresholds()
    T = combine(T_blocks)
    if method == "exhaustive":
        # One kernel call for the residuals of all subsets; only those that can be kept below become candidates.
        rss = _all_subsets_rss(T, protected)
        if n_rows is None:
            raise ValueError("n_rows: the number of whitened rows behind the factors is needed for the criteria")
        cands = _exhaustive_ranked(T, rss, protected, n_rows, penalty, CV_CANDIDATES, rules)
    else:
        cands = [c for c in candidates_for(T, protected, method, thresholds) if satisfies(c.mask, rules)]
        if n_rows is None:
            raise ValueError("n_rows: the number of whitened rows behind the factors is needed for the criteria")
        score_candidates(cands, n_rows, penalty)
    # Cross-validate the plausible candidates only (all of them would be costly for exhaustive paths).
    ranked = sorted(cands, key=lambda c: c.bic)[:CV_CANDIDATES]
    ranked += [c for c in cands if c.n_free == 0 and c not in ranked]
    cands = sorted(ranked, key=lambda c: (c.n_free, c.bic))
    cross_validate(T_blocks, cands, folds)
    if criterion == "cv":
        # one-standard-error rule: the sparsest model within 1 SE of the best CV error
        best = min(cands, key=lambda c: c.cv_rss)
        ok = [c for c in cands if c.cv_rss <= best.cv_rss + best.cv_rss_se]
        chosen = min(ok, key=lambda c: (c.n_free, c.cv_rss))
    else:
        key = "bic" if criterion == "bic" else "aicc"
        chosen = min(cands, key=lambda c: getattr(c, key))
    return Selection(cands, next(i for i, c in enumerate(cands) if c is chosen), criterion)


#: How many of the best candidates (by criterion) are cross-validated and kept in the path diagnostics.
CV_CANDIDATES = 24


def satisfies(mask: np.ndarray, rules: list | None) -> bool:
    """Whether a support meets every rule (condition masks, then mask): it does not use a column of every
    condition mask, or it uses a column of the then mask."""
    for conditions, then in rules or ():
        if all((mask & c).any() for c in conditions) and not (mask & then).any():
            return False
    return True


def score_candidates(cands: list[Candidate], n_rows: int, penalty: np.ndarray | None) -> None:
    for c in cands:
        c.bic, c.aicc = information_criteria(c.rss, n_rows, int(c.mask.sum()))
        if penalty is not None:
            extra = float(penalty[c.mask].sum())
            c.bic += extra
            c.aicc += extra


def default_thresholds(n: int = 40) -> np.ndarray:
    return np.concatenate([[0.0], np.logspace(-6, 0, n)])


def fold_slices(n_blocks: int, folds: int) -> list[np.ndarray]:
    """Contiguous groups of blocks (held-out periods stay together: slow drift is not leaked)."""
    folds = max(2, min(folds, n_blocks))
    return [idx for idx in np.array_split(np.arange(n_blocks), folds) if idx.size]


def training_blocks(n_blocks: int, test: np.ndarray, gap: int = 1) -> np.ndarray:
    """Blocks to train on when ``test`` is held out, leaving ``gap`` blocks on each side
    (weak-form windows overlap their neighbours by one period)."""
    excluded = np.arange(max(test.min() - gap, 0), min(test.max() + gap + 1, n_blocks))
    return np.setdiff1d(np.arange(n_blocks), excluded)


def cross_validate(T_blocks: np.ndarray, cands: list[Candidate], folds: int) -> None:
    """Held-out residual of each candidate support, refitted on the other folds (in place)."""
    groups = fold_slices(T_blocks.shape[0], folds)
    # the training factor of each fold, shared by all candidates
    trained = [combine(T_blocks[training_blocks(T_blocks.shape[0], test)]) for test in groups]
    for c in cands:
        per_fold = []
        for test, T_train in zip(groups, trained):
            coef, _ = subset_fit(T_train, c.mask)
            per_fold.append(block_rss(T_blocks[test], coef).sum())
        per_fold = np.asarray(per_fold)
        c.cv_rss = float(per_fold.sum())
        c.cv_rss_se = float(per_fold.std(ddof=1) * math.sqrt(len(per_fold))) if len(per_fold) > 1 else 0.0


@dataclass
class Bagging:
    inclusion: np.ndarray  # fraction of resamples selecting each column
    coef_samples: np.ndarray  # (n_boot, p) coefficients of the chosen support refitted per resample
    n_boot: int
    supports: dict = field(default_factory=dict)  # support (tuple of names) -> count


def bag(
    T_blocks: np.ndarray,
    protected: np.ndarray,
    chosen_mask: np.ndarray,
    names: list[str],
    method: str,
    criterion: str,
    thresholds: np.ndarray,
    n_boot: int,
    rng: np.random.Generator,
    n_rows: int,
    penalty: np.ndarray | None = None,
    rules: list | None = None,
) -> Bagging:
    """Bootstrap over blocks: inclusion probabilities (re-selecting) and coefficient spread (chosen support)."""
    B = T_blocks.shape[0]
    p = T_blocks.shape[-1] - 1
    n_rows_per_block = n_rows / B
    counts = np.zeros(p)
    samples = np.empty((n_boot, p))
    supports: dict[tuple, int] = {}
    key = resample_key(criterion)
    n_rows_boot = int(B * n_rows_per_block)
    crit = _SubsetCriteria(protected, n_rows_boot, penalty, rules) if method == "exhaustive" else None
    for i in range(n_boot):
        mult = rng.multinomial(B, np.full(B, 1.0 / B)).astype(float)
        T = combine(T_blocks, mult)
        pick_mask = _pick(T, protected, method, key, thresholds, n_rows_boot, penalty, rules, crit)
        counts += pick_mask
        support = tuple(n for n, m, prot in zip(names, pick_mask, protected) if m and not prot)
        supports[support] = supports.get(support, 0) + 1
        samples[i], _ = subset_fit(T, chosen_mask)
    return Bagging(counts / n_boot, samples, n_boot, supports)


def _exhaustive_pick(T: np.ndarray, protected: np.ndarray, crit: _SubsetCriteria, key: str,
                     penalty: np.ndarray | None) -> np.ndarray:
    """Mask of the subset with the lowest criterion ``key`` (the first in path order on ties), as
    ``min(exhaustive_path(...))`` after :func:`score_candidates`, from one kernel call: the subsets within
    rounding of the screened minimum are refitted exactly and compared."""
    values = crit.values(_all_subsets_rss(T, protected), key)
    best = values.min()
    near = np.flatnonzero(values <= best + crit.tol + 1e-12 * abs(best))
    if near.size == 1:
        return crit.mask(int(near[0]))
    return min(crit.exact(T, near.tolist(), penalty), key=lambda c: getattr(c, key)).mask


def resample_key(criterion: str) -> str:
    """The information criterion a re-selection uses for ``criterion`` (cross-validation per resample would
    cost folds x resamples selections, so "cv" re-selects by BIC)."""
    return "bic" if criterion in ("bic", "cv") else "aicc"


def _pick(T: np.ndarray, protected: np.ndarray, method: str, key: str, thresholds: np.ndarray, n_rows: int,
          penalty: np.ndarray | None, rules: list | None, crit: _SubsetCriteria | None = None) -> np.ndarray:
    if method == "exhaustive":
        crit = crit if crit is not None else _SubsetCriteria(protected, n_rows, penalty, rules)
        return _exhaustive_pick(T, protected, crit, key, penalty)
    cands = [c for c in candidates_for(T, protected, method, thresholds) if satisfies(c.mask, rules)]
    score_candidates(cands, n_rows, penalty)
    return min(cands, key=lambda c: getattr(c, key)).mask


def pick_support(T: np.ndarray, protected: np.ndarray, method: str, key: str, thresholds: np.ndarray, n_rows: int,
                 penalty: np.ndarray | None = None, rules: list | None = None) -> np.ndarray:
    """Mask of the support with the lowest criterion ``key`` ("bic" or "aicc") on the factor ``T`` of
    ``n_rows`` whitened rows: the choice :func:`select` makes by that criterion, without the diagnostics."""
    return _pick(T, protected, method, key, thresholds, n_rows, penalty, rules)


def pick_supports(Ts, n_rows: list[int], protected: np.ndarray, method: str, key: str, thresholds: np.ndarray,
                  penalty: np.ndarray | None = None, rules: list | None = None) -> np.ndarray:
    """:func:`pick_support` of several problems on the same columns (factors ``Ts``, ``n_rows`` whitened rows
    each), one mask per row of the result; the subset criteria are built once per distinct row count."""
    criteria: dict[int, _SubsetCriteria] = {}
    masks = []
    for T, n in zip(Ts, n_rows):
        crit = None
        if method == "exhaustive":
            crit = criteria.get(n) or criteria.setdefault(n, _SubsetCriteria(protected, n, penalty, rules))
        masks.append(_pick(T, protected, method, key, thresholds, n, penalty, rules, crit))
    return np.array(masks)


def vote_support(T: np.ndarray, protected: np.ndarray, votes: np.ndarray, method: str, key: str,
                 thresholds: np.ndarray, n_rows: int, penalty: np.ndarray | None = None, rules: list | None = None,
                 extra: list[np.ndarray] = (), undecided: float = 0.0) -> np.ndarray:
    """The support that agrees best with the clear majorities of the votes: it holds the columns voted for
    by more than half + ``undecided`` (``votes`` = fraction of voters per column) and none voted for by fewer
    than half - ``undecided``, among the supports the rules allow; the columns in between, and any other tie,
    go to the lowest criterion ``key`` on ``T`` (the whole record). Candidates: every subset for the
    exhaustive method, else the sparsity path of ``T`` plus the supports in ``extra`` (e.g. the voters' own
    choices)."""
    margin = np.asarray(votes, dtype=float) - 0.5
    margin[np.abs(margin) <= undecided + 1e-12] = 0.0
    if method == "exhaustive":
        crit = _SubsetCriteria(protected, n_rows, penalty, rules)
        free = crit.free
        bits = (np.arange(1 << free.size)[:, None] >> np.arange(free.size)) & 1
        agreement = np.where(crit.allowed, bits @ margin[free], -np.inf)
        ties = np.flatnonzero(agreement >= agreement.max() - 1e-9)
        if ties.size == 1:  # a clear majority: the record's criterion is not needed
            return crit.mask(int(ties[0]))
        values = crit.values(_all_subsets_rss(T, protected), key)[ties]
        near = ties[values <= values.min() + crit.tol + 1e-12 * abs(values.min())]
        if near.size == 1:
            return crit.mask(int(near[0]))
        return min(crit.exact(T, near.tolist(), penalty), key=lambda c: getattr(c, key)).mask
    cands = [c for c in candidates_for(T, protected, method, thresholds) if satisfies(c.mask, rules)]
    known = {c.mask.tobytes() for c in cands}
    for mask in extra:
        if mask.tobytes() not in known and satisfies(mask, rules):
            known.add(mask.tobytes())
            coef, rss = subset_fit(T, mask)
            cands.append(Candidate(mask.copy(), coef, rss, int((mask & ~protected).sum())))
    score_candidates(cands, n_rows, penalty)
    free = ~protected
    best = max(float(margin[c.mask & free].sum()) for c in cands)
    tied = [c for c in cands if float(margin[c.mask & free].sum()) >= best - 1e-9]
    return min(tied, key=lambda c: getattr(c, key)).mask


def scored_candidate(T_blocks: np.ndarray, protected: np.ndarray, mask: np.ndarray, n_rows: int,
                     penalty: np.ndarray | None, folds: int) -> Candidate:
    """One support fitted on all blocks and scored as :func:`select` scores its candidates (criteria, CV)."""
    coef, rss = subset_fit(combine(T_blocks), mask)
    cand = Candidate(mask.copy(), coef, rss, int((mask & ~protected).sum()))
    score_candidates([cand], n_rows, penalty)
    cross_validate(T_blocks, [cand], folds)
    return cand


def resampled_coefficients(T_blocks: np.ndarray, chosen_mask: np.ndarray, n_boot: int,
                           rng: np.random.Generator) -> np.ndarray:
    """(n_boot, p) coefficients of the support ``chosen_mask`` refitted on block resamples (the same draws
    and order as :func:`bag`)."""
    B = T_blocks.shape[0]
    samples = np.empty((n_boot, T_blocks.shape[-1] - 1))
    for i in range(n_boot):
        mult = rng.multinomial(B, np.full(B, 1.0 / B)).astype(float)
        samples[i], _ = subset_fit(combine(T_blocks, mult), chosen_mask)
    return samples

"""The regression system of one library on a prepared trace: library columns in the weak form, whitened and
factored per window (:func:`build_system`), and its residual (:func:`residual_sum_squares`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

import afmid.fit.regression as regression
from afmid.errors import AfmidError
from afmid.physics.library import Library
from afmid.fit.forces import CHUNK_BLOCKS

log = logging.getLogger(__name__)

from afmid.fit.prepare import Prepared, fine_chunks, map_fine_chunks
from afmid.preprocess.periods import fine_support


@dataclass
class System:
    params: dict  # d, a0, R, w and nonlinear parameters used
    theta: np.ndarray  # (W, rows, p) library columns in the regression's form (weak-form integrals)
    T_blocks: np.ndarray  # per-block factors of the whitened [Theta N | Y]
    protected: np.ndarray  # bool (p + n_nu)
    names: list[str]

    @property
    def n_rows(self) -> int:
        """Whitened equations behind the factors: blocks x Fourier coefficients."""
        return int(self.theta.shape[0] * self.theta.shape[1])


def build_system(prep: Prepared, library: Library, params: dict, theta: np.ndarray | None = None) -> System:
    """Library columns in the regression's form, whitened and factored per window (chunk by chunk).

    ``theta`` reuses the columns of an earlier system at the same parameters (only the row weights changed).
    """
    if theta is None:
        theta = library_columns(prep, library, params)
    T_blocks = np.concatenate([
        regression.factor_blocks(
            np.concatenate([theta[i:i + CHUNK_BLOCKS], prep.nuisance[i:i + CHUNK_BLOCKS]], axis=2)
            / prep.row_sigma[None, :, None],
            prep.Y[i:i + CHUNK_BLOCKS] / prep.row_sigma[None, :])
        for i in range(0, theta.shape[0], CHUNK_BLOCKS)
    ])
    protected = np.zeros(theta.shape[2] + prep.nuisance.shape[2], dtype=bool)
    protected[theta.shape[2]:] = True
    return System(dict(params), theta, T_blocks, protected, library.names + prep.nuisance_names)


def library_columns(prep: Prepared, library: Library, params: dict) -> np.ndarray:
    """The library's columns in the regression's form: weak-form integrals (windows, rows, p) or samples."""
    if prep.form == "strong":
        xs, v = prep.strong
        theta = library.evaluate(xs, v, prep.t[prep.blocks.used], params).reshape(prep.blocks.n_blocks, prep.blocks.L, -1)
        check_finite(theta.reshape(-1, theta.shape[-1]), library, params)
        return theta
    if not library.states:
        return _plain_library_columns(prep, library, params)
    parts = []
    for b0, x, v, t in fine_chunks(prep, overlap=1):
        # Hysteresis states scanned once: the library columns and the switching cells both use them.
        states = library.states_along(x.ravel(), v.ravel(), t.ravel(), params) if library.states else None
        fine = library.evaluate(x.ravel(), v.ravel(), t.ravel(), params, state_values=states).reshape(x.shape + (-1,))
        average_switching_cells(library, params, x, v, t, fine, states)
        check_finite(fine.reshape(-1, fine.shape[-1]), library, params)
        parts.append(prep.windows.integrate_fine(fine, b0))
    return np.concatenate(parts, axis=0)


def _plain_library_columns(prep: Prepared, library: Library, params: dict) -> np.ndarray:
    """:func:`library_columns` of a library without state gates, the same bits in one pass per chunk: the
    terms are written straight into the sample-major layout of the weak form's matrix product
    (:meth:`afmid.physics.library.Library.evaluate_into`), which also says whether any value is zero (only then can a
    gate switch inside a cell) or not finite (only then are the columns checked one by one)."""
    p = len(library)

    def integrals(b0, x, v, t):  # one chunk's windows (chunks are shared among threads: map_fine_chunks)
        columns = np.empty((x.shape[1], x.shape[0], p))  # (L U, blocks, p): sample-major
        fine = columns.transpose(1, 0, 2)  # (blocks, L U, p) view
        finite, any_zero = library.evaluate_into(x, v, t, params, fine)
        if any_zero:
            average_switching_cells(library, params, x, v, t, fine)
        if not finite or any_zero:
            check_finite(columns.reshape(-1, p), library, params)
        # A gated term (contact only) is integrated over the samples where it is non-zero.
        support = fine_support(columns) if any_zero else None
        return prep.windows.integrate_fine_columns(columns, b0, support)

    library.compile(params)  # once, before the threads share it
    return np.concatenate(map_fine_chunks(prep, integrals, overlap=1), axis=0)


#: Sub-samples per fine-grid cell in which a gated term switches on or off.
SWITCH_SUBSAMPLES = 32


def average_switching_cells(library: Library, params: dict, x: np.ndarray, v: np.ndarray, t: np.ndarray,
                            fine: np.ndarray, states: np.ndarray | None = None) -> None:
    """Replace (in place) the library values on fine-grid samples whose cell holds a switching gate by cell averages.

    ``x`` (m), ``v`` (m/s), ``t`` (s) are (n, M) rows of the fine grid, each
    contiguous in time with step h; ``fine`` is (n, M, p). A gated term is
    exactly zero where its gate is false, so a term that is zero on one sample
    and not on the next switched between them. The weak form integrates with
    the rectangle rule, which would put the switch on a sample: the integral of
    a step (the in-contact adhesion constant, a meniscus) then jumps as the
    separation moves the switch across samples, the residual becomes a
    staircase in the separation and its profile is useless. Both samples take
    instead the average of the terms over their cell, from sub-samples on a
    cubic Hermite interpolation of (x, xdot): the integral becomes continuous in
    the switch time, with error O(h^2). State gates (hysteresis) are scanned
    through the cell from the state of the sample before it (``states``:
    their values along the rows, (n_states, n * M), as the library scans them).
    """
    switch = _switches(fine)  # between samples j and j + 1
    flagged = np.zeros(x.shape, dtype=bool)
    flagged[:, :-1] |= switch
    flagged[:, 1:] |= switch
    flagged[:, 0] = flagged[:, -1] = False  # the cell needs both neighbours
    rows, cols = np.nonzero(flagged)
    if rows.size == 0:
        return
    h = float(t[0, 1] - t[0, 0])
    u = (np.arange(SWITCH_SUBSAMPLES) + 0.5) / SWITCH_SUBSAMPLES - 0.5  # offsets within the cell, in cells
    left = u < 0  # the left half of the cell lies between samples j - 1 and j
    a = cols[:, None] - left[None, :].astype(int)  # first sample of the interval holding each sub-sample
    s = np.where(left, 1.0 + u, u)[None, :]
    r = rows[:, None]
    xa, xb, va, vb = x[r, a], x[r, a + 1], v[r, a], v[r, a + 1]
    s2, s3 = s * s, s * s * s
    xs = (2 * s3 - 3 * s2 + 1) * xa + (s3 - 2 * s2 + s) * h * va + (3 * s2 - 2 * s3) * xb + (s3 - s2) * h * vb
    vs = (6 * s2 - 6 * s) * (xa - xb) / h + (3 * s2 - 4 * s + 1) * va + (3 * s2 - 2 * s) * vb
    ts = t[rows, cols][:, None] + u[None, :] * h
    sub_states = None
    if library.states:  # scanned through the cell from the state of the sample before it
        if states is None:
            states = library.states_along(x.ravel(), v.ravel(), t.ravel(), params)
        along = states.reshape(-1, *x.shape)
        sub_states = library.states_from(along[:, rows, cols - 1], xs, vs, ts, params)
    sub = library.evaluate(xs.ravel(), vs.ravel(), ts.ravel(), params, state_values=sub_states)
    fine[rows, cols, :] = sub.reshape(rows.size, SWITCH_SUBSAMPLES, -1).mean(axis=1)


def _switches(fine: np.ndarray) -> np.ndarray:
    """(n, M - 1) bool: whether any term of ``fine`` (n, M, p) is zero on one of samples j, j + 1 and not on the
    other. Computed in the sample-major layout the weak form keeps the columns in (``fine`` a transposed view of a
    C-contiguous (M, n, p) array) and one term at a time: a reduction over a short last axis, or over a strided
    view, is a slow per-element loop in NumPy (10x the time of the comparisons themselves)."""
    sample_major = fine.transpose(1, 0, 2)
    layout = sample_major if sample_major.flags.c_contiguous else np.ascontiguousarray(sample_major)
    switch = np.zeros(layout.shape[:2], bool)[1:]
    for j in range(layout.shape[2]):
        zero = layout[:, :, j] == 0.0
        switch |= zero[1:] != zero[:-1]
    return switch.T


def check_finite(columns: np.ndarray, library: Library, params: dict) -> None:
    # Cheap: the sum of all values is finite only if every value is (barring overflow); one pass, no copy of a
    # strided view (a per-column sum over a transposed layout copied it first).
    if np.isfinite(np.sum(columns)):
        return
    finite = np.isfinite(columns).all(axis=0)
    if not finite.all():
        bad = [library.terms[j].name for j in np.flatnonzero(~finite)]
        raise AfmidError(
            f"library terms {bad} are not finite along the trajectory at separation {params['d'] * 1e9:.3f} nm "
            "(a term singular in contact? gate it, e.g. [z > a0] * ...)",
            key="model",
        )


def residual_sum_squares(system: System, mask: np.ndarray | None = None) -> float:
    """Weighted residual sum of squares (dimensionless: rows are whitened) of the least-squares fit of ``system``
    on the columns ``mask`` selects (None: all columns, library and nuisance)."""
    T = regression.combine(system.T_blocks)
    mask = np.ones(T.shape[1] - 1, dtype=bool) if mask is None else mask
    return regression.subset_fit(T, mask)[1]

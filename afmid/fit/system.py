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

log = logging.getLogger(__name__)

from afmid.fit.prepare import CHUNK_BLOCKS, Prepared, fine_chunks, kept_columns, map_fine_chunks
from afmid.fit.thermal_bias import remove_thermal_bias, thermal_bias_rows
from afmid.kernels.switching import cell_subsamples_or_twin, switching_cells_or_twin
from afmid.preprocess.periods import fine_support


@dataclass
class System:
    params: dict  # d, a0, R, w and nonlinear parameters used
    theta: np.ndarray  # (W, rows, p) library columns in the regression's form (weak-form integrals)
    T_blocks: np.ndarray  # per-block factors of the whitened [Theta N | Y]
    protected: np.ndarray  # bool (p + n_nu)
    names: list[str]
    #: (W, rows, p) E[theta e], the thermal force's correlation with the columns, taken out of ``T_blocks``
    #: (:mod:`afmid.fit.thermal_bias`); None without a thermal force
    thermal_bias: np.ndarray | None = None

    @property
    def n_rows(self) -> int:
        """Whitened equations behind the factors: blocks x Fourier coefficients."""
        return int(self.theta.shape[0] * self.theta.shape[1])


def build_system(prep: Prepared, library: Library, params: dict, theta: np.ndarray | None = None,
                 thermal_bias: np.ndarray | None = None) -> System:
    """Library columns in the regression's form, whitened and factored per window (chunk by chunk), with the
    thermal force's bias taken out of each window's factor where the fit knows a thermal force
    (:func:`remove_thermal_bias`).

    ``theta`` reuses the columns of an earlier system at the same parameters (only the row weights changed), and
    ``thermal_bias`` its bias rows (:attr:`System.thermal_bias`; None: evaluated here, in ``library``'s order).
    """
    if theta is None:
        theta = library_columns(prep, library, params)
    if thermal_bias is None:
        thermal_bias = library_thermal_bias(prep, library, params)
    T_blocks = np.concatenate([
        regression.factor_blocks(
            np.concatenate([theta[i:i + CHUNK_BLOCKS], prep.nuisance[i:i + CHUNK_BLOCKS]], axis=2)
            / prep.row_sigma[None, :, None],
            prep.Y[i:i + CHUNK_BLOCKS] / prep.row_sigma[None, :])
        for i in range(0, theta.shape[0], CHUNK_BLOCKS)
    ])
    if thermal_bias is not None:
        T_blocks = remove_thermal_bias(T_blocks, thermal_bias, prep.row_sigma)
    protected = np.zeros(theta.shape[2] + prep.nuisance.shape[2], dtype=bool)
    protected[theta.shape[2]:] = True
    return System(dict(params), theta, T_blocks, protected, library.names + prep.nuisance_names, thermal_bias)


def library_thermal_bias(prep: Prepared, library: Library, params: dict) -> np.ndarray | None:
    """E[theta e] (W, rows, p) of the library's weak-form columns with the thermal force in the equation error
    (:func:`afmid.fit.thermal_bias.thermal_bias_rows`); None where the fit knows no thermal force (or the form is
    strong)."""
    if prep.thermal_force is None or prep.form != "weak":
        return None
    return thermal_bias_rows(fine_chunks(prep, overlap=1), prep.windows, prep.blocks, library, params,
                             prep.thermal_force, prep.drive.amplitude, prep.drive.omega, prep.base_variance)


def library_columns(prep: Prepared, library: Library, params: dict) -> np.ndarray:
    """The library's columns in the regression's form: weak-form integrals (windows, rows, p) or samples."""
    if prep.form == "strong":
        xs, v = prep.strong
        theta = library.evaluate(xs, v, prep.t[prep.blocks.used], params).reshape(prep.blocks.n_blocks, prep.blocks.L, -1)
        check_finite(theta.reshape(-1, theta.shape[-1]), library, params)
        return theta
    kept = kept_columns(prep)
    key = None if kept is None else kept.key(library, params)
    theta = None if kept is None else kept.get(key)
    if theta is None:
        theta = _library_columns(prep, library, params)
        if kept is not None:
            kept.keep(key, theta)
    return theta


def _library_columns(prep: Prepared, library: Library, params: dict) -> np.ndarray:
    """:func:`library_columns` in the weak form, evaluated."""
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
    # Both kernels (afmid.kernels.switching) are one pass each; their NumPy twins (the array expressions, ~0.6 ms
    # of passes over the fine grid and its strided views per library evaluation, the same bits) run instead while
    # the kernels are not compiled (a new install: compiling them would cost more than the first fit's calls).
    rows, cols = switching_cells_or_twin(fine)
    if rows.size == 0:
        return
    xs, vs, ts = cell_subsamples_or_twin(x, v, t, rows, cols, SWITCH_SUBSAMPLES)
    sub_states = None
    if library.states:  # scanned through the cell from the state of the sample before it
        if states is None:
            states = library.states_along(x.ravel(), v.ravel(), t.ravel(), params)
        along = states.reshape(-1, *x.shape)
        sub_states = library.states_from(along[:, rows, cols - 1], xs, vs, ts, params)
    if library.states:
        sub = library.evaluate(xs.ravel(), vs.ravel(), ts.ravel(), params, state_values=sub_states)
    else:  # the same bits through the library's generated kernel (Library.evaluate_rows)
        sub = library.evaluate_rows(xs, vs, ts, params)
    fine[rows, cols, :] = sub.reshape(rows.size, SWITCH_SUBSAMPLES, -1).mean(axis=1)


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

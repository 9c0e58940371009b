"""The fused trajectory kernel (afmid.kernels.trajectory_eval) against its NumPy twin and the VM path.

eval_rows forms the term-language variables per block inside the kernel and writes into any layout; the values
must be the VM's own (Library.evaluate on the same trajectory) bit for bit, the NumPy evaluator's to rounding
(POW_HALVES may differ from ``**`` in the last bits: rtol 1e-12, as tests/terms/test_expr.py), and the weak-form
columns built through it (fit_system.library_columns) the same bits as the evaluate-then-transpose path.
"""

from __future__ import annotations

import numpy as np
import pytest
from tapping_rows import tapping_rows

from afmid.config import ModelConfig
import afmid.terms.expr as expr
from afmid.physics.library import build_library, trajectory_variables
from repo_paths import REPO_ROOT

A0, RADIUS = 0.165e-9, 10e-9
LIBRARIES = {
    "powers (lj_table1)": ModelConfig(effects=[], library="lj_table1"),
    "gated custom terms": ModelConfig(effects=[], terms=["[z > a0] * z^-2", "delta^1.5", "[z <= a0] * deltadot",
                                                         "exp(-z / a0) * xdot", "cos(w * t) * x"]),
    "dmt": ModelConfig(effects=["dmt"]),
}


def eval_rows_numpy(library, params, x: np.ndarray, xdot: np.ndarray, t: np.ndarray,
                    out: np.ndarray) -> tuple[bool, bool]:
    """The plain-NumPy twin of :func:`eval_rows` for ``library`` at ``params`` (d, a0 and its nonlinear
    parameters): the variables as a (7, N) array (:func:`afmid.physics.library.trajectory_variables`), then each term
    by the NumPy evaluator of the term language."""
    variables = trajectory_variables(x.ravel(), xdot.ravel(), t.ravel(), params["d"], params["a0"])
    flat = np.column_stack([expr.evaluate_numpy(term.expression, variables, dict(params), ())
                            for term in library.terms]) if library.terms else np.empty((x.size, 0))
    out[...] = flat.reshape(out.shape)
    with np.errstate(invalid="ignore", over="ignore"):  # inf - inf: not finite, as the kernel says
        return bool(np.isfinite(flat.sum())), bool((flat == 0.0).any())


def _trajectory(rows=5, n=700, seed=3):
    """Rows crossing into contact (tests/support/tapping_rows.py)."""
    return tapping_rows(rows, n, seed)


def _params(library):
    params = {"d": 9.8e-9, "a0": A0, "R": RADIUS, "w": 2 * np.pi * 3e5}
    params.update({name: 1e-9 for name in getattr(library, "nonlinear", {}) or {}})
    return params


@pytest.mark.parametrize("name", list(LIBRARIES))
def test_kernel_equals_the_vm_bit_for_bit_and_the_numpy_twin_to_rounding(name):
    library = build_library(LIBRARIES[name])
    params = _params(library)
    x, v, t = _trajectory()
    p = len(library)
    reference = library.evaluate(x.ravel(), v.ravel(), t.ravel(), params).reshape(x.shape + (p,))
    sample_major = np.empty((x.shape[1], x.shape[0], p))  # the weak form's layout, written through a view
    finite, any_zero = library.evaluate_into(x, v, t, params, sample_major.transpose(1, 0, 2))
    np.testing.assert_array_equal(sample_major.transpose(1, 0, 2), reference)
    twin = np.empty_like(reference)
    twin_finite, twin_zero = eval_rows_numpy(library, params, x, v, t, twin)
    np.testing.assert_allclose(twin, reference, rtol=1e-12, atol=0)
    assert (finite, any_zero) == (twin_finite, twin_zero) == (bool(np.isfinite(reference).all()),
                                                              bool((reference == 0).any()))
    assert any_zero == (name != "powers (lj_table1)")  # only gated terms are exactly zero somewhere


def test_kernel_reports_values_that_are_not_finite():
    library = build_library(ModelConfig(effects=[], terms=["z^-2", "log(z / a0)"]))
    params = _params(library)
    x, v, t = _trajectory(rows=2, n=300)
    x[1, 17] = params["d"]  # z = 0: z^-2 is inf, log(z / a0) is -inf
    out = np.empty(x.shape + (2,))
    finite, _ = library.evaluate_into(x, v, t, params, out)
    assert not finite and np.isinf(out[1, 17]).all()
    twin = np.empty_like(out)
    assert eval_rows_numpy(library, params, x, v, t, twin)[0] is False


def test_a_library_with_state_gates_is_refused():
    library = build_library(ModelConfig(effects=["dmt", "capillary"]))
    if not library.states:
        pytest.skip("no catalog effect with a history gate")
    x, v, t = _trajectory(rows=1, n=10)
    with pytest.raises(ValueError, match="state gates"):
        library.evaluate_into(x, v, t, _params(library), np.empty(x.shape + (len(library),)))


@pytest.mark.parametrize("effects, library_name", [([], "lj_table1"), (["dmt", "viscoelastic"], None)])
def test_weak_form_columns_through_the_kernel_equal_the_evaluate_then_transpose_path(effects, library_name):
    """library_columns (kernel, sample-major) against the per-chunk path of Library.evaluate + integrate_fine,
    with the switching-cell averaging where gated terms switch (dmt) and each gated term integrated over its
    non-zero samples (afmid.preprocess.periods.fine_support, when any value is zero): the same bits."""

    from afmid.config import load_config
    from afmid.fit.pipeline import library_parameters
    from afmid.fit.prepare import prepare
    from afmid.fit.prepare import fine_chunks
    from afmid.fit.system import average_switching_cells, library_columns
    from afmid.preprocess.periods import fine_support
    from afmid.simulate.driver import simulate

    config = REPO_ROOT / "configs" / "lennard_jones.yaml"
    overrides = ["simulate.periods=8", f"model.effects={effects}".replace("'", "")]
    if library_name:
        overrides.append(f"model.library={library_name}")
    cfg = load_config(config, overrides)
    prepared = prepare(simulate(cfg), cfg.fit)
    library = build_library(cfg.model, cfg.source)
    params = dict(library_parameters(prepared, cfg, library), d=cfg.sample.separation)
    parts = []
    for b0, x, v, t in fine_chunks(prepared, overlap=1):
        fine = library.evaluate(x.ravel(), v.ravel(), t.ravel(), params).reshape(x.shape + (-1,))
        average_switching_cells(library, params, x, v, t, fine)
        columns = np.ascontiguousarray(fine.transpose(1, 0, 2))
        support = fine_support(columns) if np.any(fine == 0.0) else None
        parts.append(prepared.windows.integrate_fine_columns(columns, b0, support))
    np.testing.assert_array_equal(library_columns(prepared, library, params), np.concatenate(parts, axis=0))


@pytest.mark.parametrize("name", list(LIBRARIES) + ["capillary meniscus (state gate)"])
def test_evaluate_rows_equals_evaluate_of_the_raveled_rows(name):
    """Library.evaluate_rows (the threads' path: no variables array) gives Library.evaluate's bits, for rows (2-D),
    one series (1-D) and a strided series; a library with a state gate scans it along the raveled rows."""
    config = ModelConfig(effects=["dmt", "capillary"]) if name.startswith("capillary") else LIBRARIES[name]
    library = build_library(config)
    params = _params(library)
    x, v, t = _trajectory()
    reference = library.evaluate(x.ravel(), v.ravel(), t.ravel(), params)
    np.testing.assert_array_equal(library.evaluate_rows(x, v, t, params), reference, strict=True)
    np.testing.assert_array_equal(library.evaluate_rows(x.ravel(), v.ravel(), t.ravel(), params), reference)
    column = np.stack([x.ravel(), v.ravel()], axis=1)  # x and xdot as strided views of one array
    np.testing.assert_array_equal(library.evaluate_rows(column[:, 0], column[:, 1], t.ravel(), params), reference)

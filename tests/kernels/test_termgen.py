"""The generated per-library term kernel (afmid.kernels.termgen) against the VM kernel and the NumPy twin.

The generated code is the VM programs translated opcode for opcode (afmid.kernels.lawgen.translate_program), so
its values must be the VM kernel's (afmid.kernels.trajectory_eval.eval_rows) bit for bit, in both output layouts
(row-major and the weak form's sample-major view, which the kernel walks in tiles) and at special values (a
sample at z = 0, NaN and infinite deflections, -0.0). The plain-NumPy twin is the term language's NumPy evaluator
on the (7, N) variables array: equal to rounding (POW_HALVES may differ from ``**`` in the last bits: rtol 1e-12,
as tests/terms/test_expr.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from tapping_rows import tapping_rows

import afmid.terms.expr as expr
from afmid.config import ModelConfig
from afmid.kernels.termgen import TILE, module_source, term_kernel
from afmid.kernels.trajectory_eval import eval_rows as vm_eval_rows
from afmid.physics.library import build_library, trajectory_variables

A0, RADIUS, SEPARATION = 0.165e-9, 10e-9, 9.8e-9
LIBRARIES = {
    "dmt": ModelConfig(effects=["dmt"]),
    "powers (lj_table1)": ModelConfig(effects=[], library="lj_table1"),
    "every opcode": ModelConfig(effects=[], terms=[
        "[z > a0] * z^-2", "delta^1.5", "[z <= a0] * deltadot", "exp(-z / a0) * xdot", "cos(w * t) * x",
        "sin(w * t) * abs(x) / a0", "log(max(z, a0) / a0)", "sqrt(delta) * min(z, a0) / a0^2",
        "[z > a0 and zdot < 0] * zdot", "[z < 0 or delta > a0] * delta", "[not (z > a0)] * delta^2.5",
        "(z / a0)^(-1.7)", "[z >= a0] * ([zdot > 0] * zdot)", "pos(x) * x", "-(z - a0) * delta", "(z + a0) * x"]),
}


def _params():
    return {"d": SEPARATION, "a0": A0, "R": RADIUS, "w": 2 * np.pi * 3e5}


def _trajectory(rows=5, n=701, seed=3):
    """Rows crossing into contact (tests/support/tapping_rows.py); n is not a multiple of the tile."""
    return tapping_rows(rows, n, seed)


def _vm(library, params, x, v, t, out):
    program_set, _ = library.compile(params)
    return vm_eval_rows(program_set.code, program_set.code_offsets, program_set.consts, program_set.const_offsets,
                        x, v, t, params["d"], params["a0"], out)


def _layouts(x, p):
    """An output array in each layout: rows x samples x terms, and the weak form's sample-major view."""
    return {"row-major": np.empty(x.shape + (p,)),
            "sample-major": np.empty((x.shape[1], x.shape[0], p)).transpose(1, 0, 2)}


def numpy_twin(library, params, x, v, t) -> np.ndarray:
    """The plain-NumPy twin: the (7, N) variables, then each term by the term language's NumPy evaluator."""
    variables = trajectory_variables(x.ravel(), v.ravel(), t.ravel(), params["d"], params["a0"])
    with np.errstate(all="ignore"):
        return np.column_stack([expr.evaluate_numpy(term.expression, variables, dict(params), ())
                                for term in library.terms]).reshape(x.shape + (len(library),))


@pytest.mark.parametrize("name", list(LIBRARIES))
def test_generated_kernel_equals_the_vm_bit_for_bit_and_the_numpy_twin_to_rounding(name):
    library = build_library(LIBRARIES[name])
    params = _params()
    program_set, _ = library.compile(params)
    kernel = term_kernel(program_set.programs)
    for rows, n in ((5, 701), (1, 13), (3, TILE)):
        x, v, t = _trajectory(rows, n)
        for layout, out in _layouts(x, len(library)).items():
            reference = np.empty_like(out)
            expected = _vm(library, params, x, v, t, reference)
            got = kernel.eval_rows(x, v, t, params["d"], params["a0"], out)
            np.testing.assert_array_equal(out.view(np.int64), reference.view(np.int64), err_msg=layout)  # signs too
            assert got == tuple(bool(e) for e in expected), layout
        twin = numpy_twin(library, params, x, v, t)
        np.testing.assert_allclose(out, twin, rtol=1e-12, atol=0)



def test_one_compiled_version_serves_every_layout_and_strided_rows():
    """Issue 31: the generated eval_rows is compiled for one signature (out of any strides), not once per layout
    of out (each compilation is ~0.6-0.8 s of a new install's first fit); C-contiguous and strided out and
    strided trajectory rows all run through it, with the VM's values."""
    library = build_library(LIBRARIES["dmt"])
    params = _params()
    kernel = library.term_kernel(params)
    x, v, t = _trajectory(rows=4, n=64)
    strided = {"x": x[:, ::2], "v": v[:, ::2], "t": t[:, ::2]}  # not C-contiguous: the rows are made so first
    for rows in ({"x": x, "v": v, "t": t}, strided):
        for layout, out in _layouts(rows["x"], len(library)).items():
            reference = np.empty_like(out)
            _vm(library, params, np.ascontiguousarray(rows["x"]), np.ascontiguousarray(rows["v"]),
                np.ascontiguousarray(rows["t"]), reference)
            kernel.eval_rows(rows["x"], rows["v"], rows["t"], params["d"], params["a0"], out)
            np.testing.assert_array_equal(out.view(np.int64), reference.view(np.int64), err_msg=layout)
    assert len(kernel.module.eval_rows.signatures) == 1


def test_generated_kernel_at_special_values():
    """z = 0 (inf, -inf terms), NaN and infinite deflections, x = -0.0: the VM's values and flags, bit for bit."""
    library = build_library(LIBRARIES["every opcode"])
    params = _params()
    x, v, t = _trajectory(rows=3, n=50)
    x[0, 3] = params["d"]  # z = 0
    x[1, 4], x[1, 9], x[2, 0], x[2, 1] = np.nan, np.inf, -np.inf, -0.0
    v[2, 5] = np.nan
    program_set, _ = library.compile(params)
    kernel = term_kernel(program_set.programs)
    for layout, out in _layouts(x, len(library)).items():
        reference = np.empty_like(out)
        expected = _vm(library, params, x, v, t, reference)
        got = kernel.eval_rows(x, v, t, params["d"], params["a0"], out)
        np.testing.assert_array_equal(out.view(np.int64), reference.view(np.int64), err_msg=layout)
        assert got == tuple(bool(e) for e in expected) and got[0] is False


def test_library_uses_the_generated_kernel_and_the_vm_for_state_gates():
    params = _params()
    plain = build_library(LIBRARIES["dmt"])
    kernel = plain.term_kernel(params)
    assert kernel is not None and plain.term_kernel(params) is kernel  # kept per compiled parameter set
    assert "max(z, a0)^-2" in module_source(plain.compile(params)[0].programs)
    gated = build_library(ModelConfig(effects=["dmt", "capillary"]))
    if gated.states:
        assert gated.term_kernel(params) is None


def test_a_library_travels_to_another_process_without_its_kernel():
    import pickle

    library = build_library(LIBRARIES["dmt"])
    params = _params()
    library.term_kernel(params)
    copy = pickle.loads(pickle.dumps(library))
    x, v, t = _trajectory(rows=2, n=40)
    np.testing.assert_array_equal(copy.evaluate_rows(x, v, t, params), library.evaluate_rows(x, v, t, params))


@pytest.mark.parametrize("name", list(LIBRARIES))
def test_stiffness_squares_equals_the_columns_at_x_plus_minus_eps_to_rounding(name):
    """The fused regressor-noise pass (sum of squared central differences of the model force) against its
    NumPy twin, the columns at x +- eps times the coefficients (Library.evaluate_rows, BLAS), squared and summed by
    np.sum. Bound from the arithmetic: each force is a p-term dot product (error <= p u sum_j |c_j term_j| in
    either path), so a slope s_i errs by <= 2 p u (A_i + B_i) / (2 eps) between them (A, B: those sums at x + eps
    and x - eps); its square by 2 |s_i| ds_i + ds_i^2; the sums of n squares by n u (in sample order) + log2(n) u
    (pairwise) of their total."""
    library = build_library(LIBRARIES[name])
    params = _params()
    x, v, t = _trajectory(rows=4, n=997)
    rng = np.random.default_rng(5)
    with np.errstate(all="ignore"):  # each term's coefficient scaled to its own size: every term counts
        size = np.sqrt(np.nanmean(library.evaluate_rows(x, v, t, params) ** 2, axis=0))
    coef = rng.uniform(0.5, 2.0, len(library)) * rng.choice([-1.0, 1.0], len(library)) / np.where(size > 0, size, 1)
    eps = 2e-13
    got = library.term_kernel(params).stiffness_squares(coef, x, v, t, params["d"], params["a0"], eps)
    with np.errstate(all="ignore"):
        hi = library.evaluate_rows(x + eps, v, t, params) * coef
        lo = library.evaluate_rows(x - eps, v, t, params) * coef
    finite = np.isfinite(hi).all(axis=1) & np.isfinite(lo).all(axis=1)
    if not finite.all():  # a library singular somewhere on this trajectory: compare where it is finite
        pytest.skip("columns not finite on the test trajectory")
    slope = (hi.sum(axis=1) - lo.sum(axis=1)) / (2 * eps)
    f_hi = library.evaluate_rows(x + eps, v, t, params) @ coef
    f_lo = library.evaluate_rows(x - eps, v, t, params) @ coef
    twin = float(np.sum(((f_hi - f_lo) / (2 * eps)) ** 2))
    u, p, n = np.finfo(float).eps / 2, len(library), x.size
    d_slope = 2 * p * u * (np.abs(hi).sum(axis=1) + np.abs(lo).sum(axis=1)) / (2 * eps)
    bound = np.sum(2 * np.abs(slope) * d_slope + d_slope**2) + (n + np.log2(n)) * u * twin
    assert abs(got - twin) <= bound, (got, twin, bound)
    assert got > 0

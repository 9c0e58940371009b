"""Library terms along a trajectory by a kernel generated per library: its programs as straight-line numba code.

:func:`afmid.kernels.trajectory_eval.eval_rows` interprets the library's VM programs (:mod:`afmid.kernels.vm`)
block by block: every opcode is a loop over 128 samples through a stack in memory, ~5 ns per sample and term
on the fit's fine grid (1e8 samples at 1e7 trace samples, evaluated three times: the system's columns and the
regressor-noise pass at x +- eps). This module translates the same programs into one loop over the samples
whose body computes every term in registers (the translation is :func:`afmid.kernels.lawgen.translate_program`,
the one the simulator's generated force laws use: the VM's float64 operations in the same order, gates that
give +0.0, NaN-propagating max/min, POW_HALVES by multiplications and a sqrt), so the generated kernel's values
are the VM kernel's bit for bit; tests/kernels/test_termgen.py compares them, and both with the term language's
NumPy evaluator (the plain-NumPy twin) to rounding.

Only the structure of the programs is baked into the code; their constants (parameter values, the contact
distance a0 among them) are passed at run time (``consts``), so one kernel serves every parameter value of a
library and is compiled once per structure (~1 s), then loaded from numba's on-disk cache. Modules are written
and imported by :func:`afmid.kernels.lawgen.load_module` (one file per text hash). The contact kinematics are
copied into the text from :func:`afmid.kernels.integrate.contact_kinematics_at` (not imported: numba's cache of a
generated function would not notice a change of a function it calls in another file; a change of the copied
text changes the file).
"""

from __future__ import annotations

import inspect
import textwrap
import threading
from dataclasses import dataclass

import numpy as np

import afmid.terms.expr as expr
from afmid.kernels.lawgen import GenerationError, SourceWriter, load_module, translate_program, variables_read

#: Bump when the generated text changes in a way the text itself would not show.
GENERATOR_VERSION = 3  # 2: eval_rows compiled for one signature; 3: one inlined body per kernel

_lock = threading.Lock()
_by_structure: dict[tuple, object] = {}  # program structure -> generated module


@dataclass(frozen=True)
class TermKernel:
    """A generated module for one library structure and the constants of one parameter set for it."""

    module: object  # has eval_rows (the columns) and stiffness_squares (the regressor-noise pass)
    consts: np.ndarray  # the programs' constants concatenated in term order

    def eval_rows(self, x: np.ndarray, xdot: np.ndarray, t: np.ndarray, separation: float, a0: float,
                  out: np.ndarray) -> tuple[bool, bool]:
        """out[r, i, j] = term j at sample i of row r (x, xdot, t: (rows, n), m, m/s, s; out (rows, n, p), any
        strides): the values of :func:`afmid.kernels.trajectory_eval.eval_rows`, bit for bit. Returns (all values
        finite, any value exactly zero); an overflow of the running sum alone reads as not finite (the caller then
        checks the values themselves, as after the VM kernel)."""
        # C-contiguous trajectory rows: the one compiled signature (EVAL_ROWS_SIGNATURE; no copy when they are)
        finite, any_zero = self.module.eval_rows(self.consts, *(np.ascontiguousarray(a, dtype=np.float64)
                                                              for a in (x, xdot, t)),
                                                 float(separation), float(a0), out)
        return bool(finite), bool(any_zero)

    def stiffness_squares(self, coef: np.ndarray, x: np.ndarray, xdot: np.ndarray, t: np.ndarray,
                          separation: float, a0: float, eps: float) -> float:
        """The sum over the samples of rows (x, xdot, t: (rows, n), m, m/s, s) of the squared central difference
        ((F(x + eps) - F(x - eps)) / (2 eps))^2, (N/m)^2, of the force F = sum_j coef[j] term j: one pass, no
        columns. Its plain-NumPy twin is the columns at x +- eps times ``coef`` (afmid.fit.prepare's
        regressor-noise pass without a generated kernel); they differ by rounding (the force summed term by term
        here, by BLAS there; the squares summed in sample order here, pairwise by np.sum there)."""
        return float(self.module.stiffness_squares(self.consts, np.ascontiguousarray(coef, dtype=np.float64),
                                                   x, xdot, t, separation, a0, eps))


def _kinematics_source() -> str:
    """The source of afmid.kernels.integrate.contact_kinematics_at, decorated for inlining here."""
    from afmid.kernels.integrate import contact_kinematics_at

    text = textwrap.dedent(inspect.getsource(contact_kinematics_at.py_func))
    body = text[text.index("def contact_kinematics_at"):]
    return '@njit(cache=True, error_model="numpy", inline="always")\n' + body


#: The one signature of the generated ``eval_rows``: consts and the trajectory rows C-contiguous (the caller makes
#: them so), ``out`` of any strides ('A'). Given ahead, numba compiles this one version and converts a C-contiguous
#: ``out`` (the row-major columns) to it instead of compiling a second, C-layout version beside the weak form's
#: sample-major one: each compilation of a generated kernel is ~0.6-0.8 s of CPU on the first-ever fit,
#: and the two versions did the same float operations in the same order (the same bits).
EVAL_ROWS_SIGNATURE = "(f8[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8, f8, f8[:, :, :])"


#: Samples of a row per tile when ``out`` is sample-major (the weak form's layout, rows = blocks): the kernel runs
#: over a tile of 8 samples (a cache line of x, xdot and t) for every row, so that its writes are contiguous; row
#: by row they would land one per page (7 ns a sample against 2 ns).
TILE = 8


def module_source(programs) -> str:
    """The text of the generated module for these programs (a library's terms, in column order)."""
    programs = list(programs)
    w = SourceWriter()
    kinematics = bool(variables_read(programs) & {0, 1, 2, 3})

    def each_term(on_value) -> None:  # the terms' statements in column order; on_value(j, name of its value)
        offset = 0
        for j, program in enumerate(programs):
            w.emit(1, f"# term {j}: {program.text}")
            on_value(j, translate_program(program, offset, w, 1, 0))
            offset += len(program.consts)

    def into_out(j: int, value: str) -> None:
        w.emit(1, f"out[r, i, {j}] = {value}")
        w.emit(1, f"total += {value}")
        w.emit(1, f"if {value} == 0.0:")
        w.emit(2, "any_zero = True")

    w.emit(0, '@njit(cache=True, error_model="numpy", inline="always")')
    w.emit(0, "def terms_at(K, out, r, i, x, v, t, separation, a0):")
    w.emit(1, '"""out[r, i, :] = the terms at one sample; returns (their sum, whether one is exactly zero)."""')
    w.emit(1, "total = 0.0")
    w.emit(1, "any_zero = False")
    if kinematics:
        w.emit(1, "z, zdot, delta, deltadot = contact_kinematics_at(x, v, separation, a0)")
    each_term(into_out)
    w.emit(1, "return total, any_zero")
    w.emit(0, "")
    w.emit(0, "")
    w.emit(0, '@njit(cache=True, error_model="numpy", inline="always")')
    w.emit(0, "def force_at(K, C, x, v, t, separation, a0):")
    w.emit(1, '"""sum_j C[j] * term j at one sample, in term order."""')
    if kinematics:
        w.emit(1, "z, zdot, delta, deltadot = contact_kinematics_at(x, v, separation, a0)")
    w.emit(1, "total = 0.0")
    each_term(lambda j, value: w.emit(1, f"total += C[{j}] * {value}"))
    w.emit(1, "return total")
    w.emit(0, "")
    w.emit(0, "")
    w.emit(0, '@njit(cache=True, error_model="numpy", nogil=True, no_cfunc_wrapper=True)')
    w.emit(0, "def stiffness_squares(K, C, x_rows, v_rows, t_rows, separation, a0, eps):")
    w.emit(1, '"""sum over the samples of ((F(x + eps) - F(x - eps)) / (2 eps))^2, F = sum_j C[j] term j."""')
    w.emit(1, "rows, n = x_rows.shape")
    w.emit(1, "total = 0.0")
    w.emit(1, "for r in range(rows):")
    w.emit(2, "for i in range(n):")
    w.emit(3, "x, v, t = x_rows[r, i], v_rows[r, i], t_rows[r, i]")
    # one call site of force_at (inlined once, not twice: half the compilation), the same x +- eps as two calls
    w.emit(3, "f_hi = 0.0")
    w.emit(3, "f_lo = 0.0")
    w.emit(3, "for side in range(2):")
    w.emit(4, "force = force_at(K, C, x + eps if side == 0 else x - eps, v, t, separation, a0)")
    w.emit(4, "if side == 0:")
    w.emit(5, "f_hi = force")
    w.emit(4, "else:")
    w.emit(5, "f_lo = force")
    w.emit(3, "slope = (f_hi - f_lo) / (2 * eps)")
    w.emit(3, "total += slope * slope")
    w.emit(1, "return total")
    w.emit(0, "")
    w.emit(0, "")
    # One signature given ahead (EVAL_ROWS_SIGNATURE): compiled once for every layout of out, see its comment.
    w.emit(0, f'@njit("{EVAL_ROWS_SIGNATURE}", cache=True, error_model="numpy", nogil=True,  # nogil: chunks in threads')
    w.emit(0, "      no_cfunc_wrapper=True)")
    w.emit(0, "def eval_rows(K, x_rows, v_rows, t_rows, separation, a0, out):")
    w.emit(1, '"""out[r, i, j] = term j at sample i of row r; returns (all finite, any exactly zero)."""')
    w.emit(1, "rows, n = x_rows.shape")
    w.emit(1, "total = 0.0")
    w.emit(1, "any_zero = False")
    # One loop nest for both layouts, so that terms_at is inlined (and compiled) once: sample-major out (the weak
    # form's) runs a tile of samples for every row; row-major out one tile of the whole row, i.e. row by row.
    w.emit(1, f"tile = {TILE} if rows > 1 and out.strides[0] < out.strides[1] else max(n, 1)")
    w.emit(1, "for i0 in range(0, n, tile):")
    w.emit(2, "i1 = min(i0 + tile, n)")
    w.emit(2, "for r in range(rows):")
    w.emit(3, "for i in range(i0, i1):")
    w.emit(4, "value, zero = terms_at(K, out, r, i, x_rows[r, i], v_rows[r, i], t_rows[r, i], separation, a0)")
    w.emit(4, "total += value")
    w.emit(4, "any_zero = any_zero or zero")
    w.emit(1, "return np.isfinite(total), any_zero")
    header = (
        '"""Library terms along trajectory rows, generated by afmid.kernels.termgen. Do not edit.\n\n'
        "Terms:\n" + "".join(f"    {p.text}\n" for p in programs)
        + f'"""\n# generator version {GENERATOR_VERSION}\n\n'
        "import math\n\nimport numpy as np\nfrom numba import njit\n\n\n"
    )
    return header + _kinematics_source() + "\n\n" + "\n".join(w.lines) + "\n"


def term_kernel(programs) -> TermKernel:
    """The generated kernel for these programs (written, imported and compiled on first use) and their constants.

    Raises :class:`afmid.kernels.lawgen.GenerationError` if a program cannot be translated (a program that reads a
    state gate: libraries with gates are evaluated by the VM) or the module cannot be written.
    """
    programs = tuple(programs)
    if any(p.n_vars > len(expr.VARIABLES) for p in programs):
        raise GenerationError("a term reads a state gate: evaluated by the VM")
    structure = tuple((p.code.tobytes(), len(p.consts)) for p in programs)
    with _lock:
        module = _by_structure.get(structure)
    if module is None:
        module = load_module(module_source(programs))
        with _lock:
            _by_structure[structure] = module
    consts = np.concatenate([np.zeros(0), *(p.consts for p in programs)]).astype(np.float64)
    return TermKernel(module, consts)

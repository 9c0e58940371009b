"""Library terms evaluated straight from a trajectory (x, xdot, t), in any output layout (the fit's hot loop).

:func:`eval_rows` is :func:`afmid.kernels.vm.eval_set` with the term-language variables (z, zdot, delta,
deltadot, x, xdot, t) formed per block of samples inside the kernel, instead of a (7, N) array formed first by
:func:`afmid.physics.library.trajectory_variables` and read back; and it writes into ``out`` of any strides, so the
weak form's integration (:meth:`afmid.preprocess.periods.WeakWindows.integrate_fine_columns`) gets its columns in the
layout of its one matrix product without a transposed copy of the fine grid (~90 MB at 500 periods). In the
same pass it notes whether every value is finite and whether any is exactly zero (the switching-cell check of
:func:`afmid.fit.system.average_switching_cells`), which were two more passes over the fine grid.

For libraries without history gates (states) only: a gate's state is scanned along the whole trajectory
first (:meth:`afmid.physics.library.Library.evaluate`). Its plain-NumPy twin (the term language's NumPy evaluator) is
``eval_rows_numpy`` in tests/kernels/test_trajectory_eval.py, which compares them to rounding, and the kernel with
:meth:`afmid.physics.library.Library.evaluate`'s VM bit for bit (the same VM on the same variables). The twin lives
with the test: a kernel does not import the library that calls it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from afmid.kernels.integrate import N_VARIABLES, contact_kinematics_at
from afmid.kernels.vm import BLOCK, STACK_SIZE, run_program


@njit(cache=True, error_model="numpy", nogil=True)  # nogil: chunks of one trace run in threads
def eval_rows(code, code_offsets, consts, const_offsets, x, xdot, t, separation, a0, out):
    """out[r, i, j] = program j at sample i of row r of the trajectory (x, xdot, t: (rows, n) in m, m/s, s).

    ``out`` is (rows, n, programs), any strides. Returns (all finite, any exactly zero) over the values.
    """
    rows, n = x.shape
    n_programs = code_offsets.shape[0] - 1
    stack = np.empty((STACK_SIZE, BLOCK))
    variables = np.empty((N_VARIABLES, BLOCK))
    total = 0.0
    any_zero = False
    for r in range(rows):
        for i0 in range(0, n, BLOCK):
            nb = min(BLOCK, n - i0)
            for i in range(nb):
                xi, vi = x[r, i0 + i], xdot[r, i0 + i]
                z, zdot, delta, deltadot = contact_kinematics_at(xi, vi, separation, a0)
                variables[0, i] = z
                variables[1, i] = zdot
                variables[2, i] = delta
                variables[3, i] = deltadot
                variables[4, i] = xi
                variables[5, i] = vi
                variables[6, i] = t[r, i0 + i]
            for j in range(n_programs):
                run_program(code, code_offsets[j], code_offsets[j + 1], consts, const_offsets[j], variables, 0, nb,
                            stack)
                for i in range(nb):
                    value = stack[0, i]
                    out[r, i0 + i, j] = value
                    total += value
                    if value == 0.0:
                        any_zero = True
    # A sum is finite only if every term is (an overflow of the sum alone is reported as not finite: the
    # caller then checks the values themselves).
    return np.isfinite(total), any_zero

"""The numba stack VM that evaluates compiled force-library terms.

Programs come from :func:`afmid.terms.expr.compile_expression`; the opcodes are
declared in :mod:`afmid.terms.opcodes` (so the compiler stays free of numba).
The kernels are compiled once, never per expression: changing an expression or a parameter only changes the data they are given.

The VM runs a program on a block of up to BLOCK samples at a time: every
opcode is a loop over the block, so the interpretation overhead is paid once
per block rather than once per sample, and the loops vectorise. A point
evaluation is a block of one sample, so all entry points share one interpreter.
A gate whose condition is false on the whole block jumps over its body; if it
holds on part of the block the body is evaluated on the whole block and
GATE_END puts exactly 0.0 where it is false, so the result never depends on
the body there (which may be inf or nan).

All arithmetic follows NumPy float64 semantics (``error_model="numpy"``):
division by zero gives inf/nan instead of raising, a negative base to a
non-integer power is nan, log of a negative number is nan. POW_HALVES may
differ from ``**`` in the last bits (and where the result is subnormal).
"""

from __future__ import annotations

import math

from collections.abc import Mapping

import numpy as np
from numba import njit

from afmid.terms import opcodes
from afmid.terms.opcodes import STACK_SIZE
from afmid.terms.expr import Program, ProgramSet, check_variables, compile_expression

# Samples per block in eval_set: the (STACK_SIZE, BLOCK) float64 stack is 32 kB,
# which stays in the L1/L2 cache.
BLOCK = 128


@njit(cache=True, error_model="numpy", inline="always")
def _pow_halves(a, k):
    """a ** (k / 2) for a small integer k, by multiplication and sqrt, with pow's special values."""
    m = abs(k)
    if m % 2 == 1:
        if a == -math.inf:
            return a ** (0.5 * k)  # sqrt(-inf) is nan, but (-inf) ** 1.5 is inf
        a += 0.0  # -0.0 becomes +0.0: (-0.0) ** 1.5 is +0.0, not -0.0 * sqrt(-0.0)
    r = 1.0
    for _ in range(m // 2):
        r *= a
    if m % 2 == 1:
        r *= math.sqrt(a)
    return 1.0 / r if k < 0 else r


@njit(cache=True, error_model="numpy")
def _run(code, c0, c1, consts, k0, variables, i0, nb, stack):
    """Run program code[c0:c1] (constants consts[k0:]) on samples i0..i0+nb-1.

    ``variables`` has shape (n_vars, N); ``stack`` is a float64 work array of
    shape (STACK_SIZE, >= nb). The result is left in stack[0, :nb]. The
    compiler guarantees programs fit the stack, so there is no overflow check.
    """
    sp = 0  # number of rows in use
    pc = c0
    while pc < c1:
        op = code[pc]
        if op == opcodes.PUSH_VAR:
            v = code[pc + 1]
            for i in range(nb):
                stack[sp, i] = variables[v, i0 + i]
            sp += 1
            pc += 2
        elif op == opcodes.PUSH_CONST:
            c = consts[k0 + code[pc + 1]]
            for i in range(nb):
                stack[sp, i] = c
            sp += 1
            pc += 2
        elif op == opcodes.JUMP_IF_FALSE_PUSH0:
            pc += 2
            skip = True
            for i in range(nb):
                if stack[sp - 1, i] != 0.0:
                    skip = False
                    break
            if skip:  # false everywhere: the condition row becomes the result
                for i in range(nb):
                    stack[sp - 1, i] = 0.0  # +0.0, also where the condition was -0.0
                pc = c0 + code[pc - 1]
        elif op == opcodes.GATE_END:
            sp -= 1
            for i in range(nb):
                stack[sp - 1, i] = stack[sp, i] if stack[sp - 1, i] != 0.0 else 0.0
            pc += 1
        elif op == opcodes.POW_HALVES:
            k = code[pc + 1]
            for i in range(nb):
                stack[sp - 1, i] = _pow_halves(stack[sp - 1, i], k)
            pc += 2
        elif op < opcodes.NEG:
            # Binary (opcodes 10..29): row t = (row t) op (row u), popping row u.
            # One loop per opcode, so that the loops vectorise.
            sp -= 1
            t, u = sp - 1, sp
            if op == opcodes.MUL:
                for i in range(nb):
                    stack[t, i] *= stack[u, i]
            elif op == opcodes.ADD:
                for i in range(nb):
                    stack[t, i] += stack[u, i]
            elif op == opcodes.SUB:
                for i in range(nb):
                    stack[t, i] -= stack[u, i]
            elif op == opcodes.DIV:
                for i in range(nb):
                    stack[t, i] /= stack[u, i]
            elif op == opcodes.POW:
                for i in range(nb):
                    stack[t, i] **= stack[u, i]
            elif op == opcodes.MAX:
                for i in range(nb):
                    a, b = stack[t, i], stack[u, i]
                    stack[t, i] = a if (a > b or a != a) else b  # NaN-propagating, like np.maximum
            elif op == opcodes.MIN:
                for i in range(nb):
                    a, b = stack[t, i], stack[u, i]
                    stack[t, i] = a if (a < b or a != a) else b
            elif op == opcodes.LT:
                for i in range(nb):
                    stack[t, i] = 1.0 if stack[t, i] < stack[u, i] else 0.0
            elif op == opcodes.LE:
                for i in range(nb):
                    stack[t, i] = 1.0 if stack[t, i] <= stack[u, i] else 0.0
            elif op == opcodes.GT:
                for i in range(nb):
                    stack[t, i] = 1.0 if stack[t, i] > stack[u, i] else 0.0
            elif op == opcodes.GE:
                for i in range(nb):
                    stack[t, i] = 1.0 if stack[t, i] >= stack[u, i] else 0.0
            elif op == opcodes.AND:
                for i in range(nb):
                    stack[t, i] = 1.0 if (stack[t, i] != 0.0 and stack[u, i] != 0.0) else 0.0
            elif op == opcodes.OR:
                for i in range(nb):
                    stack[t, i] = 1.0 if (stack[t, i] != 0.0 or stack[u, i] != 0.0) else 0.0
            else:
                raise ValueError("invalid opcode")
            pc += 1
        else:
            # Unary (opcodes 30 and up): row t = f(row t).
            t = sp - 1
            if op == opcodes.NEG:
                for i in range(nb):
                    stack[t, i] = -stack[t, i]
            elif op == opcodes.EXP:
                for i in range(nb):
                    stack[t, i] = math.exp(stack[t, i])
            elif op == opcodes.LOG:
                for i in range(nb):
                    stack[t, i] = math.log(stack[t, i])
            elif op == opcodes.SQRT:
                for i in range(nb):
                    stack[t, i] = math.sqrt(stack[t, i])
            elif op == opcodes.ABS:
                for i in range(nb):
                    stack[t, i] = abs(stack[t, i])
            elif op == opcodes.SIN:
                for i in range(nb):
                    stack[t, i] = math.sin(stack[t, i])
            elif op == opcodes.COS:
                for i in range(nb):
                    stack[t, i] = math.cos(stack[t, i])
            elif op == opcodes.POS:
                for i in range(nb):
                    a = stack[t, i]
                    stack[t, i] = a if (a > 0.0 or a != a) else 0.0
            elif op == opcodes.NOT:
                for i in range(nb):
                    stack[t, i] = 1.0 if stack[t, i] == 0.0 else 0.0
            else:
                raise ValueError("invalid opcode")
            pc += 1


#: The interpreter, for kernels elsewhere that run programs on their own blocks of samples
#: (:mod:`afmid.kernels.trajectory_eval`): same signature as ``_run``.
run_program = _run


@njit(cache=True, error_model="numpy")
def eval_point(code, c0, c1, consts, k0, k1, var):
    """Value of program code[c0:c1] with constants consts[k0:k1] at variable vector ``var``."""
    stack = np.empty((STACK_SIZE, 1))
    _run(code, c0, c1, consts[k0:k1], 0, var[:, np.newaxis], 0, 1, stack)
    return stack[0, 0]


@njit(cache=True, error_model="numpy")
def eval_set_point(code, code_offsets, consts, const_offsets, var, out, stack=None):
    """out[j] = program j of a ProgramSet at variable vector ``var`` (shape (n_vars,)).

    For an ODE right-hand side: pass a work array ``stack`` of shape
    (STACK_SIZE, 1) to make the call allocation-free; without it one is
    allocated per call.
    """
    if stack is None:
        stack = np.empty((STACK_SIZE, 1))
    variables = var[:, np.newaxis]
    for j in range(code_offsets.shape[0] - 1):
        _run(code, code_offsets[j], code_offsets[j + 1], consts, const_offsets[j], variables, 0, 1, stack)
        out[j] = stack[0, 0]


@njit(cache=True, error_model="numpy", nogil=True)  # nogil: chunks of one trace run in threads
def eval_set(code, code_offsets, consts, const_offsets, variables, out):
    """out[i, j] = program j of a ProgramSet at sample i of ``variables``.

    ``variables`` has shape (n_vars, N) and at least as many rows as the
    programs read (not checked here); ``out`` has shape (N, n_programs).
    """
    n = variables.shape[1]
    stack = np.empty((STACK_SIZE, BLOCK))
    for i0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - i0)
        for j in range(code_offsets.shape[0] - 1):
            c0, c1 = code_offsets[j], code_offsets[j + 1]
            _run(code, c0, c1, consts, const_offsets[j], variables, i0, nb, stack)
            for i in range(nb):
                out[i0 + i, j] = stack[0, i]


def evaluate_numba(program_or_text: Program | str, variables: np.ndarray,
                   params: Mapping[str, float] | None = None, states: tuple[str, ...] = ()) -> np.ndarray:
    """Evaluate one expression on ``variables`` (shape (n_vars, N)) with the numba VM; returns (N,).

    A convenience wrapper around :func:`eval_set` (for tests and checks). Text is compiled with ``params`` and
    ``states`` first.
    """
    if isinstance(program_or_text, Program):
        program = program_or_text
    else:
        program = compile_expression(program_or_text, {} if params is None else params, states)
    pset = ProgramSet([program])
    variables = np.ascontiguousarray(check_variables(variables, pset.n_vars))
    out = np.empty((variables.shape[1], 1))
    eval_set(pset.code, pset.code_offsets, pset.consts, pset.const_offsets, variables, out)
    return out[:, 0]

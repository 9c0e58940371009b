"""Compilation of term-language expressions to bytecode for the numba stack VM, and its NumPy twin.

:func:`compile_expression` lowers an expression (:mod:`afmid.terms.term_lowering`)
and emits a :class:`Program` for :mod:`afmid.kernels.vm`;
:func:`switching_programs` compiles the functions whose sign changes mark
non-smooth instants; :class:`ProgramSet` concatenates programs for one kernel
call; :func:`evaluate_numpy` evaluates an expression with NumPy to test the VM.
The opcodes are declared in :mod:`afmid.terms.opcodes`, which the VM reads too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from afmid.terms import opcodes
from afmid.terms.term_lowering import Gated, VarSlot, lower, numpy_value, param_values, resolve
from afmid.terms.term_parser import (
    VARIABLES,
    BinOp,
    Call,
    Compare,
    ExpressionError,
    Neg,
    Not,
    Num,
    check_names,
    children,
    parse,
    unparse,
    walk,
)


_BINARY_OPCODES = {"+": opcodes.ADD, "-": opcodes.SUB, "*": opcodes.MUL, "/": opcodes.DIV, "^": opcodes.POW,
                   "max": opcodes.MAX, "min": opcodes.MIN, "<": opcodes.LT, "<=": opcodes.LE, ">": opcodes.GT,
                   ">=": opcodes.GE, "and": opcodes.AND, "or": opcodes.OR}
_UNARY_OPCODES = {"exp": opcodes.EXP, "log": opcodes.LOG, "sqrt": opcodes.SQRT, "abs": opcodes.ABS, "sin": opcodes.SIN,
                  "cos": opcodes.COS, "pos": opcodes.POS}


# ---------------------------------------------------------------------------
# Compilation to VM bytecode
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Program:
    """Bytecode of one expression for :mod:`afmid.kernels.vm`.

    ``code`` (int64) reads variable slots 0..n_vars-1: VARIABLES then the
    states. Parameters are folded into ``consts`` (float64), so new parameter
    values need a new Program (cheap, no numba recompilation). ``params`` (the
    values used, sorted by name) and ``states`` let :func:`evaluate_numpy`
    re-evaluate ``text`` independently.
    """

    code: np.ndarray
    consts: np.ndarray
    text: str
    n_vars: int
    params: tuple[tuple[str, float], ...] = ()
    states: tuple[str, ...] = ()

    def __repr__(self) -> str:
        return (f"Program({self.text!r}, n_vars={self.n_vars}, "
                f"{len(self.code)} code words, {len(self.consts)} consts)")


def _program(tree, text: str, values: dict[str, float], states: tuple[str, ...]) -> Program:
    emitter = _Emitter()
    emitter.value(tree)
    if emitter.max_depth > opcodes.STACK_SIZE:
        raise ExpressionError(
            f"expression is nested too deeply for the VM (needs {emitter.max_depth} stack slots, "
            f"at most {opcodes.STACK_SIZE})", text)
    code = np.array(emitter.code, dtype=np.int64)
    consts = np.array(emitter.consts, dtype=np.float64)
    code.flags.writeable = consts.flags.writeable = False
    return Program(code, consts, text, len(VARIABLES) + len(states), tuple(values.items()), states)


def compile_expression(text: str, params: Mapping[str, float], states: tuple[str, ...] = ()) -> Program:
    """Compile ``text`` with parameter values ``params`` (SI) and state names ``states``.

    Raises ExpressionError for bad syntax, unknown names, non-finite parameter
    values and expressions too deep for the VM stack. Units are not checked
    here; see :func:`expression_units`.
    """
    states = tuple(states)
    tree, values = lower(parse(text), text, params, states)
    return _program(tree, text, values, states)


def switching_programs(text: str, params: Mapping[str, float], states: tuple[str, ...] = ()) -> list[Program]:
    """Switching functions of an expression: where one changes sign, the term is not smooth.

    One Program per comparison ``a < b`` (computing ``a - b``), per ``max(a, b)``
    and ``min(a, b)`` (``a - b``), and per ``abs(a)`` and ``pos(a)`` (``a``), in
    order of appearance. An ODE integrator locates the sign changes to step
    exactly onto the kinks. Functions that are constant after folding in
    ``params`` are left out, and so are repeats of an identical function.
    """
    node = parse(text)
    states = tuple(states)
    check_names(node, text, params, states)
    programs, seen = [], set()
    for n in walk(node):
        if isinstance(n, Compare) or isinstance(n, Call) and n.func in ("max", "min"):
            left, right = (n.left, n.right) if isinstance(n, Compare) else n.args
            switch = BinOp("-", left, right)
        elif isinstance(n, Call) and n.func in ("abs", "pos"):
            switch = n.args[0]
        else:
            continue
        switch_text = unparse(switch)
        if switch_text in seen:
            continue
        seen.add(switch_text)
        tree, values = lower(switch, switch_text, params, states)
        if not isinstance(tree, Num):
            programs.append(_program(tree, switch_text, values, states))
    return programs


def _pow_halves(exponent) -> int | None:
    """k if ``exponent`` is a constant k/2 with |k| <= MAX_POW_HALVES, else None."""
    if isinstance(exponent, Num) and (2 * exponent.value).is_integer():
        k = int(2 * exponent.value)
        return k if abs(k) <= opcodes.MAX_POW_HALVES else None
    return None


class _Emitter:
    """Emits bytecode for a lowered tree, tracking the stack depth it needs."""

    def __init__(self):
        self.code: list[int] = []
        self.consts: list[float] = []
        self._const_slots: dict[bytes, int] = {}
        self.depth = 0
        self.max_depth = 0

    def emit(self, opcode: int, stack_effect: int, operand: int | None = None) -> None:
        self.code.append(opcode)
        if operand is not None:
            self.code.append(operand)
        self.depth += stack_effect
        self.max_depth = max(self.max_depth, self.depth)

    def const(self, value: float) -> None:
        key = np.float64(value).tobytes()  # bit pattern: keeps 0.0 and -0.0 apart
        slot = self._const_slots.setdefault(key, len(self.consts))
        if slot == len(self.consts):
            self.consts.append(value)
        self.emit(opcodes.PUSH_CONST, +1, slot)

    def value(self, node) -> None:
        if isinstance(node, Num):
            self.const(node.value)
        elif isinstance(node, VarSlot):
            self.emit(opcodes.PUSH_VAR, +1, node.index)
        elif isinstance(node, Neg):
            self.value(node.operand)
            self.emit(opcodes.NEG, 0)
        elif isinstance(node, Gated):
            self.gated(node)
        elif isinstance(node, BinOp) and node.op == "^" and _pow_halves(node.right) is not None:
            self.value(node.left)
            self.emit(opcodes.POW_HALVES, 0, _pow_halves(node.right))
        elif isinstance(node, Call) and node.func in _UNARY_OPCODES:
            self.value(node.args[0])
            self.emit(_UNARY_OPCODES[node.func], 0)
        else:  # BinOp, max, min
            for child in children(node):
                self.value(child)
            self.emit(_BINARY_OPCODES[node.func if isinstance(node, Call) else node.op], -1)

    def cond(self, node) -> None:
        if isinstance(node, VarSlot):
            self.emit(opcodes.PUSH_VAR, +1, node.index)
        elif isinstance(node, Not):
            self.cond(node.operand)
            self.emit(opcodes.NOT, 0)
        elif isinstance(node, Compare):
            self.value(node.left)
            self.value(node.right)
            self.emit(_BINARY_OPCODES[node.op], -1)
        else:  # BoolOp
            self.cond(node.left)
            self.cond(node.right)
            self.emit(_BINARY_OPCODES[node.op], -1)

    def gated(self, node: Gated) -> None:
        # The conditions need no short-circuit among themselves (they cannot
        # produce nan), so they are combined into one with AND.
        self.cond(node.conds[0])
        for cond in node.conds[1:]:
            self.cond(cond)
            self.emit(opcodes.AND, -1)
        operand_at = len(self.code) + 1
        self.emit(opcodes.JUMP_IF_FALSE_PUSH0, 0, -1)  # the condition stays below the body
        if node.body is None:
            self.const(1.0)
        else:
            self.value(node.body)
        self.emit(opcodes.GATE_END, -1)
        self.code[operand_at] = len(self.code)


class ProgramSet:
    """Several programs concatenated for one kernel call.

    Program j is ``code[code_offsets[j]:code_offsets[j+1]]`` with constants
    ``consts[const_offsets[j]:const_offsets[j+1]]``; ``n_vars`` is the largest
    number of variable slots any program reads.
    """

    def __init__(self, programs: list[Program]):
        self.programs = tuple(programs)
        self.n_programs = len(self.programs)
        self.n_vars = max((p.n_vars for p in self.programs), default=len(VARIABLES))
        self.code = np.concatenate([np.zeros(0, np.int64), *(p.code for p in self.programs)])
        self.consts = np.concatenate([np.zeros(0, np.float64), *(p.consts for p in self.programs)])
        self.code_offsets = np.cumsum([0, *(len(p.code) for p in self.programs)], dtype=np.int64)
        self.const_offsets = np.cumsum([0, *(len(p.consts) for p in self.programs)], dtype=np.int64)

    def __repr__(self) -> str:
        return f"ProgramSet({[p.text for p in self.programs]!r})"


# ---------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------


def check_variables(variables, n_vars: int) -> np.ndarray:
    """``variables`` as a float64 array of shape (n_vars or more, N); ValueError if it has another shape."""
    variables = np.asarray(variables, dtype=np.float64)
    if variables.ndim != 2 or variables.shape[0] < n_vars:
        raise ValueError(f"variables must have shape ({n_vars}, N), got {variables.shape}")
    return variables


def evaluate_numpy(program_or_text: Program | str, variables: np.ndarray,
                   params: Mapping[str, float] | None = None, states: tuple[str, ...] = ()) -> np.ndarray:
    """Evaluate an expression on ``variables`` (shape (n_vars, N)) with NumPy; returns shape (N,).

    The plain-NumPy twin of the VM, used to test it: it evaluates the parsed
    tree (without constant folding) with the same gate semantics. For a Program,
    its ``text`` is re-parsed with the ``params`` and ``states`` it was compiled
    with unless others are given.
    """
    if isinstance(program_or_text, Program):
        text = program_or_text.text
        params = dict(program_or_text.params) if params is None else params
        states = tuple(states) or program_or_text.states
    else:
        text = program_or_text
        params = {} if params is None else params
        states = tuple(states)
    node = parse(text)
    tree = resolve(node, param_values(node, text, params, states), states)
    variables = check_variables(variables, len(VARIABLES) + len(states))
    with np.errstate(all="ignore"):
        value = numpy_value(tree, variables)
    return np.array(np.broadcast_to(value, variables.shape[1:]), dtype=np.float64)

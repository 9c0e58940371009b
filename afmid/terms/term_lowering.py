"""Lowering of term-language ASTs: the tree the VM compiler and the NumPy twin both evaluate.

:func:`resolve` replaces names by variable slots (:class:`VarSlot`) or
parameter values, and pulls the gates of a product out into a
:class:`Gated` node (so gated factors are never multiplied by 0, which would
turn inf into nan); :func:`fold` then constant-folds the tree. The NumPy
operations here (:func:`apply_numpy`, :func:`numpy_value`) follow the float64
semantics of the VM in :mod:`afmid.kernels.vm` exactly; the compiler
(:mod:`afmid.terms.term_compile`) emits bytecode for the same lowered tree.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from afmid.terms.term_parser import (
    VARIABLES,
    BinOp,
    BoolOp,
    Call,
    Compare,
    ExpressionError,
    Gate,
    Name,
    Neg,
    Node,
    Not,
    Num,
    StateRef,
    check_names,
    children,
    free_names,
    strip_gates,
    unparse,
    walk,
)


def _power(a, b):
    """Elementwise C ``pow`` (x**y of a negative x and non-integer y is nan, 0**-1 is inf).

    NumPy's power takes shortcuts for a scalar exponent (sqrt for 0.5, ...)
    that differ from pow for -0.0 and -inf; giving it full arrays avoids them,
    so the result matches the VM's pow exactly.
    """
    shape = np.broadcast_shapes(np.shape(a), np.shape(b))
    return np.power(np.broadcast_to(a, shape).ravel(), np.broadcast_to(b, shape).ravel()).reshape(shape)


# NumPy implementations, shared by constant folding and evaluate_numpy so both
# follow the float64 semantics of the VM.
_NP_BINARY = {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide, "^": _power}
_NP_FUNCTIONS = {
    "exp": np.exp,
    "log": np.log,
    "sqrt": np.sqrt,
    "abs": np.abs,
    "sin": np.sin,
    "cos": np.cos,
    "pos": lambda a: np.maximum(a, 0.0),
    "max": np.maximum,
    "min": np.minimum,
}
_NP_COMPARE = {"<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal}


@dataclass(frozen=True)
class VarSlot:
    """A variable slot (a variable or a state). In a condition: true where nonzero."""

    index: int


@dataclass(frozen=True)
class Gated:
    """``body`` where all ``conds`` hold, else exactly 0 (body None means 1).

    A product's gates are pulled out into one of these so that the gated
    factors are never multiplied with a 0 (which would turn inf into nan).
    """

    conds: tuple
    body: object | None


def resolve(node, values: Mapping[str, float], states: tuple[str, ...]):
    """Replace names by variable slots or parameter ``values``, and gates by Gated."""
    slots = {name: i for i, name in enumerate((*VARIABLES, *states))}

    def res(n):
        if isinstance(n, Num):
            return n
        if isinstance(n, (Name, StateRef)):
            return VarSlot(slots[n.name]) if n.name in slots else Num(values[n.name])
        if isinstance(n, Gate):
            return Gated((res(n.cond),), None)
        if isinstance(n, Neg) or isinstance(n, BinOp) and n.op in ("*", "/"):
            gates, rest = strip_gates(n)
            if gates:
                return Gated(tuple(res(g.cond) for g in gates), None if rest is None else res(rest))
        if isinstance(n, Neg):
            return Neg(res(n.operand))
        if isinstance(n, Call):
            return Call(n.func, tuple(res(a) for a in n.args))
        if isinstance(n, Not):
            return Not(res(n.operand))
        return type(n)(n.op, res(n.left), res(n.right))

    return res(node)


def apply_numpy(node, args: list):
    """Apply the operation of Neg/BinOp/Call/Compare ``node`` to evaluated args (NumPy)."""
    if isinstance(node, Neg):
        return np.negative(args[0])
    if isinstance(node, Call):
        return _NP_FUNCTIONS[node.func](*args)
    if isinstance(node, Compare):
        return _NP_COMPARE[node.op](*args)
    return _NP_BINARY[node.op](*args)


def fold(node):
    """Constant-fold a resolved tree. Conditions fold to Python bools."""
    if isinstance(node, (Num, VarSlot)):
        return node
    if isinstance(node, Gated):
        conds = [fold(c) for c in node.conds]
        if any(c is False for c in conds):
            return Num(0.0)
        conds = tuple(c for c in conds if c is not True)
        body = fold(node.body) if node.body is not None else None
        if not conds:
            return body if body is not None else Num(1.0)
        return Gated(conds, body)
    if isinstance(node, Not):
        operand = fold(node.operand)
        return (not operand) if isinstance(operand, bool) else Not(operand)
    if isinstance(node, BoolOp):
        left, right = fold(node.left), fold(node.right)
        absorbing = node.op == "or"  # True absorbs 'or', False absorbs 'and'
        for a, b in ((left, right), (right, left)):
            if isinstance(a, bool):
                return absorbing if a is absorbing else b
        return BoolOp(node.op, left, right)
    args = [fold(c) for c in children(node)]
    if all(isinstance(a, Num) for a in args):
        with np.errstate(all="ignore"):
            value = apply_numpy(node, [np.float64(a.value) for a in args])
        return bool(value) if isinstance(node, Compare) else Num(float(value))
    if isinstance(node, Neg):
        return Neg(args[0])
    if isinstance(node, Call):
        return Call(node.func, tuple(args))
    return type(node)(node.op, *args)


def _is_literal(node) -> bool:
    """True for a tree of numbers and operations only (no variable, parameter, state or gate)."""
    return not any(isinstance(n, (Name, StateRef, Gate)) for n in walk(node))


def check_constants(node: Node, text: str) -> None:
    """Every constant part of ``node`` (a subtree of numbers only: ``1/0``, ``log(0)``) must be a finite number.

    Folded, ``[1/0 > 0]`` becomes a gate that is always true and ``z * (1/(2 - 2))`` a column of inf; either is a
    typing error the user should see, named, rather than a term that fits. Constants are evaluated
    with the same float64 operations as the folding (:func:`apply_numpy`)."""
    if isinstance(node, Num):
        return
    if isinstance(node, (Neg, BinOp, Call)) and _is_literal(node):
        with np.errstate(all="ignore"):
            value = float(numpy_value(node, np.empty((0, 0))))
        if not math.isfinite(value):
            raise ExpressionError(f"the constant {unparse(node)} is not finite ({value}); the constant parts of a "
                                  "term must be numbers", text, getattr(node, "pos", -1))
        return
    for child in children(node):
        check_constants(child, text)


def param_values(node: Node, text: str, params: Mapping, states: tuple[str, ...]) -> dict[str, float]:
    """Check the names and constants in ``node``; return the values of the parameters it uses, by name."""
    check_names(node, text, params, states)
    check_constants(node, text)
    values = {}
    for name in sorted(free_names(node) - set(states)):
        try:
            values[name] = float(params[name])
        except (TypeError, ValueError):
            values[name] = math.nan
        if not math.isfinite(values[name]):
            raise ExpressionError(f"parameter {name!r} = {params[name]!r} is not a finite number", text)
    return values


def lower(node: Node, text: str, params: Mapping, states: tuple[str, ...]):
    """The resolved, constant-folded tree the compiler emits, and the parameter values used."""
    values = param_values(node, text, params, states)
    return fold(resolve(node, values, states)), values


def numpy_value(node, variables: np.ndarray):
    if isinstance(node, Num):
        return np.float64(node.value)
    if isinstance(node, VarSlot):
        return variables[node.index]
    if isinstance(node, Gated):
        mask = functools.reduce(np.logical_and, [numpy_condition(c, variables) for c in node.conds])
        body = 1.0 if node.body is None else numpy_value(node.body, variables)
        return np.where(mask, body, 0.0)
    return apply_numpy(node, [numpy_value(c, variables) for c in children(node)])


def numpy_condition(node, variables: np.ndarray):
    if isinstance(node, VarSlot):
        return variables[node.index] != 0
    if isinstance(node, Not):
        return np.logical_not(numpy_condition(node.operand, variables))
    if isinstance(node, BoolOp):
        combine = np.logical_and if node.op == "and" else np.logical_or
        return combine(numpy_condition(node.left, variables), numpy_condition(node.right, variables))
    return _NP_COMPARE[node.op](numpy_value(node.left, variables), numpy_value(node.right, variables))

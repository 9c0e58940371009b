"""Units of term-language expressions: the dimensional check of :func:`expression_units`.

A term's SI unit follows from the units of the names it uses (variables:
:data:`afmid.terms.term_parser.VARIABLE_UNITS`, parameters: given by the caller,
states: dimensionless). Literal sub-expressions are evaluated with the same
float64 semantics as the VM (:func:`afmid.terms.term_lowering.apply_numpy`), so a
literal 0 or an exponent like 3/2 is recognised exactly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from afmid.terms.term_lowering import apply_numpy, check_constants
from afmid.terms.term_parser import (
    VARIABLE_UNITS,
    VARIABLES,
    BinOp,
    BoolOp,
    Call,
    Compare,
    ExpressionError,
    Gate,
    Name,
    Neg,
    Not,
    Num,
    StateRef,
    check_names,
    children,
    parse,
    unparse,
    walk,
)
from afmid.terms.units import DIMENSIONLESS, Unit, as_unit


def _literal_value(node) -> float | None:
    """The value of a subtree made of numbers and functions only, else None."""
    if isinstance(node, Num):
        return node.value
    if isinstance(node, (Neg, BinOp, Call)):
        values = [_literal_value(c) for c in children(node)]
        if any(v is None for v in values):
            return None
        with np.errstate(all="ignore"):
            return float(apply_numpy(node, [np.float64(v) for v in values]))
    return None


def _uses_variables(node, states: tuple[str, ...]) -> bool:
    return any(isinstance(n, (Name, StateRef)) and (n.name in VARIABLES or n.name in states)
               for n in walk(node))


def expression_units(text: str, param_units: Mapping[str, Unit | str], states: tuple[str, ...] = ()) -> Unit:
    """The SI unit of an expression, checking that it is dimensionally consistent.

    ``param_units`` gives each parameter's unit (a Unit or a unit string);
    states are dimensionless. Rules: the operands of + and -, of max/min and of
    comparisons need equal units (a literal 0 matches any unit); the arguments
    of exp, log, sin and cos must be dimensionless; sqrt halves the exponents;
    abs and pos keep units; gates are dimensionless. An exponent must be a
    dimensionless constant; if the base has units, it must be a number
    expression (such as 1.5 or -2 or 3/2) because the result's unit depends on
    its value, while a dimensionless base may also be raised to parameters.
    Raises ExpressionError.
    """
    node = parse(text)
    states = tuple(states)
    check_names(node, text, param_units, states)
    check_constants(node, text)  # a term's units are its first check (model.terms): 1/0 is refused here already
    units = dict(VARIABLE_UNITS)
    units.update({s: DIMENSIONLESS for s in states})
    for name, unit in param_units.items():
        try:
            units[name] = as_unit(unit)
        except ValueError as exc:
            raise ExpressionError(f"parameter {name!r} has an invalid unit: {exc}", text) from None
    return _UnitChecker(text, units, states).unit(node)


@dataclass
class _UnitChecker:
    text: str
    units: dict[str, Unit]
    states: tuple[str, ...]

    def fail(self, reason: str, node) -> ExpressionError:
        return ExpressionError(reason, self.text, node.pos if node.pos >= 0 else None)

    def same(self, what: str, node, a, b) -> Unit:
        """The common unit of operands a and b of ``node`` (a literal 0 fits any unit)."""
        ua, ub = self.unit(a), self.unit(b)
        if ua == ub or _literal_value(b) == 0:
            return ua
        if _literal_value(a) == 0:
            return ub
        raise self.fail(f"{what} needs equal units, got {ua} and {ub} in {unparse(node)!r}", node)

    def unit(self, node) -> Unit:
        if isinstance(node, Num):
            return DIMENSIONLESS
        if isinstance(node, Name):
            return self.units[node.name]
        if isinstance(node, Neg):
            return self.unit(node.operand)
        if isinstance(node, Gate):
            self.cond(node.cond)
            return DIMENSIONLESS
        if isinstance(node, Call):
            return self.call(node)
        if node.op in ("+", "-"):
            return self.same("'+'" if node.op == "+" else "'-'", node, node.left, node.right)
        if node.op == "*":
            return self.unit(node.left) * self.unit(node.right)
        if node.op == "/":
            return self.unit(node.left) / self.unit(node.right)
        return self.power(node)

    def power(self, node: BinOp) -> Unit:
        base, exponent = self.unit(node.left), self.unit(node.right)
        if not exponent.is_dimensionless:
            raise self.fail(f"an exponent must be dimensionless, got {exponent} in {unparse(node)!r}", node)
        if _uses_variables(node.right, self.states):
            raise self.fail(f"an exponent must be a constant, got {unparse(node.right)!r}", node)
        if base.is_dimensionless:
            return DIMENSIONLESS
        value = _literal_value(node.right)
        if value is None:
            raise self.fail(
                f"the exponent of a quantity in {base} must be a number, not {unparse(node.right)!r}, "
                "since the unit of the result depends on it", node)
        if not math.isfinite(value):
            raise self.fail(f"exponent {unparse(node.right)!r} is not finite", node)
        return base ** value

    def call(self, node: Call) -> Unit:
        if node.func in ("max", "min"):
            return self.same(f"{node.func}()", node, *node.args)
        arg = self.unit(node.args[0])
        if node.func in ("abs", "pos"):
            return arg
        if node.func == "sqrt":
            return arg ** 0.5
        if not arg.is_dimensionless:
            raise self.fail(f"the argument of {node.func}() must be dimensionless, got {arg}", node)
        return DIMENSIONLESS

    def cond(self, node) -> None:
        if isinstance(node, Compare):
            self.same(f"comparison {node.op!r}", node, node.left, node.right)
        elif isinstance(node, (BoolOp, Not)):
            for child in children(node):
                self.cond(child)

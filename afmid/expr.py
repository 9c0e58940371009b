"""A small, safe expression language for force-library terms.

A term is an arithmetic expression in the tip-sample variables (see
:data:`VARIABLES`), named scalar parameters and boolean history states, e.g.::

    [z <= a0] * delta^1.5          Hertz-type contact term
    [z > a0] * z^-2                van der Waals-type term, zero in contact
    exp(-z/lambda) * zdot          distance-dependent damping
    [meniscus and z > a0] * z      a term that only acts while a state is set

Grammar (usual precedence, lowest first)::

    expr   := term (('+' | '-') term)*
    term   := unary (('*' | '/') unary)*
    unary  := ('-' | '+') unary | power
    power  := atom (('^' | '**') unary)?           right-associative; -z^2 = -(z^2)
    atom   := number | name | func '(' expr (',' expr)* ')' | '(' expr ')' | '[' cond ']'
    cond   := and_c ('or' and_c)*
    and_c  := not_c ('and' not_c)*
    not_c  := 'not' not_c | expr ('<' | '<=' | '>' | '>=') expr | state | '(' cond ')'

A gate ``[cond]`` is worth 1 where ``cond`` holds and 0 elsewhere. A gate that
multiplies something short-circuits: ``[z > a0] * z^-2`` is exactly 0 where the
gate is false, even where ``z^-2`` is inf or nan.

Text is parsed by a hand-written tokenizer and recursive-descent parser (user
text is never given to eval, exec, compile or ast.parse). :func:`compile_expression`
turns an expression into a :class:`Program` for the numba stack VM in
:mod:`afmid.kernels.vm`; :func:`evaluate_numpy` is its plain-NumPy twin, used to
test the VM. This module does not import numba (nor any kernel: the VM imports
its opcodes from here; :func:`afmid.kernels.vm.evaluate_numba` evaluates one
expression with it).
"""

from __future__ import annotations

import difflib
import functools
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from .units import DIMENSIONLESS, Unit, as_unit, parse_unit

# The variable slots of every program, in this order (a contract with the
# callers that fill the variable arrays). States follow in slots 7, 8, ...
VARIABLES: tuple[str, ...] = ("z", "zdot", "delta", "deltadot", "x", "xdot", "t")

VARIABLE_UNITS: dict[str, Unit] = {
    "z": parse_unit("m"),  # tip-sample separation
    "zdot": parse_unit("m/s"),
    "delta": parse_unit("m"),  # indentation max(a0 - z, 0)
    "deltadot": parse_unit("m/s"),  # -zdot where z <= a0, else 0
    "x": parse_unit("m"),  # cantilever deflection
    "xdot": parse_unit("m/s"),
    "t": parse_unit("s"),
}

# Function name -> number of arguments.
FUNCTIONS: dict[str, int] = {
    "exp": 1,
    "log": 1,
    "sqrt": 1,
    "abs": 1,
    "sin": 1,
    "cos": 1,
    "pos": 1,  # max(a, 0)
    "max": 2,
    "min": 2,
}

KEYWORDS = ("and", "or", "not")
COMPARISONS = ("<", "<=", ">", ">=")

# ---------------------------------------------------------------------------
# Bytecode of the stack VM. The opcodes live here, not in afmid.kernels.vm, so
# that the compiler does not import numba; the VM imports them from here.
# Code is a flat int64 array: each opcode is followed by its inline operand, if
# any. Booleans are 0.0/1.0 on the stack; a value counts as true when nonzero.
# A gated product [c] * e compiles to
#     c  JUMP_IF_FALSE_PUSH0 end  e  GATE_END  end:
# ---------------------------------------------------------------------------
PUSH_VAR = 1  # operand: variable slot
PUSH_CONST = 2  # operand: index into the program's consts
# operand: jump target, relative to the program's first code word. If the
# condition on top of the stack is false (on every sample of the block the VM
# runs), it becomes the result 0.0 and control jumps over the gated body;
# otherwise the condition stays below the body for GATE_END.
JUMP_IF_FALSE_PUSH0 = 3
# Pops the body value e and the condition c below it; pushes e where c is
# true, else 0.0 (so samples where c is false get 0.0 even if e is nan there).
GATE_END = 4
# operand k: replaces the top x by x ** (k/2) for |k| <= MAX_POW_HALVES, using
# multiplications and a sqrt, since a general pow costs ~10x more.
POW_HALVES = 5
MAX_POW_HALVES = 16
# Binary opcodes (pop b, pop a, push a op b) are 10..29.
ADD = 10
SUB = 11
MUL = 12
DIV = 13
POW = 14
MAX = 15
MIN = 16
LT = 17
LE = 18
GT = 19
GE = 20
AND = 21
OR = 22
# Unary opcodes (pop a, push f(a)) are 30 and up.
NEG = 30
EXP = 31
LOG = 32
SQRT = 33
ABS = 34
SIN = 35
COS = 36
POS = 37
NOT = 38

# Stack slots of the VM. The compiler rejects deeper expressions, so the kernel
# needs no overflow check.
STACK_SIZE = 32

_BINARY_OPCODES = {"+": ADD, "-": SUB, "*": MUL, "/": DIV, "^": POW, "max": MAX, "min": MIN,
                   "<": LT, "<=": LE, ">": GT, ">=": GE, "and": AND, "or": OR}
_UNARY_OPCODES = {"exp": EXP, "log": LOG, "sqrt": SQRT, "abs": ABS, "sin": SIN, "cos": COS, "pos": POS}



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


class ExpressionError(ValueError):
    """An expression is malformed or inconsistent (syntax, unknown name, units).

    ``reason`` is the bare message; ``text`` and ``pos`` (0-based column), when
    known, are shown below it with a caret under the offending place.
    """

    def __init__(self, reason: str, text: str | None = None, pos: int | None = None):
        self.reason = reason
        self.text = text
        self.pos = pos
        super().__init__(self._format())

    def _format(self) -> str:
        if self.text is None:
            return self.reason
        if self.pos is None:
            return f"{self.reason} in {self.text!r}"
        # Show only the line holding pos, in case the text spans several lines.
        start = self.text.rfind("\n", 0, self.pos) + 1
        end = self.text.find("\n", self.pos)
        line = self.text[start:] if end < 0 else self.text[start:end]
        return f"{self.reason} (column {self.pos - start + 1}):\n    {line}\n    {' ' * (self.pos - start)}^"


# ---------------------------------------------------------------------------
# AST. ``pos`` is the 0-based column of the node's operator or name in the
# source text, used for error carets only (so it takes no part in equality).
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Num:
    value: float
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Name:
    """A variable, state or parameter used as a number."""

    name: str
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Neg:
    operand: Node
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class BinOp:
    op: str  # '+', '-', '*', '/', '^'
    left: Node
    right: Node
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Call:
    func: str
    args: tuple[Node, ...]
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Gate:
    """``[cond]``: 1 where cond holds, else 0."""

    cond: Cond
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Compare:
    op: str  # '<', '<=', '>', '>='
    left: Node
    right: Node
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class BoolOp:
    op: str  # 'and', 'or'
    left: Cond
    right: Cond
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class Not:
    operand: Cond
    pos: int = field(default=-1, compare=False)


@dataclass(frozen=True)
class StateRef:
    """A bare name in a condition: true where that state is set."""

    name: str
    pos: int = field(default=-1, compare=False)


Node = Num | Name | Neg | BinOp | Call | Gate
Cond = Compare | BoolOp | Not | StateRef


# ---------------------------------------------------------------------------
# Tokenizer and parser
# ---------------------------------------------------------------------------

_TOKEN_RE = re.compile(
    r"(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
    r"|(?P<name>[A-Za-z_][A-Za-z_0-9]*)"
    r"|(?P<op>\*\*|<=|>=|==|!=|[-+*/^()\[\],<>=])"
)
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z_0-9]*\Z")


@dataclass(frozen=True)
class _Token:
    kind: str  # 'num', 'name', 'op' or 'end'
    value: str
    pos: int

    def describe(self) -> str:
        return "end of expression" if self.kind == "end" else repr(self.value)


def _tokenize(text: str) -> list[_Token]:
    tokens = []
    pos = 0
    while pos < len(text):
        if text[pos].isspace():
            pos += 1
            continue
        m = _TOKEN_RE.match(text, pos)
        if not m:
            raise ExpressionError(f"unexpected character {text[pos]!r}", text, pos)
        kind = m.lastgroup
        tokens.append(_Token(kind, m.group(kind), pos))
        pos = m.end()
    tokens.append(_Token("end", "", len(text)))
    return tokens


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.tokens = _tokenize(text)
        self.i = 0

    def error(self, reason: str, pos: int | None = None) -> ExpressionError:
        return ExpressionError(reason, self.text, self.peek().pos if pos is None else pos)

    def peek(self) -> _Token:
        return self.tokens[self.i]

    def at(self, kind: str, *values: str) -> bool:
        tok = self.tokens[self.i]
        return tok.kind == kind and (not values or tok.value in values)

    def take(self) -> _Token:
        tok = self.tokens[self.i]
        self.i += 1
        return tok

    def expect(self, value: str, opening: _Token) -> None:
        """Consume the bracket ``value`` that closes ``opening``."""
        if not self.at("op", value):
            raise self.error(f"expected {value!r} to close the {opening.value!r} at column "
                             f"{opening.pos + 1} but found {self.peek().describe()}")
        self.i += 1

    # -- arithmetic ---------------------------------------------------------

    def parse(self) -> Node:
        if self.at("end"):
            raise ExpressionError("empty expression", self.text)
        node = self.expr()
        tok = self.peek()
        if tok.kind == "end":
            return node
        if tok.value in COMPARISONS:
            raise self.error(f"a comparison ({tok.value!r}) is only allowed inside a gate [...]")
        if tok.kind == "name" and tok.value in KEYWORDS:
            raise self.error(f"{tok.value!r} is only allowed inside a gate [...]")
        if tok.kind in ("num", "name") or tok.value in ("(", "["):
            raise self.error(f"missing operator before {tok.describe()} (write '*' to multiply)")
        raise self.error(f"unexpected {tok.describe()}")

    def expr(self) -> Node:
        node = self.term()
        while self.at("op", "+", "-"):
            tok = self.take()
            node = BinOp(tok.value, node, self.term(), tok.pos)
        return node

    def term(self) -> Node:
        node = self.unary()
        while self.at("op", "*", "/"):
            tok = self.take()
            node = BinOp(tok.value, node, self.unary(), tok.pos)
        return node

    def unary(self) -> Node:
        if self.at("op", "-"):
            tok = self.take()
            return Neg(self.unary(), tok.pos)
        if self.at("op", "+"):
            self.take()
            return self.unary()
        return self.power()

    def power(self) -> Node:
        base = self.atom()
        if self.at("op", "^", "**"):
            tok = self.take()
            # The exponent is a unary so that z^-2 works; recursing into unary ->
            # power makes ^ right-associative.
            return BinOp("^", base, self.unary(), tok.pos)
        return base

    def atom(self) -> Node:
        tok = self.peek()
        if tok.kind == "num":
            self.take()
            value = float(tok.value)
            if not math.isfinite(value):
                raise self.error(f"number {tok.value} is too large", tok.pos)
            return Num(value, tok.pos)
        if tok.kind == "name":
            return self.name_or_call()
        if self.at("op", "("):
            self.take()
            node = self.expr()
            self.expect(")", tok)
            return node
        if self.at("op", "["):
            self.take()
            cond = self.cond()
            self.expect("]", tok)
            return Gate(cond, tok.pos)
        raise self.error(f"expected a number, name, '(' or '[' but found {tok.describe()}")

    def name_or_call(self) -> Node:
        tok = self.take()
        name = tok.value
        if name in KEYWORDS:
            raise self.error(f"{name!r} is only allowed inside a gate [...]", tok.pos)
        if not self.at("op", "("):
            if name in FUNCTIONS:
                raise self.error(f"{name!r} is a function; write {name}(...)", tok.pos)
            return Name(name, tok.pos)
        if name not in FUNCTIONS:
            raise self.error(_unknown("function", name, list(FUNCTIONS)), tok.pos)
        opening = self.take()
        args = [self.expr()]
        while self.at("op", ","):
            self.take()
            args.append(self.expr())
        self.expect(")", opening)
        arity = FUNCTIONS[name]
        if len(args) != arity:
            plural = "s" if arity > 1 else ""
            raise self.error(f"{name}() takes {arity} argument{plural}, got {len(args)}", tok.pos)
        return Call(name, tuple(args), tok.pos)

    # -- conditions (inside gates) ------------------------------------------

    def cond(self) -> Cond:
        node = self.and_cond()
        while self.at("name", "or"):
            tok = self.take()
            node = BoolOp("or", node, self.and_cond(), tok.pos)
        return node

    def and_cond(self) -> Cond:
        node = self.not_cond()
        while self.at("name", "and"):
            tok = self.take()
            node = BoolOp("and", node, self.not_cond(), tok.pos)
        return node

    def not_cond(self) -> Cond:
        if self.at("name", "not"):
            tok = self.take()
            return Not(self.not_cond(), tok.pos)
        if not self.at("op", "("):
            return self.comparison()
        # '(' opens either an arithmetic operand, as in [(z - a0) < 0], or a
        # parenthesised condition, as in [(z < a0) or s]. Try the first, then
        # the second; if both fail, report the error that got further.
        start = self.i
        try:
            return self.comparison()
        except ExpressionError as as_operand:
            self.i = start
            opening = self.take()
            try:
                node = self.cond()
                self.expect(")", opening)
                return node
            except ExpressionError as as_cond:
                raise max(as_operand, as_cond, key=lambda e: e.pos) from None

    def comparison(self) -> Cond:
        left = self.expr()
        tok = self.peek()
        if tok.kind == "op" and tok.value in COMPARISONS:
            self.take()
            right = self.expr()
            if self.at("op", *COMPARISONS):
                raise self.error("chained comparisons are not supported; combine them with 'and'")
            return Compare(tok.value, left, right, tok.pos)
        if tok.value in ("==", "!=", "="):
            raise self.error(f"{tok.value!r} is not supported; use <, <=, > or >=")
        if isinstance(left, Name):
            return StateRef(left.name, left.pos)
        raise self.error(f"expected a comparison (<, <=, >, >=) but found {tok.describe()}")


# Deepest AST accepted. The passes over the tree recurse, so this keeps them
# well inside Python's recursion limit; real force terms are far shallower.
MAX_TREE_DEPTH = 200


def parse(text: str) -> Node:
    """Parse expression ``text`` into an AST; raises ExpressionError on bad syntax."""
    try:
        node = _Parser(text).parse()
    except RecursionError:
        node = None
    if node is None or _tree_depth(node) > MAX_TREE_DEPTH:
        raise ExpressionError(f"expression is nested too deeply (more than {MAX_TREE_DEPTH} levels)", text)
    return node


def _tree_depth(node) -> int:
    deepest, todo = 0, [(node, 1)]
    while todo:  # iterative, since the tree may be deeper than the recursion limit
        n, depth = todo.pop()
        deepest = max(deepest, depth)
        todo.extend((child, depth + 1) for child in _children(n))
    return deepest


def _as_node(text_or_node: str | Node) -> Node:
    return parse(text_or_node) if isinstance(text_or_node, str) else text_or_node


def _unknown(kind: str, name: str, allowed: list[str]) -> str:
    hint = difflib.get_close_matches(name, allowed, n=1, cutoff=0.5)
    message = f"unknown {kind} {name!r}"
    if hint:
        message += f" (did you mean {hint[0]!r}?)"
    return message + f"; allowed: {', '.join(allowed) if allowed else 'none'}"


# ---------------------------------------------------------------------------
# Traversal helpers
# ---------------------------------------------------------------------------


def _children(node) -> tuple:
    if isinstance(node, (Neg, Not)):
        return (node.operand,)
    if isinstance(node, (BinOp, Compare, BoolOp)):
        return (node.left, node.right)
    if isinstance(node, Call):
        return node.args
    if isinstance(node, Gate):
        return (node.cond,)
    return ()


def _walk(node) -> Iterator:
    """All nodes of a tree, parents before children, left to right."""
    yield node
    for child in _children(node):
        yield from _walk(child)


def free_names(text_or_node: str | Node) -> set[str]:
    """Names an expression uses that are not VARIABLES: its parameters and states."""
    node = _as_node(text_or_node)
    return {
        n.name for n in _walk(node) if isinstance(n, (Name, StateRef)) and n.name not in VARIABLES
    }


# Binding strength in unparse: sum 1, product 2, unary 3, power 4, atom 5.
def unparse(node: Node | Cond) -> str:
    """Canonical text of an AST; ``parse(unparse(node)) == node``."""
    return _unparse(node, 0)


def _unparse(node, context: int) -> str:
    if isinstance(node, Num):
        v = node.value
        text = str(int(v)) if v == int(v) and abs(v) < 1e15 else repr(v)
        return f"({text})" if v < 0 and context > 0 else text
    if isinstance(node, (Name, StateRef)):
        return node.name
    if isinstance(node, Call):
        return f"{node.func}({', '.join(_unparse(a, 0) for a in node.args)})"
    if isinstance(node, Gate):
        return f"[{_unparse(node.cond, 0)}]"
    if isinstance(node, Neg):
        text, level = "-" + _unparse(node.operand, 3), 3
    elif isinstance(node, BinOp):
        if node.op in ("+", "-"):
            level, left, right = 1, 1, 2
        elif node.op in ("*", "/"):
            level, left, right = 2, 2, 3
        else:
            level, left, right = 4, 5, 3
        op = f" {node.op} " if level == 1 else node.op
        text = _unparse(node.left, left) + op + _unparse(node.right, right)
    elif isinstance(node, Compare):
        text, level = f"{_unparse(node.left, 0)} {node.op} {_unparse(node.right, 0)}", 4
    elif isinstance(node, BoolOp):
        level = 1 if node.op == "or" else 2
        text = f"{_unparse(node.left, level)} {node.op} {_unparse(node.right, level + 1)}"
    elif isinstance(node, Not):
        text, level = "not " + _unparse(node.operand, 3), 3
    else:
        raise TypeError(f"not an expression node: {node!r}")
    return f"({text})" if level < context else text


# ---------------------------------------------------------------------------
# Names
# ---------------------------------------------------------------------------


def _check_declarations(text: str, params: Mapping, states: tuple[str, ...]) -> None:
    """Parameter and state names must be valid and distinct from everything else."""
    if len(set(states)) != len(states):
        raise ExpressionError(f"states {states!r} contain a duplicate", text)
    reserved = {**{v: "a variable" for v in VARIABLES}, **{f: "a function" for f in FUNCTIONS},
                **{k: "a keyword" for k in KEYWORDS}}
    for kind, names in (("state", states), ("parameter", list(params))):
        for name in names:
            if not isinstance(name, str) or not _NAME_RE.match(name):
                raise ExpressionError(f"{kind} name {name!r} is not a valid name", text)
            if name in reserved:
                raise ExpressionError(f"{kind} name {name!r} is {reserved[name]}", text)
            reserved[name] = f"a {kind}"


def _check_names(node: Node, text: str, params: Mapping, states: tuple[str, ...]) -> None:
    """Every name must be a variable, state or parameter; condition names must be states.

    Also rejects gates in divisors, the one place where a gate cannot short-circuit.
    """
    _check_declarations(text, params, states)
    for n in _walk(node):
        if isinstance(n, StateRef) and n.name not in states:
            what = "a variable" if n.name in VARIABLES else "a parameter" if n.name in params else None
            if what:
                raise ExpressionError(
                    f"{n.name!r} is {what}, not a state; a gate needs a comparison or a state name",
                    text, n.pos)
            raise ExpressionError(_unknown("state", n.name, list(states)), text, n.pos)
        if isinstance(n, Name) and n.name not in VARIABLES and n.name not in states and n.name not in params:
            allowed = [*VARIABLES, *states, *params]
            raise ExpressionError(_unknown("name", n.name, allowed), text, n.pos)
        if isinstance(n, BinOp) and n.op == "/" and _strip_gates(n.right)[0]:
            raise ExpressionError("a gate [...] cannot be a divisor (it divides by zero where it is false)",
                                  text, n.pos)


# ---------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------


def _literal_value(node) -> float | None:
    """The value of a subtree made of numbers and functions only, else None."""
    if isinstance(node, Num):
        return node.value
    if isinstance(node, (Neg, BinOp, Call)):
        values = [_literal_value(c) for c in _children(node)]
        if any(v is None for v in values):
            return None
        with np.errstate(all="ignore"):
            return float(_np_apply(node, [np.float64(v) for v in values]))
    return None


def _uses_variables(node, states: tuple[str, ...]) -> bool:
    return any(isinstance(n, (Name, StateRef)) and (n.name in VARIABLES or n.name in states)
               for n in _walk(node))


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
    _check_names(node, text, param_units, states)
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
            for child in _children(node):
                self.cond(child)


# ---------------------------------------------------------------------------
# Lowering: the tree the VM compiler and the NumPy twin both evaluate
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Var:
    """A variable slot (a variable or a state). In a condition: true where nonzero."""

    index: int


@dataclass(frozen=True)
class _Gated:
    """``body`` where all ``conds`` hold, else exactly 0 (body None means 1).

    A product's gates are pulled out into one of these so that the gated
    factors are never multiplied with a 0 (which would turn inf into nan).
    """

    conds: tuple
    body: object | None


def _resolve(node, values: Mapping[str, float], states: tuple[str, ...]):
    """Replace names by variable slots or parameter ``values``, and gates by _Gated."""
    slots = {name: i for i, name in enumerate((*VARIABLES, *states))}

    def res(n):
        if isinstance(n, Num):
            return n
        if isinstance(n, (Name, StateRef)):
            return _Var(slots[n.name]) if n.name in slots else Num(values[n.name])
        if isinstance(n, Gate):
            return _Gated((res(n.cond),), None)
        if isinstance(n, Neg) or isinstance(n, BinOp) and n.op in ("*", "/"):
            gates, rest = _strip_gates(n)
            if gates:
                return _Gated(tuple(res(g.cond) for g in gates), None if rest is None else res(rest))
        if isinstance(n, Neg):
            return Neg(res(n.operand))
        if isinstance(n, Call):
            return Call(n.func, tuple(res(a) for a in n.args))
        if isinstance(n, Not):
            return Not(res(n.operand))
        return type(n)(n.op, res(n.left), res(n.right))

    return res(node)


def _strip_gates(node) -> tuple[list[Gate], Node | None]:
    """Split the gate factors off a product: node == prod(gates) * rest.

    Replacing a gate by 1 keeps the tree shape otherwise, so ``rest`` rounds
    exactly like the original where the gates hold. ``rest`` None means 1.
    Divisors are left alone (_check_names rejects gates there).
    """
    if isinstance(node, Gate):
        return [node], None
    if isinstance(node, Neg):
        gates, rest = _strip_gates(node.operand)
        return gates, Neg(rest if rest is not None else Num(1.0), node.pos)
    if isinstance(node, BinOp) and node.op == "*":
        gl, rl = _strip_gates(node.left)
        gr, rr = _strip_gates(node.right)
        rest = rl if rr is None else rr if rl is None else BinOp("*", rl, rr, node.pos)
        return gl + gr, rest
    if isinstance(node, BinOp) and node.op == "/":
        gates, rest = _strip_gates(node.left)
        return gates, BinOp("/", rest if rest is not None else Num(1.0), node.right, node.pos)
    return [], node


def _np_apply(node, args: list):
    """Apply the operation of Neg/BinOp/Call/Compare ``node`` to evaluated args (NumPy)."""
    if isinstance(node, Neg):
        return np.negative(args[0])
    if isinstance(node, Call):
        return _NP_FUNCTIONS[node.func](*args)
    if isinstance(node, Compare):
        return _NP_COMPARE[node.op](*args)
    return _NP_BINARY[node.op](*args)


def _fold(node):
    """Constant-fold a resolved tree. Conditions fold to Python bools."""
    if isinstance(node, (Num, _Var)):
        return node
    if isinstance(node, _Gated):
        conds = [_fold(c) for c in node.conds]
        if any(c is False for c in conds):
            return Num(0.0)
        conds = tuple(c for c in conds if c is not True)
        body = _fold(node.body) if node.body is not None else None
        if not conds:
            return body if body is not None else Num(1.0)
        return _Gated(conds, body)
    if isinstance(node, Not):
        operand = _fold(node.operand)
        return (not operand) if isinstance(operand, bool) else Not(operand)
    if isinstance(node, BoolOp):
        left, right = _fold(node.left), _fold(node.right)
        absorbing = node.op == "or"  # True absorbs 'or', False absorbs 'and'
        for a, b in ((left, right), (right, left)):
            if isinstance(a, bool):
                return absorbing if a is absorbing else b
        return BoolOp(node.op, left, right)
    args = [_fold(c) for c in _children(node)]
    if all(isinstance(a, Num) for a in args):
        with np.errstate(all="ignore"):
            value = _np_apply(node, [np.float64(a.value) for a in args])
        return bool(value) if isinstance(node, Compare) else Num(float(value))
    if isinstance(node, Neg):
        return Neg(args[0])
    if isinstance(node, Call):
        return Call(node.func, tuple(args))
    return type(node)(node.op, *args)


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


def _param_values(node: Node, text: str, params: Mapping, states: tuple[str, ...]) -> dict[str, float]:
    """Check the names in ``node``; return the values of the parameters it uses, by name."""
    _check_names(node, text, params, states)
    values = {}
    for name in sorted(free_names(node) - set(states)):
        try:
            values[name] = float(params[name])
        except (TypeError, ValueError):
            values[name] = math.nan
        if not math.isfinite(values[name]):
            raise ExpressionError(f"parameter {name!r} = {params[name]!r} is not a finite number", text)
    return values


def _lower(node: Node, text: str, params: Mapping, states: tuple[str, ...]):
    """The resolved, constant-folded tree the compiler emits, and the parameter values used."""
    values = _param_values(node, text, params, states)
    return _fold(_resolve(node, values, states)), values


def _program(tree, text: str, values: dict[str, float], states: tuple[str, ...]) -> Program:
    emitter = _Emitter()
    emitter.value(tree)
    if emitter.max_depth > STACK_SIZE:
        raise ExpressionError(
            f"expression is nested too deeply for the VM (needs {emitter.max_depth} stack slots, "
            f"at most {STACK_SIZE})", text)
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
    tree, values = _lower(parse(text), text, params, states)
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
    _check_names(node, text, params, states)
    programs, seen = [], set()
    for n in _walk(node):
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
        tree, values = _lower(switch, switch_text, params, states)
        if not isinstance(tree, Num):
            programs.append(_program(tree, switch_text, values, states))
    return programs


def _pow_halves(exponent) -> int | None:
    """k if ``exponent`` is a constant k/2 with |k| <= MAX_POW_HALVES, else None."""
    if isinstance(exponent, Num) and (2 * exponent.value).is_integer():
        k = int(2 * exponent.value)
        return k if abs(k) <= MAX_POW_HALVES else None
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
        self.emit(PUSH_CONST, +1, slot)

    def value(self, node) -> None:
        if isinstance(node, Num):
            self.const(node.value)
        elif isinstance(node, _Var):
            self.emit(PUSH_VAR, +1, node.index)
        elif isinstance(node, Neg):
            self.value(node.operand)
            self.emit(NEG, 0)
        elif isinstance(node, _Gated):
            self.gated(node)
        elif isinstance(node, BinOp) and node.op == "^" and _pow_halves(node.right) is not None:
            self.value(node.left)
            self.emit(POW_HALVES, 0, _pow_halves(node.right))
        elif isinstance(node, Call) and node.func in _UNARY_OPCODES:
            self.value(node.args[0])
            self.emit(_UNARY_OPCODES[node.func], 0)
        else:  # BinOp, max, min
            for child in _children(node):
                self.value(child)
            self.emit(_BINARY_OPCODES[node.func if isinstance(node, Call) else node.op], -1)

    def cond(self, node) -> None:
        if isinstance(node, _Var):
            self.emit(PUSH_VAR, +1, node.index)
        elif isinstance(node, Not):
            self.cond(node.operand)
            self.emit(NOT, 0)
        elif isinstance(node, Compare):
            self.value(node.left)
            self.value(node.right)
            self.emit(_BINARY_OPCODES[node.op], -1)
        else:  # BoolOp
            self.cond(node.left)
            self.cond(node.right)
            self.emit(_BINARY_OPCODES[node.op], -1)

    def gated(self, node: _Gated) -> None:
        # The conditions need no short-circuit among themselves (they cannot
        # produce nan), so they are combined into one with AND.
        self.cond(node.conds[0])
        for cond in node.conds[1:]:
            self.cond(cond)
            self.emit(AND, -1)
        operand_at = len(self.code) + 1
        self.emit(JUMP_IF_FALSE_PUSH0, 0, -1)  # the condition stays below the body
        if node.body is None:
            self.const(1.0)
        else:
            self.value(node.body)
        self.emit(GATE_END, -1)
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
    tree = _resolve(node, _param_values(node, text, params, states), states)
    variables = check_variables(variables, len(VARIABLES) + len(states))
    with np.errstate(all="ignore"):
        value = _np_value(tree, variables)
    return np.array(np.broadcast_to(value, variables.shape[1:]), dtype=np.float64)


def _np_value(node, variables: np.ndarray):
    if isinstance(node, Num):
        return np.float64(node.value)
    if isinstance(node, _Var):
        return variables[node.index]
    if isinstance(node, _Gated):
        mask = functools.reduce(np.logical_and, [_np_cond(c, variables) for c in node.conds])
        body = 1.0 if node.body is None else _np_value(node.body, variables)
        return np.where(mask, body, 0.0)
    return _np_apply(node, [_np_value(c, variables) for c in _children(node)])


def _np_cond(node, variables: np.ndarray):
    if isinstance(node, _Var):
        return variables[node.index] != 0
    if isinstance(node, Not):
        return np.logical_not(_np_cond(node.operand, variables))
    if isinstance(node, BoolOp):
        combine = np.logical_and if node.op == "and" else np.logical_or
        return combine(_np_cond(node.left, variables), _np_cond(node.right, variables))
    return _NP_COMPARE[node.op](_np_value(node.left, variables), _np_value(node.right, variables))

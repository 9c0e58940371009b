"""The term language's syntax: tokenizer, recursive-descent parser, AST, names.

The grammar and semantics are described in :mod:`afmid.terms.expr` (the public facade
of the term language). This module turns text into an AST (:func:`parse`),
back into canonical text (:func:`unparse`), walks trees (:func:`children`,
:func:`walk`, :func:`free_names`) and checks the names a tree uses against
the declared parameters and states (:func:`check_names`). It also defines the
variable slots (:data:`VARIABLES`, SI units in :data:`VARIABLE_UNITS`) and
:class:`ExpressionError`, which every stage of the term language raises.

User text is never given to eval, exec, compile or ast.parse.
"""

from __future__ import annotations

import functools

import difflib
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

from afmid.terms.units import Unit, parse_unit

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


@functools.lru_cache(maxsize=1024)  # nodes are frozen: a tree may be shared; every library build parses its terms
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
        todo.extend((child, depth + 1) for child in children(n))
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


def children(node) -> tuple:
    if isinstance(node, (Neg, Not)):
        return (node.operand,)
    if isinstance(node, (BinOp, Compare, BoolOp)):
        return (node.left, node.right)
    if isinstance(node, Call):
        return node.args
    if isinstance(node, Gate):
        return (node.cond,)
    return ()


def walk(node) -> Iterator:
    """All nodes of a tree, parents before children, left to right."""
    yield node
    for child in children(node):
        yield from walk(child)


def free_names(text_or_node: str | Node) -> set[str]:
    """Names an expression uses that are not VARIABLES: its parameters and states."""
    node = _as_node(text_or_node)
    return {
        n.name for n in walk(node) if isinstance(n, (Name, StateRef)) and n.name not in VARIABLES
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


def check_names(node: Node, text: str, params: Mapping, states: tuple[str, ...]) -> None:
    """Every name must be a variable, state or parameter; condition names must be states.

    Also rejects gates in divisors, the one place where a gate cannot short-circuit.
    """
    _check_declarations(text, params, states)
    for n in walk(node):
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
        if isinstance(n, BinOp) and n.op == "/" and strip_gates(n.right)[0]:
            raise ExpressionError("a gate [...] cannot be a divisor (it divides by zero where it is false)",
                                  text, n.pos)


def strip_gates(node) -> tuple[list[Gate], Node | None]:
    """Split the gate factors off a product: node == prod(gates) * rest.

    Replacing a gate by 1 keeps the tree shape otherwise, so ``rest`` rounds
    exactly like the original where the gates hold. ``rest`` None means 1.
    Divisors are left alone (check_names rejects gates there).
    """
    if isinstance(node, Gate):
        return [node], None
    if isinstance(node, Neg):
        gates, rest = strip_gates(node.operand)
        return gates, Neg(rest if rest is not None else Num(1.0), node.pos)
    if isinstance(node, BinOp) and node.op == "*":
        gl, rl = strip_gates(node.left)
        gr, rr = strip_gates(node.right)
        rest = rl if rr is None else rr if rl is None else BinOp("*", rl, rr, node.pos)
        return gl + gr, rest
    if isinstance(node, BinOp) and node.op == "/":
        gates, rest = strip_gates(node.left)
        return gates, BinOp("/", rest if rest is not None else Num(1.0), node.right, node.pos)
    return [], node

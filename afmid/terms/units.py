"""A tiny SI dimension system for checking the units of force-library terms.

A :class:`Unit` is a vector of exponents over the base units kg, m, s, A, K
(fractional exponents allowed, e.g. a Hertz coefficient in N/m^1.5). There are
no scale factors: every quantity in afmid is stored in coherent SI units, so
only dimensions need checking.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache

BASE_SYMBOLS = ("kg", "m", "s", "A", "K")

# Exponents are snapped to the nearest fraction with a small denominator so that
# e.g. (m^(1/3))^3 equals m exactly despite float round-off (and hashes equally).
_MAX_DENOMINATOR = 1000


@lru_cache(maxsize=4096)  # a pure function of one float, called for every exponent of every Unit made
def _clean(x: float) -> float:
    # "+ 0.0" turns -0.0 into 0.0.
    return float(Fraction(float(x)).limit_denominator(_MAX_DENOMINATOR)) + 0.0


@dataclass(frozen=True)
class Unit:
    """Immutable SI dimensions: ``dims`` are the exponents of (kg, m, s, A, K)."""

    dims: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.dims) != len(BASE_SYMBOLS):
            raise ValueError(f"a Unit needs {len(BASE_SYMBOLS)} exponents, got {self.dims!r}")
        object.__setattr__(self, "dims", tuple(_clean(d) for d in self.dims))

    def __mul__(self, other: Unit) -> Unit:
        return Unit(tuple(a + b for a, b in zip(self.dims, other.dims)))

    def __truediv__(self, other: Unit) -> Unit:
        return Unit(tuple(a - b for a, b in zip(self.dims, other.dims)))

    def __pow__(self, exponent: float) -> Unit:
        return Unit(tuple(a * float(exponent) for a in self.dims))

    @property
    def is_dimensionless(self) -> bool:
        return not any(self.dims)

    def __str__(self) -> str:
        return _format(self.dims)

    def __repr__(self) -> str:
        return f"Unit({str(self)!r})"


DIMENSIONLESS = Unit((0, 0, 0, 0, 0))

# Every symbol parse_unit accepts, in base-unit exponents (kg, m, s, A, K).
SYMBOLS: dict[str, Unit] = {
    "kg": Unit((1, 0, 0, 0, 0)),
    "m": Unit((0, 1, 0, 0, 0)),
    "s": Unit((0, 0, 1, 0, 0)),
    "A": Unit((0, 0, 0, 1, 0)),
    "K": Unit((0, 0, 0, 0, 1)),
    "N": Unit((1, 1, -2, 0, 0)),
    "Pa": Unit((1, -1, -2, 0, 0)),
    "J": Unit((1, 2, -2, 0, 0)),
    "W": Unit((1, 2, -3, 0, 0)),
    "V": Unit((1, 2, -3, -1, 0)),
    "C": Unit((0, 0, 1, 1, 0)),
    "F": Unit((-1, -2, 4, 2, 0)),
    "Hz": Unit((0, 0, -1, 0, 0)),
    "rad": DIMENSIONLESS,
}

# Derived units tried as a leading factor when the kg exponent is 1, in order of
# preference for ties (so a spring constant prints as N/m, not J/m^2).
_DERIVED = ("N", "Pa", "J", "W", "V")


def _fmt_exponent(e: float) -> str:
    return str(int(e)) if e == int(e) else f"{e:.9g}"


def _factor(symbol: str, e: float) -> str:
    return symbol if e == 1 else f"{symbol}^{_fmt_exponent(e)}"


def _render(lead: str | None, dims: tuple[float, ...]) -> tuple[str, int]:
    """Text for ``lead * base-unit dims`` and its number of factors."""
    num = [lead] if lead else []
    den = []
    for symbol, e in zip(BASE_SYMBOLS, dims):
        if e > 0:
            num.append(_factor(symbol, e))
        elif e < 0:
            den.append((symbol, -e))
    n_factors = len(num) + len(den)
    if not num:  # nothing to divide: write negative exponents, e.g. "m^-2"
        return "*".join(_factor(s, -e) for s, e in den), n_factors
    text = "*".join(num)
    if len(den) == 1:
        text += "/" + _factor(*den[0])
    elif den:
        text += "/(" + "*".join(_factor(s, e) for s, e in den) + ")"
    return text, n_factors


def _format(dims: tuple[float, ...]) -> str:
    """Canonical readable text: the simplest of base units and derived-unit forms.

    When the kg exponent is 1 the unit is also written as N, Pa, J, W or V times
    the remaining base units; the candidate with the fewest factors wins, ties
    going to derived units in ``_DERIVED`` order. So a force is "N", a stiffness
    "N/m", a Hertz coefficient "N/m^1.5", a Hamaker-type coefficient "N*m^2", an
    energy "J", a viscosity "Pa*s" and a damping coefficient "kg/s".
    """
    if not any(dims):
        return "1"
    text, n_factors = _render(None, dims)
    best = (n_factors, len(_DERIVED), text)  # (factors, tie-break rank, text)
    if dims[0] == 1:
        for rank, symbol in enumerate(_DERIVED):
            rest = tuple(a - b for a, b in zip(dims, SYMBOLS[symbol].dims))
            text, n_factors = _render(symbol, rest)
            best = min(best, (n_factors, rank, text))
    return best[2]


_TOKEN = re.compile(r"\s*(?:(?P<sym>[A-Za-zµμ]+)|(?P<num>[+-]?(?:\d+\.?\d*|\.\d+))|(?P<op>\*\*|[*/^()]))")


@lru_cache(maxsize=1024)  # Units are immutable; the same few strings are parsed for every library built
def parse_unit(text: str) -> Unit:
    """Parse a unit string such as ``"N/m"``, ``"Pa*s"``, ``"Pa s"``, ``"m^-1"``, ``"m**-2"``.

    Factors are symbols from :data:`SYMBOLS` or ``1``, optionally raised to a
    signed number with ``^`` or ``**``; they are joined by ``*``, ``/`` or
    whitespace, and may be grouped in parentheses (so ``str(unit)`` round-trips).
    ``""`` and ``"1"`` are dimensionless. Raises ValueError on unknown symbols.
    """
    tokens = _tokenize_unit(text)
    parser = _UnitParser(text, tokens)
    unit, _ = parser.product()
    if parser.i != len(tokens):
        parser.fail(f"unexpected {tokens[parser.i][1]!r}")
    return unit


#: SI prefixes a symbol may carry in :func:`parse_scaled_unit` (``u`` for micro where µ cannot be typed).
SI_PREFIXES = {"a": 1e-18, "f": 1e-15, "p": 1e-12, "n": 1e-9, "u": 1e-6, "µ": 1e-6, "μ": 1e-6, "m": 1e-3,
               "c": 1e-2, "k": 1e3, "M": 1e6, "G": 1e9, "T": 1e12}


def parse_scaled_unit(text: str, extra_symbols: dict[str, Unit] | None = None) -> tuple[float, Unit]:
    """(factor to SI, dimensions) of a unit written with SI prefixes: ``"MHz"`` -> (1e6, s^-1), ``"kS/s"`` with
    ``extra_symbols={"S": DIMENSIONLESS}`` -> (1e3, s^-1), ``"ms"`` -> (1e-3, s), ``"s^-1"`` -> (1, s^-1).

    The grammar is :func:`parse_unit`'s; a symbol is first looked up whole (``Pa``, ``kg``, ``mm`` is not one),
    then as one prefix of :data:`SI_PREFIXES` before a symbol (``MHz``, ``mm``, ``kSa``). ``extra_symbols``
    adds symbols for one context (counts such as samples). Raises ValueError on anything else.
    """
    tokens = _tokenize_unit(text)
    parser = _UnitParser(text, tokens, {**SYMBOLS, **(extra_symbols or {})}, prefixes=True)
    unit, factor = parser.product()
    if parser.i != len(tokens):
        parser.fail(f"unexpected {tokens[parser.i][1]!r}")
    return factor, unit


def as_unit(unit: Unit | str) -> Unit:
    """``unit`` itself if it is a Unit, else ``parse_unit(unit)``."""
    return unit if isinstance(unit, Unit) else parse_unit(unit)


def _tokenize_unit(text: str) -> list[tuple[str, str]]:
    tokens = []
    pos = 0
    stripped_end = len(text.rstrip())
    while pos < stripped_end:
        m = _TOKEN.match(text, pos)
        if not m:
            raise ValueError(f"invalid character {text[pos:].strip()[0]!r} in unit {text!r}")
        kind = m.lastgroup
        tokens.append((kind, m.group(kind)))
        pos = m.end()
    return tokens


class _UnitParser:
    """Recursive descent over: product := power (('*' | '/' | space) power)*."""

    def __init__(self, text: str, tokens: list[tuple[str, str]], symbols: dict[str, Unit] | None = None,
                 prefixes: bool = False):
        self.text = text
        self.tokens = tokens
        self.i = 0
        self.symbols = SYMBOLS if symbols is None else symbols
        self.prefixes = prefixes  # SI prefixes allowed (a scale factor is tracked beside the dimensions)

    def fail(self, reason: str):
        raise ValueError(f"{reason} in unit {self.text!r}")

    def peek(self) -> tuple[str, str] | None:
        return self.tokens[self.i] if self.i < len(self.tokens) else None

    def product(self) -> tuple[Unit, float]:
        unit, scale = DIMENSIONLESS, 1.0  # an empty product ("" or "()") is dimensionless
        pending = None  # the '*' or '/' just read, waiting for its right-hand factor
        first = True
        while (tok := self.peek()) is not None and tok != ("op", ")"):
            if tok in (("op", "*"), ("op", "/")):
                if pending or first:
                    self.fail(f"missing factor before {tok[1]!r}")
                pending = tok[1]
                self.i += 1
                continue
            factor, factor_scale = self.power()
            # '/' divides by the next factor only: "N/m s" is N*s/m.
            unit = unit / factor if pending == "/" else unit * factor
            scale = scale / factor_scale if pending == "/" else scale * factor_scale
            pending = None
            first = False
        if pending:
            self.fail(f"missing factor after {pending!r}")
        return unit, scale

    def symbol(self, value: str) -> tuple[Unit, float]:
        if value in self.symbols:
            return self.symbols[value], 1.0
        if self.prefixes and len(value) > 1 and value[0] in SI_PREFIXES and value[1:] in self.symbols:
            return self.symbols[value[1:]], SI_PREFIXES[value[0]]
        allowed = ", ".join(self.symbols)
        prefixed = " (with an SI prefix)" if self.prefixes else ""
        raise ValueError(f"unknown unit symbol {value!r} in {self.text!r}; allowed: {allowed}, 1{prefixed}")

    def power(self) -> tuple[Unit, float]:
        kind, value = self.tokens[self.i]
        self.i += 1
        scale = 1.0
        if kind == "sym":
            base, scale = self.symbol(value)
        elif kind == "num":
            if float(value) != 1:
                self.fail(f"unexpected number {value!r} (only 1 may stand alone)")
            base = DIMENSIONLESS
        elif value == "(":
            base, scale = self.product()
            if self.peek() != ("op", ")"):
                self.fail("missing ')'")
            self.i += 1
        else:
            self.fail(f"unexpected {value!r}")
        if self.peek() in (("op", "^"), ("op", "**")):
            self.i += 1
            tok = self.peek()
            if tok is None or tok[0] != "num":
                self.fail("expected a number after '^'")
            self.i += 1
            return base ** float(tok[1]), scale ** float(tok[1])
        return base, scale

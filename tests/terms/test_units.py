"""Tests for the SI dimension system in afmid.terms.units."""

import re

import pytest

from afmid.terms.units import DIMENSIONLESS, SYMBOLS, Unit, as_unit, parse_scaled_unit, parse_unit

pytestmark = pytest.mark.numerics  # floating-point results compared (blas_sensitive ones: make test-kernels runs them again)

KG, M, S, A = (parse_unit(s) for s in ("kg", "m", "s", "A"))


@pytest.mark.parametrize(
    "text, dims",
    [
        ("N", (1, 1, -2, 0, 0)),
        ("N/m", (1, 0, -2, 0, 0)),
        ("Pa*s", (1, -1, -1, 0, 0)),
        ("Pa s", (1, -1, -1, 0, 0)),
        ("kg/s", (1, 0, -1, 0, 0)),
        ("m^-1", (0, -1, 0, 0, 0)),
        ("m**-2", (0, -2, 0, 0, 0)),
        ("J", (1, 2, -2, 0, 0)),
        ("V", (1, 2, -3, -1, 0)),
        ("F/m", (-1, -3, 4, 2, 0)),
        ("N/m^1.5", (1, -0.5, -2, 0, 0)),
        ("W", (1, 2, -3, 0, 0)),
        ("C", (0, 0, 1, 1, 0)),
        ("Hz", (0, 0, -1, 0, 0)),
        ("K", (0, 0, 0, 0, 1)),
        ("A", (0, 0, 0, 1, 0)),
        ("s", (0, 0, 1, 0, 0)),
        ("m", (0, 1, 0, 0, 0)),
        ("1", (0, 0, 0, 0, 0)),
        ("", (0, 0, 0, 0, 0)),
        ("rad", (0, 0, 0, 0, 0)),
        ("kg/(m*s)", (1, -1, -1, 0, 0)),
        ("N/m s", (1, 0, -1, 0, 0)),  # '/' divides by the next factor only
        ("  N * m ^ 2 ", (1, 3, -2, 0, 0)),
    ],
)
def test_parse_unit(text, dims):
    assert parse_unit(text) == Unit(dims)


@pytest.mark.parametrize(
    "text, canonical",
    [
        ("N", "N"),
        ("kg*m/s^2", "N"),
        ("N/m", "N/m"),
        ("kg/s^2", "N/m"),
        ("N*m^2", "N*m^2"),
        ("N/m^1.5", "N/m^1.5"),
        ("N*s/m", "kg/s"),
        ("kg/s", "kg/s"),
        ("Pa*s", "Pa*s"),
        ("N/m^2", "Pa"),
        ("N*m", "J"),
        ("J/s", "W"),
        ("m/s", "m/s"),
        ("m^1.5", "m^1.5"),
        ("m^1.5/s", "m^1.5/s"),
        ("m^-2", "m^-2"),
        ("1/s", "s^-1"),
        ("1", "1"),
        ("m/m", "1"),
    ],
)
def test_str_is_canonical_and_round_trips(text, canonical):
    unit = parse_unit(text)
    assert str(unit) == canonical
    assert parse_unit(str(unit)) == unit


def test_round_trip_of_every_symbol_and_some_products():
    for a in SYMBOLS.values():
        for b in SYMBOLS.values():
            for unit in (a * b, a / b, a**-1.5):
                assert parse_unit(str(unit)) == unit, str(unit)


def test_arithmetic():
    newton = KG * M / S**2
    assert newton == parse_unit("N")
    assert (newton / M) ** 0.5 * M**0.5 == parse_unit("N") ** 0.5
    assert (M ** (1 / 3)) ** 3 == M  # exponents are snapped, so no round-off creeps in
    assert hash((M ** (1 / 3)) ** 3) == hash(M)
    assert (M / M).is_dimensionless and DIMENSIONLESS.is_dimensionless
    assert not M.is_dimensionless
    assert M**0 == DIMENSIONLESS


def test_unit_is_immutable_and_hashable():
    unit = parse_unit("N/m")
    with pytest.raises(AttributeError):
        unit.dims = (0, 0, 0, 0, 0)
    assert {unit: 1}[parse_unit("kg/s^2")] == 1
    assert repr(unit) == "Unit('N/m')"


def test_as_unit():
    assert as_unit("N") == parse_unit("N")
    unit = parse_unit("m")
    assert as_unit(unit) is unit


@pytest.mark.parametrize(
    "text, message",
    [
        ("Nm", "unknown unit symbol 'Nm'"),
        ("nm", "unknown unit symbol 'nm'"),
        ("N/", "missing factor after '/'"),
        ("*m", "missing factor before '*'"),
        ("m^", "expected a number after '^'"),
        ("2m", "unexpected number '2'"),
        ("(N", "missing ')'"),
        ("N)", "unexpected ')'"),
        ("m$", "invalid character '$'"),
    ],
)
def test_parse_errors(text, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_unit(text)


def test_wrong_number_of_exponents():
    with pytest.raises(ValueError, match="5 exponents"):
        Unit((1, 2))


@pytest.mark.parametrize("text, factor, dims", [
    ("MHz", 1e6, "s^-1"), ("kHz", 1e3, "s^-1"), ("s^-1", 1.0, "s^-1"), ("ms", 1e-3, "s"), ("us", 1e-6, "s"),
    ("µs", 1e-6, "s"), ("nm", 1e-9, "m"), ("mm", 1e-3, "m"), ("kPa s", 1e3, "Pa*s"), ("nN/nm", 1.0, "N/m"),
    ("Pa", 1.0, "Pa"), ("kg", 1.0, "kg"), ("MS/s", 1e6, "s^-1"), ("kSa/s", 1e3, "s^-1"), ("(ms)^-2", 1e6, "s^-2"),
])
def test_parse_scaled_unit(text, factor, dims):
    """SI prefixes on any symbol (a whole symbol first: Pa, kg); S and Sa as counts of samples where given."""
    counts = {"S": DIMENSIONLESS, "Sa": DIMENSIONLESS}
    got_factor, unit = parse_scaled_unit(text, counts)
    assert got_factor == pytest.approx(factor, rel=1e-12) and unit == parse_unit(dims)


@pytest.mark.parametrize("text", ["MS/s", "XHz", "Mfoo", "M", "kHz/"])
def test_parse_scaled_unit_errors(text):
    with pytest.raises(ValueError):
        parse_scaled_unit(text)  # S is not a symbol without the counts; X is no prefix


def test_parse_unit_takes_no_prefix():
    with pytest.raises(ValueError, match="unknown unit symbol 'MHz'"):
        parse_unit("MHz")  # afmid's unit checks are dimensions of SI values: a prefix would be a scale

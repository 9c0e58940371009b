"""Human-unit formatting (afmid.quantity_text): the PDG rounding rule, display units, labels, no -0."""

import math
import re

import numpy as np
import pytest

from afmid.quantity_text import (display_unit, format_delta_bic, format_interval, format_measurement,
                                        format_value, pdg_error_digits)


@pytest.mark.parametrize("value, sigma, unit, expected", [
    # The PDG's own examples (Review of Particle Physics, introduction, "Rounding"), in a unit without a factor.
    (0.827, 0.119, "N/m", "0.83 ± 0.12 N/m (1σ)"),
    (0.827, 0.367, "N/m", "0.8 ± 0.4 N/m (1σ)"),
    (0.827, 0.0957, "N/m", "0.83 ± 0.10 N/m (1σ)"),
    # The example and the display units.
    (3.032e8, 2.6e6, "Pa", "303.2 ± 2.6 MPa (1σ)"),
    (41.13, 0.6, "Pa*s", "41.1 ± 0.6 Pa s (1σ)"),
    (1.0e-9, 0.1e-9, "N", "1.00 ± 0.10 nN (1σ)"),
    (1.65e-10, 4e-12, "m", "0.165 ± 0.004 nm (1σ)"),
    (6.7e-20, 1.2e-21, "J", "67.0 ± 1.2 zJ (1σ)"),
    # No display unit: SI in scientific notation with one exponent.
    (1.523e-7, 1.3e-8, "kg/s", "(1.52 ± 0.13)e-7 kg/s (1σ)"),
])
def test_measurement_follows_the_pdg_rule_in_display_units(value, sigma, unit, expected):
    assert format_measurement(value, sigma, unit) == expected


def test_the_label_says_what_the_error_is():
    assert format_measurement(3e8, 6e6, "Pa", kind="95 %").endswith("(95 %)")
    assert format_interval(2.97e8, 3.09e8, "Pa") == "[297.0, 309.0] MPa (95 %)"
    assert format_interval(1.2e-7, 1.9e-7, "kg/s") == "[1.20e-7, 1.90e-7] kg/s (95 %)"


def test_missing_or_zero_error_is_said_in_words():
    for sigma in (math.nan, math.inf, 0.0, -1.0):
        text = format_measurement(1e-19, sigma, "J")
        assert text == "100.0 zJ (no error estimate)"
        assert "±" not in text and "nan" not in text


def test_no_negative_zero():
    assert format_measurement(-1e-13, 3e-10, "m") == "0.00 ± 0.30 nm (1σ)"
    assert format_value(-0.0, "Pa*s") == "0 Pa s"
    assert format_delta_bic(-1e-9) == "0"
    assert not re.search(r"(^|[^\d.])-0(\.0*)?( |$)", format_interval(-1e-14, 2e-10, "m"))


def test_delta_bic_reads_as_a_number():
    assert format_delta_bic(7.39e-13) == "0"
    assert format_delta_bic(-9725.3) == "-9725"
    assert format_delta_bic(-3.44) == "-3.4"
    assert format_delta_bic(12.6) == "13"


def test_values_without_error_and_display_units():
    assert format_value(41.1, "Pa*s") == "41.1 Pa s"
    assert format_value(1.65e-10, "m") == "0.165 nm"
    assert format_value(1.5e9, "Pa") == "1500 MPa"
    assert format_value(999.96e6, "Pa") == "1000 MPa"  # rounding that adds a digit
    assert format_value(3e-7, "kg/s") == "3.00e-7 kg/s"
    assert display_unit("Pa*m^0.5") == (1.0, "Pa m^0.5")


def test_pdg_digits():
    assert [pdg_error_digits(s) for s in (0.100, 0.354, 0.355, 0.949, 0.950, 12.0, 4e-9)] == [2, 2, 1, 1, 2, 2, 1]


def test_rounding_never_moves_the_value_by_more_than_half_its_last_digit():
    """Over many random value/error pairs: the printed value is the true one rounded at the error's precision,
    and the printed error is within the rule's rounding of the true error (a property, not one example)."""
    rng = np.random.default_rng(7)
    for _ in range(2000):
        sigma = 10.0 ** rng.uniform(-3, 4)
        value = rng.normal(0, 1) * sigma * 10.0 ** rng.uniform(0, 3)
        text = format_measurement(value, sigma, "N/m")
        match = re.fullmatch(r"(-?[\d.]+) ± ([\d.]+) N/m \(1σ\)", text)
        if match is None:  # outside the plain range: scientific notation
            match = re.fullmatch(r"\((-?[\d.]+) ± ([\d.]+)\)e(-?\d+) N/m \(1σ\)", text)
            scale = 10.0 ** int(match.group(3))
        else:
            scale = 1.0
        shown_value, shown_sigma = float(match.group(1)) * scale, float(match.group(2)) * scale
        # The rule keeps at least the error's leading digit: rounding moves the value by at most half of it, and
        # the error by at most half its own last kept digit: worst with one digit at 0.355 -> 0.4 (12.7 %); two
        # digits: <= 0.5 % of 100; the 950+ round-up: <= 5.3 %.
        leading_digit = 10.0 ** math.floor(math.log10(sigma))
        assert abs(shown_value - value) <= 0.5 * leading_digit * (1 + 1e-9)
        assert abs(shown_sigma - sigma) <= 0.127 * sigma * (1 + 1e-9) + 1e-12


def _catalog_parameters():
    from afmid.physics.effects import EFFECTS

    return [(e.name, p) for e in EFFECTS for p in e.parameters]


@pytest.mark.parametrize("effect, parameter", _catalog_parameters(), ids=lambda x: getattr(x, "name", x))
def test_every_catalog_parameter_prints_in_its_declared_unit(effect, parameter):
    """Issue 33: shape parameters were printed as lengths ("relaxation_time = 104000 nm"). Every catalog parameter
    goes through every formatter of the report and the diagnosis (the candidate's shape words of the evidence and
    of 'Effects tried', a read-out cell, a plain value) and comes out in the display unit of its declared unit."""
    from afmid.diagnosis.candidate_shapes import shape_words
    from afmid.physics.effects import parameter_unit
    from afmid.report.page import fitted_text, quantity_cell

    assert parameter_unit(parameter.name, effect) == parameter.unit
    value = parameter.default if parameter.default != 0 else max(parameter.low, 1e-3 * parameter.high)
    factor, shown = display_unit(parameter.unit)
    expected = format_value(value, parameter.unit)
    assert expected.endswith(shown) and math.isfinite(value * factor)
    texts = {
        "shape words": shape_words(effect, {parameter.name: value})[0],
        "effects tried": fitted_text({"effect": effect, "parameters": {}, "nonlinear": {parameter.name: value}}),
        "effects tried, read-out": fitted_text({"effect": effect, "nonlinear": {},
                                                "parameters": {parameter.name: {"value": value, "unit": parameter.unit}}}),
    }
    for where, text in texts.items():
        assert text == f"{parameter.name} = {expected}", where
    cell = quantity_cell({"value": value, "error": abs(value) / 10, "unit": parameter.unit})
    assert re.search(rf"\d {re.escape(shown)} \(1σ\)$" if shown else r"\d\)? \(1σ\)$", cell), cell
    if parameter.unit != "m":  # a length's display unit on anything else is the bug this test guards
        assert not any(re.search(r"\bnm\b", t) for t in [*texts.values(), cell]), (texts, cell)


def test_csv_column_names_put_the_unit_at_the_end_by_one_rule():
    """afmid's CSVs (export, the batch summary) name a column ``name_unit``: '/' -> '_per_', '^' dropped, '*' and
    spaces joined, an exponent's '.' -> 'p', no suffix for a dimensionless or text column (docs/file-formats.md)."""
    from afmid.quantity_text import column_name

    cases = {("force", "N"): "force_N", ("E_star", "Pa"): "E_star_Pa", ("E_star_sigma", "Pa"): "E_star_sigma_Pa",
             ("surface_energy", "J/m^2"): "surface_energy_J_per_m2", ("acceleration", "m/s^2"): "acceleration_m_per_s2",
             ("viscosity", "Pa*s"): "viscosity_Pas", ("viscosity", "Pa s"): "viscosity_Pas",
             ("k", "Pa*m^0.5"): "k_Pam0p5", ("cv_error", "1"): "cv_error", ("name", None): "name",
             ("charge", "C^2/m^4"): "charge_C2_per_m4"}
    for (name, unit), expected in cases.items():
        assert column_name(name, unit) == expected, (name, unit)
    assert all("." not in column_name(n, u) and " " not in column_name(n, u) for n, u in cases)


@pytest.mark.parametrize("value, unit, digits, expected", [
    (0.04317, "", 3, "0.0432"),
    (57.81, "eV", 3, "57.8 eV"),
    (1.2345e-5, "nN", 3, "1.23e-05 nN"),
    (-0.0004, "", 1, "-0.0004"),
    (-0.0, "", 3, "0"),             # a rounded zero has no sign
    (-1e-30, "eV", 3, "-1e-30 eV"),  # tiny but not zero at 3 digits: the sign stays
    (7, "", 3, "7"),
    (None, "eV", 3, "–"),
    (math.nan, "", 3, "–"),
    (np.float64(math.inf), "nN", 3, "–"),
])
def test_format_number_writes_a_scaled_number_as_the_report_tables_do(value, unit, digits, expected):
    """The report's tables write numbers the caller has already scaled (nN, eV) with ``%g`` digits and a dash for
    what is missing: one formatter for the page and the loop's evidence."""
    from afmid.quantity_text import format_number

    assert format_number(value, unit, digits) == expected

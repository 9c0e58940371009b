"""Numbers as a scientist reads them: human units, honest digits, labelled intervals.

One place for how afmid prints a physical quantity in logs, the terminal and the reports (files stay SI):

- every SI unit has one display unit (the project's convention: nm, nN, MPa; zJ for the tiny energies of a
  Hamaker constant, mJ/m^2 for surface energies, µs, kHz), so a column of values or two runs compare at a glance;
  a unit without a display unit (kg/s, Pa*m^0.5, ...) stays SI in scientific notation, ``(1.52 ± 0.13)e-7 kg/s``;
- a value with an error is rounded by the Particle Data Group's rule (Review of Particle Physics, "Rounding"):
  the error keeps two significant digits when its three leading digits are 100-354, one when they are 355-949,
  and two (rounded up to 1000) above; the value keeps the same decimal place. ``3.032e8 ± 2.6e6 Pa`` prints
  ``303.2 ± 2.6 MPa (1σ)``;
- every ± and interval carries its meaning: ``(1σ)`` or ``(95 %)``;
- no ``-0``, no ``7.39e-13`` for a criterion difference that is zero;
- a declared range is written as declared, in SI (:func:`range_words`: ``[0, 1e5] Pa s``).

A foundation module (docs/architecture.md, Layers): the fit, the diagnosis, the catalog and the reports all
write with it, so it imports nothing of afmid.
"""

from __future__ import annotations

import math

#: SI unit (as afmid writes it) -> (factor from SI to the display unit, display unit as printed).
DISPLAY_UNITS: dict[str, tuple[float, str]] = {
    "m": (1e9, "nm"),
    "N": (1e9, "nN"),
    "Pa": (1e-6, "MPa"),
    "Pa*s": (1.0, "Pa s"),
    "Pa s": (1.0, "Pa s"),
    "J": (1e21, "zJ"),
    "J/m^2": (1e3, "mJ/m^2"),
    "N/m": (1.0, "N/m"),
    "V": (1.0, "V"),
    "rad": (1.0, "rad"),
    "s": (1e6, "µs"),
    "Hz": (1e-3, "kHz"),
    "W": (1e12, "pW"),
    "1": (1.0, ""),
    "": (1.0, ""),
}
#: A displayed magnitude outside [1e-3, 1e6) is written in scientific notation.
_PLAIN_RANGE = (1e-3, 1e6)
SIGMA_LABEL = "1σ"
CI95_LABEL = "95 %"


def display_unit(unit: str) -> tuple[float, str]:
    """(factor, display unit) for an SI unit; (1, the unit with ``*`` as a space) when it has no display unit."""
    if unit in DISPLAY_UNITS:
        return DISPLAY_UNITS[unit]
    return 1.0, unit.replace("*", " ")


def _has_display_unit(unit: str) -> bool:
    return unit in DISPLAY_UNITS


def _no_negative_zero(text: str) -> str:
    """``-0``, ``-0.00`` -> ``0``, ``0.00``: a rounded zero has no sign."""
    if text.startswith("-") and set(text[1:]) <= set("0."):
        return text[1:]
    return text


def _fixed(x: float, decimals: int) -> str:
    return _no_negative_zero(f"{x:.{max(decimals, 0)}f}")


def _decimals_for(x: float, significant: int) -> int:
    """Decimal places that keep ``significant`` digits of ``x`` (0 for x = 0)."""
    if x == 0 or not math.isfinite(x):
        return 0
    return significant - 1 - math.floor(math.log10(abs(x)))


def _plain(x: float, significant: int) -> str:
    """``x`` with ``significant`` digits, plain when its magnitude is in the plain range, else ``1.5e-7``."""
    if x == 0:
        return "0"
    if not math.isfinite(x):
        return str(x)
    if _PLAIN_RANGE[0] <= abs(x) < _PLAIN_RANGE[1]:
        rounded = float(f"{x:.{significant}g}")  # 999.96 -> 1000 moves the digit count: recount after rounding
        return _fixed(rounded, _decimals_for(rounded, significant))
    mantissa, exponent = f"{x:.{significant - 1}e}".split("e")
    return f"{_no_negative_zero(mantissa)}e{int(exponent)}"


def _with_unit(text: str, shown_unit: str) -> str:
    return f"{text} {shown_unit}" if shown_unit else text


def format_value(value: float, unit: str, significant: int = 3) -> str:
    """A value without an error in its display unit: ``format_value(4.11e1, "Pa*s")`` -> ``41.1 Pa s``."""
    factor, shown = display_unit(unit)
    if not _has_display_unit(unit):
        return _with_unit(_plain(value, significant), shown)
    return _with_unit(_plain(value * factor, significant), shown)


def format_number(value: float | None, unit: str = "", digits: int = 3) -> str:
    """A number already in the unit it is shown in, with ``digits`` significant digits (``%g``), for the report's
    tables and sentences: ``format_number(0.04317)`` -> ``0.0432``, ``format_number(57.81, "eV")`` -> ``57.8 eV``;
    ``–`` for a missing or non-finite value, no sign on a rounded zero. Unlike :func:`format_value` it converts
    nothing: the caller has already scaled to ``unit``."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    text = f"{value:.{digits}g}"
    text = text.lstrip("-") if float(text) == 0 else text  # a rounded zero has no sign
    return _with_unit(text, unit)


def pdg_error_digits(sigma: float) -> int:
    """Significant digits the PDG rule keeps for an error ``sigma`` > 0 (1 or 2)."""
    leading = int(f"{abs(sigma):.2e}".replace(".", "")[:3])  # the three leading digits, 100..999
    return 1 if 355 <= leading <= 949 else 2


def _rounded_pair(value: float, sigma: float) -> tuple[str, str]:
    """Value and error rounded by the PDG rule, as plain decimal strings."""
    digits = pdg_error_digits(sigma)
    leading = int(f"{abs(sigma):.2e}".replace(".", "")[:3])
    if leading >= 950:  # 0.0957 -> 0.10: two digits of the rounded-up error
        sigma = float(f"{sigma:.0e}")
        digits = 2
    decimals = _decimals_for(sigma, digits)
    sigma_text = _fixed(round(sigma, decimals), decimals)
    value_text = _fixed(round(value, decimals), decimals)
    return value_text, sigma_text


def format_measurement(value: float, sigma: float, unit: str, kind: str = SIGMA_LABEL) -> str:
    """``value ± sigma unit (kind)`` in the display unit, PDG-rounded; ``kind`` says what the ± is (1σ, 95 %).

    An error that is not finite or not positive is said in words, never printed as ``± 0`` or ``± nan``.
    """
    if not math.isfinite(value):
        return _with_unit(str(value), display_unit(unit)[1])
    if not (math.isfinite(sigma) and sigma > 0):
        return f"{format_value(value, unit, significant=4)} (no error estimate)"
    factor, shown = display_unit(unit)
    scale = factor if _has_display_unit(unit) else 1.0
    shown_value, shown_sigma = value * scale, sigma * scale
    magnitude = max(abs(shown_value), shown_sigma)
    if _has_display_unit(unit) and _PLAIN_RANGE[0] <= magnitude < _PLAIN_RANGE[1]:
        value_text, sigma_text = _rounded_pair(shown_value, shown_sigma)
        return f"{_with_unit(f'{value_text} ± {sigma_text}', shown)} ({kind})"
    # Scientific notation with one exponent for value and error: (1.52 ± 0.13)e-7 kg/s.
    exponent = math.floor(math.log10(magnitude))
    value_text, sigma_text = _rounded_pair(shown_value / 10.0**exponent, shown_sigma / 10.0**exponent)
    return f"({value_text} ± {sigma_text})e{exponent}" + (f" {shown}" if shown else "") + f" ({kind})"


def format_interval(low: float, high: float, unit: str, kind: str = CI95_LABEL) -> str:
    """``[low, high] unit (kind)`` in the display unit; both ends to the decimal place of a quarter of the width
    (about 1σ of a 95 % interval), so the ends differ in their last digits only when the interval says so."""
    factor, shown = display_unit(unit)
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"[{format_value(low, unit)}, {format_value(high, unit)}] ({kind})"
    scale = factor if _has_display_unit(unit) else 1.0
    lo, hi = low * scale, high * scale
    width = abs(hi - lo) / 4
    magnitude = max(abs(lo), abs(hi))
    if width > 0 and (_PLAIN_RANGE[0] <= magnitude < _PLAIN_RANGE[1]) and _has_display_unit(unit):
        decimals = _decimals_for(width, pdg_error_digits(width))
        text = f"[{_fixed(round(lo, decimals), decimals)}, {_fixed(round(hi, decimals), decimals)}]"
    else:
        text = f"[{_plain(lo, 3)}, {_plain(hi, 3)}]"
    return _with_unit(text, shown) + f" ({kind})"


def format_delta_bic(delta: float) -> str:
    """A BIC difference as a person reads it: ``-9725``, ``-3.4``, ``0`` (|ΔBIC| < 0.05 is zero: rounding of two
    equal fits, not evidence)."""
    if not math.isfinite(delta):
        return str(delta)
    if abs(delta) < 0.05:
        return "0"
    if abs(delta) < 10:
        return _no_negative_zero(f"{delta:.1f}")
    return _no_negative_zero(f"{delta:.0f}")


def short_number(x: float) -> str:
    """A number as a person writes a bound: 0, 1e5, 1e-22, 0.05, 5."""
    if x == 0 or 1e-3 <= abs(x) < 1e4:
        return f"{x:g}"
    mantissa, exponent = f"{x:.3e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


def unit_words(unit: str) -> str:
    """A unit as written in prose: ``Pa*s`` -> ``Pa s``."""
    return unit.replace("*", " ")


def range_words(low: float, high: float, unit: str) -> str:
    """``[0, 1e5] Pa s``: a declared range in SI (bounds in ``unit``), as the registry and `afmid effects` state it."""
    return f"[{short_number(low)}, {short_number(high)}] {unit_words(unit)}"


def unit_suffix(unit: str) -> str:
    """A unit as the end of a CSV column name (afmid's one convention for its CSVs, docs/file-formats.md "Column
    names"): ``/`` -> ``_per_``, ``^`` dropped (the exponent follows its unit), ``*``, ``·`` and spaces dropped
    (the units joined), a decimal point of an exponent -> ``p``; ``'1'`` (dimensionless) and ``''`` -> ``''``.
    'J/m^2' -> 'J_per_m2', 'm/s^2' -> 'm_per_s2', 'Pa*s' -> 'Pas', 'Pa*m^0.5' -> 'Pam0p5'."""
    if unit in ("", "1"):
        return ""
    joined = unit.replace("/", "_per_").replace("^", "").replace("*", "").replace(" ", "").replace("·", "")
    return joined.replace(".", "p")  # no '.' in a column name: a manifest CSV reads dotted columns as config keys


def column_name(name: str, unit: str | None) -> str:
    """``name_unit`` (:func:`unit_suffix`): ``force_N``, ``E_star_sigma_Pa``; the bare name for a dimensionless
    or text column (``unit`` '1', '' or None)."""
    suffix = unit_suffix(unit or "")
    return f"{name}_{suffix}" if suffix else name

"""Plausibility of the fit's physical read-outs (E*, Hamaker constant, viscosity, ...).

Every quantity an effect reports has a declared plausible range in the
registry (:func:`afmid.physics.effects.quantity_range`: the parameter's valid range, or
the quantity's own ``low``/``high``); the range also fixes its sign. After a
fit each read-out is judged against it, and a value afmid cannot stand behind
is flagged, never written or shown as a plain result:

- **outside the range** (a negative viscosity, E* = 1e13 Pa from a wrong
  detector scale): implausible. The reason says whether the sign is wrong, and
  where the 95 % interval lies (entirely outside too, or reaching into the
  range: then the value is compatible with the range only at the edge of its
  noise, still not a result to report as is);
- **exactly 0 where the range excludes 0**: the term behind it was not
  selected, so the data did not identify the quantity (E* of a fit without
  contact): implausible, "not identified";
- **inside the range but its whole 95 % interval outside** (a skewed
  bootstrap): implausible;
- **inside the range with an interval straddling a bound**: fine (a
  viscosity of 3 +- 5 Pa s is a small viscosity, not a negative one);
- **not finite**: NaN means the read-out could not be computed (the fitted term
  has the sign opposite to the effect's, or a value it needs, e.g. the tip
  radius, is missing), inf is outside every range: implausible;
- **unconstrained**: a non-zero value whose bootstrap error is more than
  :data:`UNCONSTRAINED_RATIO` times its size, or infinite: the data do not
  determine it (a number with no significant digit), implausible. A value of
  0 with an error is a term selected in some bootstrap samples only: its error
  is an upper limit and stays fine;
- no error (no bootstrap, NaN) is no verdict on its own.

Where the verdicts go (:func:`afmid.runfile.write_run`): attributes ``plausible``
(bool) and ``plausibility`` (the reason, one sentence, empty when plausible)
on ``/model/parameters/NAME``, ``n_implausible`` and ``implausible`` (the
reasons) on ``/diagnostics``, one ``afmid: warning:`` line per violation; the
report marks the value, and the batch summary gives the item the status
``suspect``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

from afmid.physics.effect_tags import Character
from afmid.physics.effects import EFFECTS, quantity_range
from afmid.quantity_text import range_words, short_number, unit_words

log = logging.getLogger("afmid")

#: The words of a not-determined read-out's reason (:func:`describe_not_determined`).
NOT_DETERMINED = " is not determined: "
#: An error this many times larger than |value| means the data do not determine the value.
UNCONSTRAINED_RATIO = 1e3

#: Units shown with an SI prefix (nm, nN, MPa, kPa s); the others in plain scientific notation.
_PREFIXED_UNITS = {"m", "N", "Pa", "Pa*s", "V", "Hz", "s"}
_PREFIXES = {-18: "a", -15: "f", -12: "p", -9: "n", -6: "µ", -3: "m", 0: "", 3: "k", 6: "M", 9: "G", 12: "T"}


@dataclass(frozen=True)
class Verdict:
    """Whether a read-out can be physical; ``reason`` (one sentence) says why not, empty when it can.

    ``finding`` is the reason without the advice on what to check in the run's calibration (for a
    context where the value comes from a trial model, not from the user's settings).
    """

    plausible: bool
    reason: str = ""
    finding: str = ""

    def __post_init__(self):
        if not self.finding:
            object.__setattr__(self, "finding", self.reason)


def display(value: float, unit: str) -> str:
    """A value in the unit a scientist reads (24 kPa s, 3.2 nN, 1.5 GPa, 1e-19 J), 3 significant digits."""
    if not math.isfinite(value):
        return f"{value} {unit_words(unit)}"
    if value == 0:
        return f"0 {unit_words(unit)}"
    if unit in _PREFIXED_UNITS:
        power = 3 * math.floor(math.log10(abs(value)) / 3)
        power = min(max(power, min(_PREFIXES)), max(_PREFIXES))
        mantissa = value / 10.0**power
        if float(f"{abs(mantissa):.3g}") >= 1000 and power + 3 in _PREFIXES:  # 999.97 nN reads 1 µN
            power += 3
            mantissa = value / 10.0**power
        return f"{mantissa:.3g} {_PREFIXES[power]}{unit_words(unit)}"
    return f"{value:.3g} {unit_words(unit)}"


def _declaring_effect(name: str, effect: str | None):
    base = name.split(".")[-1]
    if effect is None and "." in name:
        effect = name.split(".")[0]
    effects = [EFFECTS.get(effect)] if effect and effect in EFFECTS else list(EFFECTS)
    for eff in effects:
        for q in eff.quantities:
            if q.name == base:
                return eff, q
    return None, None


def plausible_range(name: str, effect: str | None = None) -> tuple[float, float, str] | None:
    """(low, high, unit) declared for a reported quantity (``name`` or ``effect.name``), None if undeclared."""
    eff, q = _declaring_effect(name, effect)
    if q is None:
        return None
    low, high = quantity_range(eff, q)
    return low, high, q.unit


def tip_scaled_range(name: str, effect: str | None, tip_radius: float) -> tuple[float, float, str] | None:
    """The declared range of a force that grows with the tip (``Quantity.high_per_radius``), its upper bound
    lowered to what a tip of radius ``tip_radius`` (m) can give; None when the quantity declares no such bound
    or the radius is unknown (the plain :func:`plausible_range` then holds)."""
    eff, q = _declaring_effect(name, effect)
    if q is None or q.high_per_radius is None or not (math.isfinite(tip_radius) and tip_radius > 0):
        return None
    low, high = quantity_range(eff, q)
    return low, min(high, q.high_per_radius * tip_radius), q.unit


def _field(q, key: str) -> float:
    try:
        return float(q.get(key, math.nan))
    except (TypeError, ValueError):
        return math.nan


def judge(name: str, quantity: Mapping | float) -> Verdict:
    """The verdict on one read-out: ``quantity`` is a value (SI) or a mapping with ``value`` and optionally
    ``error``, ``ci_low``, ``ci_high`` (95 % interval), ``unit`` and ``effect`` (as the fit's quantities)."""
    q = quantity if isinstance(quantity, Mapping) else {"value": quantity}
    value, error = _field(q, "value"), _field(q, "error")
    ci_low, ci_high = _field(q, "ci_low"), _field(q, "ci_high")
    declared = plausible_range(name, q.get("effect") or None)
    unit = str(q.get("unit") or (declared[2] if declared else ""))
    label = name.split(".")[-1]
    if q.get("determined", True) is False:  # its term was not selected: no value (afmid.fit.undetermined)
        # An effect that may be absent (0 in its range: a viscosity) is simply not seen: its interval is the
        # result. A quantity the model needs (E* of a contact model: 0 is outside its range) is not identified.
        declared = plausible_range(name, q.get("effect") or None)
        if declared is not None and declared[0] <= 0.0 <= declared[1]:
            return Verdict(True)
        return Verdict(False, describe_not_determined(name, q))
    if math.isnan(value):
        return Verdict(False, f"{label} could not be read out (NaN): the fitted term has the sign opposite to "
                              "the effect's, or the read-out needs a value the run lacks, such as "
                              "cantilever.tip_radius",
                       f"{label} could not be read out (NaN: the fitted term has the sign opposite to the effect's)")
    shown = f"{label} = {display(value, unit)}"
    has_interval = math.isfinite(ci_low) and math.isfinite(ci_high)
    interval = f"[{display(ci_low, unit)}, {display(ci_high, unit)}]" if has_interval else ""
    tip_radius = _field(q, "tip_radius")
    tip_range = tip_scaled_range(name, q.get("effect") or None, tip_radius)
    whole_interval_outside = interval_outside_range(name, q)
    if declared is not None:
        low, high, _ = tip_range or declared
        allowed = range_words(low, high, unit)
        if tip_range is not None:
            allowed += f" for the declared tip radius {display(tip_radius, 'm')}"
        if not (low <= value <= high):
            if value == 0:
                return Verdict(False, f"{shown}: not identified (its term was not selected), while a physical "
                                      f"{label} lies in {allowed}")
            if value < 0 <= low:
                what = f"{shown} has the wrong sign: a physical {label} lies in {allowed}"
                eff, _ = _declaring_effect(name, q.get("effect") or None)
                if eff is not None and eff.character is Character.DISSIPATIVE:  # the sample cannot give energy back
                    hint = ("is the lever's own damping overestimated (cantilever.quality_factor too low), or the "
                            "deflection's sign convention wrong (data.positive)?")
                else:
                    hint = "is the deflection's sign convention right (data.positive)?"
            else:
                what = f"{shown} is outside the plausible range: a physical {label} lies in {allowed}"
                hint = ("are the units and calibration right (data.units, data.invols or data.scale, "
                        "cantilever.spring_constant, cantilever.tip_radius)?")
            if has_interval:
                if whole_interval_outside:
                    what += f", and its 95 % interval {interval} is outside it too"
                else:
                    what += f", and only its 95 % interval {interval} reaches into it"
            return Verdict(False, f"{what}; {hint}", what)
        if whole_interval_outside:
            return Verdict(False, f"{shown} lies in {allowed}, but its whole 95 % interval {interval} lies outside")
    if math.isinf(error) or (value != 0 and math.isfinite(error) and error > UNCONSTRAINED_RATIO * abs(value)):
        return Verdict(False, f"{shown} ± {display(error, unit)} (1σ) is unconstrained: its error is more than "
                              f"{UNCONSTRAINED_RATIO:g} times the value, the data do not determine it")
    return Verdict(True, "")


def check_plausibility(quantities: Mapping[str, Mapping | float]) -> dict[str, Verdict]:
    """Verdicts on the fit's read-outs, by name (``FitResult.quantities`` or ``{name: value}`` in SI).

    When one factor on the spring constant brings every read-out into its range, the implausible ones say so
    (:func:`spring_constant_cause`) instead of the general advice on the calibration."""
    verdicts = {name: judge(name, q) for name, q in quantities.items()}
    cause = spring_constant_cause(quantities)
    if cause is None:
        return verdicts
    return {name: Verdict(False, f"{v.finding}; {cause}", v.finding) if name in cause.explained else v
            for name, v in verdicts.items()}


def spring_power(unit: str) -> float:
    """How a read-out in ``unit`` scales with the declared spring constant k, at fixed lengths and times.

    Every force the fit reports is k times a deflection (m = k / w0^2 and c = k / (Q w0) too), so a read-out
    made of forces, lengths and times scales with k to the power of its mass dimension: E* (Pa), H (J), gamma
    (J/m^2), a viscosity (Pa s) as k. A unit with current or temperature (a voltage: V^2 eps0 is a force) is not
    such a read-out: 0 (unknown, not used)."""
    from afmid.terms.units import parse_unit

    try:
        kg, _, _, ampere, kelvin = parse_unit(unit).dims
    except ValueError:
        return 0.0
    return 0.0 if ampere or kelvin else float(kg)


class SpringConstantCause(str):
    """The likely-cause clause (a str) and the read-outs it explains (``explained``)."""

    explained: frozenset[str]


def _factor_words(factor: float) -> str:
    return f"{short_number(float(f'{factor:.2g}'))}x"


def spring_constant_cause(quantities: Mapping[str, Mapping | float]) -> SpringConstantCause | None:
    """The clause naming a spring constant off by a factor as the likely cause, or None.

    Each read-out v that scales as k^p (:func:`spring_power`) is physical for a true k = k_declared / f only when
    low <= v / f^p <= high: an interval of f. When some read-out is outside its range by magnitude (positive, not
    of the wrong sign, determined) and the intervals of all of them intersect away from f = 1, a spring constant
    off by a factor in the intersection explains them all; the clause gives the interval and, at the power of ten
    nearest its middle (in log), what the flagged read-outs and E* would be. A wrong sign or an empty intersection
    is no such cause (then None), and so is a single read-out (any factor brings one value in)."""
    lo, hi = -math.inf, math.inf  # log10 f
    scaled: dict[str, tuple[float, float, str]] = {}  # name -> (value, power, unit)
    flagged = set()
    for name, q in quantities.items():
        q = q if isinstance(q, Mapping) else {"value": q}
        value = _field(q, "value")
        declared = judged_range(name, q)
        if declared is None or q.get("determined", True) is False or not (math.isfinite(value) and value > 0):
            continue
        low, high, unit = declared
        power = spring_power(str(q.get("unit") or unit))
        if power <= 0:
            continue
        scaled[name] = (value, power, str(q.get("unit") or unit))
        lo = max(lo, math.log10(value / high) / power)
        hi = min(hi, math.log10(value / low) / power if low > 0 else math.inf)
        if not (low <= value <= high):
            flagged.add(name)
    # One read-out alone allows any factor that brings it in (E* 10 TPa: 10x to 1e11x) and is as well a wrong
    # data.units: the cause is named only when two or more read-outs agree on a factor, and they must rest on two
    # or more fitted terms: H, the adhesion and the surface energy of one van der Waals coefficient are one piece of
    # evidence (``sources``, afmid.fit.forces.read_out; read-outs given without it count as independent).
    if not flagged or len(scaled) < 2 or lo > hi or lo <= 0.0 <= hi or not _independent(quantities, scaled):
        return None
    larger = lo > 0.0  # f > 1: the declared k is too large
    direction = "large" if larger else "small"
    near, far = (lo, hi) if larger else (-hi, -lo)
    if math.isfinite(far):  # the power of ten nearest the middle (in log), inside the interval if one is
        example = round((near + far) / 2.0)
        if math.ceil(near) <= math.floor(far):
            example = min(max(example, math.ceil(near)), math.floor(far))
        span = f"{_factor_words(10 ** near)} to {_factor_words(10 ** far)}"
    else:
        example, span = math.ceil(near), f"{_factor_words(10 ** near)} or more"
    example = max(example, 1)  # f = 1 is the declared k
    shown = [n for n in scaled if n in flagged] + [n for n in scaled if n == "E_star" and n not in flagged]
    f = 10.0 ** (example if larger else -example)
    at = " and ".join(f"{n.split('.')[-1]} would be {display(scaled[n][0] / f ** scaled[n][1], scaled[n][2])}"
                      if i == 0 else f"{n.split('.')[-1]} {display(scaled[n][0] / f ** scaled[n][1], scaled[n][2])}"
                      for i, n in enumerate(shown))
    cause = SpringConstantCause(
        f"a spring constant {span} too {direction} would explain it, since every force read-out is proportional "
        f"to it (at {_factor_words(10.0 ** example)} too {direction}: {at}): check cantilever.spring_constant")
    cause.explained = frozenset(flagged)
    return cause


def _independent(quantities: Mapping[str, Mapping | float], names) -> bool:
    """True when the read-outs ``names`` rest on at least two fitted terms (their ``sources``), or when any of them
    does not say what it rests on."""
    sources = [q.get("sources") if isinstance(q, Mapping) else None for q in (quantities[n] for n in names)]
    if any(s is None for s in sources):
        return True
    return len({label for s in sources for label in s}) >= 2 and len({tuple(s) for s in sources}) >= 2


def judged_range(name: str, quantity: Mapping) -> tuple[float, float, str] | None:
    """(low, high, unit) a read-out is judged against: for a force that grows with the tip, the range the declared
    tip allows (:func:`tip_scaled_range`), else the declared one (:func:`plausible_range`); None if undeclared."""
    effect = quantity.get("effect") or None
    return tip_scaled_range(name, effect, _field(quantity, "tip_radius")) or plausible_range(name, effect)


def interval_outside_range(name: str, quantity: Mapping) -> bool:
    """True when a determined read-out's whole 95 % interval (``ci_low``, ``ci_high``, finite) lies outside its
    physical range (:func:`judged_range`): no value the data allow is physical. Noise alone puts a small term's
    interval across a bound, never wholly beyond it (that is 2 sigma at least); a read-out without an interval
    is no evidence either way."""
    if quantity.get("determined", True) is False:
        return False
    ci_low, ci_high = _field(quantity, "ci_low"), _field(quantity, "ci_high")
    declared = judged_range(name, quantity)
    if declared is None or not (math.isfinite(ci_low) and math.isfinite(ci_high)):
        return False
    low, high, _ = declared
    return ci_high < low or ci_low > high


def unphysical(name: str, quantity: Mapping) -> bool:
    """True when a determined read-out lies outside its physical range and so does its whole 95 % interval
    (:func:`interval_outside_range`): the model fits the record only with an impossible parameter."""
    value = _field(quantity, "value")
    if not math.isfinite(value) or not interval_outside_range(name, quantity):
        return False
    low, high, _ = judged_range(name, quantity)
    return not (low <= value <= high)


def judge_separation(value: float, sigma: float) -> Verdict:
    """The verdict on an estimated rest separation ``value`` +- ``sigma`` (1 sigma), m.

    At d <= 0 the undeflected tip would sit at or below the surface's contact distance minus a0, pressed into
    the sample at rest: a tapping record does not come from there. Such an estimate means the record does not
    locate the contact point (a force nearly static over the oscillation, a long-range force the search
    confuses with contact), so neither d nor the read-outs that depend on it are results.
    """
    if math.isfinite(value) and value > 0:
        return Verdict(True, "")
    shown = f"the estimated rest separation d = {display(value, 'm')}"
    if math.isfinite(sigma):
        shown += f" ± {display(sigma, 'm')} (1σ)"
    what = f"{shown} is not above zero: the tip would rest inside the sample, so the record does not locate " \
           "the contact point"
    return Verdict(False, f"{what}; set sample.separation if it is known, or record a larger amplitude", what)


#: The key of the rest separation's verdict among a run's verdicts (:func:`check_run`).
SEPARATION = "separation"


def check_run(quantities: Mapping[str, Mapping | float], nonlinear: Mapping) -> dict[str, Verdict]:
    """:func:`check_plausibility` of the read-outs, plus the estimated rest separation's verdict
    (:func:`judge_separation`, key :data:`SEPARATION`) when ``nonlinear`` (a fit's ``nonlinear``) estimated it."""
    verdicts = check_plausibility(quantities)
    d = nonlinear.get("d")
    if d is not None and d.estimated:
        verdicts[SEPARATION] = judge_separation(float(d.value), float(d.sigma))
    return verdicts


def violations(verdicts: Mapping[str, Verdict]) -> list[str]:
    """The reasons of the implausible verdicts, in order."""
    return [v.reason for v in verdicts.values() if not v.plausible]


def attributes(verdict: Verdict) -> dict:
    """The attributes of a ``/model/parameters/NAME`` dataset that hold the verdict."""
    return {"plausible": bool(verdict.plausible), "plausibility": verdict.reason}


def flagged_value(name: str, quantity: Mapping, tip_radius: float | None = None) -> str:
    """How a table shows an implausible read-out: never as a plain number.

    ``implausible: -24 kPa s ± 3 kPa s (1σ) (plausible: [0, 1e5] Pa s)``. The range shown is the one the verdict
    used: for a force that grows with the tip, the bound of the declared tip (``tip_radius`` in m, else the
    quantity's own ``tip_radius``).
    """
    value, error = _field(quantity, "value"), _field(quantity, "error")
    effect = quantity.get("effect") or None
    radius = tip_radius if tip_radius is not None else _field(quantity, "tip_radius")
    declared = tip_scaled_range(name, effect, radius) or plausible_range(name, effect)
    unit = str(quantity.get("unit") or (declared[2] if declared else ""))
    if quantity.get("determined", True) is False:
        return not_determined_text(quantity, unit)
    text = f"implausible: {display(value, unit)}"
    if math.isfinite(error):
        text += f" ± {display(error, unit)} (1σ)"
    if declared is not None:
        text += f" (plausible: {range_words(declared[0], declared[1], unit)})"
    return text


def not_determined_text(quantity: Mapping, unit: str) -> str:
    """A not-determined read-out in a table: ``not determined (95 % with its term forced in: [a, b])``."""
    lo, hi = _field(quantity, "ci_low"), _field(quantity, "ci_high")
    text = "not determined"
    if math.isfinite(lo) and math.isfinite(hi):
        text += f" (95 % with its term forced in: [{display(lo, unit)}, {display(hi, unit)}])"
    return text


def warn(verdicts: Mapping[str, Verdict]) -> None:
    """One ``afmid: warning:`` line per implausible read-out."""
    for reason in violations(verdicts):
        log.warning("implausible read-out: %s", reason)


def describe_not_determined(name: str, q: dict) -> str:
    """One sentence for a not-determined read-out (console, report, plausibility reason)."""
    label = name.split(".")[-1]
    unit = q.get("unit", "")
    terms = ", ".join(q.get("undetermined_terms", [])) or "its term"
    text = (f"{label}{NOT_DETERMINED}{terms} was not selected (inclusion probability "
            f"{q.get('inclusion', math.nan):.2f})")
    if q.get("silent_terms"):
        text += "; its column is zero on this trace (the fitted model never reaches where it acts), so no bound"
    lo, hi = q.get("ci_low", math.nan), q.get("ci_high", math.nan)
    if math.isfinite(lo) and math.isfinite(hi):
        text += f"; with it forced in, the 95 % interval is [{display(lo, unit)}, {display(hi, unit)}]"
    return text

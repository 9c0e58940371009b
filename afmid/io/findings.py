"""What a check on a trace found, and how numbers are written in its one-line message.

Shared by the defect checks (:mod:`afmid.io.defects`), the drive-line test (:mod:`afmid.io.oscillation`) and the
resolution check (:mod:`afmid.io.resolution`), which :mod:`afmid.io.defects` runs: kept apart so that none of them
imports another's module in a cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

SEVERITIES = ("repaired", "warning", "error")


@dataclass(frozen=True)
class Finding:
    """One defect: what it is, how bad, a one-line explanation, and the numbers behind it."""

    name: str
    severity: str  # repaired | warning | error
    message: str
    key: str | None = None  # the config key the message is about (for errors)
    numbers: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.severity not in SEVERITIES:
            raise ValueError(f"severity must be one of {SEVERITIES}, got {self.severity!r}")
        if "\n" in self.message:
            raise ValueError("a finding's message is one line")

    def line(self) -> str:
        """``severity: name: message``, as ``afmid inspect`` prints it."""
        return f"{self.severity}: {self.name}: {self.message}"


# --------------------------------------------------------------------------- formatting
def length(value: float, units: str | None = "m") -> str:
    """A length for a message: metres as pm/nm/um, other units as they are."""
    if units != "m":
        suffix = f" {units}" if units else " (file units)"
        return f"{value:.3g}{suffix}"
    size = abs(value)
    for scale, name in ((1e-12, "pm"), (1e-9, "nm"), (1e-6, "um"), (1e-3, "mm")):
        if float(f"{size / scale:.3g}") < 1000:  # as printed: 999.9999 pm is "1 nm", not "1e+03 pm"
            return f"{value / scale:.3g} {name}"
    return f"{value:.3g} m"


def frequency(value: float) -> str:
    """A frequency for a message: Hz, kHz or MHz."""
    for scale, name in ((1e6, "MHz"), (1e3, "kHz")):
        if abs(value) >= scale:
            return f"{value / scale:.6g} {name}"
    return f"{value:.6g} Hz"


def yaml_number(value: float) -> str:
    """A float as a config takes it (PyYAML needs a '.' in the mantissa): 3.0e+07, 0.25, 400.0."""
    value = float(value)
    if value != 0 and not 1e-3 <= abs(value) < 1e5:
        mantissa, _, exponent = f"{value:.9e}".partition("e")
        mantissa = mantissa.rstrip("0")
        return f"{mantissa}0e{exponent}" if mantissa.endswith(".") else f"{mantissa}e{exponent}"
    text = f"{value:.10g}"
    return text if "." in text else text + ".0"

"""Does the force in contact follow the catalog's contact law? A specification test with shape probes.

The cross-validated error compares the model's force with the measured one. A force law that differs from the
catalog's only inside contact can pass it: the catalog's terms reproduce the force curve with wrong parameters.
Measured (docs/lab/2026-11-29-liquid-hydration-contact-law.md): a liquid record whose hydration force keeps
growing inside contact, fitted with a law that holds it at contact, gave E* 500 MPa for a 20 MPa sample
(z +61 to +80) with the error at its noise floor.

The test is the paper's own device (its candidate tables hold delta^2 and delta^2.5 beside Hertz's delta^1.5 as
distractors) turned into a check (Ramsey's RESET in spirit: does a term of another shape explain what the
model leaves): the fit's selection is run once more on the library plus two probe columns of the contact
law's shape with the exponent moved down and up (``[z <= a0] * delta^(n - 1/2)``, ``[z <= a0] * delta^(n + 1)``,
n the elastic term's power). The selection's own criterion decides, the one every catalog term faces, so a probe
is taken only where the data ask for it as they would for a real effect. A probe in the selected support means the
force in contact has a shape the model cannot give: the run is model-limited, its parameters biased beyond their
error bars, whatever its cross-validated error says.

Only for a library of catalog effects whose elastic term is a power of the indentation under the contact gate
(DMT with any tip); a preset library already holds its own distractors; a fit whose support holds no elastic
term has no contact to test.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmid.physics.effect_tags import Role
from afmid.physics.library import Library

#: The probes' exponents relative to the elastic term's power n: one softer, one stiffer shape.
EXPONENT_SHIFTS = (-0.5, 1.0)
_POWER_LAW = re.compile(r"^\[z <= a0\] \* delta\^(?P<power>[0-9]+(?:\.[0-9]+)?)$")


@dataclass(frozen=True)
class ContactProbe:
    """The outcome of the test: the elastic term tested, the probe expressions, the ones the selection took."""

    elastic_term: str
    probes: tuple[str, ...]
    selected: tuple[str, ...]

    @property
    def failed(self) -> bool:
        return bool(self.selected)

    def warning(self) -> str:
        """The model-limited warning of a failed test (empty when it passed)."""
        if not self.failed:
            return ""
        return (f"model-limited: the force in contact does not follow the model's contact law ({self.elastic_term}): "
                f"the selection takes {' and '.join(self.selected)} beside it when offered (a shape probe, "
                "afmid.fit.contact_probe), so the contact parameters are biased beyond their error bars even though "
                "the force error may sit at its floor; the sample's contact law differs from the catalog's (another "
                "tip shape, a surface force that does not stay at its contact value, a layered sample)")


def elastic_power(library: Library, chosen: np.ndarray) -> tuple[str, float] | None:
    """(label, power n) of the selected elastic contact term ``[z <= a0] * delta^n`` of a catalog effect, or
    None (no such term selected: nothing to test)."""
    for j, term in enumerate(library.terms):
        if term.effect is None or Role.ELASTIC_CONTACT not in term.roles or not bool(chosen[j]):
            continue
        match = _POWER_LAW.match(term.expression)
        if match:
            return f"{term.effect}.{term.label}", float(match["power"])
    return None


def probe_expressions(power: float) -> tuple[str, ...]:
    """The probe terms for an elastic law of power ``power`` (term language)."""
    return tuple(f"[z <= a0] * delta^{power + shift:g}" for shift in EXPONENT_SHIFTS)


def check_contact_law(library: Library, chosen: np.ndarray, user_terms: list[str], preset: str | None,
                     select_with: Callable[[list[str]], tuple[Library, np.ndarray]]) -> ContactProbe | None:
    """Run the test. ``select_with(extra_terms)`` selects on the fit's library plus ``extra_terms`` (custom terms
    after the user's own) and returns that library and its selected mask; None when there is nothing to test
    (a preset library, no selected elastic power law, or a probe the user already has among ``user_terms``)."""
    if preset is not None:
        return None
    found = elastic_power(library, chosen)
    if found is None:
        return None
    label, power = found
    probes = probe_expressions(power)
    if any(p in user_terms for p in probes):
        return None
    probed, mask = select_with(list(probes))
    selected = tuple(t.expression for j, t in enumerate(probed.terms)
                     if t.effect is None and t.expression in probes and bool(mask[j]))
    return ContactProbe(label, probes, selected)

"""Registration checks of the physics registry (afmid.physics.effects): units, region, character, roles."""

from __future__ import annotations

import dataclasses
import json

import pytest

from afmid.physics.effect_tags import Character, Region, Role
from afmid.errors import DefinitionError
from afmid.physics.effect_types import StateGate, forms_at_contact
from afmid.physics.effects import EFFECTS, Effect, Parameter, Quantity, Term, coefficient_unit
from afmid.terms.units import parse_unit


def test_every_declared_coefficient_unit_matches_its_term():
    for effect in EFFECTS:
        assert isinstance(effect.region, Region) and isinstance(effect.character, Character)
        for term in effect.terms:
            assert parse_unit(term.coefficient_unit) == coefficient_unit(effect, term), (effect.name, term.label)
            assert all(isinstance(r, Role) for r in term.roles)


def test_tags_read_as_their_values():
    """The enumerations keep the text the catalog, the diagnosis tables and the report show."""
    dmt = EFFECTS.get("dmt")
    assert dmt.region == "contact" and f"{dmt.region}" == "contact" and json.dumps(dmt.region) == '"contact"'
    assert {"contact": 1}[dmt.region] == 1
    assert EFFECTS.get("viscoelastic").character == "dissipative"


def _spring(**changes) -> Effect:
    term = Term("spring", "z", lambda p: -p["test_stiffness"], roles=(Role.ELASTIC_CONTACT,), coefficient_unit="N/m")
    effect = Effect(
        name="test_physics_effect", title="a test effect", formula="F = -k_t z",
        parameters=(Parameter("test_stiffness", "N/m", 1.0, 0.0, 10.0, "stiffness"),),
        terms=(term,),
        quantities=(Quantity("test_stiffness", "N/m", "k"),),
        readout=lambda c, ctx: {"test_stiffness": -c["spring"]},
        references=("none",),
    )
    term_changes = {k: changes.pop(k) for k in ("coefficient_unit", "roles", "expression") if k in changes}
    if term_changes:
        changes["terms"] = (dataclasses.replace(term, **term_changes),)
    return dataclasses.replace(effect, **changes)


@pytest.mark.parametrize("changes, message", [
    ({"coefficient_unit": ""}, "declare coefficient_unit"),
    ({"coefficient_unit": "N"}, r"coefficient \(N\) x term \(m\) is J, not N; the coefficient should be in N/m"),
    ({"expression": "z^2"}, "not N"),
    ({"coefficient_unit": "furlong"}, "furlong"),
    ({"region": "contact"}, "region must be one of Region"),
    ({"region": "surface"}, "region must be one of Region"),
    ({"character": "dissipative"}, "character must be one of Character"),
    ({"roles": ("elastic_contact",)}, "role must be one of Role"),
    ({"roles": Role.ELASTIC_CONTACT}, "roles must be a tuple"),
    ({"readout_only_terms": (Term("spring", "z", lambda p: 0.0, coefficient_unit="N/m"),)}, "labels repeat"),
    ({"readout_only_terms": (Term("offset", "[z <= a0]", lambda p: 1e-9, coefficient_unit="N"),),
      "readout": lambda c, ctx: {"test_stiffness": -c["spring"] + c.get("offset", 0.0)}},
     "changes with the read-out-only terms"),
    ({"states": (StateGate("test_gate", on="z <= 2 * a0", off="z > 3 * a0", forms_at_contact=True),)},
     "declared to form at contact, but it switches on at 'z <= 2 \\* a0'"),
], ids=["no-unit", "wrong-unit", "wrong-term", "unknown-unit", "string-region", "unknown-region", "string-character",
        "string-role", "roles-not-tuple", "readout-only-label-repeats", "readout-only-changes-readout",
        "gate-not-at-contact"])
def test_registration_refuses_a_malformed_effect(changes, message):
    n = len(EFFECTS)
    with pytest.raises(DefinitionError, match=message):
        EFFECTS.register(_spring(**changes))
    assert len(EFFECTS) == n and "test_physics_effect" not in EFFECTS


def test_the_gates_that_form_at_contact_are_declared_so():
    """A meniscus and a JKR neck switch on where the tip reaches a0 (the separation searches try each tap's contact
    threshold for them, afmid.fit.contact_thresholds); a gate is declared so only with that condition, and an
    effect without such a gate is not one."""
    assert forms_at_contact(EFFECTS.get("capillary").states) and forms_at_contact(EFFECTS.get("jkr").states)
    assert not forms_at_contact(EFFECTS.get("dmt").states)
    assert not forms_at_contact(EFFECTS.get("standard_linear_solid").states)  # a relaxing state, no gate
    for effect in EFFECTS:
        for gate in effect.states:
            if isinstance(gate, StateGate) and gate.forms_at_contact:
                assert gate.on.split() == ["z", "<=", "a0"], effect.name

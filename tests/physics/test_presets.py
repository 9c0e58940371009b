"""The library presets registry (afmid.physics.presets): typed terms, checked at registration."""

from __future__ import annotations

import pytest

from afmid.physics.effect_tags import Role
from afmid.errors import DefinitionError
from afmid.physics.effects import EFFECTS
from afmid.physics.presets import PRESETS, Preset, PresetTerm, origin_term


def test_every_preset_term_names_a_declared_effect_term_of_the_same_units():
    assert PRESETS.names() == ["lj_table1", "viscoelastic_table2", "exponential_table3", "jkr_table4"]
    for preset in PRESETS:
        for term in preset.terms:
            assert all(isinstance(r, Role) for r in term.roles)
            if term.effect is not None:
                assert term.effect in preset.effects
                origin_term(EFFECTS.get(term.effect), term.label)  # raises if undeclared


def test_the_bridging_term_is_dmts_declared_read_out_only_adhesion():
    """The seed tables' bridging column is read out as DMT's adhesion: a term DMT declares (but does not simulate)."""
    dmt = EFFECTS.get("dmt")
    assert "adhesion" not in [t.label for t in dmt.terms]  # the simulated DMT ties adhesion to the tail
    adhesion = origin_term(dmt, "adhesion")
    assert adhesion.coefficient_unit == "N" and adhesion.roles == (Role.CONTACT_ONLY, Role.CONTACT_ADHESION)
    bridging = [t for t in PRESETS.get("viscoelastic_table2").terms if t.name == "[z<=a0] (bridging)"]
    assert [(t.effect, t.label) for t in bridging] == [("dmt", "adhesion")]
    with pytest.raises(KeyError, match="declares no term 'bridge'"):
        origin_term(dmt, "bridge")


def _preset(*terms: PresetTerm, effects=("dmt",)) -> Preset:
    return Preset("test_preset", "a test preset", terms, effects, ("none",))


@pytest.mark.parametrize("preset, message", [
    (_preset(PresetTerm("z^-2", "z^-2", "dmt", "vdw"), effects=("dmt", "no_such_effect")), "unknown effect"),
    (_preset(PresetTerm("z^-2", "z^-2", "dmt", "tail")), "declares no term 'tail'"),
    (_preset(PresetTerm("z^-2", "z^-2", "jkr", "vdw")), "not among the preset's effects"),
    (_preset(PresetTerm("z^-3", "z^-3", "dmt", "vdw")), r"dmt.vdw \(N\*m\^2\) x the term \(m\^-3\) is not N"),
    (_preset(PresetTerm("z^-2", "z^-2", "dmt")), "both effect and label"),
    (_preset(PresetTerm("z^-2", "z^-2", roles=("attractive_tail",))), "must be one of Role"),
    (_preset(PresetTerm("z^-2", "z^-2", roles=(Role.ATTRACTIVE_TAIL, "tail"))), "must be one of Role"),
    (_preset(PresetTerm("bad", "z^^2")), "z\\^\\^2|unexpected|expected"),
    (_preset(PresetTerm("unknown name", "z * stiffness")), "stiffness"),
    (_preset(PresetTerm("a", "z"), PresetTerm("a", "z^2")), "names repeat"),
    (_preset(("z", "z", None)), "must be PresetTerm"),
    (_preset(), "at least one term"),
], ids=["unknown-effect", "undeclared-label", "origin-outside-effects", "units", "half-origin", "string-role",
        "misspelt-role", "unparsable", "unknown-name", "repeated-name", "untyped-tuple", "empty"])
def test_registration_refuses_a_malformed_preset(preset, message):
    n = len(PRESETS)
    with pytest.raises(DefinitionError, match=message):
        PRESETS.register(preset)
    assert len(PRESETS) == n and "test_preset" not in PRESETS

"""Library presets: the candidate-term tables of the seed paper (``model.library`` in a run config).

A :class:`Preset` is a fixed list of :class:`PresetTerm` s: the true terms of the
seed's model, labelled with the effect coefficient they estimate (so the fit can
read them out as physical quantities), and distractors with no origin. Presets
are registered in :data:`PRESETS` and checked at import: every origin names a
term its effect declares (in ``terms`` or ``readout_only_terms``), with the same
units, so that the effect's declared coefficient unit x the preset term's units
is a force (N); every expression parses in the preset's effects' names; roles are
:class:`afmid.physics.effect_tags.Role` members; the effects a preset stands for exist
and include every origin's effect.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import afmid.terms.expr as expr
from afmid.physics.effect_tags import Role, check_roles
from afmid.errors import DefinitionError
from afmid.physics.effects import CONTEXT_UNITS, EFFECTS, Effect, Term
from afmid.registry import Registry
from afmid.terms.units import Unit, parse_unit

NEWTON = parse_unit("N")


@dataclass(frozen=True)
class PresetTerm:
    """One candidate column of a preset. ``effect``/``label``: the effect coefficient it estimates (both or
    neither; a term with none is a distractor, penalised by the selection's prior)."""

    name: str  # display name, the column's name in the fit's output
    expression: str  # term language (afmid.terms.expr); SI units follow from the names it uses
    effect: str | None = None
    label: str | None = None
    roles: tuple[Role, ...] = ()  # what the term is to the selection rules


@dataclass(frozen=True)
class Preset:
    name: str
    title: str
    terms: tuple[PresetTerm, ...]
    effects: tuple[str, ...]  # effects whose read-out applies (and whose parameters the terms may name)
    references: tuple[str, ...]
    notes: str = ""


def preset_units(effects: tuple[str, ...]) -> dict[str, Unit]:
    """The units of the names a preset's terms may use: the context (R, a0, w) and its effects' parameters."""
    units = {name: parse_unit(unit) for name, unit in CONTEXT_UNITS.items()}
    units["w"] = parse_unit("1/s")
    for name in effects:
        units.update({p.name: parse_unit(p.unit) for p in EFFECTS.get(name).parameters})
    return units


def origin_term(effect: Effect, label: str) -> Term:
    """The term ``label`` of ``effect``, among its terms and its read-out-only terms (KeyError if none)."""
    for term in effect.terms + effect.readout_only_terms:
        if term.label == label:
            return term
    raise KeyError(f"effect {effect.name!r} declares no term {label!r}; it has "
                   f"{', '.join(t.label for t in effect.terms + effect.readout_only_terms)}")


def _validate_preset(preset: Preset) -> None:
    if not preset.terms:
        raise DefinitionError("a preset needs at least one term")
    for name in preset.effects:
        if name not in EFFECTS:
            raise DefinitionError(f"unknown effect {name!r}")
    states = tuple(s.name for name in preset.effects for s in EFFECTS.get(name).states)
    units = preset_units(preset.effects)
    for term in preset.terms:
        if not isinstance(term, PresetTerm):
            raise DefinitionError(f"terms must be PresetTerm, got {term!r}")
    names = [t.name for t in preset.terms]
    if len(set(names)) != len(names):
        raise DefinitionError(f"term names repeat: {names}")
    for term in preset.terms:
        check_roles(term.roles, f"term {term.name!r}")
        unit = expr.expression_units(term.expression, units, states)  # parses, and names only known values
        if (term.effect is None) != (term.label is None):
            raise DefinitionError(f"term {term.name!r}: give both effect and label, or neither")
        if term.effect is None:
            continue
        if term.effect not in preset.effects:
            raise DefinitionError(f"term {term.name!r}: its effect {term.effect!r} is not among the preset's "
                                  f"effects {list(preset.effects)} (whose read-out applies)")
        effect = EFFECTS.get(term.effect)
        declared = origin_term(effect, term.label)
        coefficient_unit = parse_unit(declared.coefficient_unit)
        if coefficient_unit * unit != NEWTON:
            raise DefinitionError(f"term {term.name!r}: the coefficient of {term.effect}.{term.label} "
                                  f"({coefficient_unit}) x the term ({unit}) is not N")


PRESETS: Registry[Preset] = Registry("library preset", _validate_preset)

_CONTACT = "[z <= a0]"
_OUT = "[z > a0]"
_ELASTIC = (Role.ELASTIC_CONTACT,)
_DISSIPATION = (Role.CONTACT_ONLY,)
_ADHESION = (Role.CONTACT_ONLY, Role.CONTACT_ADHESION)
_TAIL = (Role.ATTRACTIVE_TAIL,)
_SEED = "Chandrashekar et al., Nanoscale Adv. (2022), supplement table"
# The seed tables' sin(Omega tau) is not listed: afmid always fits the drive as
# free cos and sin terms (its amplitude and phase are unknown in a measurement).
# The tables' "z^-2 for z <= a0" bridging function is the constant in-contact
# adhesion term (C3 / a0^2 of eq. 1), DMT's read-out-only term "adhesion";
# inverse powers act out of contact as in eq. 1.
_BRIDGING = PresetTerm("[z<=a0] (bridging)", _CONTACT, "dmt", "adhesion", _ADHESION)
_TABLE_2_4 = (
    PresetTerm("z^-2", f"{_OUT} * z^-2", "dmt", "vdw", _TAIL),
    PresetTerm("z^-3", f"{_OUT} * z^-3", roles=_TAIL),
    PresetTerm("delta^0.5*deltadot", "delta^0.5 * deltadot", "viscoelastic", "kelvin_voigt", _DISSIPATION),
    PresetTerm("delta*deltadot^2", "delta * deltadot^2", roles=_DISSIPATION),
    PresetTerm("z^0.5*zdot", f"{_OUT} * z^0.5 * zdot"),
    PresetTerm("z*zdot^2", "z * zdot^2"),
    PresetTerm("delta^2", "delta^2", roles=_ELASTIC),
    PresetTerm("delta^2.5", "delta^2.5", roles=_ELASTIC),
    PresetTerm("delta^1.5", f"{_CONTACT} * delta^1.5", "dmt", "hertz", _ELASTIC),
    _BRIDGING,
)
_LJ_ORIGINS = {2: "attraction", 8: "repulsion"}

PRESETS.register(Preset(
    "lj_table1",
    "seed table I: inverse powers z^-1..z^-8, z^1.5, z^2",
    tuple(PresetTerm(f"z^-{n}", f"z^-{n}", "lennard_jones" if n in _LJ_ORIGINS else None, _LJ_ORIGINS.get(n))
          for n in range(1, 9))
    + (PresetTerm("z^1.5", "z^1.5"), PresetTerm("z^2", "z^2")),
    ("lennard_jones",),
    (f"{_SEED} I",),
))
PRESETS.register(Preset(
    "viscoelastic_table2",
    "seed table II: DMT + viscoelastic candidates",
    _TABLE_2_4,
    ("dmt", "viscoelastic"),
    (f"{_SEED} II",),
))
PRESETS.register(Preset(
    "exponential_table3",
    "seed table III: DMT + exponential damping candidates",
    (
        PresetTerm("z^-2", f"{_OUT} * z^-2", "dmt", "vdw", _TAIL),
        PresetTerm("z^-3", f"{_OUT} * z^-3", roles=_TAIL),
        PresetTerm("exp(-z/lambda)*zdot", "exp(-z / damping_length) * zdot", "exponential_damping", "surface_damping"),
        PresetTerm("exp(-z/lambda)^2*zdot^2", "exp(-2 * z / damping_length) * zdot^2"),
        PresetTerm("z*zdot", "z * zdot"),
        PresetTerm("z*zdot^2", "z * zdot^2"),
        PresetTerm("delta^2", "delta^2", roles=_ELASTIC),
        PresetTerm("delta^2.5", "delta^2.5", roles=_ELASTIC),
        PresetTerm("delta^1.5", f"{_CONTACT} * delta^1.5", "dmt", "hertz", _ELASTIC),
        _BRIDGING,
    ),
    ("dmt", "exponential_damping"),
    (f"{_SEED} III",),
))
PRESETS.register(Preset(
    "jkr_table4",
    "seed table IV: JKR candidates (same functions as table II)",
    # The same columns, read out as JKR's coefficients (JKR declares vdw, hertz and adhesion as terms).
    tuple(replace(t, effect="jkr") if t.effect == "dmt" else t for t in _TABLE_2_4),
    ("jkr", "viscoelastic"),
    (f"{_SEED} IV",),
))

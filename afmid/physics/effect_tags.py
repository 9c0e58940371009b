"""The checked vocabularies an effect and its terms are tagged with.

``Region`` (where an effect acts) and ``Character`` (how its force depends on the
direction of motion) guide the diagnosis' wording and matching; ``Role`` says what
a term is to the selection rules (:data:`SELECTION_RULES`). They are string
enumerations: a member compares, hashes, formats and serialises to JSON as its
value (``Region.CONTACT == "contact"``), so the catalog, the diagnosis tables and
run files read the same text as before; but a declaration must use a member, and
the physics registry refuses a plain or misspelt string at import.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Region(StrEnum):
    """Where an effect's force acts."""

    CONTACT = "contact"  # only while the tip indents the sample (z <= a0)
    NEAR = "near"  # near the surface, decaying within a few nm
    LONG_RANGE = "long_range"  # at all separations of a tapping cycle
    ALL = "all"  # everywhere


class Character(StrEnum):
    """How an effect's force depends on the motion: this is what the diagnosis compares with the residual."""

    CONSERVATIVE = "conservative"  # a function of the separation only: the same on approach and retraction
    DISSIPATIVE = "dissipative"  # depends on the velocity: reverses with the direction of motion
    HYSTERETIC = "hysteretic"  # depends on the history (a state gate): differs between approach and retraction


class Role(StrEnum):
    """What a term is to the selection rules."""

    ELASTIC_CONTACT = "elastic_contact"
    CONTACT_ONLY = "contact_only"
    CONTACT_ADHESION = "contact_adhesion"
    ATTRACTIVE_TAIL = "attractive_tail"


#: Roles of terms, with their meaning (shown by ``afmid effects``), used by SELECTION_RULES.
TERM_ROLES: dict[Role, str] = {
    Role.ELASTIC_CONTACT: "an elastic contact law (a force of the indentation only, e.g. Hertz)",
    Role.CONTACT_ONLY: "acts only in contact and is not elastic (adhesion, dissipation)",
    Role.CONTACT_ADHESION: "a constant attraction in contact",
    Role.ATTRACTIVE_TAIL: "an attraction out of contact that reaches the contact point (van der Waals)",
}


@dataclass(frozen=True)
class SelectionRule:
    """A support that holds a term of every role in ``if_all`` must hold a term of a role in ``then_any``."""

    if_all: tuple[Role, ...]
    then_any: tuple[Role, ...]
    why: str


#: Physical consistency of a selected force law: supports that break a rule are not candidates.
SELECTION_RULES = (
    SelectionRule((Role.CONTACT_ONLY,), (Role.ELASTIC_CONTACT,),
                  "a surface cannot pull on or damp a tip in contact without pushing back"),
    SelectionRule((Role.ATTRACTIVE_TAIL, Role.ELASTIC_CONTACT), (Role.CONTACT_ADHESION,),
                  "the van der Waals attraction does not vanish when the tip touches"),
)


def check_member(enumeration: type[StrEnum], value: object, what: str) -> None:
    """Raise ValueError unless ``value`` is a member of ``enumeration`` (a plain string is refused: declarations
    name members, so a typo fails where it is written)."""
    if not isinstance(value, enumeration):
        allowed = ", ".join(f"{enumeration.__name__}.{m.name}" for m in enumeration)
        raise ValueError(f"{what} must be one of {allowed}; got {value!r}")


def check_roles(roles: tuple, what: str) -> None:
    """Raise ValueError unless ``roles`` is a tuple of :class:`Role` members."""
    if not isinstance(roles, tuple):
        raise ValueError(f"{what}: roles must be a tuple of Role members, got {roles!r}")
    for role in roles:
        check_member(Role, role, f"{what}: role")

"""The physics registry: tip-sample force effects and the models built from them.

One source of truth for the simulator and the fit. An :class:`Effect` is a force
contribution written as a sum of *terms* in afmid's term language
(:mod:`afmid.terms.expr`), each multiplied by a coefficient that follows from the
effect's physical parameters. The simulator evaluates ``sum(coefficient * term)``;
the fit uses the same terms as library columns and turns fitted coefficients
back into physical quantities with the effect's ``readout``.

Conventions (pinned, see README): forces are on the tip, in newtons, positive =
repulsive (pushing the tip away from the sample). ``z`` is the tip-sample
separation, ``delta = max(a0 - z, 0)`` the indentation, ``zdot = dz/dt``,
``deltadot = -zdot`` in contact and 0 outside.

Adding an effect = one ``EFFECTS.register(Effect(...))`` declaration plus its
tests. Registration checks units (each term's declared coefficient unit x the
units of its expression = N), ranges, the region, character and term roles
(members of the enumerations in :mod:`afmid.physics.effect_tags`), and that the readout
inverts the coefficients at the default parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from afmid.physics.contact_effects import CONTACT_DAMPING, STANDARD_LINEAR_SOLID
from afmid.physics.liquid_effects import DOUBLE_LAYER
from afmid.physics.effect_types import (BOLTZMANN, CHECK_CONTEXT, CONTEXT_UNITS, EFFECTS, EPSILON_0, MODELS, NEWTON,
                                        Effect, Model, Parameter, Quantity, StateGate, Term, coefficient_unit,
                                        quantity_range, term_unit)
from afmid.physics.effect_tags import Character, Region, Role
from afmid.physics.tips import SPHERE, TipGeometry, shaped_effect

__all__ = ["BOLTZMANN", "CHECK_CONTEXT", "CONTEXT_UNITS", "EFFECTS", "EPSILON_0", "MODELS", "NEWTON", "Effect",
           "ForceLaw", "Model", "Parameter", "Quantity", "StateGate", "Term", "build_force_law", "coefficient_unit",
           "effect_parameter_names", "quantity_range", "term_unit"]


# =========================================================================== effects
#: Hamaker constants of condensed phases: 0.4-5e-19 J across vacuum or air (metals the largest), down to ~1e-21 J
#: across water (Israelachvili, Intermolecular and Surface Forces, 3rd ed., ch. 13). Beyond these bounds a read-out
#: is a calibration error (a spring constant 100x off gave 5e-18 or 5e-22 J, both inside the old
#: [1e-22, 1e-17]).
_HAMAKER = Parameter("hamaker", "J", 1.0e-19, 1e-21, 1e-18,
                     "Hamaker constant H (tip-sample; 1e-21 J: weak, across water; 1e-18 J: twice a metal's)")
_E_STAR = Parameter("E_star", "Pa", 1.0e9, 1e2, 1e12,
                    "reduced (effective) Young's modulus E* (100 Pa: the softest cells and hydrogels; 1e12 Pa: diamond)")


def _dmt_like_readout(adhesion_per_energy: float):
    """Read-out shared by DMT and JKR.

    The adhesion comes from its own term when the library has one (JKR, the
    seed tables' bridging term); in the DMT effect it is the van der Waals
    force at contact, H R / (6 a0^2), tied to the tail.
    """

    def readout(c: Mapping[str, float], ctx: Mapping[str, float]) -> dict[str, float]:
        R = ctx["R"]
        if "adhesion" in c:
            adhesion = -c["adhesion"]
        else:
            adhesion = -c["vdw"] / ctx["a0"] ** 2
        return {
            "hamaker": -6.0 * c["vdw"] / R,
            "E_star": 3.0 * c["hertz"] / (4.0 * math.sqrt(R)),
            "adhesion_force": adhesion,
            "surface_energy": adhesion / (adhesion_per_energy * math.pi * R),
        }

    return readout


#: The adhesion force on an AFM tip: up to ~1 uN for sharp tips, ~10-100 uN for 10 um colloidal probes.
_ADHESION_FORCE_MAX = 1e-4  # N
#: gamma, as the JKR parameter (adhesion energy per area; water 0.072, metals up to a few J/m^2).
_SURFACE_ENERGY_RANGE = (1e-4, 5.0)  # J/m^2
#: The largest adhesion per metre of tip radius, N/m: 4 pi R gamma (DMT) at the largest surface energy above
#: (JKR's 3 pi R gamma is smaller). An 8 nm tip: 0.5 uN; a reading of 33 uN there is a calibration error.
_ADHESION_PER_RADIUS_MAX = 4.0 * math.pi * _SURFACE_ENERGY_RANGE[1]
#: A meniscus: 4 pi R gamma_w cos(theta) at the largest surface tension the capillary effect accepts (1 N/m).
_MENISCUS_PER_RADIUS_MAX = 4.0 * math.pi * 1.0

_CONTACT_QUANTITIES = (
    Quantity("hamaker", "J", "Hamaker constant from the van der Waals tail"),
    Quantity("E_star", "Pa", "reduced Young's modulus from the Hertz term"),
    Quantity("adhesion_force", "N", "adhesion force in contact (positive number)", 0.0, _ADHESION_FORCE_MAX,
             _ADHESION_PER_RADIUS_MAX),
)

EFFECTS.register(
    Effect(
        name="dmt",
        title="Derjaguin-Muller-Toporov contact with van der Waals attraction",
        formula="F = -H R / (6 z^2) for z > a0;  4/3 E* sqrt(R) delta^1.5 - H R / (6 a0^2) for z <= a0",
        parameters=(_HAMAKER, _E_STAR),
        terms=(
            # One term for the tail and the DMT adhesion: the force is continuous at contact, which
            # ties the adhesion to the Hamaker constant and makes the contact point identifiable.
            Term("vdw", "max(z, a0)^-2", lambda p: -p["hamaker"] * p["R"] / 6.0,
                 "van der Waals sphere-plane, saturating at contact (DMT adhesion H R / 6 a0^2)",
                 coefficient_unit="J*m"),
            Term("hertz", "[z <= a0] * delta^1.5", lambda p: 4.0 / 3.0 * p["E_star"] * math.sqrt(p["R"]), "Hertz",
                 roles=(Role.ELASTIC_CONTACT,), coefficient_unit="Pa*m^0.5"),
        ),
        # The seed tables (library presets) fit the in-contact adhesion as a term of its own ("bridging",
        # C3 / a0^2 of seed eq. 1); its coefficient is the adhesion force, read out instead of H R / (6 a0^2).
        readout_only_terms=(
            Term("adhesion", "[z <= a0]", lambda p: -p["hamaker"] * p["R"] / (6.0 * p["a0"] ** 2),
                 "constant adhesion in contact, -H R / (6 a0^2) in DMT (fitted on its own by the seed tables)",
                 roles=(Role.CONTACT_ONLY, Role.CONTACT_ADHESION), coefficient_unit="N"),
        ),
        quantities=_CONTACT_QUANTITIES
        + (Quantity("surface_energy", "J/m^2", "gamma from the adhesion F_a = 4 pi R gamma", *_SURFACE_ENERGY_RANGE),),
        readout=_dmt_like_readout(4.0),
        references=(
            "Derjaguin, Muller, Toporov, J. Colloid Interface Sci. 53, 314 (1975)",
            "Chandrashekar et al., Nanoscale Adv. (2022), supplement eq. 1",
        ),
        region=Region.CONTACT,
    )
)


def _lj_readout(c: Mapping[str, float], ctx: Mapping[str, float]) -> dict[str, float]:
    hamaker = -6.0 * c["attraction"] / ctx["R"]
    ratio = 180.0 * c["repulsion"] / (hamaker * ctx["R"]) if hamaker > 0 else float("nan")
    return {"hamaker": hamaker, "sigma": ratio ** (1.0 / 6.0) if ratio > 0 else float("nan")}


EFFECTS.register(
    Effect(
        name="lennard_jones",
        title="Lennard-Jones sphere-plane interaction (smooth, no contact mechanics)",
        formula="F = -H R / (6 z^2) + H R sigma^6 / (180 z^8)",
        parameters=(
            _HAMAKER,
            Parameter("sigma", "m", 0.30e-9, 0.05e-9, 2e-9, "LJ length; force minimum at sigma / 30^(1/6)"),
        ),
        terms=(
            Term("attraction", "z^-2", lambda p: -p["hamaker"] * p["R"] / 6.0, coefficient_unit="J*m"),
            Term("repulsion", "z^-8", lambda p: p["hamaker"] * p["R"] * p["sigma"] ** 6 / 180.0,
                 coefficient_unit="J*m^7"),
        ),
        quantities=(
            Quantity("hamaker", "J", "Hamaker constant"),
            Quantity("sigma", "m", "Lennard-Jones length"),
        ),
        readout=_lj_readout,
        references=(
            "Rutzel, Lee, Raman, Proc. R. Soc. A 459, 1925 (2003)",
            "Chandrashekar et al., Nanoscale Adv. (2022), supplement eq. 2",
        ),
        region=Region.NEAR,
    )
)

EFFECTS.register(
    Effect(
        name="jkr",
        title="JKR-like contact: Hertz with a larger adhesion 3 pi R gamma, optional pull-off hysteresis",
        formula=(
            "F = -H R / (6 z^2) out of contact;  4/3 E* sqrt(R) delta^1.5 - 3 pi R gamma in contact; "
            "contact forms at z = a0 and breaks at z = a0 + neck_length"
        ),
        parameters=(
            _HAMAKER,
            _E_STAR,
            Parameter("surface_energy", "J/m^2", 0.05, *_SURFACE_ENERGY_RANGE, "gamma; adhesion F_a = 3 pi R gamma"),
            Parameter(
                "neck_length", "m", 0.0, 0.0, 20e-9, "extra separation at which the neck breaks (0: no hysteresis)", True
            ),
        ),
        terms=(
            Term("vdw", "[not jkr_contact] * z^-2", lambda p: -p["hamaker"] * p["R"] / 6.0,
                 roles=(Role.ATTRACTIVE_TAIL,), coefficient_unit="J*m"),
            Term("hertz", "[jkr_contact] * delta^1.5", lambda p: 4.0 / 3.0 * p["E_star"] * math.sqrt(p["R"]),
                 roles=(Role.ELASTIC_CONTACT,), coefficient_unit="Pa*m^0.5"),
            Term("adhesion", "[jkr_contact]", lambda p: -3.0 * math.pi * p["R"] * p["surface_energy"],
                 roles=(Role.CONTACT_ONLY, Role.CONTACT_ADHESION), coefficient_unit="N"),
        ),
        quantities=_CONTACT_QUANTITIES
        + (Quantity("surface_energy", "J/m^2", "gamma from the adhesion F_a = 3 pi R gamma"),),
        readout=_dmt_like_readout(3.0),
        states=(StateGate("jkr_contact", on="z <= a0", off="z > a0 + neck_length", forms_at_contact=True),),
        references=(
            "Johnson, Kendall, Roberts, Proc. R. Soc. A 324, 301 (1971)",
            "Chandrashekar et al., Nanoscale Adv. (2022), supplement eq. 5",
        ),
        character=Character.HYSTERETIC,
        region=Region.CONTACT,
    )
)

EFFECTS.register(
    Effect(
        name="viscoelastic",
        title="Kelvin-Voigt viscoelastic damping in contact",
        formula="F = eta sqrt(R delta) d(delta)/dt  for z <= a0",
        parameters=(Parameter("viscosity", "Pa*s", 100.0, 0.0, 1e5, "sample viscosity eta"),),
        terms=(Term("kelvin_voigt", "delta^0.5 * deltadot", lambda p: p["viscosity"] * math.sqrt(p["R"]),
                    roles=(Role.CONTACT_ONLY,), coefficient_unit="Pa*s*m^0.5"),),
        quantities=(Quantity("viscosity", "Pa*s", "sample viscosity eta"),),
        readout=lambda c, ctx: {"viscosity": c["kelvin_voigt"] / math.sqrt(ctx["R"])},
        references=(
            "Garcia, San Paulo, Phys. Rev. B 60, 4961 (1999)",
            "Chandrashekar et al., Nanoscale Adv. (2022), supplement eq. 3",
        ),
        character=Character.DISSIPATIVE,
        region=Region.CONTACT,
    )
)

EFFECTS.register(
    Effect(
        name="exponential_damping",
        title="Gotsmann-type surface damping decaying exponentially with separation",
        formula="F = -gamma0 exp(-z / lambda) dz/dt",
        parameters=(
            Parameter("damping_coefficient", "kg/s", 2e-6, 0.0, 1e-2, "gamma0, damping at z = 0"),
            Parameter("damping_length", "m", 1.0e-9, 0.05e-9, 50e-9, "decay length lambda", True),
        ),
        terms=(Term("surface_damping", "exp(-z / damping_length) * zdot", lambda p: -p["damping_coefficient"],
                    coefficient_unit="kg/s"),),
        quantities=(Quantity("damping_coefficient", "kg/s", "gamma0"),),
        readout=lambda c, ctx: {"damping_coefficient": -c["surface_damping"]},
        references=(
            "Gotsmann, Seidel, Anczykowski, Fuchs, Phys. Rev. B 60, 11051 (1999)",
            "Chandrashekar et al., Nanoscale Adv. (2022), supplement eq. 4",
        ),
        character=Character.DISSIPATIVE,
        region=Region.NEAR,
    )
)

EFFECTS.register(
    Effect(
        name="electrostatic",
        title="Electrostatic sphere-plane attraction (tip-sample potential difference V)",
        formula="F = -pi eps0 R V^2 / z  (z clipped at a0)",
        parameters=(Parameter("voltage", "V", 1.0, 0.0, 100.0, "tip-sample potential difference"),),
        terms=(Term("coulomb", "max(z, a0)^-1", lambda p: -math.pi * EPSILON_0 * p["R"] * p["voltage"] ** 2,
                    coefficient_unit="J"),),
        quantities=(Quantity("voltage", "V", "magnitude of the tip-sample potential difference"),),
        readout=lambda c, ctx: {
            "voltage": math.sqrt(-c["coulomb"] / (math.pi * EPSILON_0 * ctx["R"])) if c["coulomb"] < 0 else float("nan")
        },
        references=("Hudlet, Saint Jean, Guthmann, Berger, Eur. Phys. J. B 2, 5 (1998)",),
        region=Region.LONG_RANGE,
        media=("air",),  # an electrolyte screens a static bias within a few Debye lengths: see double_layer
    )
)

EFFECTS.register(
    Effect(
        name="capillary",
        title="Capillary water meniscus: forms at contact, ruptures on retraction",
        formula="F = -4 pi R gamma_w cos(theta) while the meniscus exists (formed at z <= a0, broken at z > a0 + d_rupture)",
        parameters=(
            Parameter("surface_tension", "N/m", 0.072, 0.0, 1.0, "liquid surface tension gamma_w"),
            Parameter("contact_angle", "rad", 0.5, 0.0, math.pi / 2 - 1e-6, "liquid contact angle theta"),
            Parameter("rupture_distance", "m", 1.0e-9, 0.0, 50e-9, "extra separation at which it ruptures", True),
        ),
        terms=(
            Term(
                "meniscus",
                "[meniscus]",
                lambda p: -4.0 * math.pi * p["R"] * p["surface_tension"] * math.cos(p["contact_angle"]),
                coefficient_unit="N",
            ),
        ),
        quantities=(Quantity("capillary_force", "N", "meniscus force (positive number)", 0.0, _ADHESION_FORCE_MAX,
                             _MENISCUS_PER_RADIUS_MAX),),
        readout=lambda c, ctx: {"capillary_force": -c["meniscus"]},
        states=(StateGate("meniscus", on="z <= a0", off="z > a0 + rupture_distance", forms_at_contact=True),),
        references=("Zitzler, Herminghaus, Mugele, Phys. Rev. B 66, 155436 (2002)",),
        character=Character.HYSTERETIC,
        region=Region.NEAR,
        media=("air",),  # under liquid there is no meniscus to form
    )
)

#: In liquid, hydration (solvation) lengths are searched up to here, m: measured hydration forces decay over
#: 0.2-1.1 nm (Israelachvili ch. 15); a longer exponential repulsion in an electrolyte is the double layer
#: (afmid.physics.liquid_effects.DEBYE_SEARCH_MIN: the searches overlap over [1, 1.5] nm). In air there is no
#: double layer to take it for, and the search keeps the valid range (an outside-catalog exponential is
#: recognised by the hydration shape's impossible sign there, afmid.diagnosis.diagnose).
HYDRATION_SEARCH_MAX = 1.5e-9

EFFECTS.register(
    Effect(
        name="hydration",
        title="Short-range exponential (hydration/solvation) repulsion",
        formula="F = F_h exp(-(z - a0) / lambda_h)",
        parameters=(
            Parameter("hydration_force", "N", 1.0e-9, 0.0, 1e-6, "repulsion at z = a0"),
            Parameter("hydration_length", "m", 0.3e-9, 0.02e-9, 10e-9, "decay length lambda_h (in liquid searched "
                      "up to 1.5 nm: a longer exponential repulsion there is the double layer)", True,
                      search=(("liquid", 0.02e-9, HYDRATION_SEARCH_MAX),)),
        ),
        terms=(
            Term(
                "hydration",
                "exp(-z / hydration_length)",
                lambda p: p["hydration_force"] * math.exp(p["a0"] / p["hydration_length"]),
                coefficient_unit="N",
            ),
        ),
        quantities=(Quantity("hydration_force", "N", "repulsion at z = a0"),),
        readout=lambda c, ctx: {"hydration_force": c["hydration"] * math.exp(-ctx["a0"] / ctx["hydration_length"])},
        references=("Israelachvili, Intermolecular and Surface Forces, 3rd ed., ch. 15 (2011)",),
        region=Region.NEAR,
    )
)

EFFECTS.register(
    Effect(
        name="squeeze_film",
        title="Squeeze-film (Reynolds) damping of the fluid between tip and sample",
        formula="F = -6 pi eta_f R^2 (dz/dt) / z  (z clipped at a0)",
        parameters=(Parameter("fluid_viscosity", "Pa*s", 1.8e-5, 0.0, 10.0, "viscosity of the medium eta_f"),),
        terms=(
            Term("squeeze", "zdot * max(z, a0)^-1", lambda p: -6.0 * math.pi * p["fluid_viscosity"] * p["R"] ** 2,
                 coefficient_unit="Pa*s*m^2"),
        ),
        quantities=(Quantity("fluid_viscosity", "Pa*s", "viscosity of the medium"),),
        readout=lambda c, ctx: {"fluid_viscosity": -c["squeeze"] / (6.0 * math.pi * ctx["R"] ** 2)},
        references=("Reynolds lubrication, sphere-plane: Chan, Horn, J. Chem. Phys. 83, 5311 (1985)",),
        character=Character.DISSIPATIVE,
        region=Region.NEAR,
    )
)


EFFECTS.register(CONTACT_DAMPING)
EFFECTS.register(DOUBLE_LAYER)
EFFECTS.register(STANDARD_LINEAR_SOLID)


# =========================================================================== models
def _jkr_neck_length(p: Mapping[str, float]) -> dict[str, float]:
    """JKR pull-off under displacement control: delta_c = -3 a_c^2 / R with a_c^3 = pi gamma R^2 / (4 E*)."""
    a_c = (math.pi * p["surface_energy"] * p["R"] ** 2 / (4.0 * p["E_star"])) ** (1.0 / 3.0)
    return {"neck_length": 3.0 * a_c**2 / p["R"]}


_SEED = "Chandrashekar et al., Nanoscale Adv. (2022), supplement"
MODELS.register(Model("dmt", "DMT (seed eq. 1)", ("dmt",), (_SEED + " eq. 1",)))
MODELS.register(Model("lennard_jones", "Lennard-Jones (seed eq. 2)", ("lennard_jones",), (_SEED + " eq. 2",)))
MODELS.register(
    Model("dmt_viscoelastic", "DMT + Kelvin-Voigt viscoelasticity (seed eq. 3)", ("dmt", "viscoelastic"), (_SEED + " eq. 3",))
)
MODELS.register(
    Model(
        "dmt_exponential_damping",
        "DMT + exponential surface damping (seed eq. 4)",
        ("dmt", "exponential_damping"),
        (_SEED + " eq. 4",),
    )
)
MODELS.register(Model("jkr", "JKR adhesion, no hysteresis (seed eq. 5)", ("jkr",), (_SEED + " eq. 5",)))
MODELS.register(
    Model(
        "jkr_hysteretic",
        "JKR with pull-off hysteresis: the neck breaks at the JKR pull-off point",
        ("jkr",),
        ("Johnson, Kendall, Roberts, Proc. R. Soc. A 324, 301 (1971)",),
        derived_defaults=_jkr_neck_length,
    )
)


# =========================================================================== composition
@dataclass(frozen=True)
class ForceLaw:
    """A concrete force law: effects with parameter values, ready to evaluate.

    ``terms`` are (effect name, term label, expression, coefficient) in SI; the
    force on the tip (repulsive positive) is ``sum(coefficient * expression)``.
    """

    effects: tuple[str, ...]
    parameters: Mapping[str, float]  # all effect parameters plus context R, a0
    terms: tuple[tuple[str, str, str, float], ...]
    states: tuple[StateGate, ...]

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.states)


def effect_parameter_names(effect_names: tuple[str, ...] | list[str]) -> dict[str, Parameter]:
    """All parameters of the given effects (shared names such as hamaker merged)."""
    out: dict[str, Parameter] = {}
    for name in effect_names:
        for p in EFFECTS.get(name).parameters:
            out.setdefault(p.name, p)
    return out


def build_force_law(
    effect_names: tuple[str, ...] | list[str],
    parameters: Mapping[str, float],
    context: Mapping[str, float],
    derived_defaults: Callable[[Mapping[str, float]], dict[str, float]] | None = None,
    tip: TipGeometry = SPHERE,
) -> ForceLaw:
    """Combine effects with parameter values (defaults filled in; unknown names are errors); the elastic
    contact terms follow the ``tip``'s contact law (:mod:`afmid.physics.tips`).

    Raises ValueError with a readable message for unknown or out-of-range parameters.
    """
    declared = effect_parameter_names(effect_names)
    unknown = set(parameters) - set(declared)
    if unknown:
        allowed = ", ".join(sorted(declared))
        from afmid.registry import closest

        hints = [f"{u!r} (did you mean {closest(u, list(declared))!r}?)" if closest(u, list(declared)) else repr(u)
                 for u in sorted(unknown)]
        raise ValueError(f"unknown parameter(s) {', '.join(hints)} for effects {list(effect_names)}; allowed: {allowed}")
    values = {name: p.default for name, p in declared.items()}
    values.update(context)
    if derived_defaults is not None:
        values.update({k: v for k, v in derived_defaults({**values, **parameters}).items() if k not in parameters})
    values.update(parameters)
    for name, p in declared.items():
        v = values[name]
        if not (p.low <= v <= p.high):
            raise ValueError(f"parameter {name} = {v!r} outside its valid range [{p.low}, {p.high}] {p.unit}")
    terms = []
    states: list[StateGate] = []
    for name in effect_names:
        effect = shaped_effect(EFFECTS.get(name), tip)
        states.extend(s for s in effect.states if s not in states)
        for term in effect.terms:
            terms.append((name, term.label, term.expression, float(term.coefficient(values))))
    return ForceLaw(tuple(effect_names), values, tuple(terms), tuple(states))


def parameter_unit(name: str, effect: str | None = None) -> str:
    """The declared SI unit of parameter ``name`` (of ``effect`` when given and declared there, else of the first
    effect in the catalog that declares it); "" for a name no effect declares. A shape parameter is not always a
    length (``relaxation_time`` is in s): the unit comes from the declaration, never from the parameter's role."""
    owners = ([EFFECTS.get(effect)] if effect is not None and effect in EFFECTS else []) + list(EFFECTS)
    return next((p.unit for e in owners for p in e.parameters if p.name == name), "")

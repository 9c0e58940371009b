"""Tip shapes: the contact law an elastic contact follows for each tip geometry, declared once.

``cantilever.tip_shape`` (``sphere`` by default, ``cone``, ``pyramid``, ``flat_punch``) and
``cantilever.tip_half_angle`` (rad, for cone and pyramid) select a :class:`TipShape`. Every elastic
contact law here has the form ``F = E* g delta^n`` (N, repulsive positive; delta = a0 - z, m): a
geometric factor ``g`` (m^(2-n)) times a power of the indentation. The effects declare their elastic
term (role ``ELASTIC_CONTACT``) for a sphere, ``4/3 E* sqrt(R) delta^1.5``; :func:`shaped_effect`
rewrites that term -- its power of delta, its coefficient and the read-out of E* from it -- for
another shape, so the simulator, the fit's library, the read-out and the diagnosis use one law.

What follows the shape and what does not (said in each shaped effect's formula too):

- ``dmt``, ``jkr``: the elastic term. Their van der Waals tail and adhesion keep the sphere-plane
  form with ``R`` = ``cantilever.tip_radius`` (the radius of the apex, which is what faces the
  sample at contact), and JKR's 3 pi R gamma adhesion stays the sphere's.
- ``viscoelastic`` (Kelvin-Voigt, eta sqrt(R delta) d(delta)/dt) is left as declared: its factor
  is the sphere's contact radius (for a flat punch it would be the constant R, the same column as
  ``contact_damping``); a shape-dependent dashpot is not offered yet.

Conventions: E* is the reduced modulus, 1/E* = (1 - nu_s^2)/E_s + (1 - nu_t^2)/E_t (a rigid tip:
E* = E_s / (1 - nu_s^2)), as everywhere in afmid.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

from afmid.errors import DefinitionError
from afmid.physics.effect_tags import Role
from afmid.physics.effect_types import EFFECTS, Effect, Term, validate_effect
from afmid.registry import Registry, unknown_name_message

#: The sphere's law as the effects declare it (the text a shape's law replaces).
SPHERE_POWER = "delta^1.5"


@dataclass(frozen=True)
class TipShape:
    """One tip geometry's elastic contact law ``F = E* factor(R, half_angle) delta^power``."""

    name: str
    title: str
    contact_law: str  # the force, as text
    power_text: str  # the power of delta in the term language ("delta^2", "delta")
    factor: Callable[[float, float], float]  # (R in m, half angle in rad) -> geometric factor, m^(2 - n)
    factor_text: str
    coefficient_unit: str  # of E* x factor: N / m^n
    readout: str  # E* from the term's coefficient c, as text
    references: tuple[str, ...]
    needs_half_angle: bool = False
    notes: str = ""


def _validate_shape(shape: TipShape) -> None:
    if not shape.power_text.startswith("delta"):
        raise DefinitionError(f"power_text must be a power of delta, got {shape.power_text!r}")
    value = shape.factor(10e-9, 0.3)
    if not (math.isfinite(value) and value > 0):
        raise DefinitionError(f"factor must be positive and finite, got {value!r}")


TIP_SHAPES: Registry[TipShape] = Registry("tip shape", _validate_shape)

TIP_SHAPES.register(TipShape(
    "sphere", "Sphere (paraboloid) of radius R: Hertz",
    "F = 4/3 E* sqrt(R) delta^1.5", SPHERE_POWER, lambda R, _a: 4.0 / 3.0 * math.sqrt(R), "4/3 sqrt(R)",
    "Pa*m^0.5", "E* = 3 c / (4 sqrt(R))",
    ("Hertz, J. reine angew. Math. 92, 156 (1882)", "Johnson, Contact Mechanics, Cambridge (1985), ch. 4"),
    notes="valid for delta << R (the paraboloid approximation of the sphere)"))
TIP_SHAPES.register(TipShape(
    "cone", "Cone of half-opening angle alpha: Sneddon",
    "F = 2/pi E* tan(alpha) delta^2", "delta^2", lambda _R, a: 2.0 / math.pi * math.tan(a), "2 tan(alpha) / pi",
    "Pa", "E* = pi c / (2 tan(alpha))",
    ("Sneddon, Int. J. Eng. Sci. 3, 47 (1965)", "Love, Q. J. Math. 10, 161 (1939)"),
    needs_half_angle=True, notes="a sharp cone; the apex rounding (tip_radius) is ignored in contact"))
TIP_SHAPES.register(TipShape(
    "pyramid", "Regular four-sided pyramid of face half-angle alpha: Bilodeau",
    "F = 0.7453 E* tan(alpha) delta^2", "delta^2", lambda _R, a: 0.7453 * math.tan(a), "0.7453 tan(alpha)",
    "Pa", "E* = c / (0.7453 tan(alpha))",
    ("Bilodeau, J. Appl. Mech. 59, 519 (1992)",
     "Rico, Roca-Cusachs, Gavara, Farre, Rotger, Navajas, Phys. Rev. E 72, 021914 (2005): F = 0.7453 E tan(alpha) "
     "delta^2 / (1 - nu^2)"),
    needs_half_angle=True,
    notes="alpha is the angle between a face and the axis; with the 1/sqrt(2) = 0.7071 prefactor also in use "
          "(a cone of equal face angle, approximately) E* reads 5 % higher"))
TIP_SHAPES.register(TipShape(
    "flat_punch", "Flat-ended cylinder (punch) of radius R: Boussinesq",
    "F = 2 E* R delta", "delta", lambda R, _a: 2.0 * R, "2 R", "Pa*m", "E* = c / (2 R)",
    ("Boussinesq (1885); Sneddon, Int. J. Eng. Sci. 3, 47 (1965)", "Johnson, Contact Mechanics (1985), ch. 3"),
    notes="R is cantilever.tip_radius, the punch radius"))


@dataclass(frozen=True)
class TipGeometry:
    """The configured tip: a shape name and, for cone and pyramid, the half-opening angle (rad)."""

    shape: str = "sphere"
    half_angle: float | None = None

    @property
    def declaration(self) -> TipShape:
        return TIP_SHAPES.get(self.shape)

    def factor(self, R: float) -> float:
        """The geometric factor g of F = E* g delta^n (m^(2-n)) at tip radius ``R`` (m)."""
        return self.declaration.factor(R, self.half_angle if self.half_angle is not None else math.nan)

    def describe(self) -> str:
        angle = f", half angle {math.degrees(self.half_angle):.1f} deg" if self.half_angle is not None else ""
        return f"{self.shape}{angle}"


SPHERE = TipGeometry()


def check_tip(shape: str, half_angle: float | None) -> None:
    """Raise ValueError ("cantilever.<key>: ...", one line) unless the shape is known and its half angle fits."""
    if shape not in TIP_SHAPES:
        raise ValueError("cantilever.tip_shape: " + unknown_name_message("tip shape", shape, TIP_SHAPES.names()))
    declared = TIP_SHAPES.get(shape)
    if declared.needs_half_angle:
        if half_angle is None:
            raise ValueError(f"cantilever.tip_half_angle: required for tip_shape {shape!r} (the half-opening "
                             "angle in rad, in (0, pi/2), e.g. 0.3 for 17 deg)")
        if not (0.0 < half_angle < math.pi / 2):
            raise ValueError(f"cantilever.tip_half_angle: must be in (0, pi/2) rad, got {half_angle:g}")
    elif half_angle is not None:
        raise ValueError(f"cantilever.tip_half_angle: a {shape} has no half angle (given {half_angle:g}); "
                         "remove the key or set tip_shape to cone or pyramid")


def tip_geometry(cantilever) -> TipGeometry:
    """The tip of a ``CantileverConfig`` (a sphere when the config has no cantilever section)."""
    if cantilever is None:
        return SPHERE
    return TipGeometry(getattr(cantilever, "tip_shape", "sphere"), getattr(cantilever, "tip_half_angle", None))


def shaped_effect(effect: Effect, tip: TipGeometry) -> Effect:
    """The effect with its elastic-contact term following the tip's contact law (the effect itself for a
    sphere, or when it has no elastic term). The read-out of E* divides the term's coefficient by the
    shape's factor; everything else reads out as declared."""
    if tip.shape == "sphere":
        return effect
    return _shaped(effect.name, effect, tip)


@lru_cache(maxsize=64)
def _shaped(_name: str, effect: Effect, tip: TipGeometry) -> Effect:
    shape = tip.declaration
    elastic = [t.label for t in effect.terms if Role.ELASTIC_CONTACT in t.roles]
    if not elastic:
        return effect
    if len(elastic) != 1 or "E_star" not in {p.name for p in effect.parameters}:
        raise DefinitionError(f"effect {effect.name}: a tip shape rewrites one elastic term with parameter E_star")
    label = elastic[0]

    def rewrite(term: Term) -> Term:
        if term.label != label:
            return term
        if term.expression.count(SPHERE_POWER) != 1:
            raise DefinitionError(f"effect {effect.name}: elastic term {term.expression!r} lacks {SPHERE_POWER}")
        return dataclasses.replace(
            term, expression=term.expression.replace(SPHERE_POWER, shape.power_text),
            coefficient=lambda p: tip.factor(p["R"]) * p["E_star"],
            coefficient_unit=shape.coefficient_unit, doc=f"{shape.title}: {shape.contact_law}")

    def readout(c, ctx):
        out = effect.readout(c, ctx)
        out["E_star"] = c[label] / tip.factor(ctx["R"])
        return out

    shaped = dataclasses.replace(
        effect, terms=tuple(rewrite(t) for t in effect.terms), readout=readout,
        formula=f"{effect.formula}  [{tip.describe()} tip: the elastic term is {shape.contact_law}]",
        references=effect.references + shape.references)
    validate_effect(shaped)
    return shaped


def effect_for(name: str, tip: TipGeometry = SPHERE) -> Effect:
    """The registered effect ``name`` as it acts with ``tip``."""
    return shaped_effect(EFFECTS.get(name), tip)

"""Contact effects declared outside :mod:`afmid.physics.effects` (which is near the size limit): plain
declarations, registered there, in catalog order, by ``EFFECTS.register``.

Conventions as in :mod:`afmid.physics.effects`: force on the tip in N, positive = repulsive;
``delta = a0 - z`` and ``deltadot = -zdot`` in contact (``z <= a0``), both 0 outside.
"""

from __future__ import annotations

import math

from afmid.physics.effect_tags import Character, Region, Role
from afmid.physics.effect_types import Effect, Parameter, Quantity, RelaxingState, Term

#: Linear (Newtonian dashpot) damping switched on in contact. Its force follows the indentation rate alone,
#: while Kelvin-Voigt (``viscoelastic``) scales it with the contact radius sqrt(R delta): the two columns
#: differ by the factor sqrt(R delta), which sweeps from 0 at the contact point to its maximum at the deepest
#: indentation, so a trace that reaches a few tenths of a nm into the sample tells them apart.
CONTACT_DAMPING = Effect(
    name="contact_damping",
    title="Linear viscous damping in contact (a dashpot switched on at contact)",
    formula="F = c_d d(delta)/dt = -c_d dz/dt  for z <= a0 (0 out of contact)",
    parameters=(
        Parameter("contact_damping", "kg/s", 5.0e-7, 0.0, 1e-2,
                  "c_d, damping coefficient of the contact (the cantilever's own m w0 / Q is ~1e-7 kg/s)"),
    ),
    terms=(
        Term("contact_damping", "deltadot", lambda p: p["contact_damping"],
             "linear dashpot in contact: opposes the indentation rate (repulsive while indenting)",
             roles=(Role.CONTACT_ONLY,), coefficient_unit="kg/s"),
    ),
    quantities=(Quantity("contact_damping", "kg/s", "c_d, linear contact damping coefficient"),),
    readout=lambda c, ctx: {"contact_damping": c["contact_damping"]},
    references=(
        "Tamayo, Garcia, Langmuir 12, 4430 (1996): Voigt contact with a linear dashpot in tapping mode",
        "Garcia, Amplitude Modulation Atomic Force Microscopy, Wiley-VCH (2010), ch. 4",
    ),
    character=Character.DISSIPATIVE,
    region=Region.CONTACT,
    notes="Separable from Kelvin-Voigt (viscoelastic: eta sqrt(R delta) d(delta)/dt) by its flat dependence on "
          "the indentation.",
)


def _relaxing_coefficient(p) -> float:
    """4/3 sqrt(R) (E_0 - E_inf), Pa m^0.5: the Hertz factor of the modulus that relaxes."""
    return 4.0 / 3.0 * math.sqrt(p["R"]) * p["relaxing_modulus"]


#: A standard linear solid (Zener: a spring E_inf in parallel with a Maxwell arm E_0 - E_inf, tau) under a
#: spherical tip. Its relaxation modulus E(t) = E_inf + (E_0 - E_inf) e^(-t / tau) in the Lee-Radok hereditary
#: integral over the Hertz contact gives F = 4/3 sqrt(R) [E_inf delta^1.5 + (E_0 - E_inf) integral e^(-(t - s) /
#: tau) d(delta^1.5)(s)]. The first part is DMT's Hertz term (its E* reads out as the relaxed modulus E_inf); this
#: effect adds the second, written with the lagging state q (d q / dt = (delta^1.5 / R^1.5 - q) / tau, carried
#: through the period like the meniscus): integral e^(-(t - s)/tau) d(delta^1.5) = delta^1.5 - R^1.5 q. Given tau
#: the force is linear in E_0 - E_inf; tau is searched like a decay length. Why this name, not "zener": the
#: textbook name of the model (Findley; Tschoegl), which AFM viscoelasticity papers use; "Zener" is its eponym.
STANDARD_LINEAR_SOLID = Effect(
    name="standard_linear_solid",
    title="Standard linear solid (Zener) contact: a Hertz contact whose modulus relaxes from E_0 to E_inf with tau",
    formula="F = 4/3 sqrt(R) (E_0 - E_inf) integral_0^t exp(-(t - s) / tau) d(delta^1.5)/ds ds  for z <= a0 (0 out "
            "of contact), added to DMT's Hertz term 4/3 E_inf sqrt(R) delta^1.5 (E* = E_inf, the relaxed modulus); "
            "the integral is delta^1.5 - R^1.5 q with d q/dt = (delta^1.5 / R^1.5 - q) / tau",
    parameters=(
        Parameter("relaxing_modulus", "Pa", 1.0e9, 0.0, 1e12,
                  "E_0 - E_inf, the part of the reduced modulus that relaxes (instantaneous E_0 = E* + this)"),
        Parameter("relaxation_time", "s", 1.0e-6, 1e-9, 1e-3,
                  "tau, relaxation time of the modulus at constant indentation (s)", True),
    ),
    terms=(
        Term("relaxation", "[z <= a0] * (delta^1.5 - R^1.5 * sls_lag)", _relaxing_coefficient,
             "the relaxing part of the Lee-Radok hereditary integral: the Hertz force of E_0 - E_inf on the "
             "indentation's recent increase (delta^1.5 minus its lagging value)",
             roles=(Role.CONTACT_ONLY,), coefficient_unit="Pa*m^0.5"),
    ),
    quantities=(Quantity("relaxing_modulus", "Pa",
                         "E_0 - E_inf; the relaxed modulus E_inf is DMT's E*, the instantaneous E_0 their sum"),),
    readout=lambda c, ctx: {"relaxing_modulus": 3.0 * c["relaxation"] / (4.0 * math.sqrt(ctx["R"]))},
    states=(RelaxingState("sls_lag", "delta^1.5 * R^-1.5", "relaxation_time"),),
    references=(
        "Lee, Radok, J. Appl. Mech. 27, 438 (1960): the hereditary integral over the Hertz contact (contact growing)",
        "Ting, J. Appl. Mech. 33, 845 (1966): the contact of a viscoelastic solid that shrinks (unloading)",
        "Garcia, Chem. Soc. Rev. 49, 5850 (2020): nanomechanical mapping of soft materials, the standard linear "
        "solid and its relaxation time in AFM",
        "Lopez-Guerra, Solares, Beilstein J. Nanotechnol. 5, 2149 (2014): spring-dashpot models in tapping mode",
    ),
    character=Character.DISSIPATIVE,
    region=Region.CONTACT,
    notes="Exact (Lee-Radok) while the contact grows; on withdrawal the same hereditary integral is continued "
          "(Fung's quasi-linear viscoelasticity): the surface is taken to follow the tip down to delta = 0, so the "
          "relaxing part pulls (4/3 sqrt(R) (E_0 - E_inf) R^1.5 q at the contact edge) where Ting's solution for a "
          "shrinking, non-adhesive contact would release the tip earlier; it is cut off at z = a0. Valid for small "
          "strains (delta << R) and a modulus ratio E_0 / E_inf not much above a few. tau much shorter than the "
          "contact time: the relaxed DMT contact (plus a Kelvin-Voigt-like 2 (E_0 - E_inf) tau sqrt(R delta) "
          "d(delta)/dt); much longer than the period: a stiffer elastic contact (E_0), tau then poorly determined. "
          "Sphere (Hertz) form for every tip shape. The state starts relaxed (q = delta^1.5 / R^1.5) where a "
          "trajectory begins.",
)

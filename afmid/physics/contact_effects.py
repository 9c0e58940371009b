"""Contact effects declared outside :mod:`afmid.physics.effects` (which is near the size limit): plain
declarations, registered there, in catalog order, by ``EFFECTS.register``.

Conventions as in :mod:`afmid.physics.effects`: force on the tip in N, positive = repulsive;
``delta = a0 - z`` and ``deltadot = -zdot`` in contact (``z <= a0``), both 0 outside.
"""

from __future__ import annotations

from afmid.physics.effect_tags import Character, Region, Role
from afmid.physics.effect_types import Effect, Parameter, Quantity, Term

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

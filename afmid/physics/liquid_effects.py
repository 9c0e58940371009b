"""Effects of a sample in an electrolyte (``sample.medium: liquid``), declared outside
:mod:`afmid.physics.effects` (near the size limit) and registered there in catalog order.

Conventions as in :mod:`afmid.physics.effects`: force on the tip in N, positive = repulsive; z the tip-sample
separation, contact at z = a0. The medium's relative permittivity ``eps_r`` comes from the context
(:mod:`afmid.physics.medium`: water's at the sample temperature).
"""

from __future__ import annotations

import math

from afmid.physics.effect_tags import Character, Region
from afmid.physics.effect_types import EPSILON_0, Effect, Parameter, Quantity, Term

#: Searched Debye lengths start here, m (I = 92 mM in water at 25 C). Below it a double layer has the length
#: of a hydration force (searched up to HYDRATION_SEARCH_MAX, effects.py) and the same exponential shape: the
#: two are told apart only by their lengths, so the searches overlap only over [1, 1.5] nm, where the diagnosis
#: says it cannot decide. A shorter Debye length (e.g. 0.78 nm at 150 mM) is fitted when it is fixed from
#: ``sample.ionic_strength`` (or ``model.parameters.debye_length``); left to the search it is read as hydration.
DEBYE_SEARCH_MIN = 1.0e-9


def _double_layer_coefficient(p) -> float:
    """4 pi R lambda_D sigma_t sigma_s / (eps_r eps0), N (the force at z = 0 of the exponential)."""
    return 4.0 * math.pi * p["R"] * p["debye_length"] * p["surface_charge_product"] / (p["eps_r"] * EPSILON_0)


def _double_layer_readout(c, ctx) -> dict[str, float]:
    """The force at contact (N) and sigma_t sigma_s (C^2/m^4) from the term's coefficient."""
    length, coefficient = ctx["debye_length"], c["double_layer"]
    return {"double_layer_force": coefficient * math.exp(-ctx["a0"] / length),
            "surface_charge_product": coefficient * ctx["eps_r"] * EPSILON_0 / (4.0 * math.pi * ctx["R"] * length)}


DOUBLE_LAYER = Effect(
    name="double_layer",
    title="Electrical double-layer force in an electrolyte (sphere-plane, weak overlap, constant charge)",
    formula="F = 4 pi R lambda_D sigma_t sigma_s / (eps_r eps0) exp(-max(z, a0) / lambda_D); lambda_D the Debye "
            "length (from sample.ionic_strength I for a 1:1 electrolyte: sqrt(eps_r eps0 kB T / (2 N_A e^2 I "
            "1000)) = 0.304 nm / sqrt(I / M) in water at 25 C)",
    parameters=(
        Parameter("surface_charge_product", "C^2/m^4", 1.0e-4, -0.1, 0.1,
                  "sigma_t sigma_s, product of the tip's and the sample's surface charge densities (> 0 like "
                  "charges: repulsive; 1e-4 = two surfaces of 0.01 C/m^2, one charge per 16 nm^2)"),
        Parameter("debye_length", "m", 3.0e-9, 0.1e-9, 100e-9,
                  "lambda_D, Debye screening length (0.1 nm: ~9 M; 100 nm: ~10 uM); fixed by sample.ionic_strength "
                  "or model.parameters.debye_length when given", True,
                  search=(("liquid", DEBYE_SEARCH_MIN, 20e-9),)),
    ),
    terms=(
        Term("double_layer", "exp(-max(z, a0) / debye_length)", _double_layer_coefficient,
             "screened Coulomb repulsion (attraction for opposite charges), held at its contact value in contact",
             coefficient_unit="N"),
    ),
    quantities=(
        Quantity("double_layer_force", "N", "double-layer force at contact (z = a0); < 0: attractive", -1e-6, 1e-6),
        Quantity("surface_charge_product", "C^2/m^4",
                 "sigma_t sigma_s with the medium's permittivity (water's at the sample temperature)"),
    ),
    readout=_double_layer_readout,
    references=(
        "Butt, Biophys. J. 60, 1438 (1991): the AFM tip-sample double-layer force, sphere-plane, constant charge",
        "Israelachvili, Intermolecular and Surface Forces, 3rd ed. (2011), ch. 14 (Debye length eq. 14.37; "
        "weak-overlap sphere-plane forces)",
        "Butt, Cappella, Kappl, Surf. Sci. Rep. 59, 1 (2005), sec. 4.3 (double-layer forces in AFM)",
    ),
    character=Character.CONSERVATIVE,
    region=Region.NEAR,
    media=("liquid",),
    notes="Valid for weak overlap (z >~ lambda_D), low surface potentials (|psi| <~ 25 mV, where constant charge, "
          "constant potential and linear superposition agree) and R >> lambda_D (Derjaguin); at closer approach "
          "constant charge is the upper and constant potential the lower bound. In contact the force is held at "
          "its value at z = a0 (the DMT convention for surface forces). Distinct from hydration (0.02-1.5 nm "
          "searched) by its length: searched over [1, 20] nm.",
)

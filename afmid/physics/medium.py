"""The medium the sample is imaged in (``sample.medium: air | liquid``) and what it changes.

What the medium decides (declared on each effect as ``Effect.media``, checked here):

- which effects exist: a capillary meniscus and the capacitive (vacuum-permittivity) electrostatic force only
  in air, the electrical double layer only in liquid (an electrolyte screens a static tip-sample bias beyond a
  few Debye lengths and there is no meniscus to form). The diagnosis tries only the effects of the medium; a
  config that lists another is a one-line error naming the key (:func:`check_config`).
- the relative permittivity of the medium (``eps_r`` in the effects' context, used by the double layer's
  read-out): 1 in air, water's at the sample temperature in liquid (Malmberg & Maryott 1956);
- the Debye length when ``sample.ionic_strength`` is given (a 1:1 electrolyte in water), fixed for the fit and
  the simulator instead of being searched;
- the simulator's default viscosity of the squeeze film: air 1.8e-5 Pa s (the effect's default), water's at the
  sample temperature in liquid (Vogel equation).

The sample temperature is ``sample.temperature`` (K), 298.15 K (25 C) when not given. Units SI; the ionic
strength in mol/L as chemists write it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from afmid.physics.effect_types import BOLTZMANN, EFFECTS, EPSILON_0, MODELS

AVOGADRO = 6.02214076e23  # 1/mol
ELEMENTARY_CHARGE = 1.602176634e-19  # C
#: The sample temperature when ``sample.temperature`` is not given: 25 C, K.
ROOM_TEMPERATURE = 298.15
#: Relative permittivity used in air (no effect offered in air uses it; the vacuum value to 6e-4).
AIR_PERMITTIVITY = 1.0


def water_permittivity(temperature: float) -> float:
    """Static relative permittivity of water at ``temperature`` (K), 0-100 C: 78.3 at 25 C.

    Malmberg & Maryott, J. Res. Natl. Bur. Stand. 56, 1 (1956): eps = 87.740 - 0.40008 t + 9.398e-4 t^2
    - 1.410e-6 t^3 with t in C (to 0.05 over 0-100 C).
    """
    t = temperature - 273.15
    return 87.740 - 0.40008 * t + 9.398e-4 * t**2 - 1.410e-6 * t**3


def water_viscosity(temperature: float) -> float:
    """Dynamic viscosity of water at ``temperature`` (K), Pa s: 0.890e-3 at 25 C (Vogel equation, A = 2.414e-5
    Pa s, B = 247.8 K, C = 140 K; to ~1 % over 0-100 C; Al-Shemmeri, Engineering Fluid Mechanics (2012))."""
    return 2.414e-5 * 10.0 ** (247.8 / (temperature - 140.0))


def debye_length(ionic_strength: float, temperature: float = ROOM_TEMPERATURE, eps_r: float | None = None) -> float:
    """Debye screening length of a 1:1 electrolyte, m: lambda_D = sqrt(eps_r eps0 kB T / (2 N_A e^2 I 1000)),
    I in mol/L (the 1000 turns it into mol/m^3); eps_r defaults to water's at ``temperature``.

    In water at 25 C: 0.304 nm / sqrt(I); 0.96 nm at 100 mM, 0.78 nm at 150 mM, 3.0 nm at 10 mM, 9.6 nm at 1 mM
    (Israelachvili, Intermolecular and Surface Forces, 3rd ed. (2011), eq. 14.37).
    """
    eps = water_permittivity(temperature) if eps_r is None else eps_r
    return math.sqrt(eps * EPSILON_0 * BOLTZMANN * temperature
                     / (2.0 * AVOGADRO * ELEMENTARY_CHARGE**2 * ionic_strength * 1000.0))


def sample_temperature(sample) -> float:
    """The sample's temperature, K (``sample.temperature``, else 25 C)."""
    return float(getattr(sample, "temperature", None) or ROOM_TEMPERATURE)


def relative_permittivity(sample) -> float:
    """The medium's relative permittivity (the ``eps_r`` of the effects' context)."""
    return water_permittivity(sample_temperature(sample)) if sample.medium == "liquid" else AIR_PERMITTIVITY


def offered(effect: str, medium: str) -> bool:
    """Whether the effect exists in the medium (its declaration's ``media``)."""
    return medium in EFFECTS.get(effect).media


def fixed_parameters(sample, effects: Iterable[str]) -> dict[str, float]:
    """Nonlinear parameters the sample fixes for a library of ``effects``: the Debye length from
    ``sample.ionic_strength`` when ``double_layer`` is one of them (SI)."""
    if sample.ionic_strength is not None and "double_layer" in effects:
        return {"debye_length": debye_length(sample.ionic_strength, sample_temperature(sample))}
    return {}


def simulator_defaults(sample, effects: Iterable[str]) -> dict[str, float]:
    """Parameter values the sample implies for the simulator, below ``simulate.parameters`` (SI): the fixed
    Debye length, and in liquid water's viscosity for the squeeze film."""
    effects = list(effects)
    values = fixed_parameters(sample, effects)
    if sample.medium == "liquid" and "squeeze_film" in effects:
        values["fluid_viscosity"] = water_viscosity(sample_temperature(sample))
    return values


def check_config(config) -> None:
    """Raise ValueError("KEY: message") unless the effects, the ionic strength and the fixed Debye length of a
    run config fit its ``sample.medium``; then fix the Debye length from the ionic strength in
    ``config.model.parameters`` (so the fit and every refit of the diagnosis use it)."""
    import afmid.physics.effects  # noqa: F401  (registers the catalog)

    sample = config.sample
    medium = sample.medium
    model = MODELS.get(config.simulate.model) if config.simulate.model in MODELS else None
    for key, names in (("model.effects", config.model.effects), ("simulate.model", model.effects if model else ()),
                       ("simulate.effects", config.simulate.effects)):
        wrong = [n for n in names if n in EFFECTS and not offered(n, medium)]
        if wrong:
            where = " or ".join(EFFECTS.get(wrong[0]).media)
            raise ValueError(f"{key}: {wrong[0]} is not offered in sample.medium {medium} (only in {where}); "
                             "remove it or set sample.medium")
    if sample.ionic_strength is not None and medium != "liquid":
        raise ValueError(f"sample.ionic_strength: an electrolyte needs sample.medium: liquid (got {medium})")
    if sample.ionic_strength is not None:
        length, valid = debye_length(sample.ionic_strength, sample_temperature(sample)), \
            EFFECTS.get("double_layer").parameter("debye_length")
        if not valid.low <= length <= valid.high:
            raise ValueError(f"sample.ionic_strength: {sample.ionic_strength:g} mol/L gives a Debye length of "
                             f"{length * 1e9:.3g} nm, outside the double layer's valid [{valid.low * 1e9:g}, "
                             f"{valid.high * 1e9:g}] nm")
    fixed = fixed_parameters(sample, config.model.effects)
    given = config.model.parameters.get("debye_length")
    if fixed and given is not None and not math.isclose(given, fixed["debye_length"], rel_tol=1e-6):
        raise ValueError(f"sample.ionic_strength: fixes the Debye length at {fixed['debye_length']:.4g} m, but "
                         f"model.parameters.debye_length = {given:g}; give one of them")
    config.model.parameters.update(fixed)


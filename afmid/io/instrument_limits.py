"""The instrument values afmid accepts: one table for the run config's keys and a trace file's metadata.

In the io layer (docs/architecture.md, Layers) so that a trace file's values are checked without importing the
config above it; :mod:`afmid.config` validates its keys with the same table.
"""

from __future__ import annotations

import math
from typing import Any

from afmid.config_messages import format_value

#: Largest instrument values afmid accepts, far beyond any AFM (so that a typo or a corrupt file is refused,
#: not fitted into absurd read-outs): the stiffest sensors (length-extension resonators) ~1e6 N/m, the
#: fastest probes ~100 MHz, Q up to ~1e6 in cold UHV, colloidal probes up to ~50 um, amplitudes of nm to um.
INSTRUMENT_LIMITS = {
    "cantilever.spring_constant": 1e6,  # N/m
    "cantilever.resonance_frequency": 1e9,  # Hz
    "cantilever.quality_factor": 1e7,  # 1
    "cantilever.tip_radius": 1e-3,  # m
    "drive.frequency": 1e9,  # Hz
    "drive.free_amplitude": 1e-4,  # m
    "drive.force_amplitude": 1.0,  # N
}


def instrument_value_problem(key: str, value: Any) -> str | None:
    """What is wrong with an instrument value (``key`` of :data:`INSTRUMENT_LIMITS`) that did not come through
    the config, e.g. from a trace file's metadata; None if it is a possible value (or not a limited key)."""
    if key not in INSTRUMENT_LIMITS:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return f"expected a number, got {format_value(value)}"
    if not math.isfinite(number):
        return f"must be a finite number, got {format_value(number)}"
    if not 0 < number <= INSTRUMENT_LIMITS[key]:
        return f"must be > 0 and <= {INSTRUMENT_LIMITS[key]:g}, got {format_value(number)}"
    return None

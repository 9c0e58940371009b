"""A config value against the one a data file states (an afmid trace file's instrument, a capture's header).

The config wins where it gives a value (a differing file value is recorded as overridden); else the file's
value is used, checked against the config's instrument limits; else the key is required. ``sources`` records
where each value came from (the run file's ``value_sources``).
"""

from __future__ import annotations

import numpy as np

from afmid.errors import ConfigError, InputError
from afmid.io.cantilever import Cantilever
from afmid.io.instrument_limits import instrument_value_problem


def merged_value(config, key: str, from_config, from_file, sources: dict, overridden: list):
    """Config value if given (recording an override of the file's), else the file's, else an error."""
    name = key.split(".")[-1]
    if from_config is not None:
        if from_file is not None and not same_value(from_config, from_file):
            overridden.append(key)
        sources[name] = f"config:{key}"
        return from_config
    if from_file is not None and not (isinstance(from_file, float) and np.isnan(from_file)):
        check_file_instrument_value(config, key, from_file)
        sources[name] = "file"
        return from_file
    raise ConfigError("required key is missing (not in the config nor in the trace file)", file=config.source, key=key)


def check_file_instrument_value(config, key: str, value) -> None:
    """The config's instrument limits hold for a trace file's metadata too (InputError naming the file)."""
    problem = instrument_value_problem(key, value)
    if problem:
        raise InputError(f"the trace file's {key.split('.')[-1]} {problem}; set {key} in the config if the file "
                         f"is wrong", file=config.resolve_path(config.data.path), key=key)


def same_value(a, b) -> bool:
    """Equal to rounding (relative 1e-12), or equal as values that are not numbers."""
    try:
        return bool(np.isclose(float(a), float(b), rtol=1e-12, atol=0))
    except (TypeError, ValueError):
        return a == b


def merge_cantilever(config, meta: dict, sources: dict, overridden: list) -> Cantilever:
    """The lever from the config's cantilever keys, each missing one from the file's ``meta`` (SI)."""
    c = config.cantilever
    values = {}
    for name in ("spring_constant", "resonance_frequency", "quality_factor"):
        values[name] = float(merged_value(config, f"cantilever.{name}", getattr(c, name), meta.get(name), sources, overridden))
    radius = c.tip_radius
    file_radius = meta.get("tip_radius")
    if radius is None and file_radius is not None and np.isfinite(file_radius):
        check_file_instrument_value(config, "cantilever.tip_radius", file_radius)
        radius = float(file_radius)
        sources["tip_radius"] = "file"
    elif radius is not None:
        if file_radius is not None and np.isfinite(file_radius) and not same_value(radius, file_radius):
            overridden.append("cantilever.tip_radius")
        sources["tip_radius"] = "config:cantilever.tip_radius"
    return Cantilever.from_config(c, tip_radius=radius, **values)

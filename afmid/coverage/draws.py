"""Which experiments ``afmid coverage`` draws: the distributions around a run config and draw k's values.

:func:`distributions` gives the distribution of every varied key: the defaults of :func:`default_distributions`
(around the user's own setup) with ``coverage.vary`` over them. :func:`draw` gives draw k's values and
simulation seed from (``coverage.seed``, k) alone (:func:`draw_streams`), so any draw can be re-run by itself
and gives the same experiment whatever else was run; :func:`apply_draw` puts the values into the merged
config mapping, and :func:`set_options` spells them as the ``--set`` options of ``afmid simulate`` / ``afmid fit``
that reproduce the draw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from afmid.config import MAX_SEED, RunConfig
from afmid.sections.coverage import Distribution
from afmid.errors import ConfigError

#: Default spreads around the config's own values (chosen before any coverage was measured):
#: a physical parameter within x 0.5 .. 2 (log-uniform), the rest separation within -15 % .. +10 % (further
#: out of contact than that the tip of a typical setpoint no longer reaches the sample), a setpoint +- 0.05,
#: the free amplitude +- 20 %, the detector noise x 0.5 .. 2, and the instrument the config declares within
#: its calibration's usual spread: k and Q x 0.8 .. 1.25, a detector's corner x 0.7 .. 1.4, a higher mode's
#: frequency x 0.9 .. 1.1.
PARAMETER_FACTORS = (0.5, 2.0)
SEPARATION_FACTORS = (0.85, 1.10)
SETPOINT_SHIFT = (-0.05, 0.05)
AMPLITUDE_FACTORS = (0.8, 1.2)
NOISE_FACTORS = (0.5, 2.0)
LEVER_FACTORS = (0.8, 1.25)
DETECTOR_FACTORS = (0.7, 1.4)
MODE_FACTORS = (0.9, 1.1)


def default_distributions(config: RunConfig) -> dict[str, Distribution]:
    """The distributions ``afmid coverage`` uses around ``config`` when ``coverage.vary`` does not say otherwise
    (the values in :data:`PARAMETER_FACTORS` and below; only keys the config has a value for)."""
    out: dict[str, Distribution] = {}
    for name in config.simulate.parameters:
        out[f"simulate.parameters.{name}"] = Distribution(log_uniform=PARAMETER_FACTORS)
    if config.simulate.setpoint is not None:
        out["simulate.setpoint"] = Distribution(uniform=SETPOINT_SHIFT, mode="shift")
    elif config.sample.separation is not None:
        out["sample.separation"] = Distribution(uniform=SEPARATION_FACTORS)
    if config.drive.free_amplitude is not None:
        out["drive.free_amplitude"] = Distribution(uniform=AMPLITUDE_FACTORS)
    noise = config.simulate.noise
    if noise.detector_density is not None and noise.detector_density > 0:
        out["simulate.noise.detector_density"] = Distribution(log_uniform=NOISE_FACTORS)
    elif noise.detector_rms > 0:
        out["simulate.noise.detector_rms"] = Distribution(log_uniform=NOISE_FACTORS)
    for key in ("spring_constant", "quality_factor"):
        if getattr(config.cantilever, key) is not None:
            out[f"cantilever.{key}"] = Distribution(log_uniform=LEVER_FACTORS)
    if config.data.detector is not None:
        out["data.detector.bandwidth"] = Distribution(log_uniform=DETECTOR_FACTORS)
    for i, _ in enumerate(config.cantilever.higher_modes):
        out[f"cantilever.higher_modes.{i}.resonance_frequency"] = Distribution(uniform=MODE_FACTORS)
    return out


def distributions(config: RunConfig) -> dict[str, Distribution]:
    """Every varied key's distribution: the defaults (unless ``coverage.defaults`` is false) with
    ``coverage.vary`` over them (a null entry drops a default). Keys with ``of`` come last, so that the key they
    refer to is drawn first."""
    section = config.coverage
    chosen = default_distributions(config) if section is None or section.defaults else {}
    for key, dist in (section.vary.items() if section is not None else ()):
        if dist is None:
            chosen.pop(key, None)
        else:
            chosen[key] = dist
    for key, dist in chosen.items():
        if dist.of is not None and chosen.get(dist.of) is not None and chosen[dist.of].of is not None:
            raise ConfigError(f"of: {dist.of} is itself drawn relative to {chosen[dist.of].of}; refer to a key "
                              "drawn on its own", file=config.source, key=f"coverage.vary.{key}")
    return dict(sorted(chosen.items(), key=lambda item: item[1].of is not None))


# --------------------------------------------------------------------------- keys in a config mapping
def _parts(key: str) -> list[str | int]:
    return [int(p) if p.isdecimal() else p for p in key.split(".")]


def get_value(raw: dict, key: str) -> Any:
    """The value at dotted ``key`` of a config mapping (list items by index); KeyError when absent or null."""
    node: Any = raw
    for part in _parts(key):
        if isinstance(part, int) and isinstance(node, list) and part < len(node):
            node = node[part]
        elif isinstance(part, str) and isinstance(node, dict) and node.get(part) is not None:
            node = node[part]
        else:
            raise KeyError(key)
    return node


def set_value(raw: dict, key: str, value: Any) -> None:
    """Set dotted ``key`` of a config mapping (in place; missing mappings on the way are made)."""
    parts = _parts(key)
    node: Any = raw
    for part, following in zip(parts[:-1], parts[1:]):
        if isinstance(part, int):
            if not (isinstance(node, list) and part < len(node)):
                raise KeyError(key)
            node = node[part]
            continue
        if not isinstance(node.get(part), (dict, list)):
            node[part] = [] if isinstance(following, int) else {}
        node = node[part]
    node[parts[-1]] = value


#: simulate.unsettled of every draw: an oscillation that does not settle is recorded as it is.
UNSETTLED = "record"

#: Config mappings whose keys are free (a model's parameter names), so a drawn key may be new there.
FREE_MAPPINGS = ("simulate.parameters", "model.parameters")


def check_keys(config: RunConfig, raw: dict) -> None:
    """Refuse a varied key that is no key of the config (``raw``: its merged mapping), naming
    ``coverage.vary.KEY``: a typo would otherwise be reported as the config's own unknown key, or not at all."""
    for key in distributions(config):
        parts = key.split(".")
        parent, node = ".".join(parts[:-1]), raw
        for i, part in enumerate(parts[:-1]):
            if isinstance(node, list) and part.isdecimal() and int(part) < len(node):
                node = node[int(part)]
            elif isinstance(node, dict) and part in node:
                node = node[part]
            else:
                node = False  # a missing section or list item
                break
            if node is None:  # an optional section not given (data.detector): the drawn value creates it
                break
        known = (node is None or parent in FREE_MAPPINGS
                 or (isinstance(node, dict) and parts[-1] in node))
        if not known:
            raise ConfigError(f"{key} is not a key of the run config (see afmid init-config for the keys)",
                              file=config.source, key=f"coverage.vary.{key}")


# --------------------------------------------------------------------------- one draw
@dataclass(frozen=True)
class Draw:
    """Draw ``index``: the values of the varied keys (SI, as in the config) and the simulation's seed."""

    index: int
    seed: int  # simulate.seed of this draw
    values: dict[str, Any]


def draw_streams(coverage_seed: int, index: int) -> tuple[np.random.Generator, int]:
    """(the generator of draw ``index``'s values, its simulation seed), both from (``coverage_seed``, ``index``)
    alone through :class:`numpy.random.SeedSequence` spawn keys (independent streams for every pair)."""
    values = np.random.Generator(np.random.PCG64(np.random.SeedSequence(coverage_seed, spawn_key=(index, 0))))
    seed = int(np.random.SeedSequence(coverage_seed, spawn_key=(index, 1)).generate_state(1, dtype=np.uint32)[0])
    return values, min(seed, MAX_SEED)


def _base(raw: dict, key: str, dist: Distribution, config: RunConfig) -> Any:
    where = dist.of or key
    try:
        return get_value(raw, where)
    except KeyError:
        if dist.mode == "absolute":
            return None
        raise ConfigError(f"{'of: ' + where if dist.of else where} has no value in the config to {dist.mode}; give "
                          "one, or use mode: absolute", file=config.source, key=f"coverage.vary.{key}") from None


def _is_whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def draw_number(dist: Distribution, rng: np.random.Generator) -> Any:
    """One number (or choice) from ``dist``; exactly one call of ``rng`` whatever the distribution, so that a
    change of one key's distribution leaves the others' draws as they were."""
    u = rng.random()
    if dist.uniform is not None:
        low, high = dist.uniform
        return low + u * (high - low)
    if dist.log_uniform is not None:
        low, high = dist.log_uniform
        return math.exp(math.log(low) + u * (math.log(high) - math.log(low)))
    return dist.choice[min(int(u * len(dist.choice)), len(dist.choice) - 1)]


def draw(config: RunConfig, raw: dict, index: int) -> Draw:
    """Draw ``index`` around the merged config mapping ``raw`` (:func:`afmid.config.dump_config` of ``config``):
    its values, one per varied key in :func:`distributions` order, and its simulation seed."""
    section = config.coverage
    rng, seed = draw_streams(section.seed if section is not None else 0, index)
    values: dict[str, Any] = {}
    drawn = yaml.safe_load(yaml.safe_dump(raw))  # a copy the `of` keys read the drawn values from
    for key, dist in distributions(config).items():
        number = draw_number(dist, rng)
        base = _base(drawn, key, dist, config)
        if dist.mode == "scale":
            value = base * number
        elif dist.mode == "shift":
            value = base + number
        else:
            value = number
        try:
            own = get_value(raw, key)
        except KeyError:  # no value of its own (an absolute or `of` draw): whole when every choice is
            own = dist.choice[0] if dist.choice is not None and all(_is_whole(v) for v in dist.choice) else None
        if _is_whole(own) and isinstance(value, (int, float)):
            value = int(round(value))  # simulate.periods, steps_per_period: whole numbers
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            value = float(value)
        values[key] = value
        set_value(drawn, key, value)
    return Draw(index, seed, values)


def apply_draw(raw: dict, one: Draw, separation_given: bool) -> tuple[dict, dict]:
    """(the simulation's config mapping, the fit's) for draw ``one`` from the merged mapping ``raw``: the drawn
    values, the draw's simulate.seed and simulate.unsettled :data:`UNSETTLED` in both, no data file, the coverage
    section gone; the fit's without sample.separation unless ``separation_given``."""
    simulated = yaml.safe_load(yaml.safe_dump(raw))
    simulated.pop("coverage", None)
    # The experiment is simulated, not read: no data file, nothing of one to crop (data.start / stop).
    simulated.setdefault("data", {}).update(path=None, paths=None, start=None, stop=None)
    for key, value in one.values.items():
        set_value(simulated, key, value)
    set_value(simulated, "simulate.seed", one.seed)
    # A steady oscillation that never settles (a period-n orbit) is recorded as an instrument would record it,
    # not dropped: dropping such draws would bias the measured rates toward the easy experiments.
    set_value(simulated, "simulate.unsettled", UNSETTLED)
    fitted = yaml.safe_load(yaml.safe_dump(simulated))
    if not separation_given:
        fitted["sample"]["separation"] = None
    return simulated, fitted


def yaml_text(value: Any) -> str:
    """``value`` as YAML that reads back as the same value (a float always with a '.' or exponent PyYAML
    takes as a float: 1e-09 alone would read back as a string)."""
    text = yaml.safe_dump(value, default_flow_style=True, width=math.inf).strip()
    return text.removesuffix("...").strip()


def set_options(one: Draw, separation_given: bool) -> list[str]:
    """The ``--set`` options that make ``afmid simulate CONFIG`` simulate draw ``one`` (and, with
    ``sample.separation=null`` unless given, ``afmid fit CONFIG`` fit it as the coverage run did)."""
    options = [f"{key}={yaml_text(value)}" for key, value in one.values.items()]
    options.append(f"simulate.seed={one.seed}")
    options.append(f"simulate.unsettled={UNSETTLED}")
    return options

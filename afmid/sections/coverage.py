"""The ``coverage:`` section of a run config: how many experiments ``afmid coverage`` draws and from what.

Example (every key optional)::

    coverage:
      draws: 50                  # experiments drawn (afmid coverage -n overrides it)
      seed: 1                    # draw k's values and simulation seed come from (seed, k) alone
      separation: estimated      # estimated: the fit is not told sample.separation; given: it is
      defaults: true             # start from the default distributions around this config (afmid.coverage.draws)
      vary:                      # a distribution per config key (dotted path; list items by index)
        simulate.parameters.E_star: {log_uniform: [0.5, 2.0]}                  # x 0.5 .. 2 of the config's value
        sample.separation: {uniform: [-1.0e-9, 1.0e-9], mode: shift}           # +- 1 nm around it
        cantilever.quality_factor: {log_uniform: [2, 600], mode: absolute}     # the value itself
        data.detector.bandwidth: {log_uniform: [3, 30], of: cantilever.resonance_frequency}  # 3 .. 30 f0
        simulate.periods: {choice: [50, 200, 1000], mode: absolute}
        simulate.noise.detector_rms: null                                       # drop a default: keep the value
      hidden:                    # the blind loop (afmid.coverage.loop): one entry hidden per draw
        viscoelastic: {viscosity: {log_uniform: [50, 400], mode: absolute}}
        none: {}                 # nothing hidden: a false alarm if an effect is named

A distribution is one of ``uniform: [low, high]``, ``log_uniform: [low, high]`` (both > 0) or ``choice: [...]``
(equally likely), and ``mode`` says what the drawn number is: ``scale`` (default; a factor on the base value),
``shift`` (added to the base value) or ``absolute`` (the value). The base value is the key's own value in the
config, or with ``of: KEY`` that key's value in the same draw (after it was drawn). A key whose config value is
a whole number (simulate.periods) gets whole numbers (rounded).

This module imports only pydantic: :mod:`afmid.config` imports it for the section's schema.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: The largest seed (as simulate.seed: stored as a 32-bit HDF5 attribute).
MAX_COVERAGE_SEED = 2**32 - 1
#: The most draws one run may ask for (a typo of 1e9 must not start a week of simulations).
MAX_DRAWS = 100_000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class Distribution(_Strict):
    """How one config key is drawn (see the module docstring)."""

    uniform: tuple[float, float] | None = Field(None, description="[low, high], equally likely in between")
    log_uniform: tuple[float, float] | None = Field(
        None, description="[low, high], both > 0: equally likely in log (a factor of 2 up as likely as down)")
    choice: list[Any] | None = Field(None, description="values, each equally likely")
    mode: Literal["scale", "shift", "absolute"] = Field(
        "scale", description="scale: base value x drawn number; shift: base + drawn; absolute: the drawn value")
    of: str | None = Field(None, description="the config key whose value (in this draw) is the base, instead of "
                           "this key's own")

    @model_validator(mode="after")
    def _one_kind(self) -> "Distribution":
        kinds = [k for k in ("uniform", "log_uniform", "choice") if getattr(self, k) is not None]
        if len(kinds) != 1:
            raise ValueError("give exactly one of uniform: [low, high], log_uniform: [low, high] or choice: [...]"
                             + (f", got {' and '.join(kinds)}" if kinds else ""))
        for kind in ("uniform", "log_uniform"):
            span = getattr(self, kind)
            if span is None:
                continue
            low, high = span
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise ValueError(f"{kind}: expected [low, high] with low <= high, both finite, got {list(span)}")
            if kind == "log_uniform" and low <= 0:
                raise ValueError(f"log_uniform: both ends must be > 0, got {list(span)}")
        if self.choice is not None:
            if not self.choice:
                raise ValueError("choice: the list is empty")
            if self.mode != "absolute" and not all(_is_number(v) for v in self.choice):
                raise ValueError(f"choice: mode {self.mode} needs numbers, got {self.choice}; use mode: absolute "
                                 "for other values")
        if self.mode == "absolute" and self.of is not None:
            raise ValueError("of: an absolute value has no base value; use mode: scale or shift with of")
        return self

    @property
    def kind(self) -> str:
        return next(k for k in ("uniform", "log_uniform", "choice") if getattr(self, k) is not None)

    def describe(self) -> str:
        """One line, e.g. ``log_uniform [0.5, 2] x (scale)`` or ``uniform [-1e-09, 1e-09] + (shift)``."""
        values = getattr(self, self.kind)
        span = ", ".join(f"{v:g}" if _is_number(v) else repr(v) for v in values)
        base = f" of {self.of}" if self.of else ""
        return f"{self.kind} [{span}] ({self.mode}{base})"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class CoverageConfig(_Strict):
    """``coverage:``: the experiments ``afmid coverage`` draws around the run config."""

    draws: Annotated[int, Field(ge=1, le=MAX_DRAWS)] = Field(50, description="experiments drawn")
    seed: Annotated[int, Field(ge=0, le=MAX_COVERAGE_SEED)] = Field(
        0, description="draw k's values and simulation seed come from (seed, k) alone")
    separation: Literal["estimated", "given"] = Field(
        "estimated", description="estimated: the fit estimates the rest separation; given: it is told the truth")
    defaults: bool = Field(True, description="start from the default distributions around the config "
                           "(afmid.coverage.draws.default_distributions); vary adds to and overrides them")
    vary: dict[str, Distribution | None] = Field(
        default_factory=dict, description="config key (dotted) -> distribution; null drops a default")
    diagnose: bool = Field(False, description="run the blind loop on every draw: diagnose the fit, add the top "
                           "suggestion, refit (afmid.coverage.loop); implied by hidden")
    hidden: dict[str, dict[str, Distribution]] = Field(
        default_factory=dict, description="effect the fit's model lacks -> a distribution (mode absolute) per "
        "parameter of it; each draw hides one entry, equally likely; 'none': a draw with nothing hidden")

    @property
    def loop(self) -> bool:
        """True when the draws run the blind loop (afmid.coverage.loop)."""
        return self.diagnose or bool(self.hidden)

    @model_validator(mode="after")
    def _keys_are_paths(self) -> "CoverageConfig":
        for key, dist in self.vary.items():
            parts = key.split(".")
            if len(parts) < 2 or not all(parts):
                raise ValueError(f"coverage.vary: {key!r} is not a dotted config key such as "
                                 "simulate.parameters.E_star")
            if parts[0] in ("coverage", "data") and parts[:2] != ["data", "detector"] and parts[:2] != [
                    "data", "sample_rate"]:
                raise ValueError(f"coverage.vary: {key!r}: only data.detector and data.sample_rate of the data "
                                 "section (and nothing of coverage) describe a simulated experiment")
            if dist is not None and dist.of is not None and dist.of == key:
                raise ValueError(f"coverage.vary.{key}: of names the key itself")
        for effect, params in self.hidden.items():
            for name, dist in params.items():
                if dist.mode != "absolute":
                    raise ValueError(f"coverage.hidden.{effect}.{name}: a hidden effect's parameter has no value in "
                                     "the config to scale or shift; give mode: absolute")
        return self

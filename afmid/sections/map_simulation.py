"""The ``simulate.map`` section: a sample described as phases, for :mod:`afmid.maps.simulate`.

A map is ``rows`` x ``cols`` pixels ``pixel_size`` apart. The first phase is the matrix (it fills every pixel not
covered by a domain); every further phase is a round domain (``center`` [x, y] in m from the first pixel,
``radius`` in m) with its own force-model parameters (merged over ``simulate.parameters``) and ``height`` (m,
raises the sample there: the rest separation of the pixel is ``sample.separation - height``). Later domains
are drawn over earlier ones. Example (``configs/maps/blend_map.yaml``)::

    simulate:
      map:
        rows: 6
        cols: 6
        pixel_size: 20.0e-9
        phases:
          - {name: matrix, parameters: {E_star: 2.0e9}}
          - {name: soft, center: [50.0e-9, 50.0e-9], radius: 40.0e-9, height: 1.0e-9, parameters: {E_star: 0.5e9}}
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class MapPhase(_Strict):
    """One phase of a simulated sample (SI)."""

    name: str = Field(..., min_length=1, description="phase name (stored in /truth/phase_names)")
    parameters: dict[str, float] = Field(default_factory=dict, description="model parameters of this phase, SI")
    height: float = Field(0.0, description="m; topography of the phase (raises the sample: less separation)")
    center: tuple[float, float] | None = Field(None, description="m; [x, y] of a round domain (not the matrix)")
    radius: Annotated[float, Field(gt=0)] | None = Field(None, description="m; radius of a round domain")


class MapSimulation(_Strict):
    """``simulate.map``: a force map of ``rows`` x ``cols`` traces over a sample made of phases."""

    rows: Annotated[int, Field(ge=1, le=4096)]
    cols: Annotated[int, Field(ge=1, le=4096)]
    pixel_size: Annotated[float, Field(gt=0, lt=1e-3)] = Field(..., description="m between pixel centres")
    phases: list[MapPhase] = Field(..., min_length=1, description="the matrix first, then round domains")

    @model_validator(mode="after")
    def _domains_are_round(self) -> "MapSimulation":
        first = self.phases[0]
        if first.center is not None or first.radius is not None:
            raise ValueError("phases[0]: the first phase is the matrix: it has no center or radius")
        for i, phase in enumerate(self.phases[1:], start=1):
            if phase.center is None or phase.radius is None:
                raise ValueError(f"phases[{i}]: a domain needs center [x, y] (m) and radius (m)")
        names = [p.name for p in self.phases]
        if len(set(names)) != len(names):
            raise ValueError(f"phases: names must differ, got {names}")
        return self

"""The ``fit.separation_track`` section (afmid.fit.separation_track): a rest separation d(t) per block of periods.

Example: ``fit: {separation_track: {bandwidth: 1500.0}}`` fits a record taken while scanning with d(t) resolved to
1.5 kHz (blocks of f_drive / (2 bandwidth) whole periods), one force law for all blocks. SI (Hz).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field


class SeparationTrackConfig(BaseModel):
    """``fit.separation_track``: the track's bandwidth."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    bandwidth: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        ..., description="Hz; the highest frequency of d(t) the track follows (blocks of f / (2 bandwidth) periods)")
    within_block: Literal["constant", "mean_force", "rows"] = Field(
        "constant", description="d within a block: constant, or per period from its mean force under the law, or "
        "from all its weak-form rows under the law (afmid.fit.period_separation; for records under an amplitude "
        "feedback, see "
        "docs/lab/2026-11-29-scanning-record.md; wrong on a record whose d steps under a still piezo, hence not "
        "the default)")

"""The schemas of the record's own config sections: ``data:``, ``cantilever:`` and ``drive:``.

They describe the trace (where it is, its units and sign, its sampling, the detector), the lever that recorded
it and the drive it was recorded with, so they live in io, the lowest layer that reads them: a run config
(afmid.config.RunConfig, a layer above) is made of them plus the sections of the stages above, and
:meth:`afmid.io.trace.Trace.from_array` validates its arguments with them alone (:class:`RecordSections`), with
the same keys, defaults and one-line messages as a config file. Units: SI (m, Hz, N, N/m, rad).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator,
                      model_validator)

import afmid.config_messages as config_messages
from afmid.io.instrument_limits import INSTRUMENT_LIMITS
from afmid.registry import unknown_name_message


def _not_bool(value: Any) -> Any:
    """Refuse YAML booleans (``yes``, ``on``, ``true``) where a number is expected; pydantic would take them as 1/0."""
    if isinstance(value, bool):
        raise ValueError(f"expected a number, got {value!r}")
    return value


#: A number that is not a YAML boolean (``yes`` would otherwise be 1).
NumberNotBool = BeforeValidator(_not_bool)


def _column_not_bool(value: Any) -> Any:
    """Refuse YAML booleans where a column is named: ``column: no`` is False, which pydantic takes as index 0."""
    if isinstance(value, bool):
        word = "yes/no/on/off/true/false"
        raise ValueError(f"expected a column name or a 0-based column index, got the YAML boolean {value!r} "
                         f"({word} unquoted); quote a column named like that, e.g. 'no'")
    return value


_Column = BeforeValidator(_column_not_bool)
PositiveFloat = Annotated[float, NumberNotBool, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, NumberNotBool, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, NumberNotBool, Field(allow_inf_nan=False)]
#: A relative 1-sigma uncertainty: 0.1 = 10 % (a percentage written as 10 is an error, not a 1000 % error bar).
RelativeUncertainty = Annotated[float, NumberNotBool, Field(ge=0, lt=1, allow_inf_nan=False)]


#: A frequency in Hz (positive, finite, at most 1e10: beyond any detector).
InstrumentHz = Annotated[float, NumberNotBool, Field(gt=0, le=1e10, allow_inf_nan=False)]


class StrictModel(BaseModel):
    """Base for config sections: unknown keys are errors, values are re-validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


# --------------------------------------------------------------------------- data
class DetectorConfig(StrictModel):
    """The detector / anti-alias low-pass between the deflection and the samples (afmid.preprocess.instrument)."""

    bandwidth: InstrumentHz = Field(..., description="-3 dB frequency, Hz")
    filter: str = Field("butterworth", description="butterworth, bessel or first_order")
    order: Annotated[int, NumberNotBool, Field(ge=1, le=12)] | None = Field(
        None, description="filter order (poles); default 2 (butterworth, bessel) or 1 (first_order)")

    @field_validator("filter")
    @classmethod
    def _known_filter(cls, name: str) -> str:
        from afmid.preprocess.instrument import FILTERS

        if name not in FILTERS:
            raise ValueError(unknown_name_message("detector filter", name, FILTERS.names()))
        return name

    @model_validator(mode="after")
    def _order_fits_filter(self) -> "DetectorConfig":
        from afmid.preprocess.instrument import FILTERS

        kind = FILTERS.get(self.filter)
        if self.order is not None and self.order > kind.max_order:
            raise ValueError(f"data.detector.order: a {self.filter} filter has at most order {kind.max_order}, "
                             f"got {self.order}")
        return self

    @property
    def resolved_order(self) -> int:
        return self.order if self.order is not None else (1 if self.filter == "first_order" else 2)


class DataConfig(StrictModel):
    """Where the deflection trace is and how to read it."""

    path: Path | None = Field(None, description="trace file, relative to the config file")
    paths: list[Path] | None = Field(
        None, description="several trace files of one sample and one tip (e.g. set-points), fitted jointly: one "
        "force law, a separation per trace (afmid.fit.joint); instead of data.path")
    format: str = Field("auto", description="auto (from the suffix), csv, npy, hdf5, mat, ibw, tdms, hsdc")
    column: Annotated[str | int | None, _Column] = Field(
        None, description="CSV column / HDF5 dataset path / MAT variable (or a 0-based column index)")
    time_column: Annotated[str | int | None, _Column] = Field(None, description="optional time column (s)")
    sample_rate: PositiveFloat | None = Field(None, description="Hz; required if there is no time column")
    units: Literal["m", "nm", "pm", "um", "V", "raw"] | None = Field(
        None, description="units of the samples in the file; V needs invols, raw needs scale"
    )
    invols: PositiveFloat | None = Field(None, description="inverse optical lever sensitivity, m/V")
    invols_uncertainty: RelativeUncertainty | None = Field(
        None, description="relative 1-sigma uncertainty of the deflection sensitivity (0.05 = 5 %): it scales every "
        "deflection, so it is propagated into every read-out (afmid.fit.invols_share)")
    scale: FiniteFloat | None = Field(None, description="for units: raw, metres per count")
    offset: FiniteFloat = Field(0.0, description="subtracted from the samples before scaling (file units)")
    positive: Literal["toward_sample", "away_from_sample"] = Field(
        "toward_sample", description="sign convention of the deflection in the file"
    )
    start: NonNegativeFloat | None = Field(
        None, description="s from the first sample: fit the record from here on; default: from the first sample, "
        "or after the onset of the oscillation when the record starts at rest (the drive switched on mid-record)")
    stop: PositiveFloat | None = Field(None, description="s from the first sample: fit the record up to here")
    detector: DetectorConfig | None = Field(
        None, description="detector low-pass {bandwidth, filter, order}; absent: an ideal detector")

    @model_validator(mode="after")
    def _distinct_columns(self) -> "DataConfig":
        if self.column is not None and self.column == self.time_column:
            raise ValueError(f"data.time_column: names the same column as data.column ({self.column!r}): the "
                             "deflection cannot be its own time axis")
        if self.paths is not None:  # afmid.fit.joint
            if self.path is not None:
                raise ValueError("data.paths: give data.path (one trace) or data.paths (a joint fit), not both")
            if not self.paths:
                raise ValueError("data.paths: the list is empty; give the trace files to fit jointly")
        if self.start is not None and self.stop is not None and self.stop <= self.start:
            raise ValueError(f"data.stop: {self.stop:g} s is not after data.start ({self.start:g} s)")
        return self


def instrument_value(key: str):
    """A positive, finite float no larger than the key's limit."""
    limit = INSTRUMENT_LIMITS[key]

    def at_most(value: float) -> float:
        if value > limit:
            raise ValueError(f"must be <= {limit:g} (beyond any AFM), got {value:g}")
        return value

    return Annotated[float, NumberNotBool, Field(gt=0, allow_inf_nan=False), AfterValidator(at_most)]


class ModeConfig(StrictModel):
    """A higher flexural mode of the lever, seen at the tip (afmid.preprocess.instrument.Mode)."""

    resonance_frequency: instrument_value("cantilever.resonance_frequency") = Field(..., description="f_i, Hz")
    quality_factor: instrument_value("cantilever.quality_factor") = Field(..., description="Q_i")
    spring_constant: instrument_value("cantilever.spring_constant") = Field(..., description="k_i, N/m")


class CantileverConfig(StrictModel):
    spring_constant: instrument_value("cantilever.spring_constant") | None = Field(None, description="k, N/m")
    resonance_frequency: instrument_value("cantilever.resonance_frequency") | None = Field(None, description="f0, Hz")
    quality_factor: instrument_value("cantilever.quality_factor") | None = Field(None, description="Q")
    tip_radius: instrument_value("cantilever.tip_radius") | None = Field(None, description="R, m")
    tip_shape: str = Field("sphere", description="sphere | cone | pyramid | flat_punch (`afmid effects --tips`)")
    tip_half_angle: FiniteFloat | None = Field(None, description="half-opening angle of a cone or pyramid, rad")
    spring_constant_uncertainty: RelativeUncertainty | None = Field(
        None, description="relative 1-sigma uncertainty of k (0.1 = 10 %), propagated into every read-out")
    quality_factor_uncertainty: RelativeUncertainty | None = Field(
        None, description="relative 1-sigma uncertainty of Q (0.1 = 10 %), propagated into every read-out")
    higher_modes: list[ModeConfig] = Field(
        default_factory=list, description="higher flexural modes [{resonance_frequency, quality_factor, "
        "spring_constant}]; the tip is the sum of the modes")

    @model_validator(mode="after")
    def _known_tip(self) -> "CantileverConfig":
        from afmid.physics.tips import check_tip

        check_tip(self.tip_shape, self.tip_half_angle)
        return self

    @model_validator(mode="after")
    def _modes_above_first(self) -> "CantileverConfig":
        f0 = self.resonance_frequency
        for i, mode in enumerate(self.higher_modes):
            if f0 is not None and mode.resonance_frequency <= f0:
                raise ValueError(f"cantilever.higher_modes[{i}].resonance_frequency: must be above the first "
                                 f"mode's {f0:g} Hz, got {mode.resonance_frequency:g}")
        return self


class DriveConfig(StrictModel):
    frequency: instrument_value("drive.frequency") | None = Field(None, description="drive frequency, Hz")
    free_amplitude: instrument_value("drive.free_amplitude") | None = Field(
        None, description="A0, free oscillation amplitude, m")
    force_amplitude: instrument_value("drive.force_amplitude") | None = Field(
        None, description="F0, drive force amplitude, N (with drive.phase: a calibrated drive the fit does not fit)")
    phase: FiniteFloat | None = Field(None, description="phi, rad: F_drive = F0 cos(2 pi f t + phi), t = 0 at the "
                                      "trace's time zero; given, the drive is calibrated, not fitted (fit.declared_drive)")
    force_amplitude_uncertainty: RelativeUncertainty | None = Field(
        None, description="relative 1-sigma uncertainty of drive.force_amplitude (0.02 = 2 %)")
    phase_uncertainty: NonNegativeFloat | None = Field(None, description="1-sigma uncertainty of drive.phase, rad")
    @model_validator(mode="after")
    def _calibrated(self) -> "DriveConfig":
        # The uncertainties of a calibrated drive (afmid.fit.declared_drive) without the drive they belong to.
        for name in ("force_amplitude_uncertainty", "phase_uncertainty"):
            if getattr(self, name) is not None and self.phase is None:
                raise ValueError(f"drive.{name}: belongs to a calibrated drive, which needs drive.phase (rad)")
        return self


class RecordSections(StrictModel):
    """The record's sections alone (no fit, model or sample): what :meth:`afmid.io.trace.Trace.from_array` is
    given, checked as a config file's ``data:``, ``cantilever:`` and ``drive:`` would be. ``fit`` is None: the
    checks on load then use the fit's defaults (:func:`afmid.io.defects.settings_for`)."""

    data: DataConfig = Field(default_factory=DataConfig)
    cantilever: CantileverConfig = Field(default_factory=CantileverConfig)
    drive: DriveConfig = Field(default_factory=DriveConfig)
    fit: None = None  # no fit section: the checks on load take the fit's defaults


def record_sections(raw: dict, source: str | Path) -> RecordSections:
    """Validate ``raw`` ({data, cantilever, drive}) into :class:`RecordSections`; the first problem as the same
    one-line :class:`afmid.errors.ConfigError` a config file gets (naming ``source`` and the key)."""
    try:
        return RecordSections.model_validate(raw)
    except ValidationError as exc:
        raise config_messages.validation_error(exc, source, RecordSections) from None

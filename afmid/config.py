"""Run configuration: schema, validation and layering, in one place.

A run config is a YAML file (one per run). It is validated once, here, against a
pydantic schema that rejects unknown keys (the record's sections ``data``, ``cantilever`` and ``drive`` are
declared in :mod:`afmid.io.sections`, the rest here). Every error names the file, the key
path and what was expected, e.g.::

    configs/x.yaml: cantilever.quality_factor: must be > 0, got -3

Layering: the packaged defaults (the schema's defaults) < the YAML file <
command-line ``--set key.path=value`` overrides. Paths in a config are relative
to the config file. The merged config (:func:`dump_config`) is stored in every
output file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

import afmid.config_messages as config_messages
from afmid.errors import ConfigError
from afmid.io.files import check_input_file
# The record's sections (data, cantilever, drive) are io's (afmid.io.sections): Trace.from_array validates with them.
from afmid.io.sections import (CantileverConfig, DataConfig, DriveConfig, FiniteFloat, NonNegativeFloat, NumberNotBool,
                               PositiveFloat, StrictModel)
from afmid.sections.coverage import CoverageConfig
from afmid.sections.separation_track import SeparationTrackConfig
from afmid.sections.map_simulation import MapSimulation
from afmid.sections.scan import ScanSimulation
from afmid.registry import closest, unknown_name_message


#: Largest random seed: numpy's generators take any non-negative integer, but a seed is stored in the
#: output files as an HDF5 attribute and is conventionally 32-bit.
MAX_SEED = 2**32 - 1
Seed = Annotated[int, NumberNotBool, Field(ge=0, le=MAX_SEED)]


class SampleConfig(StrictModel):
    separation: PositiveFloat | None = Field(
        None, description="d, rest tip-sample separation, m; estimated by the fit if absent; with data.paths a "
        "list, one per trace in the same order"
    )
    a0: PositiveFloat = Field(0.165e-9, description="intermolecular distance, m")
    medium: Literal["air", "liquid"] = Field("air", description="which effects exist (afmid.physics.medium)")
    ionic_strength: PositiveFloat | None = Field(None, description="mol/L, 1:1 electrolyte: fixes the Debye length")
    temperature: PositiveFloat | None = Field(None, description="K, for the Debye length; default 298.15")

    @field_validator("separation", mode="wrap")
    @classmethod
    def _one_per_trace(cls, value, handler):
        # A list (data.paths: one per trace) is checked entry by entry like a single value; a union type would
        # report a bad single value twice, once as "not a list".
        if isinstance(value, (list, tuple)):
            return [handler(v) for v in value]
        return handler(value)


class ModelConfig(StrictModel):
    effects: list[str] = Field(default_factory=lambda: ["dmt"], description="names from `afmid effects`")
    library: str | None = Field(None, description="a preset term library instead of effects")
    terms: list[str] = Field(default_factory=list, description="custom terms in the term language")
    parameters: dict[str, FiniteFloat] = Field(
        default_factory=dict, description="fixed values for nonlinear parameters (e.g. decay lengths), SI"
    )

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, names: list[str]) -> list[str]:
        from afmid.physics.effects import EFFECTS

        for name in names:
            if name not in EFFECTS:
                hint = closest(name, EFFECTS.names())
                msg = f"unknown effect {name!r}"
                msg += f" (did you mean {hint!r}?)" if hint else ""
                raise ValueError(msg + f"; allowed: {', '.join(EFFECTS.names())}")
        if len(set(names)) != len(names):
            raise ValueError(f"effects listed twice: {names}")
        return names

    @model_validator(mode="after")
    def _library_or_effects(self) -> "ModelConfig":
        # A preset replaces the effects' terms: both given, one of them would be ignored without a word.
        if self.library is not None and "effects" in self.model_fields_set and self.effects:
            raise ValueError(f"model.library: the preset {self.library!r} and model.effects {self.effects} are both "
                             "given, but a preset replaces the effects' terms; keep one of them")
        return self


class NoiseConfig(StrictModel):
    """Instrument noise added by the simulator."""

    # Upper bounds beyond any AFM detector, as for the instrument values (free_amplitude <= 1e-4 m): 1e300 m rms
    # made a trace of +-3e300 m. 1e-7 m/sqrt(Hz) is 1e-4 m rms over a 1 MHz band.
    detector_rms: Annotated[NonNegativeFloat, Field(le=1e-4)] = Field(0.0, description="white detector noise, m rms")
    detector_density: Annotated[NonNegativeFloat, Field(le=1e-7)] | None = Field(
        None, description="white detector noise density, m/sqrt(Hz) (overrides detector_rms)"
    )
    thermal: bool = Field(True, description="thermal force noise consistent with k_B T and the damping")
    temperature: PositiveFloat = Field(300.0, description="K")
    adc_step: Annotated[NonNegativeFloat, Field(le=1e-4)] = Field(0.0, description="ADC quantization step, m; 0 = none")


class SimulateConfig(StrictModel):
    model: str = Field("dmt", description="force model, see `afmid effects --models`")
    effects: list[str] = Field(default_factory=list, description="extra effects switched on over the model")
    parameters: dict[str, FiniteFloat] = Field(default_factory=dict, description="model parameters, SI")
    mode: Literal["steady", "transient"] = "steady"
    periods: Annotated[int, Field(ge=3)] = Field(50, description="drive periods kept in the output")
    samples_per_period: PositiveFloat | None = Field(
        200.0, description="output sampling; ignored if data.sample_rate is set"
    )
    steps_per_period: Annotated[int, Field(ge=100)] = Field(2000, description="minimum RK4 steps per period")
    setpoint: Annotated[float, Field(gt=0, lt=1)] | None = Field(
        None, description="A/A0; the separation is searched to reach it (needs drive.free_amplitude)"
    )
    settle_tolerance: PositiveFloat = Field(1e-7, description="relative amplitude change per period at steady state")
    max_settle_periods: Annotated[int, Field(ge=1)] = 20000
    unsettled: Literal["fail", "record"] = Field(
        "fail", description="steady: an oscillation that does not settle within max_settle_periods is refused "
        "(fail) or recorded as it then is (record: a period-n or aperiodic orbit, as an instrument records it)"
    )
    transient_start: Literal["rest", "free"] = Field(
        "free", description="transient: start at rest or in free steady oscillation far from the sample"
    )
    noise: NoiseConfig = Field(default_factory=NoiseConfig)
    seed: Seed = Field(0, description=f"random seed, 0 to {MAX_SEED}")
    map: MapSimulation | None = Field(None, description="a force map over phases (afmid.sections.map_simulation); afmid simulate "
                                      "then writes a map file")
    scan: ScanSimulation | None = Field(None, description="a record taken while scanning a surface under amplitude "
                                        "feedback (afmid.sections.scan)")

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, names: list[str]) -> list[str]:
        return ModelConfig._known_effects(names)


class FitConfig(StrictModel):
    """Sparse-identification settings. The defaults suit steady-state tapping traces."""

    form: Literal["weak", "strong"] = Field(
        "weak",
        description="weak: the equation integrated against windowed Fourier test functions (no derivatives "
        "of data; default, best on the accuracy tests); strong: the equation at every sample with "
        "derivatives from fit.differentiation",
    )
    differentiation: str = Field("savgol", description="differentiator for fit.form: strong (see docs)")
    differentiation_options: dict[str, float] = Field(default_factory=dict)
    max_harmonic: Annotated[int, Field(ge=2, le=500)] = Field(60, description="highest drive harmonic used")
    periods_per_block: Annotated[int, Field(ge=1, le=100)] = 1
    smooth_periods: Annotated[int, Field(ge=1, le=1001)] | None = Field(
        None,
        description="smooth the trajectory the library sees over this many periods (Savitzky-Golay; 1 = none); "
        "default: a Kalman smoother with the cantilever's thermal correlation time Q / pi periods",
    )
    oversample: Annotated[int, Field(ge=1, le=256)] | None = Field(
        None, description="fine-grid points per sample for library terms; default: >= 2048 points per period"
    )
    cantilever: Literal["fixed", "free"] = Field(
        "fixed", description="fixed: calibrated k, Q, f0 held; free: k and damping identified too (as the paper)"
    )
    baseline: Literal["zero", "free"] = Field(
        "zero", description="zero: the file's zero deflection is the rest position; free: fit an offset"
    )
    detrend: Literal["none", "offset", "linear"] = "none"
    drive_frequency: Literal["auto", "response", "search", "nominal"] = Field(
        "auto",
        description="response: the deflection's spectral peak (exact in steady state); search: the frequency at "
        "which the regression's residual is smallest (a record from rest or still settling holds the free "
        "response too, which biases the peak); nominal: drive.frequency as given; auto: search in records whose "
        "amplitude changes by more than 2 %, else response",
    )
    method: Literal["auto", "stlsq", "lasso", "exhaustive"] = Field(
        "auto", description="auto: exhaustive search up to 14 free terms, STLSQ path beyond"
    )
    distractor_odds: Annotated[float, Field(ge=1)] = Field(
        10.0,
        description="prior odds against a library term that belongs to no catalog effect (1 = no prior)",
    )
    selection: Literal["bic", "aicc", "cv"] = "bic"
    selection_scope: str = Field(
        "vote",
        description="vote: the support held by the majority of the selections on groups of fit.vote_periods "
        "periods (consistent as the record grows); record: one selection on all periods at once",
    )
    vote_periods: Annotated[int, Field(ge=1, le=10000)] = Field(
        6, description="periods per group of the selection vote (fit.selection_scope: vote); 6 chosen by measurement "
        "(docs/accuracy.md, 'Selection as the record grows')"
    )
    thresholds: list[NonNegativeFloat] | None = Field(None, description="STLSQ thresholds (relative); default path")
    folds: Annotated[int, Field(ge=2, le=50)] = 5
    bootstrap: Annotated[int, Field(ge=0, le=10000)] = 100
    seed: Seed = Field(0, description=f"random seed, 0 to {MAX_SEED}")
    temperature: PositiveFloat = Field(300.0, description="K, for the thermal force noise weights")
    thermal_noise: bool = True
    thermal_bias: Literal["auto"] | bool = Field(
        "auto", description="take the thermal force's bias of the regression out (afmid.fit.thermal_bias): true, "
        "false, or auto: for a lever of quality factor <= 20 (liquid), where it moves damping terms by several %; in "
        "air it moves E*, H and eta by < 1 % of themselves at 2.4x the fit's CPU"
    )
    estimate_nonlinear: bool = Field(True, description="search decay lengths etc. not fixed in model.parameters")
    separation_window: list[PositiveFloat] = Field(
        default_factory=lambda: [6e-9, 3e-9],
        description="m below / above first contact searched when sample.separation is absent",
    )
    phase_points: Annotated[int, Field(ge=16, le=8192)] = 256
    separation_track: SeparationTrackConfig | None = Field(
        None, description="a slowly varying rest separation d(t) (a record taken while scanning) estimated per block "
        "of periods with one force law (afmid.fit.separation_track); needs sample.separation absent")

    @field_validator("thermal_bias", mode="before")
    @classmethod
    def _thermal_bias_setting(cls, value):
        if value == "auto" or isinstance(value, bool):
            return value
        raise ValueError(f"expected auto, true or false, got {value!r}")

    @field_validator("differentiation")
    @classmethod
    def _known_differentiator(cls, name: str) -> str:
        from afmid.preprocess.differentiation import DIFFERENTIATORS

        if name not in DIFFERENTIATORS:
            raise ValueError(unknown_name_message("differentiator", name, DIFFERENTIATORS.names()))
        return name

    @field_validator("selection_scope")
    @classmethod
    def _known_selection_scope(cls, name: str) -> str:
        from afmid.sections.selection_scopes import SELECTION_SCOPES

        if name not in SELECTION_SCOPES:
            raise ValueError(unknown_name_message("selection scope", name, SELECTION_SCOPES.names()))
        return name

    @model_validator(mode="after")
    def _known_differentiation_options(self) -> "FitConfig":
        from afmid.preprocess.differentiation import DIFFERENTIATORS

        if self.differentiation in DIFFERENTIATORS:
            problem = DIFFERENTIATORS.get(self.differentiation).check_options(self.differentiation_options)
            if problem:
                raise ValueError(problem)
        return self

    @field_validator("separation_window")
    @classmethod
    def _two_values(cls, v: list[float]) -> list[float]:
        if len(v) != 2:
            raise ValueError(f"expected [below, above] in metres, got {v}")
        return v


class RunConfig(StrictModel):
    data: DataConfig = Field(default_factory=DataConfig)
    cantilever: CantileverConfig = Field(default_factory=CantileverConfig)
    drive: DriveConfig = Field(default_factory=DriveConfig)
    sample: SampleConfig = Field(default_factory=SampleConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    fit: FitConfig = Field(default_factory=FitConfig)
    simulate: SimulateConfig = Field(default_factory=SimulateConfig)
    coverage: CoverageConfig | None = Field(
        None, description="experiments `afmid coverage` draws around this config (afmid.sections.coverage)")

    @model_validator(mode="after")
    def _usable_terms(self) -> "RunConfig":
        from afmid.physics.consistency import term_problem

        for i, text in enumerate(self.model.terms):
            problem = term_problem(text, self.fit.baseline)
            if problem:
                raise ValueError(f"model.terms[{i}]: {problem}")
        return self

    @model_validator(mode="after")
    def _separation_per_trace(self) -> "RunConfig":
        separation, paths = self.sample.separation, self.data.paths
        if isinstance(separation, list):
            if paths is None:
                raise ValueError("sample.separation: a list (one separation per trace) needs data.paths; with "
                                 "data.path give one value")
            if len(separation) != len(paths):
                raise ValueError(f"sample.separation: {len(separation)} value(s) for {len(paths)} trace(s) in "
                                 "data.paths; give one per trace, in the same order")
        elif separation is not None and paths is not None and len(paths) > 1:
            raise ValueError("sample.separation: one value for several traces in data.paths; give a list, one "
                             "per trace in the same order (the traces are recorded at different separations)")
        return self

    @model_validator(mode="after")
    def _effects_fit_the_medium(self) -> "RunConfig":
        from afmid.physics.medium import check_config

        check_config(self)  # capillary only in air, double_layer only in liquid; Debye length from ionic strength
        return self

    @model_validator(mode="after")
    def _instrument_fits_the_fit(self) -> "RunConfig":
        declared = [k for k, on in (("data.detector", self.data.detector is not None),
                                    ("cantilever.higher_modes", bool(self.cantilever.higher_modes))) if on]
        if declared and self.fit.form == "strong":
            raise ValueError(f"fit.form: the strong form cannot model {' and '.join(declared)} (the weak form "
                             "applies them per harmonic); use fit.form: weak")
        if "cantilever.higher_modes" in declared and self.fit.cantilever == "free":
            raise ValueError("fit.cantilever: free identifies one mode's k and damping; with "
                             "cantilever.higher_modes declared use fit.cantilever: fixed")
        return self

    # Not part of the YAML: where the config came from, for messages and relative paths.
    _source: Path | None = None
    _base_dir: Path = Path(".")

    @property
    def source(self) -> Path | None:
        return self._source

    def resolve_path(self, path: Path) -> Path:
        """A path from the config, made relative to the config file's folder."""
        return path if path.is_absolute() else (self._base_dir / path)


# --------------------------------------------------------------------------- errors
def validation_error(exc: ValidationError, file: str | Path | None, schema: type[BaseModel] = RunConfig) -> ConfigError:
    """The first pydantic error of ``exc`` as a one-line :class:`ConfigError` (afmid.config_messages)."""
    return config_messages.validation_error(exc, file, schema)


# --------------------------------------------------------------------------- loading
def parse_override(text: str) -> tuple[list[str], Any]:
    """``'cantilever.quality_factor=150'`` -> (['cantilever', 'quality_factor'], 150)."""
    if "=" not in text:
        raise ConfigError(f"--set expects KEY.PATH=VALUE, got {text!r}", key="--set")
    key, raw = text.split("=", 1)
    path = [p for p in key.strip().split(".") if p]
    if not path:
        raise ConfigError(f"--set expects KEY.PATH=VALUE, got {text!r}", key="--set")
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(
            f"--set {key.strip()}: the value {raw!r} is not valid YAML ({problem}); quote it or fix the brackets",
            key="--set",
        ) from None
    return path, value


def apply_overrides(raw: dict, overrides: list[tuple[list[str], Any]]) -> dict:
    """Set nested keys in a plain config mapping (command-line layer)."""
    for path, value in overrides:
        node = raw
        for part in path[:-1]:
            child = node.get(part)
            if not isinstance(child, dict):
                child = {}
                node[part] = child
            node = child
        node[path[-1]] = value
    return raw


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML silently keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key: SafeLoader reports it
                continue
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice in the same section", key_node.start_mark
                )
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: Path) -> dict:
    """Read a YAML mapping, with a clear error for a missing, special, unreadable or binary file or bad syntax."""
    check_input_file(path, what="config file", error=ConfigError, allow_empty=True)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read the config file: {exc.strerror or exc}", file=path) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"not a text file: byte 0x{raw[exc.start]:02x} at offset {exc.start} is not UTF-8 (a config is UTF-8 YAML)",
            file=path,
        ) from None
    if "\0" in text:
        raise ConfigError(f"not a text file: it holds a NUL byte at offset {text.index(chr(0))} (expected YAML)",
                          file=path)
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"invalid YAML: {where}{problem}", file=path) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"expected a mapping of sections at the top level, got {type(data).__name__}", file=path)
    return data


def build_config(raw: dict, source: Path | None = None, base_dir: Path | None = None) -> RunConfig:
    """Validate a plain mapping into a :class:`RunConfig` (errors name ``source``)."""
    try:
        config = RunConfig.model_validate(raw)
    except ValidationError as exc:
        raise validation_error(exc, source) from None
    config._source = source
    config._base_dir = base_dir if base_dir is not None else (source.parent if source else Path("."))
    return config


def load_config(path: str | Path, overrides: list[str] | None = None) -> RunConfig:
    """Load, layer and validate a run config file."""
    path = Path(path)
    raw = read_yaml(path)
    if overrides:
        raw = apply_overrides(raw, [parse_override(o) for o in overrides])
    return build_config(raw, source=path)


def dump_config(config: RunConfig) -> str:
    """The merged config as YAML text (stored in every output for provenance)."""
    data = config.model_dump(mode="json")
    if config.model.library is not None:
        data["model"]["effects"] = []  # a preset's run uses no effects (and both given is refused on reading)
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


#: With ``--simulate`` these template lines are switched on: ``afmid simulate`` needs a drive (A0) and a rest
#: separation, so the config simulates as written (A0 = 10 nm at d = 8.5 nm: the tip taps the sample).
_SIMULATE_LINES = {
    "  # free_amplitude: 10.0e-9 ": "  free_amplitude: 10.0e-9   ",
    "  # separation: 14.0e-9        # m, rest tip-sample distance d; estimated by the fit if absent":
        "  separation: 8.5e-9           # m, rest tip-sample distance d of the simulation; the fit takes it as "
        "given: comment it out to have d estimated",
}


def template_text(simulate: bool = False) -> str:
    """The commented template written by ``afmid init-config`` (``simulate``: with a commented simulate section,
    and the drive's A0 and the rest separation it needs switched on, :data:`_SIMULATE_LINES`)."""
    names = ["run_config.yaml"] + (["simulate_section.yaml"] if simulate else [])
    text = "".join((Path(__file__).parent / "templates" / n).read_text(encoding="utf-8") for n in names)
    if simulate:
        for commented, active in _SIMULATE_LINES.items():
            if commented not in text:  # the template changed: fail loudly rather than write a config that fails
                raise RuntimeError(f"template line not found: {commented.strip()!r}")
            text = text.replace(commented, active, 1)
    return text

"""The front door's inputs: a trace from a file or a simulation, and the force model to fit to it.

:func:`read` goes through the readers and checks of ``afmid fit`` (:func:`afmid.io.trace.load_trace`);
:func:`simulate_trace` through ``afmid simulate``'s driver; :class:`ForceModel` builds the same run config the command
line builds from a YAML file (:func:`afmid.config.build_config`) and :meth:`ForceModel.fit` calls the same
pipeline (:func:`afmid.fit.pipeline.run_fit`). The cantilever is the trace's (given once: with the array, in the
file's metadata or to :func:`read`); the model holds what belongs to the sample and the fit.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

from afmid.config import RunConfig, build_config, load_config
from afmid.errors import ConfigError, InputError
from afmid.io.cantilever import Cantilever
from afmid.io.trace import Trace, check_trace, load_trace

#: How a model names itself in error lines (there is no config file).
MODEL = Path("ForceModel")


def read(path: str | Path, *, cantilever: Cantilever | None = None, drive_frequency: float | None = None,
         **data: Any) -> Trace:
    """The trace in the file ``path``, read and checked as ``afmid fit`` reads ``data.path``.

    ``data``: the config's ``data:`` keys (column, time_column, sample_rate in Hz, units, positive, invols in m/V,
    start / stop in s, detector, ...); ``cantilever`` and ``drive_frequency`` (Hz) where the file does not say
    them (an afmid trace file does; given, they override the file's, as the config's keys do).
    """
    raw: dict[str, Any] = {"data": {**data, "path": str(Path(path).absolute())}}
    if cantilever is not None:
        raw["cantilever"] = cantilever.config_section()
    if drive_frequency is not None:
        raw["drive"] = {"frequency": drive_frequency}
    return load_trace(build_config(raw, source=Path(path)))


def simulate_trace(config: str | Path | dict | RunConfig, progress: bool = False) -> Trace:
    """A simulated trace with its ground truth, as ``afmid simulate`` makes it: ``config`` a run config (a YAML
    file, a mapping of its sections or a :class:`afmid.config.RunConfig`) whose ``simulate:`` section describes
    the sample; checked as a loaded trace is."""
    from afmid.simulate.driver import simulate as run_simulation

    if isinstance(config, dict):
        config = build_config(config, source=Path("afmid.simulate_trace"))
    elif not isinstance(config, RunConfig):
        config = load_config(config)
    return check_trace(run_simulation(config, progress=progress), config)


class ForceModel:
    """A force model to identify: catalog ``effects`` (``afmid effects``), or a preset ``library`` and custom
    ``terms``; ``parameters`` fixed nonlinear parameters (SI, e.g. a decay length); ``separation`` the rest
    separation d in m (None: estimated); ``a0`` the intermolecular distance in m; ``medium`` air or liquid;
    ``sample``, ``fit``, ``drive``: further keys of those config sections (e.g. ``fit={"bootstrap": 20}``; a
    calibrated drive ``drive={"force_amplitude": ..., "phase": ...}``); ``separation_track`` the keys of
    ``fit.separation_track`` (e.g. ``{"bandwidth": 2500.0}`` in Hz, ``"within_block": "rows"``): the record is
    fitted in blocks, a rest separation per block, one force law (:meth:`afmid.api.fit.Fit.of_track`). Validated as
    a config file is."""

    def __init__(self, effects: list[str] | tuple[str, ...] = ("dmt",), *, parameters: dict | None = None,
                 separation: float | None = None, a0: float | None = None, medium: str | None = None,
                 library: str | None = None, terms: list[str] | tuple[str, ...] = (), sample: dict | None = None,
                 fit: dict | None = None, drive: dict | None = None, separation_track: dict | None = None):
        model: dict[str, Any] = {"terms": list(terms), "parameters": dict(parameters or {})}
        fit = dict(fit or {})
        if separation_track is not None:
            if fit.get("separation_track") is not None:
                raise ConfigError("the separation track is given twice: as separation_track=... and in "
                                  "fit={'separation_track': ...}; give it once", file=MODEL, key="separation_track")
            fit["separation_track"] = dict(separation_track)
        if library is None:
            model["effects"] = list(effects)
        else:
            model["library"] = library
        sample = dict(sample or {})
        for key, value in (("separation", separation), ("a0", a0), ("medium", medium)):
            if value is not None:
                sample[key] = value
        self._sections = {"model": model, "sample": sample, "fit": fit, "drive": dict(drive or {})}
        self._checked = build_config(copy.deepcopy(self._sections), source=MODEL)  # a bad key fails here

    @classmethod
    def from_config(cls, config: RunConfig) -> "ForceModel":
        """The model of a run config (its model, sample, fit and drive sections; the data, lever and drive
        frequency are the trace's)."""
        dump = config.model_dump(mode="json", exclude_none=True)
        model = dump["model"]
        drive = {k: v for k, v in dump["drive"].items() if k not in ("frequency", "free_amplitude")}
        return cls(model.get("effects", ()) if model.get("library") is None else (), library=model.get("library"),
                   terms=model["terms"], parameters=model["parameters"], sample=dump["sample"], fit=dump["fit"],
                   drive=drive)

    @classmethod
    def of(cls, fit) -> "ForceModel":
        """The model a :class:`afmid.api.fit.Fit` was fitted with (also of a fit loaded from its run file)."""
        return cls.from_config(fit.config)

    @property
    def effects(self) -> list[str]:
        return list(self._checked.model.effects) if self._checked.model.library is None else []

    def config(self, trace: Trace) -> RunConfig:
        """The run config of this model fitted to ``trace``: its data keys (how the file was read), its lever
        and drive frequency, and this model's sections."""
        raw = copy.deepcopy(self._sections)
        raw["data"] = dict(trace.reading)
        raw["cantilever"] = trace.cantilever.config_section()
        raw["drive"] = {"frequency": trace.drive_frequency, **raw["drive"]}
        return build_config(raw, source=MODEL, base_dir=Path.cwd())

    def fit(self, trace: Trace | list[Trace] | tuple[Trace, ...], *, progress: bool = False,
            name: str | None = None, separations: list[float | None] | None = None):
        """Identify the force law in ``trace`` (:func:`afmid.fit.pipeline.run_fit`, as ``afmid fit``): an
        :class:`afmid.api.fit.Fit` named ``name`` (default: its effects joined by +).

        With a separation track (``separation_track=``), ``trace`` is one record, fitted in blocks
        (:meth:`afmid.api.fit.Fit.of_track`, as ``afmid fit`` of ``fit.separation_track``).

        A list of traces of one sample, lever and tip is fitted jointly (:func:`afmid.fit.joint.fit_traces_jointly`,
        as ``afmid fit`` of ``data.paths``): one shared force law, a separation per trace; ``separations`` gives
        them (m, one per trace, None: estimated), as ``sample.separation`` does for ``data.paths``."""
        from afmid.api.fit import Fit
        from afmid.fit.pipeline import run_fit

        tracked = self._checked.fit.separation_track is not None
        if isinstance(trace, (list, tuple)):
            if tracked:
                raise ConfigError("a separation track is fitted on one record: give one trace, not a list",
                                  file=MODEL, key="fit(traces)")
            return self._fit_jointly(list(trace), progress, name, separations)
        self._check_trace(trace, "fit(trace)")
        if separations is not None:
            raise ConfigError("separations are given per trace of a joint fit; for one trace give "
                              "ForceModel(separation=...)", file=MODEL, key="fit(separations)")
        config = self.config(trace)
        if tracked:
            return Fit.of_track(config, trace, progress=progress, name=name)
        result = run_fit(config, progress=progress, trace=trace)
        return Fit(result, config, trace=trace, name=name)

    def _fit_jointly(self, traces: list[Trace], progress: bool, name: str | None,
                     separations: list[float | None] | None):
        from afmid.api.fit import Fit
        from afmid.fit.joint import fit_traces_jointly, lever_mismatch

        if not traces:
            raise ConfigError("the list is empty; give the traces to fit jointly", file=MODEL, key="fit(traces)")
        for i, trace in enumerate(traces):
            self._check_trace(trace, f"fit(traces[{i}])")
        given = self._checked.sample.separation
        if separations is not None and given is not None:
            raise ConfigError("give the separations once: ForceModel(separation=...) or fit(separations=[...])",
                              file=MODEL, key="fit(separations)")
        if separations is None:
            if given is not None and len(traces) > 1:  # as sample.separation with data.paths
                raise ConfigError("one separation for several traces; give one per trace, "
                                  "fit(traces, separations=[...])", file=MODEL, key="separation")
            separations = [given] * len(traces)
        if len(separations) != len(traces):
            raise ConfigError(f"{len(separations)} separation(s) for {len(traces)} trace(s); give one per trace, "
                              "in the same order", file=MODEL, key="fit(separations)")
        mismatch = lever_mismatch(traces, "traces[0]")
        if mismatch is not None:
            i, reason = mismatch
            raise InputError(reason, file=traces[i].path or MODEL, key=f"fit(traces[{i}])")
        configs = [self._with_separation(trace, d) for trace, d in zip(traces, separations)]
        result = fit_traces_jointly(configs[0], configs, traces, progress)
        return Fit.of_joint(result, name=name)

    def _with_separation(self, trace: Trace, separation: float | None) -> RunConfig:
        """The run config of this model fitted to ``trace`` at rest separation ``separation`` (m; None:
        estimated), checked as ``sample.separation`` is."""
        if separation == self._checked.sample.separation:
            return self.config(trace)
        changed = copy.deepcopy(self)
        changed._sections["sample"] = {**self._sections["sample"], "separation": separation}
        return changed.config(trace)

    @staticmethod
    def _check_trace(trace, key: str) -> None:
        if not isinstance(trace, Trace):
            raise ConfigError(f"expected an afmid.Trace (afmid.read, afmid.Trace.from_array), got "
                              f"{type(trace).__name__}", file=MODEL, key=key)

    def _changed(self, add: tuple[str, ...], remove: tuple[str, ...]) -> "ForceModel":
        from afmid.fit.pipeline import apply_effect_changes

        config = copy.deepcopy(self._checked)
        apply_effect_changes(config, add, remove)  # the checks of --add / --remove
        changed = copy.deepcopy(self)
        changed._sections["model"]["effects"] = list(config.model.effects)
        changed._checked = config
        return changed

    def add(self, *effects: str) -> "ForceModel":
        """A new model with ``effects`` added (as ``afmid fit --add``); this one is unchanged."""
        return self._changed(effects, ())

    def remove(self, *effects: str) -> "ForceModel":
        """A new model without ``effects`` (as ``afmid fit --remove``); this one is unchanged."""
        return self._changed((), effects)

    def __repr__(self) -> str:
        model = self._checked.model
        what = f"library={model.library!r}" if model.library is not None else f"effects={list(model.effects)}"
        extra = [f"{k}={v!r}" for k, v in (("terms", list(model.terms)), ("parameters", dict(model.parameters)))
                 if v]
        separation = self._checked.sample.separation
        extra.append("separation=estimated" if separation is None else f"separation={separation:g} m")
        track = self._checked.fit.separation_track
        if track is not None:
            extra.append(f"separation_track={track.bandwidth:g} Hz ({track.within_block} within a block)")
        return f"ForceModel({', '.join([what] + extra)})"

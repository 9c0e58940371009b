"""A fit as a Python object: :class:`Fit` (made by :meth:`afmid.api.model.ForceModel.fit`, or read back by :func:`load`).

A Fit is its run record (:class:`afmid.runfile.RunData`: everything the run file holds, made from the fit by
:func:`afmid.runfile.run_data` or read by :func:`afmid.runfile.load_run`; :meth:`Fit.save` writes it), so a fit and
its saved file give the same table, text (verbose included: the candidate supports are in the record),
warnings and verdicts. A fit made here also keeps the pipeline's working state privately, what its record is
made from.
The diagnosis and the report run on that RunData with the trace held in memory (no temporary file); a fit loaded
without its trace refits the candidates on the run's input file, as ``afmid report`` does.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from afmid.api.tables import Diagnosis, ForceCurve, Parameters, SeparationTrackTable
from afmid.errors import ConfigError


class Fit:
    """An identified force law with its parameters, forces, diagnosis and run file (SI throughout)."""

    def __init__(self, result, config, *, trace=None, name: str | None = None, run=None):
        # The pipeline's working state of a fit made here (None: loaded): what the run record is made from
        self._result = result
        self.config = config
        self._trace = trace if trace is not None or result is None else result.prep.trace
        self.name = name or default_name(config)
        self._run = run
        self._diagnosis: Diagnosis | None = None

    @classmethod
    def from_config(cls, config, progress: bool = False, name: str | None = None) -> "Fit":
        """The fit of a run config's own trace (``data.path``), or the joint fit of its traces (``data.paths``:
        :meth:`of_joint`), or the separation track of its trace (``fit.separation_track``: :meth:`of_track`), as
        ``afmid fit CONFIG`` makes it."""
        if config.fit.separation_track is not None:
            if config.data.path is None:
                raise ConfigError("a separation track is fitted on one record: give data.path", file=config.source,
                                  key="data.path")
            from afmid.io.trace import load_trace

            return cls.of_track(config, load_trace(config), progress=progress, name=name)
        if config.data.paths is not None:
            from afmid.fit.joint import run_joint_fit

            return cls.of_joint(run_joint_fit(config, progress=progress), name=name)
        from afmid.fit.pipeline import run_fit

        return cls(run_fit(config, progress=progress), config, name=name)

    @classmethod
    def of_joint(cls, result, name: str | None = None) -> "Fit":
        """The fit of a joint fit's result (:class:`afmid.fit.joint.JointResult`: several traces of one sample,
        one force law): its run record is the joint one (:func:`afmid.joint_runfile.joint_record`, what ``afmid
        fit`` of ``data.paths`` writes: trace 0's in the single-trace layout, every trace's row in ``/joint``);
        its trace is trace 0."""
        from afmid.joint_runfile import joint_record

        first = result.traces[0].config
        name = name or default_name(first)
        run, per_trace = joint_record(result, name)
        return cls(per_trace[0], first, name=name, run=run)

    @classmethod
    def of_track(cls, config, record, progress: bool = False, name: str | None = None) -> "Fit":
        """The separation track of ``record`` (``config``'s ``fit.separation_track``: the record, checked as ``afmid
        fit`` checks it, cut into blocks of whole periods fitted jointly, one force law and a d per block;
        :func:`afmid.fit.separation_track.fit_separation_track`). Its run record is the blocks' joint record with
        the track (:func:`afmid.joint_runfile.track_run`): the rest of the fit is block 0's; its trace is
        ``record``."""
        from afmid.fit.separation_track import fit_separation_track
        from afmid.io.trace import check_trace
        from afmid.joint_runfile import track_run

        track = fit_separation_track(config, check_trace(record, config), config.fit.separation_track.bandwidth,
                                     progress=progress)
        name = name or default_name(config)
        run, per_block = track_run(track, name)
        return cls(per_block[0], config, trace=record, name=name, run=run)

    # ------------------------------------------------------------------ what the run holds
    @property
    def trace(self):
        """The fitted :class:`afmid.io.trace.Trace` (of a loaded fit: the one given to :func:`load`, or None)."""
        return self._trace

    @property
    def run(self):
        """The run as its run file holds it (:class:`afmid.runfile.RunData`)."""
        if self._run is None:
            from afmid.runfile import run_data

            self._run = run_data(self._result, self.config, self.name)
        return self._run

    @property
    def effects(self) -> list[str]:
        return list(self.run.effects)

    @property
    def joint(self) -> list[dict]:
        """A joint fit's traces, in order (empty for a fit of one trace): each a dict of path, sha256,
        separation (m), separation_estimated, separation_error (m, 1 sigma; 0 when given), cv_error,
        cv_error_noise_floor, model_limited, drive_frequency (Hz) and its per-period curves (``periods``, SI, as
        the run file's ``/joint/trace_<i>/periods``). The rest of the fit is trace 0's, with the shared law."""
        return list(self.run.joint or [])

    @property
    def separation_track(self) -> SeparationTrackTable | None:
        """A separation track's blocks (``fit.separation_track``): each block's time, d and its 1 sigma, samples
        (SI, :class:`afmid.api.tables.SeparationTrackTable`); None for a fit without a track. The blocks are also
        :attr:`joint`'s rows; the rest of the fit is block 0's."""
        return SeparationTrackTable.of_run(self.run)

    @property
    def terms(self) -> list[str]:
        """The selected terms of the identified law."""
        return list(self.run.selected_terms)

    @property
    def cv_error(self) -> float:
        """The cross-validated relative force error (1: no better than zero)."""
        return float(self.run.cv_error)

    @property
    def noise_floor(self) -> float:
        """The cross-validated error a perfect model would show at this noise."""
        return float(self.run.cv_error_noise_floor)

    @property
    def model_limited(self) -> bool:
        """The error stands above its noise floor: the parameters are biased beyond their error bars."""
        return bool(self.run.model_limited)

    @property
    def warnings(self) -> list[str]:
        """The run's warning lines (``warning: ...``): the trace's findings on load, then the fit's own
        (model-limited, non-periodic motion, a failed contact-law probe, ...)."""
        return list(self.run.warnings)

    @property
    def implausible(self) -> list[str]:
        """Why read-outs cannot be physical, one reason per implausible read-out and for an estimated rest
        separation out of range (:mod:`afmid.fit.plausibility`; the same verdicts the run file stores); empty when
        every read-out is plausible."""
        return list(self.run.implausible)

    def summary_line(self) -> str:
        """One line for a log: ``cv_error 0.0434; terms: ...`` (the selected terms, or none); for a joint fit
        ``joint fit of 2 traces; terms: ...`` (each trace has its own error: :attr:`joint`); for a separation
        track ``3 blocks, one force law; terms: ...``."""
        terms = ", ".join(self.terms) or "none"
        if self.run.separation_track is not None:
            return f"{len(self.run.separation_track['separation'])} blocks, one force law; terms: {terms}"
        if self.run.joint:
            return f"joint fit of {len(self.run.joint)} traces; terms: {terms}"
        return f"cv_error {self.cv_error:.4f}; terms: {terms}"

    @property
    def parameters(self) -> Parameters:
        """The physical parameters: value, 1 sigma, unit (SI), 95 % interval, flags."""
        return Parameters.of_run(self.run)

    # ------------------------------------------------------------------ text
    def text(self, verbose: bool = False) -> str:
        """What ``afmid fit`` prints (:func:`afmid.report.fit_text.fit_text`); ``verbose`` as ``afmid fit -v``."""
        from afmid.report.fit_text import fit_text

        from afmid.api.readout import RunReadout

        path = self.run.selection_path
        if verbose and (not path or (path["criterion"] == "aicc" and "aicc" not in path)):
            raise ConfigError("the run file keeps no candidate supports with their criterion values (written by an "
                              "older afmid): verbose text needs a newer run file", file=self.run.path, key="verbose")
        text = fit_text(RunReadout(self.run), verbose=verbose)
        track = self.separation_track
        if track is not None:  # the blocks' d(t), not the traces' table: every block is a part of one record
            return f"{text}\n{track.text()}"
        if not self.run.joint:
            return text
        from afmid.fit.joint_output import joint_table

        return f"{text}\n{joint_table(self.run.joint)}"

    def print(self, verbose: bool = False) -> None:
        print(self.text(verbose))

    def __repr__(self) -> str:
        limited = "model-limited" if self.model_limited else "at the noise floor"
        return (f"<afmid.Fit {self.name!r}: effects {self.effects}, terms {self.terms}; cv error "
                f"{self.cv_error:.3f}, noise floor {self.noise_floor:.3f} ({limited}); "
                f"{len(self.parameters)} parameters>")

    # ------------------------------------------------------------------ forces
    def force_curve(self) -> ForceCurve:
        """The force against separation over one period, averaged over the periods (:class:`ForceCurve`)."""
        periods = self.run.periods
        separation, model, inverted = (np.asarray(periods[k], dtype=float)
                                       for k in ("separation", "force_model", "force_inverted"))
        n = separation.shape[0]
        force = model.mean(axis=0)
        total = float(self.run.force_total_uncertainty)
        sigma = np.full(force.shape, total * float(np.max(np.abs(force))) if math.isfinite(total) else math.nan)
        mean_separation = separation.mean(axis=0)
        spread = inverted.std(axis=0, ddof=1) / math.sqrt(n) if n > 1 else np.full(force.shape, math.nan)
        phase = np.asarray(periods["phase"], dtype=float)
        return ForceCurve(phase if phase.ndim == 1 else phase[0], mean_separation, force, sigma,
                          inverted.mean(axis=0), spread, np.gradient(mean_separation) < 0, n)

    def predict(self, separation, velocity=0.0) -> np.ndarray:
        """The identified law's force on the tip (N, positive = repulsive) at ``separation`` z (m) moving at
        ``velocity`` dz/dt (m/s; arrays broadcast). A law with a state (hysteresis, relaxation) depends on the
        path, not on (z, dz/dt): refused, see :meth:`force_curve`."""
        from afmid.simulate.driver import identified_law
        from afmid.simulate.model import compile_force_law, force_numpy

        compiled = compile_force_law(identified_law(self.run))
        if compiled.n_gates:
            raise ConfigError("the identified law has a state (its force depends on the path, not only on z and "
                              "dz/dt); use force_curve()", file=self.run.path, key="predict")
        z, v = np.broadcast_arrays(np.asarray(separation, dtype=float), np.asarray(velocity, dtype=float))
        d = float(self.run.separation)
        force = force_numpy(compiled, (d - z).ravel(), -v.ravel(), np.zeros(z.size), d, np.zeros(0))
        return np.broadcast_to(force, (z.size,)).reshape(z.shape)

    # ------------------------------------------------------------------ diagnosis, report, file
    def diagnose(self, progress: bool = False) -> Diagnosis:
        """Where the model fails and which catalog effect is missing (``afmid report``'s diagnosis): each missing
        effect refitted on this fit's trace."""
        if self._diagnosis is None:
            from afmid.diagnosis.stored import diagnosed

            # A loaded run file's /diagnosis (written by save() below) or a cached one is reused when made for
            # this very run (afmid.diagnosis.stored)
            self._diagnosis = Diagnosis.of(diagnosed(self.run, progress=progress, trace=self.trace))
        return self._diagnosis

    def report(self, folder: str | Path, *, compare: list["Fit"] | tuple["Fit", ...] = (), overwrite: bool = False,
               suggest: bool = True, progress: bool = False, allow_different_traces: bool = False) -> str:
        """Write ``afmid report``'s folder for this fit (``compare``: earlier fits of the same trace, drawn first,
        as ``afmid report run1.h5 run2.h5``; of different traces only with ``allow_different_traces``, and the
        report says so); return the summary it prints."""
        from afmid.report.page import write_report
        from afmid.runcheck import check_same_traces

        fits = [*compare, self]
        names = [f.name for f in fits]
        made = [f.name for f in fits if f._result is not None]  # a loaded fit is named by its file: one run
        if len(set(made)) != len(made) or set(made) & {f.name for f in fits if f._result is None}:
            raise ConfigError(f"two fits are named alike ({names}); give them distinct names (fit(trace, name=...))",
                              file=Path(folder), key="compare")
        traces = [f.trace for f in fits]
        runs = [f.run for f in fits]
        notes = check_same_traces(runs, allow_different_traces)  # the input files' SHA-256
        arrays_differ = any(t is not traces[0] and t is not None and traces[0] is not None
                            and not np.array_equal(t.deflection, traces[0].deflection) for t in traces)
        if arrays_differ and not allow_different_traces:  # arrays have no SHA-256 in the run: their samples
            raise ConfigError("the fits are of different traces: comparing them compares the traces, not the "
                              "models; pass allow_different_traces=True to do that on purpose", file=Path(folder),
                              key="compare")
        if arrays_differ and not notes:
            notes = ["the runs were fitted on different traces: their errors and parameters compare the traces as "
                     "much as the models"]
        run_files = {f.run.path: "a run file" for f in fits if f._result is None}  # never replaced by the folder
        return write_report(runs, Path(folder), overwrite, suggest, progress, notes=notes, names=names,
                            traces=traces, inputs=run_files)

    def save(self, path: str | Path, overwrite: bool = False) -> Path:
        """Write the run file (the same file as ``afmid fit -o PATH``); after :meth:`diagnose` it also holds the
        diagnosis (/diagnosis, docs/file-formats.md), which ``afmid report`` then reuses instead of refitting."""
        from afmid.runfile import write_run

        if self._result is None:
            raise ConfigError("a loaded fit is its run file already; copy the file", file=Path(path), key="save")
        if self._diagnosis is None:
            return write_run(Path(path), self.run, overwrite=overwrite)
        from afmid.diagnosis.stored import diagnosis_key, write_group

        answer, key = self._diagnosis.details, diagnosis_key(self.run)
        return write_run(Path(path), self.run, overwrite=overwrite, extra=lambda h5: write_group(h5, answer, key))


def default_name(config) -> str:
    """A fit's name when none is given: its effects joined by +, else its library, else ``fit``."""
    return "+".join(config.model.effects) or (config.model.library or "fit")


def load(path: str | Path, trace=None) -> Fit:
    """The :class:`Fit` of a run file (``afmid fit -o``, :meth:`Fit.save`), named by ``path`` as given (as
    ``afmid report`` names its runs); ``trace``: its trace in memory, for the diagnosis of a fit of an array
    (otherwise the run's input file is read again)."""
    from afmid.runfile import load_run

    run = load_run(path)
    return Fit(None, run.config, trace=trace, name=str(run.path), run=run)

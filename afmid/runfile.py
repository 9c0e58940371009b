"""Run files: the run record (:class:`RunData`, made from a fit by :func:`run_data`), its one writer
(:func:`write_run`: the file is the record's serialisation) and the readers of what ``afmid fit`` stores.

The layout is documented in docs/file-formats.md (tests/cli/test_run_file.py checks
it against a written file; tests/cli/test_run_data.py that ``write_run(load_run(file))`` writes the same file).
Readers:

- :func:`load_run`: the whole run as a :class:`RunData`, for the diagnosis and
  the report. Strict: a run file of another version, a missing dataset or
  attribute, a stored config that is not valid or unreadable data is one
  InputError naming the file and the path inside it (the checks of
  :mod:`afmid.runcheck`).
- :func:`read_summary` and :func:`read_batch_key`: the values of one row of a
  batch summary and the key that tells whether a run file is up to date. Lenient
  on purpose: a batch reads the files it wrote itself, older files lack a few
  attributes (NaN or an empty string then), and a file it cannot read is fitted
  again rather than reported (OSError / KeyError, as h5py raises them).

Text comes back from h5py as ``str`` or ``bytes`` depending on how it was
stored; every reader here turns it into ``str`` with :func:`text`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import afmid.fit.plausibility as plausibility
from afmid.config import RunConfig, build_config, dump_config
from afmid.errors import ConfigError, InputError
from afmid.io.files import check_input_file, is_regular_file
from afmid.physics.effects import EFFECTS
from afmid.io.trace import RUN_FORMAT, TRACE_FORMAT, Truth, atomic_hdf5, check_output_path, create_dataset, read_truth, write_dataset
from afmid.fit.uncertainty import (ERROR_ATTRS, ERROR_LABEL, FLOOR_FACTOR, FLOOR_QUANTILE, TRACK_LEVEL_ERROR,
                                   floor_threshold, intervals_kind)
from afmid.runcheck import RunReader, check_version, input_unchanged, stored_config

if TYPE_CHECKING:  # an annotation only: the run file is written from a fit's result (fit is a layer below)
    from afmid.fit.pipeline import FitResult

log = logging.getLogger(__name__)

#: Units of the datasets in ``/periods`` (per-period summaries and curves), by name.
PERIOD_UNITS = {
    "phase": "rad", "period_start_time": "s", "deflection": "m", "velocity": "m/s", "acceleration": "m/s^2", "separation": "m",
    "force_model": "N", "force_inverted": "N", "peak_force": "N", "adhesion_force": "N", "max_indentation": "m",
    "contact_time": "s", "dissipated_energy": "J", "dissipated_energy_inverted": "J", "virial": "J",
    "virial_inverted": "J", "amplitude": "m", "period_error": "N",
}

#: ``/model/drive`` attribute ``source``: whence the drive force the inverted force is computed with.
DRIVE_FITTED = "fitted (two nuisance columns of the regression: depends on the force model)"
DRIVE_CALIBRATED = "calibrated (drive.force_amplitude, drive.phase: given, not fitted)"

#: Names of older run files (before the inverted force was named for what it is), read as the new ones.
LEGACY_NAMES = {"force": {"direct": "inverted"},
                "periods": {"force_direct": "force_inverted", "dissipated_energy_direct": "dissipated_energy_inverted",
                            "virial_direct": "virial_inverted"}}


def drive_kind(declared) -> str:
    """``fitted`` or ``calibrated``: the drive the inverted force is computed with."""
    return "fitted" if declared is None else "calibrated"


def inverted_force_meaning(calibrated: bool) -> str:
    """What the run file's inverted force is and what it depends on."""
    if calibrated:
        return ("inverted force F = F_drive - (m x'' + c x' + k x) from the cantilever equation with the calibrated "
                "drive (drive.force_amplitude, drive.phase): depends on the data, k, Q, f0 and the drive calibration, "
                "not on the force model; band-limited to the signal harmonics")
    return ("inverted force F = F_drive - (m x'' + c x' + k x) from the cantilever equation with the drive fitted "
            "together with the force model: its first harmonic (dissipated energy, virial) depends on the model; "
            "band-limited to the signal harmonics")


def renamed(group: str, items) -> dict:
    """``{name: value}`` of a run file's group with the names of older files (:data:`LEGACY_NAMES`) made current."""
    legacy = LEGACY_NAMES.get(group, {})
    return {legacy.get(k, k): v for k, v in items}


def text(value, errors: str = "strict") -> str:
    """An HDF5 string as ``str``.

    h5py returns attributes written as ``str`` as ``str``, but fixed-length strings and the elements of string
    datasets as ``bytes`` (UTF-8); anything else (a number) goes through ``str()``. ``errors`` as for
    :meth:`bytes.decode`.
    """
    if isinstance(value, bytes):
        return value.decode("utf-8", errors)
    return str(value)


# --------------------------------------------------------------------------- writer
def write_run(path, run: RunData, overwrite: bool = False, root_attrs: dict | None = None, extra=None):
    """Write the run file of the run record ``run`` (layout: docs/file-formats.md): the file is the record's
    serialisation, :func:`load_run` its inverse (tests/cli/test_run_data.py). ``root_attrs`` are further root
    attributes (a batch's resume key), written with the rest rather than by opening the file again;
    ``extra(h5)`` writes further groups into the same file before it appears (a joint fit's /joint,
    afmid.joint_runfile)."""
    path = check_output_path(path, overwrite)
    inputs = {str(run.input_path): run.input_sha256} if run.input_path is not None else {}
    with atomic_hdf5(path, RUN_FORMAT, run.stored_config, inputs) as h5:
        for name, value in (root_attrs or {}).items():
            h5.attrs[name] = value
        write_run_contents(h5, run)
        if extra is not None:
            extra(h5)
    # one warning line per implausible read-out, as the file lists them (afmid.fit.plausibility.warn)
    plausibility.warn({str(i): plausibility.Verdict(False, reason) for i, reason in enumerate(run.implausible)})
    return path


def run_data(result: FitResult, config: RunConfig, name: str = "fit") -> RunData:
    """The run record of a fit: everything its run file holds (:func:`write_run` writes it, :func:`load_run` reads
    it back; tests/cli/test_run_data.py compares the two field by field on several fits), in the types
    :func:`load_run` reads them as. ``name`` stands for the file's name (``path``); the ground truth is the
    fitted trace's own."""
    trace = result.prep.trace
    path = Path(name)
    p = result.n_library
    input_path = Path(str(Path(trace.path).resolve())) if trace.path else None
    verdicts = plausibility.check_run(result.quantities, result.nonlinear)
    best = result.selection.best
    d_estimate = result.nonlinear.get("d")
    periods = result.periods
    config_text = dump_config(config)
    separation_verdict = verdicts.get(plausibility.SEPARATION)
    declared = result.prep.declared_drive
    return RunData(
        path=path,
        config=run_config(stored_config(config_text, path), path, input_path),
        effects=[e for e in result.library.effects if e],
        terms=list(result.library.names),
        expressions=[t.expression for t in result.library.terms],
        units=[t.coefficient_unit for t in result.library.terms],
        coefficients=stored_coefficients(result),
        errors=np.array(result.coef_std[:p]),
        selected=np.array(result.selected[:p], dtype=bool),
        inclusion=np.array(result.inclusion[:p]),
        # by name, as the file's groups are read back
        quantities={name: quantity_record(name, q, verdicts[name]) for name, q in sorted(result.quantities.items())},
        nonlinear={name: nonlinear_record(est) for name, est in sorted(result.nonlinear.items())},
        separation=float(result.system.params["d"]),
        separation_error=float(d_estimate.sigma) if d_estimate is not None else 0.0,
        separation_estimated=config.sample.separation is None,
        cv_error=float(result.cv_error),
        cv_error_noise_floor=float(result.cv_error_noise_floor),
        bic=float(best.bic),
        chi2_reduced=float(chi2_reduced(result)),
        drive={k: float(v) for k, v in sorted(drive_values(result).items())},  # the file's (name) order
        cantilever={k: float(v) for k, v in sorted(cantilever_values(trace.cantilever).items())},
        periods=dict(sorted((k, np.array(periods[k])) for k in periods)),
        force=dict(sorted(force_values(result).items())),
        drive_source=DRIVE_CALIBRATED if declared is not None else DRIVE_FITTED,
        input_path=input_path,
        input_sha256=(trace.sha256 or "") if input_path is not None else None,
        warnings=[str(w) for w in result.warnings],
        n_rows=int(result.system.n_rows),
        harmonics=np.asarray(result.prep.blocks.harmonics).astype(int),
        signal_rows=np.asarray(result.signal_rows).astype(bool),
        model_limited=bool(result.model_limited),
        cv_error_floor_dof=float(getattr(result, "cv_error_floor_dof", math.nan)),
        cv_error_folds=np.atleast_1d(np.asarray(result.cv_error_folds)).astype(float),
        truth=trace.truth,
        **force_shares(result),
        stored_config=config_text,
        intervals=intervals_kind(config),
        overridden=[str(v) for v in trace.overridden],
        value_sources="; ".join(f"{k}: {v}" for k, v in trace.sources.items()),
        library_source=str(result.library.source),
        coefficients_ci_low=np.array(result.ci_low[:p], dtype=float),
        coefficients_ci_high=np.array(result.ci_high[:p], dtype=float),
        drive_notes=drive_notes(result, config),
        identified=identified_values(result, config),
        descriptions={name: str(q["doc"]) for name, q in sorted(result.quantities.items())},
        separation_verdict=dict(sorted(plausibility.attributes(separation_verdict).items())) if separation_verdict else {},
        rss=float(best.rss),
        noise_rms=float(result.prep.noise_rms),
        steadiness=float(result.prep.steadiness),
        row_sigma=np.array(result.prep.row_sigma, dtype=float),
        selection_path=selection_path(result),
        implausible=plausibility.violations(verdicts),
    )


def drive_notes(result: FitResult, config: RunConfig) -> dict[str, str]:
    """The text attributes of ``/model/drive`` beside its source, by name: whence the drive frequency and (a
    calibrated drive) its amplitude."""
    declared = result.prep.declared_drive
    found = getattr(result, "drive_search", None)
    notes = {"frequency_source": (
        "nominal (calibrated drive, drive.phase)" if declared is not None
        else "regression search (record not in steady state)" if found is not None
        else "nominal (fit.drive_frequency: nominal)" if config.fit.drive_frequency == "nominal"
        else "spectral peak of the deflection")}
    if declared is not None:
        notes["force_amplitude_source"] = str(declared.amplitude_source)
    return dict(sorted(notes.items()))


#: Units of the cantilever constants a fit with ``fit.cantilever: free`` identifies, by dataset name.
IDENTIFIED_UNITS = {"identified_damping": "kg/s", "identified_stiffness": "N/m"}


def identified_values(result: FitResult, config: RunConfig) -> dict[str, float]:
    """The cantilever's stiffness (N/m) and damping (kg/s) the regression identified (``fit.cantilever: free``;
    empty otherwise), by dataset name."""
    if config.fit.cantilever != "free":
        return {}
    p = result.n_library
    nu = result.coef[p:]
    return {"identified_damping": float(nu[result.system.names.index("damping") - p]),
            "identified_stiffness": float(nu[result.system.names.index("stiffness") - p])}


def selection_path(result: FitResult) -> dict:
    """``/diagnostics/path`` by name: the candidate supports (``masks`` over the library's terms, ``n_terms``),
    their whitened ``rss``, ``bic``, ``aicc`` and ``cv_rss``, the ``chosen`` one's index, the ``criterion`` and
    ``scope`` of the choice and (grouped selection) each term's ``votes``."""
    p = result.n_library
    cands = result.selection.candidates
    path = {"masks": np.array([c.mask[:p] for c in cands]), "n_terms": np.array([c.n_free for c in cands]),
            "rss": np.array([c.rss for c in cands]), "bic": np.array([c.bic for c in cands]),
            "aicc": np.array([c.aicc for c in cands]),
            "cv_rss": np.array([c.cv_rss for c in cands]), "chosen": int(result.selection.chosen),
            "criterion": str(result.selection.criterion), "scope": str(result.config.fit.selection_scope)}
    if result.selection.votes is not None:
        path["votes"] = np.asarray(result.selection.votes[:p], dtype=float)
    return dict(sorted(path.items()))


def stored_coefficients(result: FitResult) -> np.ndarray:
    """The library's coefficients as stored: the selected terms' values, 0 for the others (SI)."""
    p = result.n_library
    return np.where(result.selected[:p], result.coef[:p], 0.0)


def chi2_reduced(result: FitResult) -> float:
    """rss / (n - k) of the chosen support over the whitened rows (about 1 when the model explains the data to
    the predicted noise)."""
    best = result.selection.best
    return best.rss / max(result.system.n_rows - int(best.mask.sum()), 1)


def quantity_record(name: str, q: dict, verdict: plausibility.Verdict) -> dict:
    """A read-out as :class:`RunData` holds it (the attributes of ``/model/parameters/NAME`` as :func:`load_run`
    reads them): value, unit, error, 95 % interval, effect (SI), the error's shares, the marks and the verdict."""
    return {"value": float(q["value"]), "unit": str(q["unit"]), "error": float(q["error"]),
            "ci_low": float(q["ci_low"]), "ci_high": float(q["ci_high"]), "effect": str(q["effect"]),
            **{k: float(q[k]) for k in ("error_statistical", "error_calibration", TRACK_LEVEL_ERROR,
                                        "information_bound") if k in q},
            "model_limited": bool(q.get("model_limited", False)),
            **read_undetermined(undetermined_attributes(q)),
            **plausibility.attributes(verdict)}


def nonlinear_record(est) -> dict:
    """A nonlinear parameter (an :class:`afmid.fit.search.NonlinearEstimate`) as :class:`RunData` holds it: value,
    its 1 sigma, unit (SI), the record's information bound (NaN: not computed), estimated (or given)."""
    return {"value": float(est.value), "error": float(est.sigma), "unit": str(est.unit),
            "information_bound": float(getattr(est, "information_bound", math.nan)),
            "estimated": bool(est.estimated)}


def cantilever_values(cantilever) -> dict[str, float]:
    """``/cantilever``'s attributes (as given): k (N/m), f0 (Hz), Q, the tip radius (m, NaN: not given)."""
    return {"spring_constant": cantilever.spring_constant, "resonance_frequency": cantilever.resonance_frequency,
            "quality_factor": cantilever.quality_factor,
            "tip_radius": np.nan if cantilever.tip_radius is None else cantilever.tip_radius}


def drive_values(result: FitResult) -> dict[str, float]:
    """The numbers of ``/model/drive`` (SI; as given, the file stores their own type), in the writer's order: F_drive = cos * cos(w t) + sin * sin(w t) in
    the trace's time base (the fit's columns are -F_drive; a calibrated drive's given values), its amplitude,
    a calibrated drive's phase and uncertainties, the drive frequency (and a searched one's sigma and the
    response peak it replaced), the offset force and the baseline's drift when the fit had those columns."""
    p = result.n_library
    nu = result.coef[p:]
    declared = result.prep.declared_drive
    drive_cos, drive_sin = (declared.cos, declared.sin) if declared is not None else (-nu[0], -nu[1])
    out = {"force_amplitude": float(np.hypot(drive_cos, drive_sin)), "cos": float(drive_cos),
           "sin": float(drive_sin)}
    if declared is not None:
        out.update(phase=declared.phase, force_amplitude_uncertainty=declared.force_amplitude_uncertainty,
                   phase_uncertainty=declared.phase_uncertainty)
    out.update(frequency=result.prep.drive.frequency, nominal_frequency=result.prep.drive.nominal)
    found = getattr(result, "drive_search", None)
    if found is not None:
        out.update(frequency_sigma=found.sigma, response_frequency=found.response_frequency)
    if "offset" in result.system.names:
        out["offset_force"] = float(nu[result.system.names.index("offset") - p])
    if "drift" in result.system.names:
        out["baseline_drift"] = float(baseline_drift(result))
    return out


def force_values(result: FitResult) -> dict[str, np.ndarray]:
    """``/force``'s per-sample arrays: the model force and the inverted force (N, positive = repulsive), the
    time (s) and the deflection (m, positive toward the sample)."""
    return {"estimate": np.asarray(result.force_estimate), "inverted": np.asarray(result.force_inverted),
            "time": np.asarray(result.prep.t), "deflection": np.asarray(result.prep.x)}


def force_shares(result: FitResult) -> dict[str, float]:
    """The force curve's relative 1-sigma shares as :class:`RunData` names them (NaN: not computed)."""
    return {"force_calibration_uncertainty": float(result.force_calibration_uncertainty),
            "force_separation_uncertainty": float(getattr(result, "force_separation_uncertainty", math.nan)),
            "force_statistical_uncertainty": float(getattr(result, "force_statistical_uncertainty", math.nan)),
            "force_selection_uncertainty": float(getattr(result, "force_selection_uncertainty", math.nan)),
            "force_total_uncertainty": float(getattr(result, "force_total_uncertainty", math.nan))}


#: ``/cantilever``'s ``units`` attribute.
CANTILEVER_UNITS = "spring_constant: N/m; resonance_frequency: Hz; quality_factor: 1; tip_radius: m"

#: What a number's ``information_bound`` attribute is (afmid.fit.information_bound).
INFORMATION_BOUND_MEANING = ("the record's Cramer-Rao bound on the 1-sigma error, in the dataset's units (NaN: not "
                             "computed); the error is never below it")


def bound_attributes(quantity: dict) -> dict:
    """The ``information_bound`` attributes of a number whose dict may hold it (nothing when it does not)."""
    if "information_bound" not in quantity:
        return {}
    return {"information_bound": float(quantity["information_bound"]),
            "information_bound_meaning": INFORMATION_BOUND_MEANING}


def write_run_contents(h5, run: RunData) -> None:
    """Everything of a run file below its provenance (docs/file-formats.md) into the open HDF5 file ``h5``, from
    the run record alone."""
    h5.attrs["cv_error"] = run.cv_error
    h5.attrs["intervals"] = run.intervals  # statistical only unless a calibration uncertainty is declared
    h5.attrs["overridden"] = list(run.overridden) or [""]
    h5.attrs["value_sources"] = run.value_sources
    cg = h5.create_group("cantilever")
    for name, value in run.cantilever.items():
        cg.attrs[name] = value
    cg.attrs["units"] = CANTILEVER_UNITS
    m = h5.create_group("model")
    write_dataset(m, "terms", np.array(run.terms), "1")
    write_dataset(m, "expressions", np.array(run.expressions), "1")
    write_dataset(m, "units", np.array(run.units), "1")
    write_dataset(m, "coefficients", run.coefficients, "see /model/units")
    write_dataset(m, "coefficients_errors", run.errors, "see /model/units", meaning="bootstrap std, 1 sigma")
    write_dataset(m, "coefficients_ci_low", run.coefficients_ci_low, "see /model/units", meaning="lower end of the 95 % bootstrap interval (2.5 % percentile)")
    write_dataset(m, "coefficients_ci_high", run.coefficients_ci_high, "see /model/units", meaning="upper end of the 95 % bootstrap interval (97.5 % percentile)")
    write_dataset(m, "selected", run.selected, "1")
    write_dataset(m, "inclusion_probability", run.inclusion, "1")
    write_dataset(m, "effects", np.array(list(run.effects) or [""]), "1")
    m.attrs["library"] = run.library_source
    dg = m.create_group("drive")
    drive = run.drive
    for name in ("force_amplitude", "cos", "sin"):
        write_dataset(dg, name, drive[name], "N")
    dg.attrs["source"] = run.drive_source
    if run.drive_calibrated:  # afmid.fit.declared_drive: given, not fitted
        write_dataset(dg, "phase", drive["phase"], "rad", meaning="F_drive = F0 cos(2 pi f t + phase)")
        write_dataset(dg, "force_amplitude_uncertainty", drive["force_amplitude_uncertainty"], "1",
                      meaning="relative, 1 sigma (0: not given)")
        write_dataset(dg, "phase_uncertainty", drive["phase_uncertainty"], "rad", meaning="1 sigma (0: not given)")
    write_dataset(dg, "frequency", drive["frequency"], "Hz")
    write_dataset(dg, "nominal_frequency", drive["nominal_frequency"], "Hz")
    if "frequency_sigma" in drive:  # a transient record: the regression chose the drive frequency (afmid.fit.drive_search)
        write_dataset(dg, "frequency_sigma", drive["frequency_sigma"], "Hz", meaning="1 sigma")
        write_dataset(dg, "response_frequency", drive["response_frequency"], "Hz",
                      meaning="spectral peak of the deflection, replaced by the searched drive frequency")
    for name, note in run.drive_notes.items():  # frequency_source, a calibrated drive's force_amplitude_source
        dg.attrs[name] = note
    if "offset_force" in drive:
        write_dataset(dg, "offset_force", drive["offset_force"], "N")
    if "baseline_drift" in drive:  # fit.detrend: linear
        write_dataset(dg, "baseline_drift", drive["baseline_drift"], "m/s",
                      meaning="slope of the deflection baseline estimated with the force law (afmid.preprocess.baseline)")
    for name, value in run.identified.items():  # fit.cantilever: free
        write_dataset(m, name, value, IDENTIFIED_UNITS[name])
    pg = m.create_group("parameters")
    for name, q in run.quantities.items():
        parts = {k: q[k] for k in ("error_statistical", "error_calibration", TRACK_LEVEL_ERROR) if k in q}
        parts.update(undetermined_attributes(q))
        parts.update(bound_attributes(q))
        write_dataset(pg, name, q["value"], q["unit"], error=q["error"], ci_low=q["ci_low"], ci_high=q["ci_high"],
                      effect=q["effect"], description=run.descriptions[name],
                      model_limited=bool(q.get("model_limited", False)), **ERROR_ATTRS, **parts,
                      plausible=bool(q["plausible"]), plausibility=q["plausibility"])
    ng = m.create_group("nonlinear")
    for name, est in run.nonlinear.items():
        write_dataset(ng, name, est["value"], est["unit"], error=est["error"], estimated=est["estimated"],
                      error_kind=ERROR_LABEL, **bound_attributes(est))
    d_estimate = run.nonlinear.get("d")
    write_dataset(m, "separation", run.separation, "m", estimated=run.separation_estimated,
                  error=d_estimate["error"] if d_estimate is not None else 0.0, error_kind=ERROR_LABEL,
                  **bound_attributes(d_estimate if d_estimate is not None else {}), **run.separation_verdict)
    fg = h5.create_group("force")
    write_dataset(fg, "estimate", run.force["estimate"], "N", positive="repulsive",
                  calibration_relative_uncertainty=run.force_calibration_uncertainty, error_kind=ERROR_LABEL,
                  separation_relative_uncertainty=run.force_separation_uncertainty,
                  statistical_relative_uncertainty=run.force_statistical_uncertainty,
                  selection_relative_uncertainty=run.force_selection_uncertainty,
                  total_relative_uncertainty=run.force_total_uncertainty,
                  meaning="model force; calibration_relative_uncertainty: its relative 1-sigma share of the "
                          "declared k and Q uncertainties; separation_relative_uncertainty: the RMS of its "
                          "1-sigma change with the estimated rest separation, relative to the peak |force| "
                          "(NaN: the separation was given); statistical_relative_uncertainty: the RMS of its "
                          "bootstrap standard deviation, relative to the peak (NaN: no bootstrap); "
                          "selection_relative_uncertainty: half the RMS change with the dropped terms of "
                          "the selected effects forced in; total_relative_uncertainty: the shares in "
                          "quadrature (1 sigma)")
    write_dataset(fg, "inverted", run.force["inverted"], "N", positive="repulsive",
                  drive="calibrated" if run.drive_calibrated else "fitted",
                  meaning=inverted_force_meaning(run.drive_calibrated))
    write_dataset(fg, "time", run.force["time"], "s")
    write_dataset(fg, "deflection", run.force["deflection"], "m", positive="toward_sample")
    pgp = h5.create_group("periods")
    for name, arr in run.periods.items():
        write_dataset(pgp, name, arr, PERIOD_UNITS[name])
    dg = h5.create_group("diagnostics")
    write_dataset(dg, "cv_error", run.cv_error, "1", definition="normalised cross-validated force error")
    write_dataset(dg, "cv_error_folds", run.cv_error_folds, "1")
    write_dataset(dg, "cv_error_noise_floor", run.cv_error_noise_floor, "1",
                  definition="expected cv_error of a perfect model at the estimated noise")
    floor_dof = run.cv_error_floor_dof
    write_dataset(dg, "cv_error_floor_dof", floor_dof, "1",
                  definition="effective degrees of freedom of (cv_error / cv_error_noise_floor)^2 for a right model "
                             "(Satterthwaite over the held-out rows; NaN: not known)")
    write_dataset(dg, "model_limited", bool(run.model_limited), "1",
                  definition=f"cv_error above floor_threshold x cv_error_noise_floor (the one-sided "
                             f"{FLOOR_QUANTILE:.0%} point of sqrt(chi2_nu / nu) at nu = cv_error_floor_dof, at most "
                             f"{FLOOR_FACTOR}; here {floor_threshold(floor_dof):.3f}), or a failed test of the law's "
                             "shape: the parameters are biased by a missing effect beyond their error bars")
    write_dataset(dg, "bic", run.bic, "1", definition="n ln(rss/n) + k ln n over whitened rows")
    write_dataset(dg, "rss", run.rss, "1", definition="whitened residual sum of squares")
    write_dataset(dg, "n_rows", run.n_rows, "1")
    write_dataset(dg, "chi2_reduced", run.chi2_reduced, "1",
                  definition="rss / (n - k); about 1 when the model explains the data to the predicted noise")
    inverted, estimate = run.force["inverted"], run.force["estimate"]
    residual = create_dataset(dg, "residual", inverted.shape, np.float64, "N")
    for lo in range(0, residual.shape[0], 1 << 20):  # chunk by chunk: no third per-sample array
        piece = slice(lo, lo + (1 << 20))
        residual[piece] = inverted[piece] - estimate[piece]
    write_dataset(dg, "noise_rms", run.noise_rms, "m")
    write_dataset(dg, "steadiness", run.steadiness, "1")
    write_dataset(dg, "harmonics", run.harmonics, "1")
    write_dataset(dg, "row_sigma", run.row_sigma, "N*s", meaning="noise of each weak-form row")
    write_dataset(dg, "signal_rows", run.signal_rows, "1")
    path_g = dg.create_group("path")
    path = run.selection_path
    write_dataset(path_g, "masks", path["masks"], "1")
    write_dataset(path_g, "n_terms", path["n_terms"], "1")
    write_dataset(path_g, "rss", path["rss"], "1", meaning="whitened residual sum of squares")
    write_dataset(path_g, "bic", path["bic"], "1")
    if "aicc" in path:  # run files written before the record kept it have none
        write_dataset(path_g, "aicc", path["aicc"], "1", meaning="corrected Akaike information criterion")
    write_dataset(path_g, "cv_rss", path["cv_rss"], "1")
    for name in ("chosen", "criterion", "scope"):
        path_g.attrs[name] = path[name]
    if "votes" in path:
        write_dataset(path_g, "votes", path["votes"], "1",
                      meaning="fraction of the period groups whose own selection used each term")
    if run.warnings:
        dg.attrs["warnings"] = run.warnings
    dg.attrs["n_implausible"] = len(run.implausible)
    if run.implausible:
        dg.attrs["implausible"] = run.implausible
    if run.joint is not None:
        write_joint(h5, run)
    if run.separation_track is not None:
        write_separation_track(m.create_group("separation_track"), run.separation_track)


#: /model/separation_track's format: what a reader of the group can rely on.
TRACK_LAYOUT = "afmid separation track 1"
#: The per-block datasets of /model/separation_track, with their units.
TRACK_ARRAYS = {"time": "s", "first_sample": "1", "stop_sample": "1", "separation": "m", "separation_error": "m"}
#: The keys of :attr:`RunData.separation_track`, in order.
TRACK_KEYS = (*TRACK_ARRAYS, "bandwidth", "within_block", "period_offsets")


def write_separation_track(group, track: dict) -> None:
    """A separation track (:attr:`RunData.separation_track`) into HDF5 ``group`` (/model/separation_track): per
    block its middle time (s), sample range, d (m) and 1 sigma (m); the bandwidth (Hz) and how d moved within a
    block as attributes; the per-period offsets (m) when d moved within the blocks."""
    group.attrs["layout"] = TRACK_LAYOUT
    group.attrs["bandwidth"] = float(track["bandwidth"])
    group.attrs["within_block"] = track["within_block"]
    group.attrs["units"] = "bandwidth: Hz"
    group.attrs["meaning"] = ("the rest separation d(t) (topography under feedback) per block of whole drive periods, "
                              "fitted jointly with one force law; block i is /joint/trace_<i>")
    notes = {"time": {"definition": "each block's middle, from the record's first sample"}, "first_sample": {},
             "stop_sample": {"definition": "one past the block's last sample"},
             "separation": {"definition": "rest separation d of the block"},
             "separation_error": {"error_kind": "1 sigma"}}
    for name, unit in TRACK_ARRAYS.items():
        write_dataset(group, name, track[name], unit, **notes[name])
    offsets = track["period_offsets"]
    if offsets is not None:
        write_dataset(group, "period_offsets", np.concatenate(offsets), "m",
                      definition="each harmonic block's (period's) rest separation relative to its block's d, the "
                                 "blocks one after the other (period_offset_counts per block)")
        write_dataset(group, "period_offset_counts", np.array([o.size for o in offsets]), "1")


def write_joint(h5, run: RunData) -> None:
    """A joint fit's ``/joint`` (docs/file-formats.md, "`/joint` — several traces, one force law"): the traces'
    table, a group per trace with its per-period forces, and ``/model``'s note that its law is shared."""
    traces = run.joint
    g = h5.create_group("joint")
    for name, value in run.joint_attrs.items():  # config, layout, meaning, n_traces, search_evaluations
        g.attrs[name] = value
    write_dataset(g, "paths", np.array([t["path"] for t in traces]), "1")
    write_dataset(g, "sha256", np.array([t["sha256"] for t in traces]), "1")
    write_dataset(g, "separation", np.array([t["separation"] for t in traces]), "m",
                  estimated=np.array([t["separation_estimated"] for t in traces]))
    write_dataset(g, "separation_error", np.array([t["separation_error"] for t in traces]), "m",
                  error_kind="1 sigma")
    write_dataset(g, "cv_error", np.array([t["cv_error"] for t in traces]), "1",
                  definition="each trace's cross-validated force error with the shared law")
    write_dataset(g, "cv_error_noise_floor", np.array([t["cv_error_noise_floor"] for t in traces]), "1")
    write_dataset(g, "model_limited", np.array([t["model_limited"] for t in traces]), "1")
    for i, t in enumerate(traces):
        tg = g.create_group(f"trace_{i}")
        tg.attrs["path"] = t["path"]
        write_dataset(tg, "separation", t["separation"], "m", estimated=t["separation_estimated"],
                      error=t["separation_error"], error_kind="1 sigma")
        write_dataset(tg, "cv_error", t["cv_error"], "1")
        write_dataset(tg, "cv_error_noise_floor", t["cv_error_noise_floor"], "1")
        write_dataset(tg, "drive_frequency", t["drive_frequency"], "Hz")
        pg = tg.create_group("periods")
        for name, arr in t["periods"].items():
            write_dataset(pg, name, arr, PERIOD_UNITS[name])
    h5["model"].attrs["joint"] = f"shared by the {len(traces)} traces of /joint"


def baseline_drift(result: FitResult) -> float:
    """The deflection baseline's slope, m/s: the slope removed from the trajectory plus what the regression's
    drift column took (its coefficient is -k x slope x half the record's duration in the equation)."""
    p = result.n_library
    t = result.prep.t
    half = 0.5 * float(t[-1] - t[0])
    k = result.prep.trace.cantilever.spring_constant
    residual = -float(result.coef[p + result.system.names.index("drift") - p]) / (k * half) if half > 0 else 0.0
    return float(result.prep.removed.get("drift", 0.0)) + residual


# --------------------------------------------------------------------------- the whole run
@dataclass
class RunData:
    """The run record: everything a run file holds (SI). :func:`write_run` writes the file from it alone,
    :func:`load_run` reads it back; :func:`run_data` makes it from a fit."""

    path: Path
    config: RunConfig
    effects: list[str]
    terms: list[str]
    expressions: list[str]
    units: list[str]
    coefficients: np.ndarray
    errors: np.ndarray
    selected: np.ndarray
    inclusion: np.ndarray
    quantities: dict[str, dict]
    nonlinear: dict[str, dict]
    separation: float
    cv_error: float
    cv_error_noise_floor: float
    bic: float
    chi2_reduced: float
    drive: dict
    cantilever: dict  # spring_constant (N/m), resonance_frequency (Hz), quality_factor, tip_radius (m)
    periods: dict[str, np.ndarray]
    force: dict[str, np.ndarray]
    input_path: Path | None
    input_sha256: str | None
    truth: Truth | None = None
    warnings: list[str] = field(default_factory=list)
    n_rows: int = 0  # whitened equations behind bic / chi2_reduced (0 if the file does not say)
    harmonics: np.ndarray | None = None  # drive harmonic of each Fourier row (0, 1, 1, 2, 2, ...)
    signal_rows: np.ndarray | None = None  # rows used by the inverted force (above the noise)
    drive_source: str = DRIVE_FITTED  # /model/drive attribute source: fitted or calibrated (older files: fitted)

    @property
    def drive_calibrated(self) -> bool:
        """True when the fit used a calibrated drive: the inverted force does not depend on the force model."""
        return self.drive_source == DRIVE_CALIBRATED
    model_limited: bool = False  # cv_error above its noise floor (afmid.fit.uncertainty.model_limited)
    cv_error_floor_dof: float = math.nan  # the noise floor's degrees of freedom (afmid.fit.uncertainty.floor_threshold)
    force_calibration_uncertainty: float = 0.0  # relative 1 sigma of the force from the declared k / Q
    force_separation_uncertainty: float = math.nan  # RMS 1 sigma of the force from the estimated d, / peak
    force_statistical_uncertainty: float = math.nan  # RMS bootstrap 1 sigma of the force, / peak
    force_selection_uncertainty: float = math.nan  # half the force's change with dropped terms forced in, / peak
    force_total_uncertainty: float = math.nan  # the shares in quadrature (afmid.fit.force_band), 1 sigma
    separation_error: float = math.nan  # 1 sigma of the rest separation (m); 0 when it was given
    separation_estimated: bool = True  # False when the config gave sample.separation
    cv_error_folds: np.ndarray | None = None  # the cross-validated error of each fold (cv_error is their mean)
    #: A joint fit's traces (/joint, data.paths), in order, each a dict of :data:`JOINT_TRACE_KEYS`: path, its
    #: SHA-256, separation, whether estimated, its 1 sigma (m; 0 when given), cv error, noise floor, model-limited,
    #: drive frequency (Hz), per-period curves (by name, as /periods). None for a single trace. The rest of
    #: RunData is trace 0's.
    joint: list[dict] | None = None
    #: A separation track (/model/separation_track, fit.separation_track), a dict of :data:`TRACK_KEYS`: each
    #: block's middle time (s), sample range in the checked record, rest separation d and its 1 sigma (m), the
    #: track's bandwidth (Hz), how d moved within a block and each block's per-period offsets (m; None when d was
    #: held per block). The blocks are /joint's traces; the rest of RunData is block 0's. None without a track.
    separation_track: dict | None = None
    joint_attrs: dict = field(default_factory=dict)  # /joint's attributes: config, layout, meaning, counts
    # What the file holds beside the read-outs above (the record is all the writer writes from).
    stored_config: str = ""  # the run config as stored (YAML, the root attribute ``config``)
    intervals: str = ""  # what the intervals cover (afmid.fit.uncertainty.intervals_kind)
    overridden: list[str] = field(default_factory=list)  # the trace's values the config overrode
    value_sources: str = ""  # whence each of the trace's values (``name: source; ...``)
    library_source: str = ""  # the library the fit selected from (``/model`` attribute ``library``)
    coefficients_ci_low: np.ndarray | None = None  # the 95 % bootstrap interval of each coefficient (SI)
    coefficients_ci_high: np.ndarray | None = None
    drive_notes: dict[str, str] = field(default_factory=dict)  # /model/drive's text attributes beside ``source``
    identified: dict[str, float] = field(default_factory=dict)  # fit.cantilever: free: N/m, kg/s (IDENTIFIED_UNITS)
    descriptions: dict[str, str] = field(default_factory=dict)  # each read-out's one-line meaning, by name
    separation_verdict: dict = field(default_factory=dict)  # an estimated separation's plausibility attributes
    rss: float = math.nan  # whitened residual sum of squares of the chosen support
    noise_rms: float = math.nan  # the deflection's noise, m
    steadiness: float = math.nan  # afmid.fit.prepare's steady-state measure of the record
    row_sigma: np.ndarray | None = None  # noise of each weak-form row, N s
    selection_path: dict = field(default_factory=dict)  # the candidate supports (:func:`selection_path`)
    implausible: list[str] = field(default_factory=list)  # why read-outs cannot be physical, in order

    @property
    def track_block(self) -> dict | None:
        """A separation track's first block, whose result the rest of the record is: its samples in the checked
        record (first_sample, stop_sample) and its periods' rest separations relative to its d (period_offsets, m;
        None when d was held per block). None for a run without a track."""
        return None if self.separation_track is None else first_track_block(self.separation_track)

    @property
    def residual(self) -> np.ndarray:
        """The per-sample residual (``/diagnostics/residual``): the inverted force minus the model force, N."""
        return self.force["inverted"] - self.force["estimate"]

    @property
    def n_terms(self) -> int:
        return int(self.selected.sum())

    @property
    def n_periods(self) -> int | None:
        """The drive periods of the record the fit used: one row of ``/periods`` per block, times
        ``fit.periods_per_block`` (None: a file without the periods' start times)."""
        starts = self.periods.get("period_start_time")
        return None if starts is None else int(len(starts) * self.config.fit.periods_per_block)

    @property
    def selected_terms(self) -> list[str]:
        return [t for t, s in zip(self.terms, self.selected) if s]


def readout_order(quantities: dict[str, dict], effects: list[str]) -> list[str]:
    """The read-outs' names in the order the fit reads them out (:func:`afmid.fit.forces.read_out`: effect by
    effect as the library lists them, each effect's quantities as its catalog entry declares them); the run file
    keeps them by name. A read-out of an effect the catalog does not know goes last, by name."""
    def place(name: str) -> tuple[int, int, str]:
        effect = str(quantities[name].get("effect", ""))
        declared = [q.name for q in EFFECTS.get(effect).quantities] if effect in EFFECTS else []
        label = name.split(".")[-1]
        return (effects.index(effect) if effect in effects else len(effects),
                declared.index(label) if label in declared else len(declared), name)

    return sorted(quantities, key=place)


def nonlinear_order(nonlinear: dict[str, dict], effects: list[str]) -> list[str]:
    """The nonlinear parameters' names in the fit's order (:func:`afmid.fit.pipeline.estimate_nonlinear`: the rest
    separation ``d``, then the library's decay lengths effect by effect as the catalog declares them); the run
    file keeps them by name. One no effect declares goes last, by name."""
    declared = ["d"] + [name for effect in effects if effect in EFFECTS
                        for name in EFFECTS.get(effect).nonlinear_parameters]
    return sorted(nonlinear, key=lambda name: (declared.index(name) if name in declared else len(declared), name))


#: The signature an HDF5 file starts with (at byte 0, or at 512, 1024, ... after a user block).
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _not_hdf5_words(path: Path) -> str:
    """Why a file h5py cannot open is no run file: not HDF5 at all (a trace given where a run was expected), or
    an HDF5 file that is damaged."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        head = b""
    if any(head[at:at + 8] == _HDF5_SIGNATURE for at in (0, 512, 1024, 2048)):
        return "not a readable HDF5 file (truncated or corrupt?)"
    return (f"expected a run file from afmid fit (HDF5), but this is not an HDF5 file; a trace "
            f"({path.suffix or 'no suffix'}) is fitted first: afmid fit CONFIG -o RUN.h5")


def _not_a_run_words(found) -> str:
    """Why an HDF5 file of another kind (its ``format`` attribute) is no run file."""
    if found == TRACE_FORMAT:
        return ("expected a run file from afmid fit, but this is an afmid trace file (afmid simulate); fit it "
                "first: afmid fit CONFIG -o RUN.h5")
    return f"expected a run file from afmid fit: not an afmid run file (format attribute {found!r})"


def load_run(path: str | Path) -> RunData:
    """Read a run file; one-line InputError if it is not one, is of a version this afmid does not read,
    or is damaged (a missing dataset or attribute, a stored config that is not valid, unreadable data)."""
    import h5py

    path = check_input_file(path, what="run file")  # missing, a link loop, a FIFO (would block), a folder
    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise InputError(_not_hdf5_words(path), file=path) from None
    try:
        with h5:
            if h5.attrs.get("format") != RUN_FORMAT:
                raise InputError(_not_a_run_words(h5.attrs.get("format")), file=path)
            check_version(h5.attrs, path)
            config_attr = h5.attrs.get("config")
            # decoded leniently: an undecodable byte shows up in the YAML error, not as an unreadable file
            config_text = None if config_attr is None else text(config_attr, errors="replace")
            data = _read_run(RunReader(h5, path), path, stored_config(config_text, path))
    except ConfigError as exc:  # the stored config: the run file is the input here
        raise InputError(f"the stored config is not valid: {exc.key + ': ' if exc.key else ''}{exc.message}",
                         file=path, key="config") from None
    except (OSError, RuntimeError, ValueError, TypeError) as exc:  # h5py: unreadable chunks, wrong shapes/types
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"damaged run file: cannot read its contents ({first})", file=path) from None
    if data.input_path is not None and data.input_path.exists() and not is_regular_file(data.input_path):
        # a FIFO or a device (/dev/zero) at the stored path: reading it for the check would block or never end
        log.warning("%s: its stored input %s is not a regular file; its SHA-256 is not checked and it is not read",
                    path, data.input_path)
    elif data.input_path is not None and data.input_path.exists():
        if input_unchanged(data.input_path, data.input_sha256):
            try:
                data.truth = read_truth(data.input_path)
            except InputError as exc:  # the truth is an extra for the report, not what it is about
                log.warning("%s: the ground truth of its input is ignored: %s", path, exc.format())
                data.truth = None
        else:
            log.warning("%s: its input %s changed since the fit (SHA-256 differs): its ground truth is ignored",
                        path, data.input_path)
    return data


def _required_attr(ds, name: str, path: Path):
    """An attribute of a dataset of a run file; InputError naming it when missing."""
    try:
        return ds.attrs[name]
    except KeyError:
        raise InputError(f"missing attribute {name!r} of {ds.name} (damaged or incomplete run file)", file=path,
                         key=f"{ds.name}@{name}") from None


def undetermined_attributes(q: dict) -> dict:
    """The attributes of ``/model/parameters/NAME`` that carry afmid.fit.undetermined's marks."""
    out = {"determined": bool(q.get("determined", True)), "interval_kind": q.get("interval_kind", "95 % bootstrap interval")}
    for key in ("inclusion", "forced_value", "forced_error"):
        if key in q:
            out[key] = float(q[key])
    if q.get("undecided"):
        out["undecided"] = True
    for key in ("undetermined_terms", "undecided_terms"):
        if q.get(key):
            out[key] = ";".join(q[key])
    return out


def _texts(ds) -> list[str]:
    """A string dataset as a list of ``str``."""
    return [text(v) for v in ds[...]]


def _read_run(h5: RunReader, path: Path, raw: dict) -> RunData:
    """The contents of an open run file (``raw``: its stored config as a mapping)."""
    input_path = h5.attrs.get("input_path")
    input_sha256 = h5.attrs.get("input_sha256")
    config = run_config(raw, path, Path(text(input_path)) if input_path else None)
    m = h5["model"]
    quantities = {
        name: {"value": float(ds[()]), "unit": text(_required_attr(ds, "units", path)),
               "error": float(_required_attr(ds, "error", path)),
               "ci_low": float(_required_attr(ds, "ci_low", path)), "ci_high": float(_required_attr(ds, "ci_high", path)),
               "effect": text(_required_attr(ds, "effect", path)),
               **{k: float(ds.attrs[k]) for k in ("error_statistical", "error_calibration", TRACK_LEVEL_ERROR,
                                                  "information_bound")
                  if k in ds.attrs},
               "model_limited": bool(ds.attrs.get("model_limited", False)),
               **read_undetermined(ds.attrs),
               **plausibility.attributes(read_verdict(name, ds))}
        for name, ds in m["parameters"].items()
    }
    nonlinear = {name: {"value": float(ds[()]), "error": float(_required_attr(ds, "error", path)),
                        "unit": text(_required_attr(ds, "units", path)),
                        "information_bound": float(ds.attrs.get("information_bound", math.nan)),
                        "estimated": bool(ds.attrs.get("estimated", True))}
                 for name, ds in m["nonlinear"].items()}
    d = h5["diagnostics"]
    return RunData(
        path=path,
        config=config,
        effects=[e for e in _texts(m["effects"]) if e],
        terms=_texts(m["terms"]),
        expressions=_texts(m["expressions"]),
        units=_texts(m["units"]),
        coefficients=m["coefficients"][...],
        errors=m["coefficients_errors"][...],
        selected=m["selected"][...].astype(bool),
        inclusion=m["inclusion_probability"][...],
        quantities=quantities,
        nonlinear=nonlinear,
        separation=float(m["separation"][()]),
        separation_error=float(m["separation"].attrs.get("error", math.nan)),
        separation_estimated=bool(m["separation"].attrs.get("estimated", True)),
        cv_error=float(d["cv_error"][()]),
        cv_error_noise_floor=float(d["cv_error_noise_floor"][()]),
        bic=float(d["bic"][()]),
        chi2_reduced=float(d["chi2_reduced"][()]),
        drive={k: float(v[()]) for k, v in m["drive"].items()},
        cantilever={k: float(v) for k, v in h5["cantilever"].attrs.items() if k != "units"},
        periods=renamed("periods", ((k, v[...]) for k, v in h5["periods"].items())),
        force=renamed("force", ((k, v[...]) for k, v in h5["force"].items())),
        drive_source=text(m["drive"].attrs.get("source", DRIVE_FITTED)),
        input_path=Path(text(input_path)) if input_path else None,
        input_sha256=text(input_sha256) if input_sha256 is not None else None,
        warnings=[text(w) for w in d.attrs.get("warnings", [])],
        n_rows=int(d["n_rows"][()]) if "n_rows" in d else 0,
        harmonics=d["harmonics"][...].astype(int) if "harmonics" in d else None,
        signal_rows=d["signal_rows"][...].astype(bool) if "signal_rows" in d else None,
        model_limited=bool(d["model_limited"][()]) if "model_limited" in d else False,
        cv_error_floor_dof=float(d["cv_error_floor_dof"][()]) if "cv_error_floor_dof" in d else math.nan,
        cv_error_folds=np.atleast_1d(d["cv_error_folds"][...]).astype(float) if "cv_error_folds" in d else None,
        force_calibration_uncertainty=float(h5["force"]["estimate"].attrs.get("calibration_relative_uncertainty", 0.0)),
        force_separation_uncertainty=float(h5["force"]["estimate"].attrs.get("separation_relative_uncertainty",
                                                                             math.nan)),
        force_statistical_uncertainty=float(h5["force"]["estimate"].attrs.get("statistical_relative_uncertainty",
                                                                              math.nan)),
        force_selection_uncertainty=float(h5["force"]["estimate"].attrs.get("selection_relative_uncertainty",
                                                                            math.nan)),
        force_total_uncertainty=float(h5["force"]["estimate"].attrs.get("total_relative_uncertainty", math.nan)),
        joint=read_joint_traces(h5["joint"]) if "joint" in h5 else None,
        separation_track=read_separation_track(m["separation_track"], path) if "separation_track" in m else None,
        joint_attrs=read_joint_attrs(h5["joint"]) if "joint" in h5 else {},
        stored_config=text(h5.attrs.get("config", ""), errors="replace"),
        intervals=text(h5.attrs.get("intervals", "")),
        overridden=[t for t in (text(v) for v in np.atleast_1d(h5.attrs.get("overridden", []))) if t],
        value_sources=text(h5.attrs.get("value_sources", "")),
        library_source=text(m.attrs.get("library", "")),
        coefficients_ci_low=m["coefficients_ci_low"][...] if "coefficients_ci_low" in m else None,
        coefficients_ci_high=m["coefficients_ci_high"][...] if "coefficients_ci_high" in m else None,
        drive_notes={k: text(v) for k, v in sorted(m["drive"].attrs.items()) if k != "source"},
        identified={k: float(m[k][()]) for k in sorted(IDENTIFIED_UNITS) if k in m},
        descriptions={name: text(ds.attrs.get("description", "")) for name, ds in m["parameters"].items()},
        separation_verdict={k: (bool(v) if k == "plausible" else text(v))
                            for k, v in sorted(m["separation"].attrs.items()) if k in ("plausible", "plausibility")},
        rss=float(d["rss"][()]) if "rss" in d else math.nan,
        noise_rms=float(d["noise_rms"][()]) if "noise_rms" in d else math.nan,
        steadiness=float(d["steadiness"][()]) if "steadiness" in d else math.nan,
        row_sigma=d["row_sigma"][...] if "row_sigma" in d else None,
        selection_path=read_selection_path(d["path"]) if "path" in d else {},
        implausible=([text(v) for v in d.attrs.get("implausible", [])] if "n_implausible" in d.attrs
                     else judged_now(quantities, m["separation"])),
    )


def judged_now(quantities: dict, separation) -> list[str]:
    """The implausible reasons of a run file older than its ``implausible`` list: the read-outs' verdicts (judged
    when read, :func:`read_verdict`) and an estimated separation's."""
    reasons = [str(q["plausibility"]) for q in quantities.values() if not q["plausible"]]
    if bool(separation.attrs.get("estimated", True)):
        verdict = plausibility.judge_separation(float(separation[()]), float(separation.attrs.get("error", math.nan)))
        if not verdict.plausible:
            reasons.append(verdict.reason)
    return reasons


def read_selection_path(group) -> dict:
    """``/diagnostics/path`` as :func:`selection_path` gives it, by name."""
    path = {name: ds[...] for name, ds in group.items()}
    path.update(chosen=int(group.attrs["chosen"]), criterion=text(group.attrs["criterion"]),
                scope=text(group.attrs["scope"]))
    return dict(sorted(path.items()))


def run_config(raw: dict, path: Path, input_path: Path | None) -> RunConfig:
    """The run config stored in a run file (``raw``: its mapping): relative paths as seen from the input's folder
    (the run file's own when the input is not known)."""
    model = raw.get("model")
    if isinstance(model, dict) and model.get("library") is not None:
        model.pop("effects", None)  # older afmid stored the unused default effects beside a preset
    return build_config(raw, source=path, base_dir=input_path.parent if input_path else path.parent)


def first_track_block(track: dict) -> dict:
    """The first block of a separation track (:attr:`RunData.separation_track`): its sample range and its periods'
    offsets (m; None when d was held per block)."""
    offsets = track["period_offsets"]
    return {"first_sample": int(track["first_sample"][0]), "stop_sample": int(track["stop_sample"][0]),
            "period_offsets": None if offsets is None else np.asarray(offsets[0], dtype=float)}


def read_separation_track(group, path: Path | None = None) -> dict:
    """``/model/separation_track`` (:func:`write_separation_track`) of the run file ``path`` as
    :attr:`RunData.separation_track`: the datasets as stored, the per-period offsets split per block (None when the
    file holds none); InputError when the bandwidth is missing."""
    if "bandwidth" not in group.attrs:
        raise InputError("missing attribute 'bandwidth' of /model/separation_track (damaged or incomplete run file)",
                         file=path, key="/model/separation_track@bandwidth")
    offsets = None
    if "period_offsets" in group and "period_offset_counts" in group:
        counts = group["period_offset_counts"][...]
        offsets = np.split(group["period_offsets"][...], np.cumsum(counts)[:-1])
    track = {name: group[name][...] for name in TRACK_ARRAYS}
    # Files written before d could move within a block have no within_block: d was held per block
    track.update(bandwidth=float(group.attrs["bandwidth"]),
                 within_block=text(group.attrs.get("within_block", "constant")), period_offsets=offsets)
    return {key: track[key] for key in TRACK_KEYS}


#: The keys of each trace of :attr:`RunData.joint`, in order.
JOINT_TRACE_KEYS = ("path", "sha256", "separation", "separation_estimated", "separation_error", "cv_error",
                    "cv_error_noise_floor", "model_limited", "drive_frequency", "periods")


def read_joint_traces(joint) -> list[dict]:
    """The table of a joint fit's traces (``/joint``, afmid.fit.joint_output): one dict per trace
    (:data:`JOINT_TRACE_KEYS`; older files: what they hold)."""
    columns = {"path": _texts(joint["paths"]), "separation": joint["separation"][...],
               "separation_error": joint["separation_error"][...], "cv_error": joint["cv_error"][...],
               "cv_error_noise_floor": joint["cv_error_noise_floor"][...],
               "model_limited": joint["model_limited"][...].astype(bool)}
    if "sha256" in joint:
        columns["sha256"] = _texts(joint["sha256"])
    estimated = joint["separation"].attrs.get("estimated")
    if estimated is not None:
        columns["separation_estimated"] = np.atleast_1d(estimated).astype(bool)
    out = []
    for i in range(len(columns["path"])):
        row = {k: (v[i] if k in ("path", "sha256") else bool(v[i]) if k in ("model_limited", "separation_estimated")
                   else float(v[i])) for k, v in columns.items()}
        group = joint[f"trace_{i}"] if f"trace_{i}" in joint else None
        if group is not None and "drive_frequency" in group:
            row["drive_frequency"] = float(group["drive_frequency"][()])
        if group is not None and "periods" in group:
            row["periods"] = renamed("periods", ((k, v[...]) for k, v in group["periods"].items()))
        out.append({k: row[k] for k in JOINT_TRACE_KEYS if k in row})
    return out


def read_joint_attrs(joint) -> dict:
    """``/joint``'s attributes by name (:attr:`RunData.joint_attrs`)."""
    return {k: (int(v) if k in ("n_traces", "search_evaluations") else text(v)) for k, v in sorted(joint.attrs.items())}


def read_verdict(name: str, dataset) -> plausibility.Verdict:
    """The plausibility verdict stored on ``/model/parameters/NAME`` (judged now for files older than it)."""
    attrs = dataset.attrs
    if "plausible" in attrs:
        return plausibility.Verdict(bool(attrs["plausible"]), text(attrs.get("plausibility", "")))
    quantity = {"value": float(dataset[()]), "unit": text(attrs.get("units", "")), "effect": text(attrs.get("effect", ""))}
    quantity.update({k: float(attrs[k]) for k in ("error", "ci_low", "ci_high") if k in attrs})
    quantity.update(read_undetermined(attrs))
    return plausibility.judge(name, quantity)


def read_undetermined(attrs) -> dict:
    """The not-determined / undecided marks of ``/model/parameters/NAME`` (afmid.fit.undetermined; older files:
    determined, no marks)."""
    out = {"determined": bool(attrs.get("determined", True))}
    for key in ("interval_kind",):
        if key in attrs:
            out[key] = text(attrs[key])
    for key in ("inclusion", "forced_value", "forced_error"):
        if key in attrs:
            out[key] = float(attrs[key])
    if "undecided" in attrs:
        out["undecided"] = bool(attrs["undecided"])
    for key in ("undetermined_terms", "undecided_terms"):
        if key in attrs:
            out[key] = [t for t in text(attrs[key]).split(";") if t]
    return out


# --------------------------------------------------------------------------- a batch's view
def read_batch_key(path: Path) -> str | None:
    """The ``batch_key`` root attribute of a run file (None if absent or the file is unreadable)."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            return text(h5.attrs["batch_key"]) if "batch_key" in h5.attrs else None
    except (OSError, KeyError):
        return None


def read_summary(path: Path) -> dict:
    """The values of a run file that a batch summary lists, SI: ``{'key', 'values', 'quantities', 'implausible'}``.

    ``key`` is the ``batch_key`` attribute (None if absent); ``values`` the columns of the row (input SHA-256,
    effects and selected terms joined by ``;``, errors, chi-square, separation); ``quantities`` each read-out's
    value, error, interval, unit and effect; ``implausible`` the reasons of the implausible read-outs. Raises
    OSError or KeyError (as h5py does) for a file it cannot read.
    """
    import h5py

    with h5py.File(path, "r") as h5:
        key = h5.attrs.get("batch_key")
        diag = h5["diagnostics"]
        model = h5["model"]
        terms = _texts(model["terms"])
        selected = model["selected"][...]
        sep = model["separation"]
        effects = _texts(model["effects"]) if "effects" in model else []
        values = {
            "input_sha256": text(h5.attrs.get("input_sha256", "")),
            "effects": ";".join(e for e in effects if e),
            "cv_error": float(diag["cv_error"][()]),
            "cv_error_noise_floor": float(diag["cv_error_noise_floor"][()]),
            "cv_error_floor_dof": float(diag["cv_error_floor_dof"][()]) if "cv_error_floor_dof" in diag else math.nan,
            "chi2_reduced": float(diag["chi2_reduced"][()]),
            "terms": ";".join(t for t, s in zip(terms, selected) if s),
            "separation": float(sep[()]),
            "separation_error": float(sep.attrs.get("error", np.nan)),
        }
        quantities = {}
        implausible = []
        for name, ds in model["parameters"].items():
            quantities[name] = {
                "determined": bool(ds.attrs.get("determined", True)),
                "value": float(ds[()]),
                "error": float(ds.attrs.get("error", np.nan)),
                "ci_low": float(ds.attrs.get("ci_low", np.nan)),
                "ci_high": float(ds.attrs.get("ci_high", np.nan)),
                "unit": text(ds.attrs.get("units", "")),
                "effect": text(ds.attrs.get("effect", "")),
            }
            verdict = read_verdict(name, ds)
            if not verdict.plausible:
                implausible.append(verdict.reason)
        if not sep.attrs.get("plausible", True):  # an estimated rest separation afmid cannot stand behind
            implausible.append(text(sep.attrs.get("plausibility", "")))
    return {"key": None if key is None else text(key), "values": values, "quantities": quantities,
            "implausible": implausible}

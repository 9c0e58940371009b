"""What a joint fit (:mod:`afmid.fit.joint`) gives per trace, and its run file.

Each trace's forces come from the shared law with its own drive and separation: :func:`trace_result` makes
the :class:`afmid.fit.pipeline.FitResult` of trace ``i`` (the shared coefficients, intervals and read-outs;
its own columns, cross-validated error, forces and per-period curves), so everything that reads a single
fit's result reads it. :func:`write_joint_run` writes the first trace's result in the single-trace layout
(``afmid report`` renders it: the first trace's plots, the shared parameters) and adds ``/joint``: the
traces' table (file, SHA-256, separation and its 1 sigma, cv error and noise floor) and a group per trace
with its per-period forces (docs/file-formats.md, "Joint fits").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import afmid.fit.regression as regression
from afmid.config import dump_config
from afmid.fit.forces import per_sample_forces, period_curves, signal_rows
from afmid.fit.joint import JointResult, trace_coefficients
from afmid.fit.pipeline import FitResult
from afmid.fit.search import NonlinearEstimate
from afmid.io.trace import write_dataset

#: /joint's format: what a reader of the group can rely on.
JOINT_LAYOUT = "afmid joint fit 1"


def _trace_vector(result: JointResult, values: np.ndarray, i: int) -> np.ndarray:
    return trace_coefficients(result.system, values, i, len(result.library))


def trace_selection(result: JointResult, i: int) -> regression.Selection:
    """The joint selection path in trace ``i``'s column space (masks and coefficients restricted; the rss and
    criteria are the joint system's)."""
    cands = []
    for c in result.selection.candidates:
        mask = _trace_vector(result, c.mask, i).astype(bool)
        cands.append(regression.Candidate(mask, _trace_vector(result, c.coef, i), c.rss, c.n_free, c.bic, c.aicc,
                                          c.cv_rss, c.cv_rss_se))
    votes = result.selection.votes
    return regression.Selection(cands, result.selection.chosen, result.selection.criterion,
                                votes=None if votes is None else _trace_vector(result, np.asarray(votes), i))


def trace_result(result: JointResult, i: int) -> FitResult:
    """Trace ``i`` of a joint fit as a single fit's result: the shared law with its own drive and separation."""
    t = result.traces[i]
    prep, library, fit = t.prep, result.library, result.config.fit
    from afmid.fit.system import build_system

    system = build_system(prep, library, t.params)
    coef = _trace_vector(result, result.coef, i)
    rows = signal_rows(prep, system, coef)
    force_estimate, force_inverted = per_sample_forces(prep, library, system, coef, rows)
    periods = period_curves(prep, library, system, coef, t.params, rows, fit.phase_points)
    nonlinear = {k: NonlinearEstimate(k, v.value, v.sigma, v.unit, v.estimated) for k, v in result.shared.items()}
    if t.separation is not None:
        nonlinear["d"] = t.separation
    warnings = list(result.warnings) + [w for w in t.single.warnings if w not in result.warnings]
    return FitResult(t.config, prep, library, system, trace_selection(result, i), coef,
                     _trace_vector(result, result.coef_std, i), _trace_vector(result, result.ci_low, i),
                     _trace_vector(result, result.ci_high, i), _trace_vector(result, result.inclusion, i),
                     result.bagging, nonlinear, result.quantities, t.cv_error, t.cv_error_folds,
                     t.cv_error_noise_floor, rows, force_estimate, force_inverted, periods, warnings,
                     t.single.drive_search, 0.0, t.model_limited)


def write_joint_run(path, result: JointResult, overwrite: bool = False, more=None) -> tuple[Path, list[FitResult]]:
    """Write the joint run file (the first trace in the single layout, plus ``/joint``; ``more(h5)`` adds more
    inside the same atomic write); returns the path and every trace's :func:`trace_result`."""
    from afmid.runfile import PERIOD_UNITS, write_run

    per_trace = [trace_result(result, i) for i in range(len(result.traces))]

    def add_joint(h5) -> None:
        g = h5.create_group("joint")
        g.attrs["layout"] = JOINT_LAYOUT
        g.attrs["n_traces"] = len(result.traces)
        g.attrs["config"] = dump_config(result.config)
        g.attrs["meaning"] = ("one force law fitted to every trace: /model holds the shared coefficients and "
                              "parameters; /force, /periods, /diagnostics and /model/separation are trace 0's; "
                              "each trace's own in /joint/trace_<i>")
        g.attrs["search_evaluations"] = result.rounds
        traces = result.traces
        write_dataset(g, "paths", np.array([str(t.prep.trace.path) for t in traces]), "1")
        write_dataset(g, "sha256", np.array([t.prep.trace.sha256 or "" for t in traces]), "1")
        write_dataset(g, "separation", np.array([t.params["d"] for t in traces]), "m",
                      estimated=np.array([t.separation is not None for t in traces]))
        write_dataset(g, "separation_error", np.array([t.separation.sigma if t.separation is not None else 0.0
                                                       for t in traces]), "m", error_kind="1 sigma")
        write_dataset(g, "cv_error", np.array([t.cv_error for t in traces]), "1",
                      definition="each trace's cross-validated force error with the shared law")
        write_dataset(g, "cv_error_noise_floor", np.array([t.cv_error_noise_floor for t in traces]), "1")
        write_dataset(g, "model_limited", np.array([t.model_limited for t in traces]), "1")
        for i, (t, r) in enumerate(zip(traces, per_trace)):
            tg = g.create_group(f"trace_{i}")
            tg.attrs["path"] = str(t.prep.trace.path)
            write_dataset(tg, "separation", t.params["d"], "m", estimated=t.separation is not None,
                          error=t.separation.sigma if t.separation is not None else 0.0, error_kind="1 sigma")
            write_dataset(tg, "cv_error", t.cv_error, "1")
            write_dataset(tg, "cv_error_noise_floor", t.cv_error_noise_floor, "1")
            write_dataset(tg, "drive_frequency", t.prep.drive.frequency, "Hz")
            pg = tg.create_group("periods")
            r.periods.write(pg, PERIOD_UNITS)  # afmid.fit.forces.PeriodCurves, chunk by chunk
        h5["model"].attrs["joint"] = f"shared by the {len(traces)} traces of /joint"
        if more is not None:
            more(h5)

    written = write_run(path, per_trace[0], per_trace[0].config, overwrite=overwrite, extra=add_joint)
    return written, per_trace


def joint_table(result: JointResult, per_trace: list[FitResult]) -> str:
    """The traces of a joint fit, one line each: file, separation (1 sigma), cv error against its floor."""
    lines = [f"joint fit of {len(result.traces)} traces, one force law (the parameters above are shared):"]
    for i, (t, r) in enumerate(zip(result.traces, per_trace)):
        d = t.params["d"]
        sigma = f" ± {t.separation.sigma * 1e9:.3f}" if t.separation is not None else " (given)"
        flag = "  MODEL-LIMITED" if t.model_limited else ""
        lines.append(f"  trace {i}: {t.prep.trace.path.name if t.prep.trace.path else '-'}: d = {d * 1e9:.3f}{sigma} nm"
                     f" (1 sigma); cv_error {t.cv_error:.3f} (noise floor {t.cv_error_noise_floor:.3f}){flag}")
    return "\n".join(lines)


def fit_joint(config, output, overwrite: bool, quiet: bool, read_out) -> None:
    """``afmid fit`` of a config with ``data.paths``: the joint fit, its run file, its read-out on stdout.

    ``read_out(run_data) -> str`` writes the first trace's result (the caller passes the report's ``fit_text``:
    the fit does not import the report above it, docs/architecture.md, Layers)."""
    import logging

    import click

    from afmid.fit.joint import run_joint_fit

    log = logging.getLogger("afmid.cli")
    result = run_joint_fit(config, progress=not quiet)
    _, per_trace = write_joint_run(output, result, overwrite=overwrite)
    log.info("wrote %s: joint fit of %d traces; terms: %s", output, len(result.traces),
             ", ".join(result.selected_terms()) or "none")
    if not quiet:
        click.echo(read_out(per_trace[0]))
        click.echo(joint_table(result, per_trace))
    for line in result.warnings:
        log.warning("%s: %s", output, line.removeprefix("warning: "))

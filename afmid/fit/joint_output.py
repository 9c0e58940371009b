"""What a joint fit (:mod:`afmid.fit.joint`) gives per trace; its run file is written by
:mod:`afmid.joint_runfile`.

Each trace's forces come from the shared law with its own drive and separation: :func:`trace_result` makes
the :class:`afmid.fit.pipeline.FitResult` of trace ``i`` (the shared coefficients, intervals and read-outs;
its own columns, cross-validated error, forces and per-period curves), so everything that reads a single
fit's result reads it; :func:`joint_table` is the traces' table printed by ``afmid fit``, from the run record.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import afmid.fit.regression as regression
from afmid.fit.forces import per_sample_forces, period_curves, signal_rows
from afmid.fit.joint import JointResult, trace_coefficients
from afmid.fit.pipeline import FitResult
from afmid.fit.search import NonlinearEstimate

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
                     t.single.drive_search, 0.0, t.model_limited, cv_error_floor_dof=t.cv_error_floor_dof)


def joint_table(traces: list[dict]) -> str:
    """The traces of a joint fit, one line each: file, separation (1 sigma), cv error against its floor.
    ``traces``: the run record's rows (``RunData.joint``, as ``/joint`` holds them: path, separation and
    separation_error in m, separation_estimated, cv_error, cv_error_noise_floor, model_limited)."""
    lines = [f"joint fit of {len(traces)} traces, one force law (the parameters above are shared):"]
    for i, t in enumerate(traces):
        name = Path(t["path"]).name if t["path"] else "-"
        sigma = f" ± {t['separation_error'] * 1e9:.3f}" if t["separation_estimated"] else " (given)"
        flag = "  MODEL-LIMITED" if t["model_limited"] else ""
        lines.append(f"  trace {i}: {name}: d = {t['separation'] * 1e9:.3f}{sigma} nm (1 sigma); cv_error "
                     f"{t['cv_error']:.3f} (noise floor {t['cv_error_noise_floor']:.3f}){flag}")
    return "\n".join(lines)

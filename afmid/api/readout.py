"""A run read from its file, seen as :func:`afmid.report.fit_text.fit_text` reads a fit's result.

``afmid fit`` prints its text from the run record (:class:`afmid.runfile.RunData`: what the run file holds, for a
fit made and a fit loaded alike). :class:`RunReadout` presents it under the pipeline's result's names that
:func:`afmid.report.fit_text.fit_text` reads, so both print the same lines (the parameters in the fit's order,
:func:`readout_order`; with ``-v`` the candidate supports of ``/diagnostics/path``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmid.runfile import nonlinear_order, readout_order


@dataclass(frozen=True)
class StoredTerm:
    """A library term as the run file names it."""

    name: str
    expression: str
    coefficient_unit: str


@dataclass(frozen=True)
class StoredEstimate:
    """A nonlinear parameter as the run file holds it (value and its profile's 1 sigma, SI)."""

    value: float
    sigma: float
    unit: str
    estimated: bool = True


@dataclass(frozen=True)
class StoredCandidate:
    """A candidate support of the selection path as the run file keeps it (``/diagnostics/path``): its mask over
    the library's terms, free terms, whitened rss, BIC, AICc (NaN in files written before it was kept) and
    cross-validated rss."""

    mask: np.ndarray
    n_free: int
    rss: float
    bic: float
    aicc: float
    cv_rss: float


class StoredSelection:
    """The selection path of a run (``RunData.selection_path``) under the names of the fit's
    :class:`afmid.fit.regression.Selection` that ``afmid fit -v`` reads: ``candidates``, ``best``, ``criterion``."""

    def __init__(self, path: dict):
        n = len(path["bic"])
        aicc = path.get("aicc", np.full(n, math.nan))
        self.candidates = [StoredCandidate(np.asarray(path["masks"][i], dtype=bool), int(path["n_terms"][i]),
                                           float(path["rss"][i]), float(path["bic"][i]), float(aicc[i]),
                                           float(path["cv_rss"][i])) for i in range(n)]
        self.criterion = str(path["criterion"])
        self.best = self.candidates[int(path["chosen"])]


class StoredLibrary:
    def __init__(self, run):
        self.terms = [StoredTerm(n, e, u) for n, e, u in zip(run.terms, run.expressions, run.units)]
        self.names = list(run.terms)


class RunReadout:
    """A :class:`afmid.runfile.RunData` under the names of :class:`afmid.fit.pipeline.FitResult` that the fit's
    text uses."""

    def __init__(self, run):
        self.config = run.config  # the merged config the run was fitted with (its calibration, for the notes)
        self.library = StoredLibrary(run)
        self.n_library = len(run.terms)
        self.n_periods = run.n_periods
        self.selected = np.asarray(run.selected, dtype=bool)
        self.inclusion = np.asarray(run.inclusion, dtype=float)
        self.selection = StoredSelection(run.selection_path) if run.selection_path else None
        self.coef = np.asarray(run.coefficients, dtype=float)
        self.coef_std = np.asarray(run.errors, dtype=float)
        # Each read-out is judged with the tip it was read out for (a force that grows with R has a bound scaled
        # to the tip), as the fit's own quantities carry it; the file keeps the radius once, under /cantilever.
        radius = float(run.cantilever.get("tip_radius", math.nan))
        self.quantities = {name: {**run.quantities[name], "tip_radius": radius}
                           for name in readout_order(run.quantities, run.effects)}
        self.nonlinear = {name: StoredEstimate(run.nonlinear[name]["value"], run.nonlinear[name]["error"],
                                               run.nonlinear[name]["unit"])
                          for name in nonlinear_order(run.nonlinear, run.effects)}
        self.cv_error = run.cv_error
        self.cv_error_noise_floor = run.cv_error_noise_floor
        self.cv_error_floor_dof = run.cv_error_floor_dof
        self.cv_error_folds = run.cv_error_folds if run.cv_error_folds is not None else np.zeros(0)
        self.model_limited = run.model_limited
        self.force_calibration_uncertainty = run.force_calibration_uncertainty
        self.force_separation_uncertainty = run.force_separation_uncertainty
        self.force_statistical_uncertainty = run.force_statistical_uncertainty
        self.force_selection_uncertainty = run.force_selection_uncertainty
        self.force_total_uncertainty = run.force_total_uncertainty

    def selected_terms(self) -> list[str]:
        return [n for n, s in zip(self.library.names, self.selected) if s]

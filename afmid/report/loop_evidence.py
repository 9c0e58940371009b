"""Each run's own evidence on the loop page: where it fails and the effects tried for it.

A report of several runs (``afmid report run1.h5 run2.h5``) tells the loop: run1 fails here -> this effect ->
added -> the error falls. The figures that make that case are run1's (its residual by region, its ΔBIC chart with
the accepted effect in green), not the last run's, which already fits. So every run of the loop gets its own
"where the model fails" (the residual figure and the table by region) and "effects tried" (the ΔBIC chart), drawn
from the run's own localisation and its own diagnosis (the one :func:`afmid.diagnosis.stored.diagnosed` kept or
made: no refit here). A run that fits shows them collapsed (``<details>``), a model-limited one open.

Figure files: ``residual_run<i>`` and ``suggestions_run<i>`` (i from 1, in the order given) for every run but the
last, whose figures are the page's own ``residual`` and ``suggestions``.
"""

from __future__ import annotations

import html
from pathlib import Path

from afmid.report.figures import figure_html
from afmid.report.plots import fig_residual, fig_suggestions
from afmid.report.quantity_text import format_number

NN = 1e9  # N -> nN for display

REGION_HEADER = ["region", "time", "share of residual", "rms", "noise", "approach", "retraction",
                 "correlation with dz/dt"]


def region_rows(local: dict) -> list[list[str]]:
    """The residual by region (:func:`afmid.diagnosis.localize.localize`'s ``by_region``) as table rows, forces
    in nN."""
    return [[k, f"{100 * v['fraction_of_time']:.0f} %", f"{100 * v['share_of_residual']:.0f} %",
             format_number(v["rms"] * NN, "nN"), format_number(v["noise_rms"] * NN, "nN"), format_number(v["rms_approach"] * NN, "nN"),
             format_number(v["rms_retraction"] * NN, "nN"), format_number(v["rate_correlation"])] for k, v in local["by_region"].items()]


def residual_caption(local: dict) -> str:
    """The caption of a residual figure: what is drawn and what the bandwidth does to it."""
    limit = local.get("max_signal_harmonic")
    return ("Systematic residual (inverted force − model, averaged over periods): vs separation for approach and "
            "retraction, by region, by harmonic. "
            + (f"Both forces keep only the drive harmonics up to {limit} (those above the noise), so a feature "
               f"narrower in time than 1/{2 * limit} of a period (e.g. a jump at contact) is smeared over the "
               "neighbouring separations and rings." if limit else ""))


SUGGESTIONS_CAPTION = "Candidates: BIC decrease (green = accepted) and error after adding each"


def earlier_run_figures(runs: list, diagnoses: list[dict], localized: list[dict], folder: Path) -> list[dict]:
    """Per run but the last, in order: ``{"residual": PNG name, "suggestions": PNG name or None}``; a run given
    twice is drawn once."""
    out, drawn = [], {}
    for i, (run, diagnosis, local) in enumerate(zip(runs[:-1], diagnoses, localized)):
        key = Path(run.path).resolve()
        if key not in drawn:
            drawn[key] = {
                "residual": fig_residual(local, folder, run.config.sample.a0, name=f"residual_run{i + 1}"),
                "suggestions": fig_suggestions({"tried": diagnosis.get("tried") or [], "diagnosis": diagnosis},
                                               folder, name=f"suggestions_run{i + 1}"),
            }
        out.append(drawn[key])
    return out


def run_evidence_html(run, diagnosis: dict, local: dict, figures: dict, folder: Path, table, rich) -> str:
    """One run's where-it-fails and effects-tried block (``table``, ``rich``: the page's table maker and escaper);
    open when the run is model-limited or a missing effect was found, else collapsed."""
    failing = bool(run.model_limited or diagnosis.get("missing_effect"))
    name = html.escape(Path(run.path).name)
    summary = (f"{name}: where the model fails and the effects tried"
               + ("" if failing else " (the model fits: collapsed)"))
    parts = [f"<details class='run-evidence' data-run='{name}'{' open' if failing else ''}>",
             f"<summary>{summary}</summary>",
             f"<h3>Where the model fails ({name})</h3>",
             f"<p>{rich(diagnosis.get('description', ''))}.</p>",
             table(REGION_HEADER, region_rows(local)),
             figure_html(folder, figures["residual"], f"{Path(run.path).name}: " + residual_caption(local))]
    parts.append(f"<h3>Effects tried ({name})</h3>")
    if figures.get("suggestions"):
        parts.append(figure_html(folder, figures["suggestions"], f"{Path(run.path).name}: " + SUGGESTIONS_CAPTION))
    else:
        parts.append(f"<p>No candidate was tried for this run ({rich(diagnosis.get('verdict', ''))}).</p>")
    parts.append("</details>")
    return "".join(parts)

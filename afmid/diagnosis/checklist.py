"""What to check on a record no catalog model explains: the calibration, the channel, stationarity.

When the diagnosis ends with "not explained by the catalog" (a significant residual no catalog effect removes,
or one that only removes part of it), the honest next step is not another effect: the inputs the force law is
built on may be wrong. Three of them are checked here, each with the evidence the run and its record hold:

- **calibration** (``cantilever.spring_constant``, ``data.invols``, ``cantilever.quality_factor``,
  ``cantilever.tip_radius``): a wrong k scales every force, a wrong invols every deflection (and so the
  indentation, nonlinearly), a wrong Q the dissipative part. Evidence: read-outs of the run or of the candidate
  refits outside their physical ranges (e.g. an adhesion no tip of the declared radius can give), an implausible
  separation, the calibration's source (the config, not the file) and whether its uncertainty was declared.
- **channel** (``data.column``, ``data.positive``): the deflection channel and its sign. Evidence: the
  model-free look at the harmonics (the repulsive turn at the most negative deflection: sign flipped?), and the
  file's other channels.
- **stationarity**: the fit assumes every period repeats the same orbit. Evidence: the motion's classification
  (non-periodic, a slow modulation of the amplitude, periods differing more than noise) and the trace's
  defect findings (drift, unsteady amplitude, glitches).

Each item says what to check and the evidence found for it; an item without evidence says so ("no evidence
against it found here"). Nothing here proposes a change the data do not show: no effect, and no instrument
declaration (a detector or a second mode is named by afmid.diagnosis.instrument_signature only with its own
evidence).
"""

from __future__ import annotations

import math

import afmid.fit.plausibility as plausibility
from afmid.errors import AfmidError
from afmid.io import defects
from afmid.quantity_text import format_value

#: Defect findings (afmid.io.findings.Finding.name) of a record that changes over time: an amplitude not in steady
#: state and a drifting mean deflection (removed by fit.detrend, but a drifting lever may change more than its mean).
#: An edge transient the fit cut (glitches) is not: the part fitted no longer holds it.
UNSTEADY_FINDINGS = ("not_steady", "drift", "phase_jump")


def unexplained(summary: dict) -> bool:
    """True when a diagnosis (afmid.diagnosis.diagnose.suggest) ends with a residual the catalog does not
    explain: neither a catalog effect that removes it, nor an undecided pair, nor an instrument named with
    evidence."""
    diagnosis = summary.get("diagnosis") or {}
    return (bool(summary.get("missing_effect")) and not diagnosis.get("explained_by_catalog", False)
            and not summary.get("undecided") and "instrument" not in diagnosis)


def with_what_to_check(summary: dict, run, prepared, candidate_findings: dict[str, list[str]]) -> dict:
    """``summary`` with ``what_to_check`` (a list of items, see :func:`what_to_check`) when it is
    :func:`unexplained`; unchanged otherwise."""
    if not unexplained(summary):
        return summary
    return {**summary, "what_to_check": what_to_check(run, prepared, candidate_findings)}


def what_to_check(run, prepared, candidate_findings: dict[str, list[str]]) -> list[dict]:
    """The checks for an unexplained record, those with evidence first: each ``{"check": name, "keys": [config
    keys], "what": text, "evidence": [texts]}``. ``run`` the run (afmid.runfile.RunData), ``prepared`` its record
    (afmid.fit.prepare.Prepared), ``candidate_findings`` the implausible read-outs of each candidate refit by
    effect name."""
    items = [_calibration(run, prepared.trace, candidate_findings), _channel(run, prepared.trace),
             _stationarity(prepared)]
    return sorted(items, key=lambda item: not item["evidence"])


def check_lines(items: list[dict]) -> list[str]:
    """The checks as text lines (the terminal and the report): one per check, its evidence after it."""
    lines = []
    for item in items:
        evidence = "; ".join(item["evidence"]) if item["evidence"] else "no evidence against it found here"
        lines.append(f"{item['check']} ({', '.join(item['keys'])}): {item['what']} Evidence: {evidence}.")
    return lines


def _calibration(run, trace, candidate_findings: dict[str, list[str]]) -> dict:
    cl, data = run.config.cantilever, run.config.data
    values = [f"k = {format_value(trace.cantilever.spring_constant, 'N/m', 3)}",
              f"Q = {trace.cantilever.quality_factor:.4g}"]
    keys = ["cantilever.spring_constant", "cantilever.quality_factor"]
    if data.invols is not None:
        values.insert(1, f"invols = {data.invols * 1e9:.3g} nm/V")
        keys.insert(1, "data.invols")
    if trace.cantilever.tip_radius is not None:
        values.append(f"R = {format_value(trace.cantilever.tip_radius, 'm', 3)}")
        keys.append("cantilever.tip_radius")
    # A value outside its physical range points at the calibration; a term not selected does not.
    evidence = [f"{run.path.name}: {q['plausibility']}" for q in run.quantities.values()
                if not q.get("plausible", True) and q.get("plausibility") and q.get("determined", True) is not False]
    if math.isfinite(run.separation) and run.config.sample.separation is None:
        sigma = run.nonlinear.get("d", {}).get("error", math.nan)
        verdict = plausibility.judge_separation(run.separation, sigma)
        if not verdict.plausible:
            evidence.append(verdict.finding)
    for effect, findings in candidate_findings.items():
        evidence.extend(f"the refit with {effect} needs {finding}" for finding in findings[:1])
    sources = [f"{key} from {where}" for key, where in trace.sources.items()
               if key in ("spring_constant", "quality_factor", "tip_radius", "invols")]
    declared = [key for key, value in (("cantilever.spring_constant_uncertainty", cl.spring_constant_uncertainty),
                                       ("cantilever.quality_factor_uncertainty", cl.quality_factor_uncertainty),
                                       ("data.invols_uncertainty", data.invols_uncertainty)) if value]
    what = (f"the calibration the forces are built on ({', '.join(values)}"
            + (f"; {', '.join(sources)}" if sources else "") + "): a wrong k scales every force, a wrong invols "
            "every deflection and so the indentation, a wrong Q the dissipative part; "
            + ("its declared uncertainty is in the error bars." if declared else
               "no calibration uncertainty is declared, so the error bars hold none of it."))
    return {"check": "calibration", "keys": keys, "what": what, "evidence": evidence}


def _channel(run, trace) -> dict:
    data = run.config.data
    column = data.column if data.column is not None else "the file's default"
    what = (f"that data.column ({column}) is the vertical deflection and data.positive ({data.positive}) its sign "
            "toward the sample.")
    evidence = []
    try:
        analysis = defects.analyse_with(trace.deflection, defects.settings_for(trace, run.config))
    except (AfmidError, ValueError, FloatingPointError):  # the look at the harmonics is evidence, not a requirement
        analysis = None
    if analysis is not None and analysis.contact == "none":
        evidence.append("no tip-sample force is seen in the harmonics (a free oscillation, or another channel)")
    elif analysis is not None and analysis.flipped:
        evidence.append("the force turns repulsive at the most negative deflection, not at the closest approach: "
                        "is the sign flipped (data.positive)?")
    return {"check": "channel", "keys": ["data.column", "data.positive"], "what": what, "evidence": evidence}


def _stationarity(prepared) -> dict:
    motion = prepared.motion
    evidence = []
    if motion is not None and (motion.non_periodic or motion.modulation is not None or motion.incoherent):
        evidence.append("the motion: " + motion.words(prepared.drive.frequency))
    evidence.extend(f.message for f in prepared.trace.findings
                    if f.severity != "error" and f.name in UNSTEADY_FINDINGS)
    what = ("that the record is stationary: the fit takes every period as the same orbit; a scanning tip, a "
            "feedback at work or a drifting lever changes it (fit a steady part: data.start, data.stop).")
    return {"check": "non-stationarity", "keys": ["data.start", "data.stop"], "what": what, "evidence": evidence}

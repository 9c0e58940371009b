"""Read-outs the data do not determine, and terms the data cannot decide on (poor signals).

A physical quantity is read out from its effect's selected terms. When a term it needs was not selected (the
Hertz term of a lever in liquid that barely touches, the van der Waals tail at 10 pm of detector noise), the
read-out used to be the effect's formula at a zero coefficient: "E* = 0 ± 0", a tight-looking number that no
measurement supports. Here such a quantity is marked **not determined**:

- its value is NaN and ``determined`` is False (stored as such in the run file, the batch and map rows);
- its interval is the 95 % bootstrap interval of the read-out **with the missing terms forced into the
  support** (the fit's other terms as selected, the same period resamples as the error bars): what the data
  allow if the effect is there (``interval_kind`` says so; its upper end is the "at most" a user may quote);
- ``inclusion`` is the smallest inclusion probability of the missing terms (how often a resample of the
  periods selects them) and ``undetermined_terms`` names them.

A quantity whose terms were selected but are selected in only part of the resamples (inclusion below
:data:`DECIDED`) is **undecided**: the data cannot say whether the term belongs in the model. Its error and
interval then include the spread between the read-outs with and without the doubt resolved: the bootstrap of
the support forced to hold the term, widened by the difference to the model-averaged read-out (each resample's
own support); a warning names the term and its inclusion probability.
"""

from __future__ import annotations

import math

from typing import TYPE_CHECKING

import numpy as np

import afmid.fit.regression as regression
from afmid.fit.forces import read_out
from afmid.fit.uncertainty import widen_interval

if TYPE_CHECKING:  # annotations only
    from afmid.fit.fit_state import FitState

#: A selected term that a resample of the periods re-selects at least this often counts as decided by the data.
DECIDED = 0.9
#: What the interval of a not-determined quantity is (run file attribute ``interval_kind``).
FORCED_INTERVAL = "95 % bootstrap interval with the unselected term(s) forced into the model"
#: What the interval of a quantity is whose value moves with the terms its effect's selection dropped.
BOTH_MODELS_INTERVAL = "95 %: the union of the bootstrap intervals without and with the dropped term(s) forced in"
#: What the interval of a determined quantity is.
USUAL_INTERVAL = "95 % bootstrap interval"


def whole_effects(library, mask: np.ndarray) -> np.ndarray:
    """The columns a nonlinear parameter is profiled with: the support ``mask`` plus every term of each catalog
    effect that has a term in it (the nuisance columns as in ``mask``).

    An effect is one piece of physics: DMT's tail and adhesion are tied, and a term the selection drops because
    the data cannot resolve it (the van der Waals tail on a noisy record) is still there. Profiling the
    separation without it lets the remaining contact term imitate the missing adhesion by moving d, with a
    profile that ends where the contact ends: measured on the poor instrument (10 pm, 50 samples per period),
    support [hertz], d +891 pm at a sigma of 101 pm (seed 301), +831 at 195 (seed 235); with the whole effect
    +729 +- 1312 and +582 +- 2319 pm. Effects with no selected term stay out (they would only blur d).
    """
    out = np.array(mask, dtype=bool, copy=True)
    chosen = {library.terms[j].effect for j in np.flatnonzero(out[:len(library)])} - {None}
    for j, term in enumerate(library.terms):
        if term.effect in chosen:
            out[j] = True
    return out


def _effect_term_indices(library, effect: str) -> list[int]:
    return [j for j, t in enumerate(library.terms) if t.effect == effect]


def _read(read_out, library, coef, params, mask, trace, name: str) -> float:
    return float(read_out(library, coef, None, params, mask, trace).get(name, {}).get("value", math.nan))


def _silent_columns(T: np.ndarray, columns: list[int]) -> list[int]:
    """The ``columns`` that carry no signal on this trace (their whitened norm is zero to rounding: a contact
    term where the model's tip never reaches the contact): forcing them in says nothing, not "0"."""
    norms = np.linalg.norm(T[:, :-1], axis=0)  # the columns are in SI units: only an exact zero is scale-free
    return [j for j in columns if not norms[j] > 0]


def _interval(read_out, library, samples: np.ndarray, params, mask, trace, name: str) -> tuple[float, float, float]:
    """(1-sigma std, 2.5 %, 97.5 % percentile) of the read-out ``name`` over coefficient samples (NaN if < 3)."""
    values = np.array([_read(read_out, library, c, params, mask, trace, name) for c in samples], dtype=float)
    values = values[np.isfinite(values)]
    if values.size < 3:
        return math.nan, math.nan, math.nan
    lo, hi = np.percentile(values, [2.5, 97.5])
    return float(values.std(ddof=1)), float(lo), float(hi)


def mark(state: FitState, n_boot: int, seed: int | None) -> None:
    """Mark the not-determined and the undecided read-outs of a fit (in place on ``state.quantities``; see the
    module docstring).

    ``state`` (:class:`afmid.fit.fit_state.FitState`): the fit's coefficients and support (all columns) and
    ``inclusion``, per column the fraction of period resamples selecting it (the chosen mask when there was no
    bootstrap); ``n_boot``: the resamples of the forced supports' intervals (0: no interval, the flags only), drawn
    from ``seed``. Warning lines are appended to ``state.warnings``.
    """
    quantities, library, system, coef, mask = state.quantities, state.library, state.system, state.coef, state.mask
    params, trace, inclusion, warnings = state.params, state.trace, state.inclusion, state.warnings
    T = regression.combine(system.T_blocks)
    for name, q in quantities.items():
        q.setdefault("determined", True)
        q.setdefault("interval_kind", USUAL_INTERVAL)
        effect = q.get("effect")
        own = _effect_term_indices(library, effect)
        missing = [j for j in own if not mask[j]]
        if missing:
            forced = mask.copy()
            forced[missing] = True
            forced_coef, _ = regression.subset_fit(T, forced)
            value_forced = _read(read_out, library, forced_coef, params, forced, trace, name)
            # The quantity needs a missing term when the missing terms' own coefficients change its read-out,
            # the other coefficients held (E* needs Hertz, not vdW; refitting would move both).
            # A column that is zero on this trace keeps a coefficient of exactly 0 when forced in, which reads out
            # as now ("E* = 0"): a unit coefficient (SI) probes whether the read-out is made of the term.
            probe = coef.copy()
            probe[missing] = np.where(forced_coef[missing] != 0, forced_coef[missing], 1.0)
            value_probe = _read(read_out, library, probe, params, forced, trace, name)
            value_now = q["value"]
            needs = not (math.isfinite(value_now) and math.isfinite(value_probe)
                         and abs(value_probe - value_now) <= 1e-9 * max(abs(value_now), abs(value_probe)))
            if needs:
                std = lo = hi = math.nan
                silent = _silent_columns(T, missing)
                if n_boot > 0 and not silent:
                    rng = np.random.default_rng(seed)
                    samples = regression.resampled_coefficients(system.T_blocks, forced, n_boot, rng)
                    # The least squares drop a column below its pivot tolerance (coefficient exactly 0 in every
                    # resample): silent too, not a tight interval around 0.
                    silent = [j for j in missing if not np.any(samples[:, j] != 0)]
                    if not silent:
                        std, lo, hi = _interval(read_out, library, samples, params, forced, trace, name)
                terms = [library.names[j] for j in missing]
                q.update(value=math.nan, error=math.nan, ci_low=lo, ci_high=hi, determined=False,
                         interval_kind=FORCED_INTERVAL, forced_value=value_forced, forced_error=std,
                         inclusion=float(min(inclusion[j] for j in missing)), undetermined_terms=terms)
                if silent:  # e.g. a contact term while the fitted separation keeps the tip off the sample
                    q.update(forced_value=math.nan, silent_terms=[library.names[j] for j in silent])
                if "error_statistical" in q:  # no error bar at all: neither part exists
                    q.update(error_statistical=math.nan, error_calibration=math.nan)
                continue
    _widen_for_undecided_terms(quantities, library, T, mask, params, trace, inclusion, read_out, warnings)
    _widen_for_dropped_terms(quantities, library, system, T, mask, params, trace, inclusion, n_boot, seed, read_out,
                             warnings)


def _widen_for_undecided_terms(quantities, library, T, mask, params, trace, inclusion, read_out, warnings) -> None:
    """Each library term the resamples select only sometimes (1 - DECIDED < inclusion < DECIDED) is a model
    the data cannot rule out: the read-outs with the term toggled (dropped if selected, forced in if not) are
    the other model's. A determined quantity gains sqrt(p (1 - p)) |value - value_toggled| in quadrature
    (the between-model spread of a two-model average with weights p, 1 - p), unless it needs the term
    itself (E* without Hertz is no E*: then it is flagged, its value is the one with the term)."""
    n_lib = len(library)
    spreads = {name: 0.0 for name in quantities}
    for j in range(n_lib):
        p = float(inclusion[j])
        if not (1.0 - DECIDED < p < DECIDED):
            continue
        toggled = mask.copy()
        toggled[j] = not mask[j]
        toggled_coef, _ = regression.subset_fit(T, toggled)
        other = read_out(library, toggled_coef, None, params, toggled, trace)
        term = library.names[j]
        shown = False
        for name, q in quantities.items():
            if not q.get("determined", True) or not math.isfinite(q["value"]):
                continue
            needs_term = library.terms[j].effect == q.get("effect")
            v_other = float(other.get(name, {}).get("value", math.nan))
            if needs_term and (not math.isfinite(v_other) or v_other == 0.0):
                q.update(undecided=True, inclusion=p, undecided_terms=q.get("undecided_terms", []) + [term])
                continue
            if math.isfinite(v_other):
                spreads[name] = math.hypot(spreads[name], math.sqrt(p * (1.0 - p)) * abs(q["value"] - v_other))
                q.update(undecided=True, undecided_terms=q.get("undecided_terms", []) + [term])
            shown = True
        state = "selected" if mask[j] else "not selected"
        warnings.append(f"warning: the data cannot decide whether {term} belongs in the model ({state}; selected in "
                        f"{100 * p:.0f} % of the period resamples)" + (": the error bars of the read-outs include "
                                                                      "the spread between the two models" if shown else ""))
    for name, q in quantities.items():
        widen(q, spreads[name])


def _widen_for_dropped_terms(quantities, library, system, T, mask, params, trace, inclusion, n_boot, seed, read_out,
                             warnings) -> None:
    """The terms the selection dropped from an effect it kept (and the resamples drop too: the undecided ones are
    above) are still that effect's physics: DMT's van der Waals tail at 10 pm of detector noise is below the
    selection's penalty, yet leaving it out moves E* by 30-50 % (measured: poor instrument variant b, 50 periods,
    separation given: E* 1.47 +- 0.03 GPa without it, 2.04 with it, truth 3.0). The support with those terms
    forced in (:func:`whole_effects`) is the other model the data allow. Each determined quantity gains half the
    difference of the two read-outs in quadrature (as the force does: afmid.fit.force_band.selection_share;
    where the data reject the terms their forced coefficients are near 0, and so is this). A quantity that
    moves by more than twice its error is one the data cannot decide: it is marked undecided (the terms named,
    a warning), its 1 sigma becomes the two models' equal mixture's, sqrt((s1^2 + s2^2) / 2 + (v1 - v2)^2 / 4),
    and its 95 % interval the union of the two models' bootstrap intervals."""
    whole = whole_effects(library, mask)
    dropped = [j for j in np.flatnonzero(whole[:len(library)] & ~mask[:len(library)]) if inclusion[j] <= 1 - DECIDED]
    if not dropped:
        return
    forced = mask.copy()
    forced[dropped] = True
    forced_coef, _ = regression.subset_fit(T, forced)
    other = read_out(library, forced_coef, None, params, forced, trace)
    samples = None
    terms = [library.names[j] for j in dropped]
    moved = []
    for name, q in quantities.items():
        if not q.get("determined", True) or not math.isfinite(q["value"]):
            continue
        value, v_other = q["value"], float(other.get(name, {}).get("value", math.nan))
        if not math.isfinite(v_other) or v_other == value:
            continue
        error = q["error"] if math.isfinite(q["error"]) else 0.0
        if abs(v_other - value) <= 2 * error:
            widen(q, 0.5 * abs(v_other - value))
            continue
        std_other, lo_other, hi_other = math.nan, v_other, v_other
        if n_boot > 0:
            if samples is None:
                samples = regression.resampled_coefficients(system.T_blocks, forced, n_boot, np.random.default_rng(seed))
            std_other, lo, hi = _interval(read_out, library, samples, params, forced, trace, name)
            if math.isfinite(lo) and math.isfinite(hi):
                lo_other, hi_other = min(lo, v_other), max(hi, v_other)
        spread = math.sqrt(max(0.5 * ((std_other if math.isfinite(std_other) else error) ** 2 - error**2), 0.0)
                           + 0.25 * (v_other - value) ** 2)
        own = (q["ci_low"], q["ci_high"])
        widen(q, spread)  # error -> the mixture's sqrt((s1^2 + s2^2) / 2 + d^2 / 4) when s2 >= s1
        if all(math.isfinite(e) for e in own):  # the union of the two models' intervals (else widen's +-1.96 sigma)
            q["ci_low"], q["ci_high"] = own
        q["ci_low"], q["ci_high"] = min(q["ci_low"], lo_other), max(q["ci_high"], hi_other)
        q.update(undecided=True, undecided_terms=q.get("undecided_terms", []) + terms,
                 interval_kind=BOTH_MODELS_INTERVAL)
        moved.append(f"{name} {value:.3g} -> {v_other:.3g} {q.get('unit', '')}".rstrip())
    if moved:
        one = len(terms) == 1
        warnings.append(f"warning: {', '.join(terms)} not selected (the data cannot resolve {'it' if one else 'them'}),"
                        f" but {'it belongs' if one else 'they belong'} to an effect of the model; forced in, "
                        f"{'it moves' if one else 'they move'} {'; '.join(moved)} by more than twice the error: the "
                        "data cannot decide, the error bars and 95 % intervals include both models")


def widen(q: dict, spread: float) -> None:
    """Add a 1-sigma model-uncertainty ``spread`` in quadrature to the error and the 95 % interval (in place)."""
    if not math.isfinite(spread) or spread <= 0:
        return
    if "error_statistical" in q:  # the model uncertainty comes from the data: part of the statistical error
        stat = q["error_statistical"] if math.isfinite(q["error_statistical"]) else 0.0
        q["error_statistical"] = math.hypot(stat, spread)
    widen_interval(q, spread)

"""Diagnosis: where a fitted model fails, and which physical effect is missing.

Works from run files (written by ``afmid fit``) so reports can be made later
and compared across runs. :func:`localize` splits the residual between the
model-free force and the model force by region (contact / near / far), by
approach vs retraction, by phase and by drive harmonic, and into a
conservative part (same on approach and retraction) and a dissipative part
(reverses with the direction of motion). :func:`suggest` refits the trace with
each catalog effect the model lacks and ranks them by cross-validated error,
accepting an effect only when the evidence is strong (information criterion
and error both improve, and the effect's own terms are selected).
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .config import RunConfig, build_config
from .errors import InputError
from .io import RUN_FORMAT, Truth, read_truth, sha256_file
from .physics import EFFECTS

log = logging.getLogger(__name__)

#: Separations within this distance above a0 count as "near" the surface, m.
NEAR_RANGE = 2e-9
#: An added effect must lower BIC by at least this much ("very strong" evidence, Kass & Raftery 1995) ...
BIC_EVIDENCE = 10.0
#: ... and lower the cross-validated error to at most this fraction of the current one.
ERROR_RATIO = 0.8
#: The model explains the data to the noise level when its error is within this factor of the noise floor.
FLOOR_FACTOR = 1.3
#: Effects that are base contact models: one at a time, never suggested on top of another.
BASE_MODELS = ("dmt", "jkr", "lennard_jones")


@dataclass
class RunData:
    """A run file's contents (SI)."""

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

    @property
    def n_terms(self) -> int:
        return int(self.selected.sum())

    @property
    def selected_terms(self) -> list[str]:
        return [t for t, s in zip(self.terms, self.selected) if s]


def _str_list(ds) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in ds[...]]


def load_run(path: str | Path) -> RunData:
    """Read a run file; InputError if it is not one."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise InputError("run file not found", file=path)
    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise InputError("not a readable HDF5 file (truncated or corrupt?)", file=path) from None
    with h5:
        if h5.attrs.get("format") != RUN_FORMAT:
            raise InputError(f"not an afmid run file (format attribute {h5.attrs.get('format')!r})", file=path)
        raw = yaml.safe_load(h5.attrs["config"])
        input_path = h5.attrs.get("input_path")
        config = build_config(raw, source=path, base_dir=Path(input_path).parent if input_path else path.parent)
        m = h5["model"]
        quantities = {
            name: {"value": float(ds[()]), "unit": ds.attrs["units"], "error": float(ds.attrs["error"]),
                   "ci_low": float(ds.attrs["ci_low"]), "ci_high": float(ds.attrs["ci_high"]),
                   "effect": str(ds.attrs["effect"])}
            for name, ds in m["parameters"].items()
        }
        nonlinear = {name: {"value": float(ds[()]), "error": float(ds.attrs["error"]), "unit": ds.attrs["units"]}
                     for name, ds in m["nonlinear"].items()}
        d = h5["diagnostics"]
        data = RunData(
            path=path,
            config=config,
            effects=[e for e in _str_list(m["effects"]) if e],
            terms=_str_list(m["terms"]),
            expressions=_str_list(m["expressions"]),
            units=_str_list(m["units"]),
            coefficients=m["coefficients"][...],
            errors=m["coefficients_errors"][...],
            selected=m["selected"][...].astype(bool),
            inclusion=m["inclusion_probability"][...],
            quantities=quantities,
            nonlinear=nonlinear,
            separation=float(m["separation"][()]),
            cv_error=float(d["cv_error"][()]),
            cv_error_noise_floor=float(d["cv_error_noise_floor"][()]),
            bic=float(d["bic"][()]),
            chi2_reduced=float(d["chi2_reduced"][()]),
            drive={k: float(v[()]) for k, v in m["drive"].items()},
            cantilever={k: float(v) for k, v in h5["cantilever"].attrs.items() if k != "units"},
            periods={k: v[...] for k, v in h5["periods"].items()},
            force={k: v[...] for k, v in h5["force"].items()},
            input_path=Path(input_path) if input_path else None,
            input_sha256=h5.attrs.get("input_sha256"),
            warnings=list(d.attrs.get("warnings", [])),
        )
    if data.input_path is not None and data.input_path.exists():
        try:
            data.truth = read_truth(data.input_path)
        except OSError:
            data.truth = None
    return data


# --------------------------------------------------------------------------- localisation
def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2))) if a.size else 0.0


def localize(run: RunData) -> dict:
    """Residual (model-free minus model force, N) broken down by region, direction, phase, harmonic and character."""
    P = run.periods
    r = P["force_direct"] - P["force_model"]
    z = P["separation"]
    zdot = -P["velocity"]
    a0 = run.config.sample.a0
    regions = {
        "contact": z <= a0,
        "near": (z > a0) & (z <= a0 + NEAR_RANGE),
        "far": z > a0 + NEAR_RANGE,
    }
    total = float(np.sum(r**2)) or 1e-300
    by_region = {}
    for name, sel in regions.items():
        app = sel & (zdot < 0)
        ret = sel & (zdot >= 0)
        by_region[name] = {
            "fraction_of_time": float(sel.mean()),
            "share_of_residual": float(np.sum(r[sel] ** 2) / total),
            "rms": _rms(r[sel]),
            "rms_force": _rms(P["force_direct"][sel]),
            "rms_approach": _rms(r[app]),
            "rms_retraction": _rms(r[ret]),
        }
    # Conservative / dissipative split: compare approach and retraction at equal separation.
    interacting = z <= a0 + NEAR_RANGE
    zi = z[interacting]
    edges = np.linspace(zi.min(), zi.max(), 41) if zi.size else np.array([0.0, 1.0])
    cons, diss = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        band = interacting & (z >= lo) & (z < hi)
        app, ret = r[band & (zdot < 0)], r[band & (zdot >= 0)]
        if app.size and ret.size:
            cons.append(0.5 * (app.mean() + ret.mean()))
            diss.append(0.5 * (app.mean() - ret.mean()))
    cons_rms, diss_rms = _rms(np.asarray(cons)), _rms(np.asarray(diss))
    period = 2 * np.pi / (2 * np.pi * run.drive["frequency"])
    dt = period / r.shape[1]
    residual_dissipation = float(np.mean(-np.sum(r * zdot, axis=1) * dt))
    # Harmonic content of the residual (along the phase axis).
    spectrum = np.abs(np.fft.rfft(r, axis=1)) / r.shape[1]
    spectrum[:, 1:] *= 2
    by_harmonic = np.sqrt(np.mean(spectrum**2, axis=0))
    phase_bins = 16
    by_phase = np.sqrt(np.mean(r.reshape(r.shape[0], phase_bins, -1) ** 2, axis=(0, 2)))
    contact = regions["contact"]
    rate_corr = math.nan
    if contact.sum() > 10 and np.std(r[contact]) > 0 and np.std(zdot[contact]) > 0:
        rate_corr = float(np.corrcoef(r[contact], zdot[contact])[0, 1])
    main_region = max(by_region, key=lambda k: by_region[k]["share_of_residual"])
    return {
        "rms": _rms(r),
        "rms_force": _rms(P["force_direct"]),
        "by_region": by_region,
        "region": main_region,
        "character": "dissipative" if diss_rms > cons_rms else "conservative",
        "conservative_rms": cons_rms,
        "dissipative_rms": diss_rms,
        "residual_dissipated_energy": residual_dissipation,
        "rate_correlation": rate_corr,
        "by_harmonic": by_harmonic,
        "by_phase": by_phase,
        "per_period_rms": np.sqrt(np.mean(r**2, axis=1)),
    }


def energy_check(run: RunData) -> dict:
    """Dissipated energy per period (J) three ways: model-free force, cantilever energy balance, model."""
    P = run.periods
    out = {
        "model_free": float(np.mean(P["dissipated_energy_direct"])),
        "model": float(np.mean(P["dissipated_energy"])),
    }
    # Energy balance of the cantilever: drive work - viscous loss per period, from the first harmonic.
    x = P["deflection"]
    v = P["velocity"]
    phase = P["phase"]
    omega = 2 * np.pi * run.drive["frequency"]
    period = 2 * np.pi / omega
    drive = run.drive["cos"] * np.cos(phase) + run.drive["sin"] * np.sin(phase)  # curves are at w t = phase
    cl = run.cantilever
    damping = cl["spring_constant"] / (cl["quality_factor"] * 2 * np.pi * cl["resonance_frequency"])
    work = np.mean(np.sum(drive * v, axis=1)) * period / x.shape[1]
    viscous = damping * np.mean(np.sum(v**2, axis=1)) * period / x.shape[1]
    out["energy_balance"] = float(work - viscous)
    return out


# --------------------------------------------------------------------------- suggestions
@dataclass
class Trial:
    effect: str
    error_after: float
    bic_after: float
    delta_bic: float
    effect_terms_selected: bool
    quantities: dict
    significant: bool
    evidence: str = ""


def candidate_effects(current: list[str]) -> list[str]:
    has_base = any(e in BASE_MODELS for e in current)
    return [e.name for e in EFFECTS if e.name not in current and not (has_base and e.name in BASE_MODELS)]


def refit_config(run: RunData, effects: list[str]) -> RunConfig:
    """The run's own config with another effect list, pointing at the run's input file."""
    config = copy.deepcopy(run.config)
    config.model.effects = effects
    if run.input_path is not None:
        config.data.path = run.input_path
    config.fit.bootstrap = 0
    return config


def suggest(run: RunData, progress: bool = False) -> dict:
    """Try each missing catalog effect; return the diagnosis and ranked suggestions (pinned summary layout)."""
    from tqdm import tqdm

    from .fit import run_fit
    from .io import load_trace

    if run.config.model.library is not None:
        return {"missing_effect": False, "suggestions": [], "tried": [],
                "note": "suggestions need a model built from effects (model.effects), not a preset library"}
    if run.input_path is None or not run.input_path.exists():
        raise InputError("the run's input trace is not available for refitting", file=run.path, key="input_path")
    if run.input_sha256 and sha256_file(run.input_path) != run.input_sha256:
        log.warning("%s changed since the run was made (SHA-256 differs); refitting the current file", run.input_path)
    local = localize(run)
    base_config = refit_config(run, run.effects)
    trace = load_trace(base_config)
    trials: list[Trial] = []
    candidates = candidate_effects(run.effects)
    for effect in tqdm(candidates, desc="trying effects", disable=not progress, leave=False):
        config = refit_config(run, run.effects + [effect])
        try:
            result = run_fit(config, trace=trace)
        except Exception as exc:  # one effect that cannot be fitted must not stop the diagnosis
            log.info("refit with %s failed: %s", effect, exc)
            continue
        names = result.library.names
        selected = [n for n, s in zip(names, result.selected) if s and n.startswith(effect + ".")]
        bic_after = result.selection.best.bic
        dbic = bic_after - run.bic
        significant = bool(selected) and dbic < -BIC_EVIDENCE and result.cv_error < ERROR_RATIO * run.cv_error
        qty = {k: v for k, v in result.quantities.items() if v["effect"] == effect}
        trials.append(Trial(effect, result.cv_error, bic_after, dbic, bool(selected), qty, significant))
    trials.sort(key=lambda t: t.error_after)
    for t in trials:
        t.evidence = _evidence(t, local, run)
    good = [t for t in trials if t.significant]
    residual_significant = not run.cv_error <= FLOOR_FACTOR * run.cv_error_noise_floor
    return {
        "missing_effect": bool(good),
        "diagnosis": {
            "region": local["region"],
            "character": local["character"],
            "explained_by_catalog": bool(good) or not residual_significant,
            "residual_significant": residual_significant,
            "chi2_reduced": run.chi2_reduced,
            "error": run.cv_error,
            "noise_floor": run.cv_error_noise_floor,
            "description": describe_residual(local, run),
        },
        "suggestions": [_trial_record(t) for t in good],
        "tried": [_trial_record(t) for t in trials],
    }


def _trial_record(t: Trial) -> dict:
    return {"effect": t.effect, "error_after": t.error_after, "delta_bic": t.delta_bic,
            "terms_selected": t.effect_terms_selected, "significant": t.significant, "evidence": t.evidence,
            "parameters": {k: {"value": v["value"], "error": v["error"], "unit": v["unit"]} for k, v in t.quantities.items()}}


def describe_residual(local: dict, run: RunData) -> str:
    reg = local["by_region"][local["region"]]
    text = (f"residual {local['rms'] * 1e9:.3g} nN rms ({100 * local['rms'] / max(local['rms_force'], 1e-300):.1f} % of "
            f"the force), {100 * reg['share_of_residual']:.0f} % of it {_region_words(local['region'])}, "
            f"mostly {local['character']} (dissipative part {local['dissipative_rms'] * 1e9:.3g} nN, conservative "
            f"{local['conservative_rms'] * 1e9:.3g} nN)")
    if local["residual_dissipated_energy"] and abs(local["residual_dissipated_energy"]) > 0:
        text += f"; the model misses {local['residual_dissipated_energy'] / 1.602176634e-19:.3g} eV per period"
    if not math.isnan(local["rate_correlation"]) and abs(local["rate_correlation"]) > 0.5:
        text += "; in contact it follows the indentation rate"
    return text


def _region_words(region: str) -> str:
    return {"contact": "in contact", "near": f"within {NEAR_RANGE * 1e9:g} nm of contact",
            "far": "far from the surface"}[region]


def _evidence(t: Trial, local: dict, run: RunData) -> str:
    effect = EFFECTS.get(t.effect)
    text = f"{describe_residual(local, run)}: `{t.effect}` ({effect.character}, acts {effect.region})"
    text += f"; adding it changes the error from {run.cv_error:.3g} to {t.error_after:.3g} (ΔBIC {t.delta_bic:.0f})"
    if t.quantities:
        parts = [f"{k} = {v['value']:.3g} {v['unit']}" for k, v in t.quantities.items() if np.isfinite(v["value"])]
        if parts:
            text += "; it yields " + ", ".join(parts)
    if not t.effect_terms_selected:
        text += "; its terms were not selected"
    return text

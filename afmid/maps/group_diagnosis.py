"""The catalog diagnosis per group of pixels: which effect is missing where.

For each group of :mod:`afmid.maps.groups` whose typical pixel is model-limited (median cross-validated error above
:data:`afmid.fit.uncertainty.FLOOR_FACTOR` x its noise floor), up to :data:`REPRESENTATIVES` pixels nearest the
group's centre are diagnosed as single traces, in memory: the pixel's trace fitted as ``afmid fit`` fits it (no
bootstrap), and :func:`afmid.diagnosis.diagnose.suggest` run on that run (every catalog
effect the model lacks refitted, BIC with the per-period evidence of afmid.diagnosis.decide). The group's verdict
is what more than half of its representatives say, in this order:

- ``missing: EFFECT`` (or ``A + B``): the diagnosis names the same effect(s) and they explain the residual;
- ``nothing missing``: the diagnosis finds no effect missing;
- ``not explained by the catalog``: a significant residual that no catalog effect explains;
- ``cannot decide: A or B``: effects the per-period evidence does not tell apart (afmid.diagnosis.decide);
- ``instrument: KIND``: the residual is the instrument's (afmid.diagnosis.instrument_signature);
- ``leading candidate: EFFECT``: no verdict has a majority, but more than half of the representatives rank the same
  effect first among those their diagnosis accepts (it names it with a reservation: not told apart from a rival,
  or a significant residual left); every representative's verdict is kept and said;
- ``undecided``: the representatives disagree (each one's verdict is kept).

The representatives are those nearest the group's centre in the grouping's scaled features (residual signature and
parameters: :func:`afmid.maps.groups.representatives`), nearest first; those left are skipped once the verdict
cannot change (the first two of three agree on the verdict and the leading candidate: :func:`verdict_settled`); the
group's record then holds the pixels diagnosed ("2 of 2 representative pixels").

Where they run: each representative is one task (:func:`diagnose_pixel_task`) on the map's engine, the workers that
fitted the pixels. The groups are known only once every pixel is fitted (k-means over the whole map), so the
diagnoses follow the map's fit; they run in rounds, every model-limited group's next pixels in one round: as many
as could settle the group (two of three at first, then the third only if the two disagree). A round never
diagnoses a pixel the one-after-another order would have skipped, and its results are taken in that order, so the
verdicts are the same as diagnosing one pixel after another in this process; with two workers the first two
representatives of a group take the wall time of one.

A group whose median error is within the model-limited rule (at most FLOOR_FACTOR x the floor) is not refitted:
its verdict is ``nothing missing`` by the error rule, and says so ("not diagnosed"). The cost is a few single-trace
diagnoses per model-limited group, never one per pixel.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

#: Pixels diagnosed per model-limited group (the verdict is their majority).
REPRESENTATIVES = 3
NOTHING = "nothing missing"
UNEXPLAINED = "not explained by the catalog"
UNDECIDED = "undecided"
NOT_DIAGNOSED = "model-limited, not diagnosed"
LEADING = "leading candidate: "


@dataclass
class GroupVerdict:
    """One group's verdict and what it rests on (SI; pixel indices flat, row-major)."""

    group: int
    pixels: int  # pixels in the group
    fraction: float  # of the fitted pixels
    error_over_floor: float  # median over the group's pixels
    effects: list[str]  # the missing effects named (empty: none)
    verdict: str  # NOTHING, UNEXPLAINED, UNDECIDED or "missing: A + B"
    diagnosed: bool  # False: judged by the error rule alone
    representatives: list[int] = field(default_factory=list)
    pixel_verdicts: list[str] = field(default_factory=list)  # each representative's diagnosis verdict
    delta_bic: list[float] = field(default_factory=list)  # each representative's BIC change with the effect(s)
    error_after: list[float] = field(default_factory=list)  # each representative's error after adding them
    floor: list[float] = field(default_factory=list)  # each representative's noise floor
    leading: list[str] = field(default_factory=list)  # each representative's leading candidate ("" none)
    region: str = ""  # the most common residual region of the group's pixels
    character: str = ""  # the most common residual character

    def sentence(self) -> str:
        """The group's verdict in one sentence."""
        head = f"group {self.group + 1} ({100 * self.fraction:.0f} % of the pixels, {self.pixels}"
        head += f" pixels; median error {self.error_over_floor:.2f}x its noise floor"
        head += f", residual mostly {self.character}, {self.region})" if self.character else ")"
        if self.verdict == NOT_DIAGNOSED:
            return f"{head}: {NOT_DIAGNOSED} (afmid map --no-diagnosis)"
        if not self.diagnosed:
            return (f"{head}: nothing missing by the error rule (within the model-limited factor); not diagnosed")
        n = len(self.representatives)
        agree = sum(v == self.verdict for v in self.pixel_verdicts)
        basis = f"{agree} of {n} representative pixels"
        if self.verdict.startswith(LEADING):
            effect = self.effects[0]
            first = sum(e == effect for e in self.leading)
            bic = [b for b, e in zip(self.delta_bic, self.leading) if e == effect and math.isfinite(b)]
            extra = f"; ΔBIC {min(bic):.0f} .. {max(bic):.0f}" if bic else ""
            return (f"{head}: {effect} the leading candidate ({first} of {n} representative pixels rank it first"
                    f"{extra}; but not one catalog verdict: {'; '.join(self.pixel_verdicts)})")
        if self.effects:
            bic = [b for b, v in zip(self.delta_bic, self.pixel_verdicts) if v == self.verdict and math.isfinite(b)]
            after = [e / f for e, f, v in zip(self.error_after, self.floor, self.pixel_verdicts)
                     if v == self.verdict and math.isfinite(e) and f > 0]
            extra = f"; ΔBIC {min(bic):.0f} .. {max(bic):.0f}" if bic else ""
            extra += f"; their error falls to {np.median(after):.2f}x the floor" if after else ""
            others = [v for v in self.pixel_verdicts if v != self.verdict]
            extra += f"; the other{'s' if len(others) > 1 else ''}: {'; '.join(others)}" if others else ""
            return f"{head}: {' + '.join(self.effects)} missing ({basis}{extra})"
        if self.verdict == UNDECIDED and not self.representatives:
            return f"{head}: undecided (none of its representative pixels could be diagnosed)"
        if self.verdict == UNDECIDED:
            return f"{head}: undecided (the representative pixels disagree: {'; '.join(self.pixel_verdicts)})"
        return f"{head}: {self.verdict} ({basis})"


def summary_sentence(verdicts: list[GroupVerdict]) -> str:
    """The map's verdict: which effect is missing where ("viscoelastic missing in group 2 (38 % of pixels);
    nothing missing elsewhere")."""
    missing = [v for v in verdicts if v.effects]
    other = [v for v in verdicts if not v.effects and v.verdict != NOTHING]
    parts = [f"{' + '.join(v.effects)} {'the leading candidate' if v.verdict.startswith(LEADING) else 'missing'} "
             f"in group {v.group + 1} ({100 * v.fraction:.0f} % of the pixels)" for v in missing]
    parts += [f"{v.verdict} in group {v.group + 1} ({100 * v.fraction:.0f} % of the pixels)" for v in other]
    if not parts:
        return "nothing missing anywhere on the map"
    if any(v.verdict == NOTHING for v in verdicts):
        parts.append("nothing missing elsewhere")
    return "; ".join(parts)


def pixel_verdict(summary: dict) -> tuple[str, list[str]]:
    """A single-trace diagnosis (:func:`afmid.diagnosis.diagnose.suggest`'s summary) as (verdict, effects)."""
    if not summary.get("missing_effect"):
        return NOTHING, []
    diagnosis = summary.get("diagnosis", {})
    if summary.get("undecided"):  # afmid.diagnosis.decide: candidates the per-period evidence does not tell apart
        return "cannot decide: " + " or ".join(t["effect"] for t in summary["undecided"]), []
    if diagnosis.get("instrument"):  # afmid.diagnosis.instrument_signature: the instrument, not the sample
        return f"instrument: {diagnosis['instrument'].get('kind', '')}", []
    effects = [s["effect"] for s in summary.get("suggestions", [])]
    if effects and diagnosis.get("explained_by_catalog"):
        return "missing: " + " + ".join(effects), effects
    return UNEXPLAINED, []


def diagnose_groups(grouping, maps: dict[str, np.ndarray], source, config_text: str, config_source: str | None,
                    diagnose: bool = True, engine=None) -> list[GroupVerdict]:
    """The verdict of every group (see the module docstring). ``maps``: name -> flat arrays over the pixels
    (cv_error, cv_error_noise_floor, residual_region, residual_character); ``source``: the map
    (:func:`afmid.maps.input_file.open_map`). ``diagnose`` False: no refit; a model-limited group's verdict is
    :data:`NOT_DIAGNOSED`. ``engine``: where the representatives are diagnosed (an
    :class:`afmid.batch.engine.Engine`, e.g. the map's own); None: in this process, one after another."""
    from afmid.fit.uncertainty import FLOOR_FACTOR
    from afmid.maps.groups import representatives
    from afmid.maps.residual import CHARACTERS, REGIONS

    labels = grouping.labels.ravel()
    fitted = int(np.count_nonzero(labels >= 0))
    ratio = maps["cv_error"] / maps["cv_error_noise_floor"]
    out, to_diagnose = [], []
    for g in range(grouping.n_groups):
        members = labels == g
        median = float(np.nanmedian(ratio[members]))
        verdict = GroupVerdict(g, int(members.sum()), members.sum() / max(fitted, 1), median, [], NOTHING, False,
                               region=_most_common(maps["residual_region"][members], REGIONS),
                               character=_most_common(maps["residual_character"][members], CHARACTERS))
        if median > FLOOR_FACTOR and not diagnose:
            verdict.verdict = NOT_DIAGNOSED
        elif median > FLOOR_FACTOR:
            to_diagnose.append((verdict, [int(p) for p in representatives(grouping, g, REPRESENTATIVES)]))
        out.append(verdict)
    if to_diagnose:
        diagnose_representatives(to_diagnose, source, config_text, config_source, engine)
    for verdict in out:
        log.info("%s", verdict.sentence())
    return out


@dataclass
class _Diagnosis:
    """A model-limited group being diagnosed: its verdict (filled in place) and its chosen representatives, of which
    the first ``tried`` have been diagnosed (or failed)."""

    verdict: GroupVerdict
    chosen: list[int]
    tried: int = 0

    def next_pixels(self) -> list[int]:
        """The representatives to diagnose in the next round: none once the verdict is settled or every one is
        tried; else as many as could settle it (:func:`fewest_to_settle`), never more than are left."""
        v = self.verdict
        if self.tried >= len(self.chosen) or verdict_settled(v.pixel_verdicts, v.leading, len(self.chosen)):
            return []
        need = fewest_to_settle(v.pixel_verdicts, v.leading, len(self.chosen))
        return self.chosen[self.tried:self.tried + need]


def fewest_to_settle(texts: list[str], leads: list[str], chosen: int) -> int:
    """A lower bound (at least 1) on the further representatives whose diagnoses :func:`verdict_settled` needs: a
    strict majority of ``chosen`` agreeing on verdict and leading candidate, less the largest such agreement so
    far. Diagnosing that many at once never spends a diagnosis the one-after-another order would have skipped."""
    pairs = list(zip(texts, leads))
    agreeing = max((pairs.count(p) for p in set(pairs)), default=0)
    return max(1, chosen // 2 + 1 - agreeing)


def diagnose_representatives(chosen: list[tuple[GroupVerdict, list[int]]], source, config_text: str,
                             config_source: str | None, engine=None) -> None:
    """Diagnose each group's chosen representative pixels (flat indices, nearest the centre first) in rounds on
    ``engine`` (None: in this process; see the module docstring) and set each group's verdict in place. ``source``:
    the map (:func:`afmid.maps.input_file.open_map`; its path is what the tasks name)."""
    import time

    groups = [_Diagnosis(verdict, [int(p) for p in pixels]) for verdict, pixels in chosen]
    for d in groups:
        d.verdict.diagnosed = True

    started, cpu = time.perf_counter(), 0.0
    task = {"input": str(source.path.resolve()), "config": config_text, "source": config_source}
    rounds = 0
    while True:
        batch = [(d, pixel) for d in groups for pixel in d.next_pixels()]
        if not batch:
            break
        rounds += 1
        tasks = [(k, {**task, "pixel": pixel}) for k, (_, pixel) in enumerate(batch)]
        results: dict[int, dict] = {}
        if engine is None:
            results = {k: diagnose_pixel_task(t) for k, t in tasks}
        else:
            def report(outcome) -> None:
                if outcome.result is not None:
                    results[outcome.key] = outcome.result
                elif outcome.crashed:
                    results[outcome.key] = {"error": outcome.crashed}

            engine.run(diagnose_pixel_task, tasks, report, lambda: None)
        for k, (d, pixel) in enumerate(batch):  # in the order of the representatives, as one after another
            d.tried += 1
            result = results.get(k, {"error": "no result from the engine"})
            cpu += result.get("cpu_s", 0.0)
            if verdict_settled(d.verdict.pixel_verdicts, d.verdict.leading, len(d.chosen)):
                continue  # one after another would not have diagnosed it (a round of fewest_to_settle never has one)
            if "summary" in result:
                _record(d.verdict, pixel, result["summary"])
            else:
                log.warning("pixel %s could not be diagnosed: %s", divmod(pixel, source.cols), result["error"])
    for d in groups:
        if d.verdict.representatives:
            d.verdict.verdict, d.verdict.effects = majority(d.verdict.pixel_verdicts, d.verdict.leading)
        else:
            d.verdict.verdict = UNDECIDED
    diagnosed = sum(len(d.verdict.representatives) for d in groups)
    where = "in this process" if engine is None else f"on {engine.workers_for(2)} worker(s)"
    log.info("diagnosed %d representative pixel(s) of %d group(s) in %d round(s) %s: %.1f s wall, %.1f s of CPU",
             diagnosed, len(groups), rounds, where, time.perf_counter() - started, cpu)


def _most_common(codes: np.ndarray, names: tuple[str, ...]) -> str:
    codes = codes[codes >= 0].astype(int)
    return names[int(np.bincount(codes).argmax())] if codes.size else ""


def _record(verdict: GroupVerdict, pixel: int, summary: dict) -> None:
    """Add one representative's diagnosis (:func:`afmid.diagnosis.diagnose.suggest`'s summary) to its group."""
    text, effects = pixel_verdict(summary)
    diagnosis = summary.get("diagnosis", {})
    lead = leading_candidate(summary)
    verdict.representatives.append(int(pixel))
    verdict.pixel_verdicts.append(text)
    verdict.leading.append(lead["effect"] if lead else "")
    if effects:  # the named effect(s) together
        after, delta = diagnosis.get("error_after"), diagnosis.get("delta_bic_after")
    else:  # the leading candidate's own refit (NaN: none)
        after, delta = (lead["error_after"], lead["delta_bic"]) if lead else (None, None)
    verdict.delta_bic.append(float(delta) if delta is not None else math.nan)
    verdict.error_after.append(float(after) if after is not None else math.nan)
    verdict.floor.append(float(diagnosis.get("noise_floor", math.nan)))


def diagnose_pixel_task(task: dict) -> dict:
    """One representative pixel diagnosed where an engine runs it: ``task`` names the map file (``input``), the
    merged config (``config``, YAML text; ``source``, its path or None) and the flat ``pixel``. Returns
    ``{"pixel", "summary", "cpu_s"}``, or ``{"pixel", "error", "cpu_s"}`` (one line) when the pixel cannot be
    diagnosed: never raises for a bad pixel (the fitted map must not be lost)."""
    import time

    from afmid.errors import AfmidError
    from afmid.maps.input_file import open_map
    from afmid.maps.task import map_config

    started = time.process_time()
    pixel = int(task["pixel"])
    try:
        source = open_map(task["input"], map_config(task["config"], task.get("source")))
        out = {"summary": diagnose_pixel(pixel, source, task["config"], task.get("source"))}
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - one pixel that cannot be diagnosed is said, not raised
        out = {"error": exc.message if isinstance(exc, AfmidError) else f"{type(exc).__name__}: {exc}"}
    return {"pixel": pixel, **out, "cpu_s": time.process_time() - started}


def majority(texts: list[str], leading: list[str]) -> tuple[str, list[str]]:
    """The group's (verdict, effects) from its representatives' verdicts and leading candidates ("" none), by the
    rules of the module docstring."""
    leads = [e for e in leading if e]
    n = len(texts)
    top = max(set(texts), key=lambda t: (texts.count(t), t))
    first = max(set(leads), key=lambda e: (leads.count(e), e)) if leads else ""
    if texts.count(top) * 2 > n and top.startswith("missing: "):
        return top, top[len("missing: "):].split(" + ")
    if first and leads.count(first) * 2 > n:
        return LEADING + first, [first]
    if texts.count(top) * 2 > n:
        return top, []
    return UNDECIDED, []


def verdict_settled(texts: list[str], leads: list[str], chosen: int) -> bool:
    """Whether the majority rule of :func:`majority` gives the same group verdict whatever the remaining of the
    ``chosen`` representatives say: one verdict holds a strict majority of all ``chosen`` and its pixels share
    one leading candidate (then rule 1 ``missing: ...`` holds; or the leading candidate has that majority, rule
    2; or no other leading candidate can reach a majority and rule 3 gives that verdict). With 3 representatives:
    the first two agree (verdict and leading candidate), and the third is not diagnosed (a diagnosis is
    ~3-9 s of CPU per pixel, most of a map's group diagnosis)."""
    for text in set(texts):
        agreeing = [lead for t, lead in zip(texts, leads) if t == text]
        if 2 * len(agreeing) > chosen and len(set(agreeing)) == 1:
            return True
    return False


def leading_candidate(summary: dict) -> dict | None:
    """The catalog effect a single-trace diagnosis ranks first among those it accepts (its trial record), also when
    it does not name it alone: not told apart from a rival, or a significant residual left; None when it accepts
    none."""
    ranked = summary.get("suggestions") or summary.get("undecided") or []
    return ranked[0] if ranked else None


def diagnose_pixel(pixel: int, source, config_text: str, config_source: str | None) -> dict:
    """The single-trace diagnosis of one pixel, in memory: its trace (read and checked as the map's fit reads it)
    fitted without bootstrap (the separation estimated), the run made by :func:`afmid.runfile.run_data` (the
    values a run file would hold, no file) and :func:`suggest` run on it with the pixel's trace for the candidates'
    refits. No temporary trace or run file (writing both and reading them back cost measurable time
    per group)."""
    from afmid.diagnosis.diagnose import suggest
    from afmid.fit.pipeline import run_fit
    from afmid.maps.input_file import pixel_trace, read_pixels
    from afmid.maps.task import map_config
    from afmid.runfile import run_data

    config = map_config(config_text, config_source)
    trace = pixel_trace(source, read_pixels(source, pixel, pixel + 1)[0], config, pixel)
    config.fit.bootstrap = 0
    logger = logging.getLogger("afmid")
    level = logger.level
    logger.setLevel(logging.ERROR)  # the pixel's own warnings are the map's (status, messages)
    try:
        result = run_fit(config, trace=trace, uncertainty=False)
        return suggest(run_data(result, config, name=f"pixel {divmod(pixel, source.cols)}"), trace=trace)
    finally:
        logger.setLevel(level)


def write_groups(h5, grouping, verdicts: list[GroupVerdict]) -> None:
    """``/maps/group`` and ``/groups`` (one entry per group; padded per representative) into the open result."""
    from afmid.io.trace import write_dataset
    from afmid.maps.groups import MAX_GROUPS, MIN_SILHOUETTE

    write_dataset(h5["maps"], "group", grouping.labels.astype(np.int16), "1",
                  meaning="group of pixels by residual signature and parameters (0-based; -1: not fitted); the "
                          "verdict of each group in /groups")
    groups = h5.create_group("groups")
    groups.attrs["summary"] = summary_sentence(verdicts)
    groups.attrs["method"] = (f"k-means over the scaled features, k of 2..{MAX_GROUPS} by the mean silhouette (taken "
                              f"when >= {MIN_SILHOUETTE}, else one group); per model-limited group the catalog "
                              f"diagnosis of up to {REPRESENTATIVES} pixels nearest its centre, majority verdict "
                              "(afmid.maps.groups, afmid.maps.group_diagnosis)")
    groups.attrs["silhouette"] = grouping.silhouette
    groups.attrs["features"] = grouping.feature_names
    if not verdicts:
        return
    n, r = len(verdicts), REPRESENTATIVES

    def padded(name: str, fill, dtype=float) -> np.ndarray:
        out = np.full((n, r), fill, dtype=dtype)
        for i, v in enumerate(verdicts):
            values = getattr(v, name)
            out[i, :len(values)] = values
        return out

    write_dataset(groups, "verdict", np.array([v.verdict for v in verdicts]), "1",
                  meaning=f"'missing: EFFECT', '{LEADING}EFFECT', '{NOTHING}', '{UNEXPLAINED}', "
                          f"'cannot decide: A or B', 'instrument: KIND', '{UNDECIDED}' or '{NOT_DIAGNOSED}'")
    write_dataset(groups, "effects", np.array([" + ".join(v.effects) for v in verdicts]), "1",
                  meaning="the missing effects named, or the leading candidate (empty: none)")
    write_dataset(groups, "sentence", np.array([v.sentence() for v in verdicts]), "1")
    write_dataset(groups, "pixels", np.array([v.pixels for v in verdicts]), "1")
    write_dataset(groups, "fraction", np.array([v.fraction for v in verdicts]), "1", meaning="of the fitted pixels")
    write_dataset(groups, "error_over_floor", np.array([v.error_over_floor for v in verdicts]), "1",
                  meaning="median over the group's pixels of cv_error / cv_error_noise_floor")
    write_dataset(groups, "diagnosed", np.array([v.diagnosed for v in verdicts]), "1",
                  meaning="False: the median error is within the model-limited factor; judged by that rule alone")
    write_dataset(groups, "residual_region", np.array([v.region for v in verdicts]), "1",
                  meaning="the most common /maps/residual_region of the group's pixels")
    write_dataset(groups, "residual_character", np.array([v.character for v in verdicts]), "1",
                  meaning="the most common /maps/residual_character of the group's pixels")
    write_dataset(groups, "representatives", padded("representatives", -1, np.int64), "1",
                  meaning="flat (row-major) index of each diagnosed pixel (-1: none)")
    write_dataset(groups, "pixel_verdicts", padded("pixel_verdicts", "", object).astype(str), "1",
                  meaning="each representative pixel's diagnosis verdict")
    write_dataset(groups, "leading", padded("leading", "", object).astype(str), "1",
                  meaning="each representative's leading candidate: the effect its diagnosis ranks first among those "
                          "it accepts (empty: none)")
    write_dataset(groups, "delta_bic", padded("delta_bic", np.nan), "1",
                  meaning="each representative's BIC change when the effect(s) it names, else its leading candidate, "
                          "are added (NaN: none)")
    write_dataset(groups, "error_after", padded("error_after", np.nan), "1",
                  meaning="each representative's normalised cv error with that effect (those effects) added")
    write_dataset(groups, "noise_floor", padded("floor", np.nan), "1",
                  meaning="each representative's cv error noise floor (its single-trace refit)")

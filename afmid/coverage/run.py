"""``afmid coverage``: draw experiments around a run config, simulate and fit each, and count how often the truth
lies within the reported error bars (:func:`run_coverage` -> :class:`CoverageResult`).

Draw k is a function of (``coverage.seed``, k) and the config alone (:mod:`afmid.coverage.draws`), so
``--draw K`` re-runs it by itself and gives the same numbers (bit for bit in the same kind of process: this one,
or a worker with one BLAS thread). Draws run in this process one after the other, or with ``jobs`` > 1 in worker
processes of :class:`afmid.batch.engine.LocalPoolEngine`; a failing draw is counted and listed with why.
"""

from __future__ import annotations

import logging
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from afmid.config import RunConfig, build_config, dump_config
from afmid.coverage.draws import Draw, apply_draw, check_keys, distributions, draw, set_options, yaml_text
from afmid.coverage.loop import (NOTHING_HIDDEN, check_hidden, draw_hidden, hidden_distributions, hide, loop_summary,
                                 loop_text)
from afmid.coverage.summary import QuantitySummary, summarize, table_text
from afmid.coverage.task import draw_task, run_draw
from afmid.errors import ConfigError
from afmid.io.trace import now_iso
from afmid.progress import Progress
from afmid.sections.coverage import CoverageConfig
from afmid.version import __version__

log = logging.getLogger(__name__)


@dataclass
class CoverageResult:
    """The draws of one coverage run (each as :func:`afmid.coverage.task.run_draw` returns it, in draw order) and
    their summaries per quantity (all numbers, and those no flag marked)."""

    config: RunConfig
    config_text: str  # the merged config, coverage section included (provenance)
    section: CoverageConfig  # the coverage section as run (-n, --seed applied)
    distributions: dict[str, str]  # varied key -> its distribution in words
    draws: list[dict]
    summaries: list[QuantitySummary]
    unflagged: list[QuantitySummary]
    seconds: float
    loop: dict | None = None  # the blind loop's counts (afmid.coverage.loop.loop_summary) when it ran
    created: str = field(default_factory=now_iso)
    version: str = __version__

    @property
    def failed(self) -> list[dict]:
        return [d for d in self.draws if d["status"] != "ok"]

    def reproduce(self, index: int, config_path: Path | str = "CONFIG", overrides: tuple[str, ...] = ()) -> str:
        """The commands that re-run draw ``index`` (``overrides``: the run's own ``--set`` options): ``afmid
        coverage --draw``; and ``afmid simulate`` with the ``--set`` options that simulate it, then ``afmid fit`` of
        that trace as the coverage run fitted it (the config's data section must suit an afmid trace file)."""
        one = next(d for d in self.draws if d["index"] == index)
        given = self.section.separation == "given"
        own = " ".join(f"--set {shlex.quote(o)}" for o in overrides)
        options = set_options(Draw(one["index"], one["seed"], one["values"]), given)
        if one.get("hidden", NOTHING_HIDDEN) != NOTHING_HIDDEN:  # the blind loop's hidden effect, simulated only
            effects = [*(self.config.simulate.effects or []), one["hidden"]]
            options += [f"simulate.effects={yaml_text(effects)}"]
            options += [f"simulate.parameters.{k}={yaml_text(v)}" for k, v in one["hidden_parameters"].items()]
        drawn = " ".join(f"--set {shlex.quote(o)}" for o in options)
        config = " ".join(p for p in (shlex.quote(str(config_path)), own) if p)
        fit_sets = "--set data.path=draw{0}.h5".format(index) + ("" if given else " --set sample.separation=null")
        return (f"afmid coverage {config} --seed {self.section.seed} --draw {index}\n"
                f"afmid simulate {config} {drawn} -o draw{index}.h5\n"
                f"afmid fit {config} {drawn} {fit_sets} -o draw{index}.run.h5")

    def text(self, config_path: Path | str = "CONFIG", overrides: tuple[str, ...] = ()) -> str:
        """What ``afmid coverage`` prints: the distributions, the table (all numbers; then the unflagged ones when
        any was flagged), the failed draws with why, and how to re-run the worst draw."""
        n, failed = len(self.draws), self.failed
        lines = [f"afmid coverage: {n} draw(s) around {config_path} (coverage seed {self.section.seed}, separation "
                 f"{self.section.separation}); drawn: "
                 + ("; ".join(f"{k} {v}" for k, v in self.distributions.items()) or "nothing (every draw the same "
                                                                                      "experiment, its own noise)")]
        title = (f"\n{n - len(failed)} of {n} draws fitted; z = (estimate - truth) / reported 1 sigma; fraction "
                 "[95 % Wilson interval]; flag: draws marked model-limited / separation-limited / not determined / "
                 "implausible; miss: fitted draws without a z; >5 unfl: |z| > 5 with no flag")
        lines.append(table_text(self.summaries, title))
        if any(s.flagged for s in self.summaries):
            lines.append(table_text(self.unflagged, "\nthe same over the numbers no flag marked:"))
        if self.loop is not None:
            lines.append("hidden: " + "; ".join(f"{k} {v}" for k, v in hidden_distributions(self.section).items())
                         if self.section.hidden else "hidden: nothing (every draw a null draw)")
            lines.append(loop_text(self.loop))
        for one in failed:
            lines.append(f"failed: draw {one['index']} (seed {one['seed']}) in {one['stage']}: {one['error']}")
        worst = max((s.worst[0] for s in self.summaries if s.worst), key=lambda w: abs(w[2]), default=None)
        if worst is not None:
            lines.append(f"\nthe worst draw ({worst[0]}, z {worst[2]:+.2f}) alone:\n"
                         + self.reproduce(worst[0], config_path, overrides))
        return "\n".join(lines)


def coverage_section(config: RunConfig, draws: int | None = None, seed: int | None = None) -> CoverageConfig:
    """The config's coverage section (the defaults when it has none) with ``draws`` / ``seed`` over it."""
    section = config.coverage.model_copy() if config.coverage is not None else CoverageConfig()
    changes = {k: v for k, v in (("draws", draws), ("seed", seed)) if v is not None}
    return CoverageConfig.model_validate({**section.model_dump(), **changes}) if changes else section


def prepare_draws(config: RunConfig, indices: list[int]) -> list[dict]:
    """The task of every draw in ``indices`` (:func:`afmid.coverage.task.draw_task`). The first draw's configs are
    validated here, so that a config the simulation or the fit refuses stops with its one line before any work."""
    raw = yaml.safe_load(dump_config(config))
    check_keys(config, raw)
    section = config.coverage
    given = section.separation == "given"
    if section.loop:
        from afmid.physics.effects import EFFECTS

        check_hidden(section, EFFECTS, config.source)
    tasks = []
    for index in indices:
        one = draw(config, raw, index)
        simulated, fitted = apply_draw(raw, one, given)
        task = draw_task(index, one.seed, one.values, simulated, fitted, config.source, given)
        if section.loop:
            effect, parameters = draw_hidden(section, index)
            task.update(simulate=hide(simulated, effect, parameters), loop=True, hidden=effect,
                        hidden_parameters=parameters)
        tasks.append(task)
    if tasks:
        from afmid.simulate.model import resolve_setup

        resolve_setup(build_config(tasks[0]["simulate"], source=config.source))
        build_config(tasks[0]["fit"], source=config.source)
        # one task per hidden effect: its simulation config is checked before any work
        for task in {t["hidden"]: t for t in tasks if t.get("loop")}.values():
            resolve_setup(build_config(task["simulate"], source=config.source))
    return tasks


def run_coverage(config: RunConfig, draws: int | None = None, seed: int | None = None, jobs: int = 1,
                 only: list[int] | None = None, progress: bool = False) -> CoverageResult:
    """Draw, simulate, fit and compare ``draws`` experiments (default ``coverage.draws``) around ``config``
    (``seed`` over ``coverage.seed``); ``only``: just these draw indices (e.g. a draw re-run alone); ``jobs`` > 1:
    in that many worker processes."""
    section = coverage_section(config, draws, seed)
    config = config.model_copy(update={"coverage": section})
    if config.fit.bootstrap == 0:
        raise ConfigError("is 0: the fit then reports no error bars, and coverage checks error bars; give the "
                          "number of resamples (e.g. 50)", file=config.source, key="fit.bootstrap")
    if config.simulate.map is not None:
        raise ConfigError("afmid coverage draws single traces; remove simulate.map", file=config.source,
                          key="simulate.map")
    indices = sorted(set(only)) if only else list(range(section.draws))
    bad = [i for i in indices if i < 0]
    if bad:
        raise ConfigError(f"draw indices start at 0, got {bad[0]}", key="--draw")
    tasks = prepare_draws(config, indices)
    started = time.perf_counter()
    results = _run(tasks, jobs, progress)
    results.sort(key=lambda d: d["index"])
    return CoverageResult(config, dump_config(config), section,
                          {k: d.describe() for k, d in distributions(config).items()}, results,
                          summarize(results), summarize(results, unflagged_only=True), time.perf_counter() - started,
                          loop=loop_summary(results) if section.loop else None)


def _run(tasks: list[dict], jobs: int, progress: bool) -> list[dict]:
    bar = Progress("coverage", enabled=progress)
    bar.stage("draws", total=len(tasks), unit="draws")
    results: list[dict] = []
    try:
        if jobs <= 1 or len(tasks) <= 1:
            for task in tasks:
                results.append(run_draw(task))
                bar.advance()
            return results
        from afmid.batch.engine import LocalPoolEngine

        by_key = dict(enumerate(tasks))

        def report(outcome) -> None:
            task = by_key[outcome.key]
            if outcome.result is not None:
                results.append(outcome.result)
            else:  # the worker died on it, or the run was stopped: listed, never dropped
                results.append({"index": task["index"], "seed": task["seed"], "values": task["values"],
                                "status": "failed", "stage": "worker", "numbers": {}, "warnings": [],
                                "error": outcome.crashed or "not run (stopped)", "seconds": {}})
            bar.advance()

        LocalPoolEngine(jobs).run(run_draw, list(by_key.items()), report, lambda: None)
        return results
    finally:
        bar.close()

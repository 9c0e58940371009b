"""The ``afmid`` command line: a thin shell over plain functions.

Heavy modules (numpy kernels, numba, h5py, matplotlib) are imported inside the
commands so that ``afmid --help`` stays fast. User errors (:class:`AfmidError`)
print one line and exit with its code; ``-v`` adds the traceback.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from afmid.threads import limit_native_threads

# One BLAS / OpenMP / numba thread unless the user chose otherwise: before NumPy loads (afmid.threads says why).
limit_native_threads()

import click  # noqa: E402

from afmid.errors import escape_controls  # noqa: E402
from afmid.version import __version__  # noqa: E402

log = logging.getLogger("afmid")
_state = {"verbose": 0, "quiet": False}

# readable=False: click's own check would print a four-line usage error; afmid.io.files.check_input_file says it in one.
CONFIG_ARG = click.argument("config", type=click.Path(path_type=Path, readable=False))
OVERWRITE = click.option("--overwrite", is_flag=True, help="Replace the output if it exists.")
# None: afmid.batch.engine_dask.DEFAULT_WORKER_TIMEOUT (not imported here: `import afmid.cli` stays light)
WORKER_TIMEOUT = click.option(
    "--worker-timeout", type=click.FloatRange(min=0, min_open=True), default=None, metavar="SECONDS",
    help="With dask: end with an error (the finished part kept; run again to resume) when the cluster has had no "
         "worker for this long, none joined or all lost (default: 60).")
SET = click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY.PATH=VALUE",
    help="Override a config value, e.g. --set cantilever.quality_factor=200 (repeatable).",
)


class _PlainFormatter(logging.Formatter):
    """Progress messages as they are; warnings and errors marked, so they are not read as progress. Control
    characters (of a name the user gave) are escaped (afmid.errors.escape_controls)."""

    def format(self, record: logging.LogRecord) -> str:
        text = escape_controls(super().format(record), keep="\n\t")
        if record.levelno >= logging.WARNING:
            return f"afmid: {record.levelname.lower()}: {text}"
        return text


class _VerboseFormatter(logging.Formatter):
    """``-v``: the level before each record (tracebacks included); control characters escaped as above."""

    def format(self, record: logging.LogRecord) -> str:
        return escape_controls(super().format(record), keep="\n\t")


def _echo(text: str, err: bool = False) -> None:
    """A command's result on stdout (or a line on stderr), a name's control characters escaped."""
    click.echo(escape_controls(text, keep="\n\t"), err=err)


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_VerboseFormatter("%(levelname)s: %(message)s") if verbose else _PlainFormatter("%(message)s"))
    root = logging.getLogger("afmid")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False
    logging.captureWarnings(True)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="afmid")
@click.option("-v", "--verbose", count=True, help="More detail; -v also shows tracebacks of errors.")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
def cli(verbose: int, quiet: bool) -> None:
    """afmid: quantitative tip-sample forces from tapping-mode AFM deflection traces.

    \b
    Typical loop:
      afmid init-config -o run.yaml          # write a commented config, edit it
      afmid simulate configs/dmt.yaml -o trace.h5   # or bring a measured trace
      afmid fit run.yaml -o run1.h5          # sparse force identification
      afmid report run1.h5 -o report/        # where the model fails, what is missing
      afmid fit run.yaml --add viscoelastic -o run2.h5
      afmid report run1.h5 run2.h5 -o report/

    Units: SI in files; forces are on the tip, positive = repulsive.
    """
    _state["verbose"] = verbose
    _state["quiet"] = quiet
    _setup_logging(verbose, quiet)


@cli.command()
@CONFIG_ARG
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Trace file to write (.h5).")
@OVERWRITE
@SET
@click.option("--seed", default=None, metavar="N", help="Random seed, 0 to 4294967295 (overrides simulate.seed).")
def simulate(config: Path, output: Path, overwrite: bool, overrides: tuple[str, ...], seed: str | None) -> None:
    """Simulate a deflection trace from the force model in CONFIG's `simulate:` section.

    Writes an afmid trace file with the ground truth (/truth/force, /truth/separation,
    /truth/velocity and the exact parameters). See `afmid effects --models`.
    """
    from afmid.config import MAX_SEED, dump_config, load_config
    from afmid.errors import ConfigError
    from afmid.io.trace import check_output_path, write_trace_file

    # Checked here rather than by click, whose usage error takes four lines.
    if seed is not None and not (seed.strip().isdecimal() and int(seed) <= MAX_SEED):
        raise ConfigError(f"must be a whole number from 0 to {MAX_SEED}, got {seed!r}", key="--seed")
    extra = list(overrides) + ([f"simulate.seed={int(seed)}"] if seed is not None else [])
    cfg = load_config(config, extra)
    check_output_path(output, overwrite, inputs={config: "the config"})
    if cfg.simulate.map is not None:  # a force map over phases (afmid.maps.simulate)
        from afmid.maps.simulate import simulate_map, write_map_file

        simulated = simulate_map(cfg, progress=not _state["quiet"])
        write_map_file(output, simulated, dump_config(cfg), overwrite=overwrite)
        log.info("wrote %s (map %dx%d, %d samples per pixel)", output, *simulated["deflection"].shape)
        return
    from afmid.simulate.driver import simulate as run_simulation

    trace = run_simulation(cfg, progress=not _state["quiet"])
    write_trace_file(output, trace, dump_config(cfg), overwrite=overwrite)
    log.info("wrote %s (%d samples, %.1f periods)", output, trace.n_samples, trace.n_periods)


@cli.command()
@CONFIG_ARG
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Run file to write (.h5).")
@OVERWRITE
@SET
@click.option("--add", "add_effects", multiple=True, metavar="EFFECT", help="Add an effect to model.effects (repeatable).")
@click.option(
    "--remove", "remove_effects", multiple=True, metavar="EFFECT", help="Remove an effect from model.effects (repeatable)."
)
def fit(
    config: Path,
    output: Path,
    overwrite: bool,
    overrides: tuple[str, ...],
    add_effects: tuple[str, ...],
    remove_effects: tuple[str, ...],
) -> None:
    """Identify the tip-sample force from the trace in CONFIG and write a run file.

    Loads data.path, segments it into drive periods, differentiates, fits a sparse
    model over the term library and writes coefficients, physical parameters, the
    per-sample and per-period forces and diagnostics to OUTPUT (HDF5).
    """
    from afmid.config import load_config
    from afmid.io.trace import check_output_path

    cfg = load_config(config, list(overrides))
    from afmid.placeholders import refuse_placeholders

    refuse_placeholders(config, cfg)  # a template's example value (marked CHECK) is not a calibration
    trace_path = None if cfg.data.path is None else cfg.resolve_path(cfg.data.path)
    joint_paths = {cfg.resolve_path(p): f"a trace file, data.paths[{i}]" for i, p in enumerate(cfg.data.paths or [])}
    check_output_path(output, overwrite, inputs={config: "the run config", trace_path: "the trace file, data.path",
                                                 **joint_paths})
    from afmid.fit.pipeline import apply_effect_changes

    apply_effect_changes(cfg, add_effects, remove_effects)
    # The Python front door's calls (docs/python.md); data.paths: a joint fit; fit.separation_track: d(t) per block
    from afmid.api import Fit

    fitted = Fit.from_config(cfg, progress=not _state["quiet"])
    fitted.save(output, overwrite=overwrite)
    implausible = fitted.implausible
    flagged = f"; {len(implausible)} read-out(s) implausible, flagged in the file (see the warnings)" if implausible else ""
    log.info("wrote %s: %s%s", output, fitted.summary_line(), flagged)
    if not _state["quiet"]:  # the read-out is the command's result: stdout (afmid.report.fit_text builds it)
        _echo(fitted.text(verbose=_state["verbose"] > 0))
    # The fit's own warnings (model-limited, non-periodic motion); the trace's findings were logged on loading.
    loaded = {f"{f.severity}: {f.message}" for f in fitted.trace.findings}
    for line in fitted.warnings:
        if line not in loaded:
            log.warning("%s: %s", output, line.removeprefix("warning: "))


@cli.command()
@click.argument("config", required=False, type=click.Path(path_type=Path))
@click.option("-i", "--inputs", multiple=True, metavar="GLOB",
              help="Trace files to fit with CONFIG, e.g. 'traces/*.csv' (quote it; repeatable; ** recurses).")
@click.option("--manifest", type=click.Path(path_type=Path), default=None,
              help="YAML or CSV list of traces (path) and/or run configs (config) with per-entry overrides "
                   "(key.path=value), instead of --inputs / --configs.")
@click.option("-c", "--configs", multiple=True, metavar="GLOB",
              help="Run configs to run, each on its own data (data.path, or simulated first from its "
                   "simulate: section), e.g. 'configs/*.yaml' (quote it; repeatable); no CONFIG.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="Folder for the run files, simulated traces and summary.csv / summary.h5 (created if needed).")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None,
              help="Worker processes (default: the usable CPU cores).")
@SET
@click.option("--force", is_flag=True, help="Simulate and fit everything again, even what is up to date.")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Run the items on this dask cluster's workers (they must see the same paths).")
@WORKER_TIMEOUT
def batch(config: Path | None, inputs: tuple[str, ...], manifest: Path | None, configs: tuple[str, ...],
          output: Path, jobs: int | None, overrides: tuple[str, ...], force: bool, scheduler: str | None,
          worker_timeout: float | None) -> None:
    """Fit many traces with one CONFIG, or run many run configs, in parallel; resumable.

    \b
      afmid batch CONFIG --inputs 'traces/*.csv' -o DIR   # many traces, one config
      afmid batch --configs 'configs/*.yaml' -o DIR       # many configs, each its own lever/model/data

    With --configs, each config is run on its own data: its data.path is fitted as
    `afmid fit CONFIG` would; a config without data.path is simulated first into
    OUTPUT/NAME.trace.h5 (as `afmid simulate`), then fitted. --set applies to every config.

    Writes OUTPUT/NAME.run.h5 per item (NAME from the trace's or the config's stem) and
    OUTPUT/summary.csv + summary.h5: one row per item with its status (ok, model-limited,
    suspect, failed, skipped), the failure message, config, error metric against its noise floor, a
    diagnosis (at the noise floor, or model-limited with the residual's region and character)
    and physical parameters with their 1-sigma errors (`*_sigma`) and 95 % intervals (SI
    units; the union over all runs, empty where a run has no such quantity). Items
    whose outputs are up to date (same input bytes, config and afmid version) are
    skipped; a failing item does not stop the batch. An item whose read-outs are not all
    plausible (outside their declared range, see `afmid effects`) is `suspect`, with the
    reasons in the failure column and a warning; one whose cv error stands above its
    noise-floor limit is `model-limited` (its parameters are biased beyond their error
    bars), with a warning. Exit code 1 if any item failed (suspect and model-limited
    items alone exit 0: their run files are written and flagged), 130 if interrupted.
    One batch at a time per OUTPUT (lock file OUTPUT/.afmid-batch.lock).
    """
    from afmid.batch.run import BatchInterrupted, run_batch
    from afmid.errors import AfmidError

    if config is not None and not configs and config.is_file():  # the shared config (the usage checks are run_batch's)
        # a template's example value (marked CHECK) stops it, as in fit
        from afmid.config import load_config
        from afmid.placeholders import refuse_placeholders

        refuse_placeholders(config, load_config(config, list(overrides)))

    engine = None
    if scheduler is not None:  # the items on an existing dask cluster (afmid.batch.engine_dask)
        from afmid.batch.engine_dask import DaskEngine, scheduler_address

        engine = DaskEngine(jobs=jobs, scheduler=scheduler_address(scheduler), worker_timeout=worker_timeout)
        output = output.absolute()  # the workers run elsewhere: every path they get must be absolute
    try:
        result = run_batch(config, output, inputs=inputs, manifest=manifest, configs=configs, jobs=jobs,
                           overrides=overrides, force=force, progress=not _state["quiet"], engine=engine)
    except BatchInterrupted as exc:
        _echo(f"afmid: batch stopped with {exc.result.line()}; run the same command again to resume", err=True)
        from afmid.interrupts import Terminated

        raise (Terminated() if exc.terminated else KeyboardInterrupt()) from None  # main() reports it: 143 / 130
    log.info("batch: %s", result.line())
    suspect = [r.item.name for r in result.rows if r.status == "suspect"]
    if suspect:  # results, but not ones to take as they are: flagged, not an error (see the docstring)
        log.warning("%d of %d %s suspect (%s): implausible read-outs, the reasons are in %s", len(suspect),
                    result.total, result.unit, ", ".join(suspect[:3]) + (", ..." if len(suspect) > 3 else ""),
                    output / "summary.csv")
    limited = [r.item.name for r in result.rows if r.status == "model-limited"]
    if limited:  # as suspect: written and flagged, not an error; the summary's failure column says by how much
        log.warning("%d of %d %s model-limited (%s): the model misses part of the force, the parameters are biased "
                    "beyond their error bars; see %s", len(limited), result.total, result.unit,
                    ", ".join(limited[:3]) + (", ..." if len(limited) > 3 else ""), output / "summary.csv")
    failed = [r.item.name for r in result.rows if r.status == "failed"]
    if failed:
        from afmid.tempfiles import NO_SPACE_TEXT

        names = ", ".join(failed[:3]) + (", ..." if len(failed) > 3 else "")
        full = sum(NO_SPACE_TEXT in r.failure for r in result.rows if r.status == "failed")
        why = f" ({full} of them: {NO_SPACE_TEXT})" if full else ""  # the one cause that fails every item after
        raise AfmidError(f"{len(failed)} of {result.total} {result.unit} failed ({names}); why is in the "
                         f"summary's failure column{why}", file=output / "summary.csv")


@cli.command()
@CONFIG_ARG
@click.option("-n", "--draws", type=click.IntRange(min=1), default=None,
              help="Experiments to draw (default: coverage.draws, else 50).")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=1, show_default=True, help="Worker processes.")
@click.option("-o", "--output", type=click.Path(path_type=Path), default=None,
              help="Write every draw and the summary here (.json or .h5).")
@OVERWRITE
@SET
@click.option("--seed", type=click.IntRange(min=0, max=2**32 - 1), default=None,
              help="Coverage seed (overrides coverage.seed): draw k comes from (seed, k) alone.")
@click.option("--draw", "only", multiple=True, type=click.IntRange(min=0), metavar="K",
              help="Run only draw K (repeatable): a draw re-run alone gives the same numbers.")
def coverage(config: Path, draws: int | None, jobs: int, output: Path | None, overwrite: bool,
             overrides: tuple[str, ...], seed: int | None, only: tuple[int, ...]) -> None:
    """Check afmid's error bars on experiments drawn around CONFIG (simulation-based calibration).

    Draws N experiments from the `coverage:` section's distributions (default: the physical
    parameters x0.5-2, the separation -15..+10 %, the amplitude +-20 %, the noise x0.5-2, the
    declared instrument within its calibration), simulates each as `afmid simulate` would, fits it as
    `afmid fit` would with the separation estimated, and prints per quantity (separation, every
    read-out, the force curve) how often |estimate - truth| <= 1 and 2 reported sigma (68 % and 95 %
    for honest error bars), the rms z and the worst draws with their seeds. docs/coverage.md.
    """
    from afmid.config import load_config
    from afmid.coverage.run import run_coverage

    cfg = load_config(config, list(overrides))
    if output is not None:
        from afmid.coverage.output import check_suffix
        from afmid.io.trace import check_output_path

        check_suffix(output)
        check_output_path(output, overwrite, inputs={config: "the config"})
    result = run_coverage(cfg, draws=draws, seed=seed, jobs=jobs, only=list(only) or None,
                          progress=not _state["quiet"])
    _echo(result.text(config, overrides))
    if output is not None:
        from afmid.coverage.output import write_output

        write_output(output, result)
        log.info("wrote %s (%d draws)", output, len(result.draws))
    if result.failed:
        log.warning("%d of %d draws failed (listed above)", len(result.failed), len(result.draws))


@cli.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Report folder to write.")
@click.option("--overwrite", is_flag=True,
              help="Replace OUTPUT if it is a report folder afmid wrote that holds only afmid's files.")
@click.option("--no-suggest", is_flag=True, help="Skip refitting with candidate effects.")
@click.option("--allow-different-traces", is_flag=True,
              help="Compare runs fitted on different traces (refused otherwise); the report says so.")
@click.option("--export", "export_tables", default=None, metavar="TABLES",
              help="Also write the last run's tables as CSV into OUTPUT, e.g. force-curves,parameters,periods "
                   "(as `afmid export`: OUTPUT/RUN.force-curves.csv, ...).")
def report(runs: tuple[Path, ...], output: Path, overwrite: bool, no_suggest: bool,
           allow_different_traces: bool, export_tables: str | None) -> None:
    """Compare run files: where the model fails, which effect is missing, how the error falls.

    Given one force-map result (afmid map), draws its maps instead: every parameter with its
    1-sigma map and colour bar, histograms, topography, error over floor, the failed pixels, the
    residual's character and which effect is missing where. Given two (an earlier fit of the same
    map first, e.g. before --add EFFECT), also the error over its floor before and after.

    Writes OUTPUT/report.html (self-contained), OUTPUT/*.png with an SVG of each figure beside
    it (OUTPUT/*.svg, linked under the figure), OUTPUT/summary.json and the
    marker OUTPUT/.afmid-report; a folder without it, or holding other files or an input, is
    never replaced (docs/file-formats.md).
    """
    from afmid.report.maps import is_map_result
    from afmid.tempfiles import is_write_refused, write_refused_error

    tables = None
    if export_tables is not None:  # checked before the report's work
        from afmid.report.report_exports import parse_exports

        tables = parse_exports(export_tables)
    try:
        if len(runs) in (1, 2) and all(is_map_result(r) for r in runs):  # force maps' results (afmid map)
            from afmid.errors import ConfigError
            from afmid.report.maps import make_map_report

            if tables:
                raise ConfigError("is for run files; a force map's result has maps, not one run's tables",
                                  key="--export")
            # two: the earlier fit of the same map first (e.g. before afmid map --add EFFECT), drawn before / after
            _echo(make_map_report(runs[-1], output, overwrite=overwrite,
                                       before=runs[0] if len(runs) == 2 else None))
            return
        from afmid.api import load  # the Python front door's calls (docs/python.md)

        fits = [load(run) for run in runs]
        summary = fits[-1].report(output, compare=fits[:-1], overwrite=overwrite, suggest=not no_suggest,
                                  progress=not _state["quiet"], allow_different_traces=allow_different_traces)
        if tables:  # the last run's CSVs beside the page, listed in the folder's marker
            from afmid.report.report_exports import export_into_report

            for name, rows in export_into_report(runs[-1], output, tables):
                log.info("wrote %s (%d rows)", output / name, rows)
    except OSError as exc:  # the report's temporary folder is removed already
        if is_write_refused(exc):  # a full disk, a file-size limit, a read-only file system
            raise write_refused_error(exc, output) from None
        raise
    _echo(summary)


@cli.command()
@click.argument("run", type=click.Path(path_type=Path, readable=False))
@click.option("--what", required=True, type=click.Choice(["force-curves", "parameters", "periods"]),
              help="force-curves: F(z) per period, approach / retract; parameters: value, 1 sigma, 95 % interval; "
                   "periods: one row per period.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="CSV file to write.")
@OVERWRITE
def export(run: Path, what: str, output: Path, overwrite: bool) -> None:
    """Write a table of the run file RUN as CSV for other tools (SI, the unit at the end of each column name).

    \b
      afmid export run1.h5 --what force-curves -o curves.csv  # period, branch, separation_m, force_N, ...
      afmid export run1.h5 --what parameters -o params.csv    # name, value, sigma_1, ci95_low, ci95_high, ...
      afmid export run1.h5 --what periods -o periods.csv      # period, peak_force_N, dissipated_energy_J, ...

    force_N is the identified model's force, force_inverted_N the force from the cantilever
    equation on the harmonics above the noise (docs/file-formats.md, "CSV exports").
    """
    from afmid.report.export import export_run

    rows = export_run(run, what, output, overwrite=overwrite)
    log.info("wrote %s (%s, %d rows)", output, what, rows)


@cli.command()
@click.option("--models", is_flag=True, help="List the simulator's models (combinations of effects).")
@click.option("--tips", is_flag=True, help="List the tip shapes (cantilever.tip_shape) and their contact laws.")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.argument("names", nargs=-1)
def effects(models: bool, tips: bool, as_json: bool, names: tuple[str, ...]) -> None:
    """List the effect catalog: formula, parameters, units, fit terms, references; and the tip shapes."""
    from afmid.physics.catalog import describe_effects, describe_tips

    click.echo(describe_tips(as_json) if tips else describe_effects(list(names), models=models, as_json=as_json))


@cli.command("init-config")
@click.option("-o", "--output", type=click.Path(path_type=Path), default=None, help="Write here (default: stdout).")
@OVERWRITE
@click.option("--from", "from_file", type=click.Path(path_type=Path, readable=False), default=None,
              help="Pre-fill from a trace file.")
@click.option("--simulate", "with_simulate", is_flag=True,
              help="Add a commented simulate: section (the model, parameters and noise `afmid simulate` uses).")
def init_config(output: Path | None, overwrite: bool, from_file: Path | None, with_simulate: bool) -> None:
    """Write a commented template run config to edit."""
    from afmid.config import template_text
    from afmid.io.trace import atomic_path, check_output_path

    text = template_text(simulate=with_simulate)
    if output is not None:
        check_output_path(output, overwrite, inputs={from_file: "the trace file, --from"})
    if from_file is not None:
        from afmid.io.inspect import prefill_config

        text = prefill_config(from_file, text, config_dir=output.parent if output is not None else None)
    if output is None:
        click.echo(text, nl=False)
        return
    with atomic_path(output) as tmp:
        tmp.write_text(text, encoding="utf-8")
    log.info("wrote %s", output)


@cli.command()
@click.argument("file", type=click.Path(path_type=Path, readable=False))
@click.option("--column", default=None, help="Channel to analyse (default: the reader's choice).")
@click.option("--sample-rate", type=float, default=None, help="Hz, if the file does not say.")
def inspect(file: Path, column: str | None, sample_rate: float | None) -> None:
    """Show what afmid sees in a data file: channels, length, rate, drive, noise."""
    from afmid.io.inspect import inspect_file

    _echo(inspect_file(file, column=column, sample_rate=sample_rate))


@cli.command(name="map")
@CONFIG_ARG
@click.option("--input", "input_path", required=True, type=click.Path(path_type=Path),
              help="Map file: HDF5 with /deflection (rows, cols, samples), or a .npy array of that shape.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Result file to write (.h5).")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None, help="Local worker processes (default: CPUs).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Use this dask scheduler's workers (default: $AFMID_SCHEDULER, else a local cluster).")
@click.option("--chunk", type=click.IntRange(min=1), default=None, metavar="PIXELS",
              help="Pixels per task (default: about 32 tasks per map).")
@click.option("--pixel-fit", type=click.Choice(["shared", "full"]), default="shared", show_default=True,
              help="shared: support and separation offset carried across pixels, a short separation search, "
                   "covariance error bars; full: every pixel as `afmid fit` (bootstrap, ~10x slower).")
@click.option("--add", "add_effects", multiple=True, metavar="EFFECT", help="Add an effect to model.effects (repeatable).")
@click.option("--remove", "remove_effects", multiple=True, metavar="EFFECT",
              help="Remove an effect from model.effects (repeatable).")
@click.option("--diagnosis/--no-diagnosis", default=True, show_default=True,
              help="Diagnose each model-limited group of pixels (grouped by residual signature and parameters) with "
                   "the catalog, on a few representative pixels: which effect is missing where (/groups).")
@WORKER_TIMEOUT
@OVERWRITE
@SET
def map_command(config: Path, input_path: Path, output: Path, jobs: int | None, scheduler: str | None,
                chunk: int | None, pixel_fit: str, add_effects: tuple[str, ...], remove_effects: tuple[str, ...],
                diagnosis: bool, worker_timeout: float | None, overwrite: bool, overrides: tuple[str, ...]) -> None:
    """Fit every pixel of a force map with CONFIG and write maps of the parameters.

    Each pixel's trace is fitted with CONFIG's model (the separation estimated per pixel:
    the topography); --pixel-fit says how (docs/maps.md). RESULT.h5 holds /maps/NAME and /maps/NAME_sigma (1 sigma) per
    parameter, the separation, the cv error and its noise floor, the selected terms (bit
    mask), and a status per pixel (0 ok, 1 suspect, 2 failed; reasons in /maps/message).
    Runs on dask.distributed: a local cluster of -j single-threaded processes, or the
    cluster at --scheduler. Finished chunks are kept beside the output
    (RESULT.h5.afmid-map/): after Ctrl-C, run the same command again to resume.
    Exit code 1 if any pixel failed.
    """
    from afmid.config import dump_config, load_config
    from afmid.batch.engine_dask import DaskEngine, scheduler_address, scheduler_key
    from afmid.fit.pipeline import apply_effect_changes
    from afmid.maps.run import run_map

    from afmid.placeholders import refuse_placeholders

    cfg = load_config(config, list(overrides))
    refuse_placeholders(config, cfg)
    apply_effect_changes(cfg, add_effects, remove_effects)
    engine = DaskEngine(jobs=jobs, scheduler=scheduler_address(scheduler), worker_timeout=worker_timeout,
                        scheduler_key=scheduler_key(scheduler))
    counts = run_map(cfg, dump_config(cfg), input_path, output, engine, chunk=chunk, overwrite=overwrite,
                     pixel_fit=pixel_fit, diagnose=diagnosis)
    if counts["failed"]:  # the maps are written; the failed pixels are NaN there, flagged in /maps/status
        from afmid.errors import AfmidError

        raise AfmidError(f"{counts['failed']} of {sum(counts.values())} pixels failed; the maps are written, the "
                         "reasons are in /maps/message", file=output)


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit code.

    Ctrl-C exits with 130 and SIGTERM with 143, each with one line; SIGTERM is raised as an exception like
    Ctrl-C so that temporary files are removed (afmid/interrupts.py)."""
    import afmid.interrupts as interrupts

    # Run as the process's command (no argv given): once the command is over, the process only exits, and a
    # Ctrl-C or SIGTERM then is ignored (with the default handlers back, it would print a traceback or kill a
    # command that had finished with whole outputs). Called with argv (tests, scripts): the handlers restored.
    with interrupts.handled(then_ignore=argv is None):
        try:
            code = _run(argv)
            interrupts.raise_if_pending()  # an interrupt that Python swallowed (a weakref callback) still counts
        except KeyboardInterrupt as exc:
            code = _interrupted(exc)
        except Exception:
            # A signal whose exception was swallowed where Python cannot propagate it (a C callback: LLVM
            # handing numba the object code of a kernel it compiles) leaves that code half done, and the error
            # that follows ("no compiled object yet") is the interruption's, not a bug to show as a traceback.
            if interrupts.pending() is None:
                raise
            try:
                interrupts.raise_if_pending()
            except KeyboardInterrupt as exc:
                code = _interrupted(exc)
    return code


def _interrupted(exc: BaseException) -> int:
    from afmid.interrupts import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated, clear

    clear()
    if isinstance(exc, Terminated):
        click.echo("afmid: terminated; no partial output was written", err=True)
        return EXIT_TERMINATED
    click.echo("afmid: interrupted; no partial output was written", err=True)
    return EXIT_INTERRUPTED


def _run(argv: list[str] | None) -> int:
    from afmid.errors import AfmidError

    try:
        cli.main(args=argv, prog_name="afmid", standalone_mode=False)
    except AfmidError as exc:
        if _state["verbose"]:
            log.exception("afmid error")
        click.echo(f"afmid: error: {exc.format()}", err=True)
        return exc.exit_code
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.UsageError as exc:  # one line, as every user error (click's own form takes four)
        command = exc.ctx.command_path if exc.ctx is not None else "afmid"
        message = " ".join(exc.format_message().split())
        _echo(f"afmid: error: {message} (see '{command} --help')", err=True)
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except click.exceptions.Abort as exc:
        # click turns Ctrl-C (and SIGTERM, a KeyboardInterrupt here) inside a command into Abort, after
        # printing a newline
        if isinstance(exc.__cause__, KeyboardInterrupt):
            return _interrupted(exc.__cause__)
        click.echo("afmid: aborted", err=True)
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""The run files of a joint fit and of a separation track, and ``afmid fit`` of them.

:func:`write_joint_run` writes the first trace's result in the single-trace layout through
:func:`afmid.runfile.write_run` (``afmid report`` renders it: the first trace's plots, the shared parameters) and
adds ``/joint``: the traces' table (file, SHA-256, separation and its 1 sigma, cv error and noise floor) and a
group per trace with its per-period forces (docs/file-formats.md, "Joint fits"); :func:`write_track_run` adds
``/model/separation_track``. They sit in the run files' layer, above the fit (docs/architecture.md, Layers): the
fit (:mod:`afmid.fit.joint`, :mod:`afmid.fit.joint_output`, :mod:`afmid.fit.separation_track`) computes, this
module writes.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click
import numpy as np

from afmid.config import RunConfig, dump_config
from afmid.errors import ConfigError
from afmid.fit.joint import JointResult, run_joint_fit
from afmid.fit.joint_output import JOINT_LAYOUT, joint_table, trace_result
from afmid.fit.pipeline import FitResult
from afmid.fit.separation_track import SeparationTrack, fit_separation_track, track_table, write_track
from afmid.io.trace import check_trace, load_trace, write_dataset
from afmid.runfile import PERIOD_UNITS, write_run


def write_joint_run(path, result: JointResult, overwrite: bool = False, more=None) -> tuple[Path, list[FitResult]]:
    """Write the joint run file (the first trace in the single layout, plus ``/joint``; ``more(h5)`` adds more
    inside the same atomic write); returns the path and every trace's result
    (:func:`afmid.fit.joint_output.trace_result`)."""
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


def write_track_run(path, track: SeparationTrack, overwrite: bool = False):
    """The joint run file of the blocks (:func:`write_joint_run`) with /model/separation_track; returns the path
    and every block's result."""
    return write_joint_run(path, track.joint, overwrite=overwrite,
                           more=lambda h5: write_track(h5["model"].create_group("separation_track"), track))


def fit_joint(config, output, overwrite: bool, quiet: bool, read_out) -> None:
    """``afmid fit`` of a config with ``data.paths``: the joint fit, its run file, its read-out on stdout.

    ``read_out(run_data) -> str`` writes the first trace's result (the caller passes the report's ``fit_text``:
    the run files do not import the report above them, docs/architecture.md, Layers)."""
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


def fit_track(config: RunConfig, output, overwrite: bool, quiet: bool, read_out) -> None:
    """``afmid fit`` of a config with ``fit.separation_track``: the track, its run file, its read-out on stdout.

    ``read_out(run_data) -> str`` writes the first block's result (the caller passes the report's ``fit_text``:
    the run files do not import the report above them, docs/architecture.md, Layers)."""
    log = logging.getLogger("afmid.cli")
    if config.data.path is None:
        raise ConfigError("a separation track is fitted on one record: give data.path", file=config.source,
                          key="data.path")
    trace = check_trace(load_trace(config), config)
    track = fit_separation_track(config, trace, config.fit.separation_track.bandwidth, progress=not quiet)
    _, per_block = write_track_run(output, track, overwrite=overwrite)
    log.info("wrote %s: %d blocks, one force law; terms: %s", output, len(track.separation),
             ", ".join(track.joint.selected_terms()) or "none")
    if not quiet:
        click.echo(read_out(per_block[0]))
        click.echo(track_table(track))
    for line in track.joint.warnings:
        log.warning("%s: %s", output, line.removeprefix("warning: "))

"""The run files of a joint fit and of a separation track, and ``afmid fit`` of a separation track.

:func:`joint_run_data` (:func:`joint_record`) is a joint fit's run record: the first trace's in the single-trace layout
(:func:`afmid.runfile.run_data`; ``afmid report`` renders it: the first trace's plots, the shared parameters) with
every trace's row and per-period forces (``/joint``: file, SHA-256, separation and its 1 sigma, cv error and noise
floor; docs/file-formats.md, "Joint fits"); :func:`write_joint_run` writes it through
:func:`afmid.runfile.write_run`, :func:`write_track_run` adds ``/model/separation_track``. They sit in the run
files' layer, above the fit (docs/architecture.md, Layers): the fit (:mod:`afmid.fit.joint`,
:mod:`afmid.fit.joint_output`, :mod:`afmid.fit.separation_track`) computes, this module records.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click
import numpy as np

from afmid.config import RunConfig, dump_config
from afmid.errors import ConfigError
from afmid.fit.joint import JointResult
from afmid.fit.joint_output import JOINT_LAYOUT, trace_result
from afmid.fit.pipeline import FitResult
from afmid.fit.separation_track import SeparationTrack, fit_separation_track, track_table, write_track
from afmid.io.trace import check_trace, load_trace
from afmid.runfile import RunData, run_data, write_run


def joint_run_data(result: JointResult, per_trace: list[FitResult], name: str = "fit") -> RunData:
    """The run record of a joint fit: trace 0's in the single-trace layout (:func:`afmid.runfile.run_data`) with
    every trace's row and per-period curves in ``joint`` and ``/joint``'s attributes in ``joint_attrs``
    (``per_trace``: :func:`afmid.fit.joint_output.trace_result` of each trace)."""
    run = run_data(per_trace[0], per_trace[0].config, name)
    run.joint = [{
        "path": str(t.prep.trace.path or ""), "sha256": t.prep.trace.sha256 or "", "separation": float(t.params["d"]),
        "separation_estimated": t.separation is not None,
        "separation_error": float(t.separation.sigma) if t.separation is not None else 0.0,
        "cv_error": float(t.cv_error), "cv_error_noise_floor": float(t.cv_error_noise_floor),
        "model_limited": bool(t.model_limited), "drive_frequency": float(t.prep.drive.frequency),
        "periods": dict(sorted((k, np.array(r.periods[k])) for k in r.periods)),
    } for t, r in zip(result.traces, per_trace)]
    run.joint_attrs = {
        "config": dump_config(result.config), "layout": JOINT_LAYOUT,
        "meaning": ("one force law fitted to every trace: /model holds the shared coefficients and parameters; "
                    "/force, /periods, /diagnostics and /model/separation are trace 0's; each trace's own in "
                    "/joint/trace_<i>"),
        "n_traces": len(result.traces), "search_evaluations": int(result.rounds)}
    return run


def joint_record(result: JointResult, name: str = "fit") -> tuple[RunData, list[FitResult]]:
    """A joint fit's run record (:func:`joint_run_data`) and every trace's result
    (:func:`afmid.fit.joint_output.trace_result`; trace 0's is what the record's single-trace part is made of)."""
    per_trace = [trace_result(result, i) for i in range(len(result.traces))]
    return joint_run_data(result, per_trace, name), per_trace


def write_joint_run(path, result: JointResult, overwrite: bool = False, more=None) -> tuple[Path, list[FitResult]]:
    """Write the joint run file (its record, :func:`joint_record`; ``more(h5)`` adds more inside the same atomic
    write); returns the path and every trace's result (:func:`afmid.fit.joint_output.trace_result`)."""
    run, per_trace = joint_record(result)
    written = write_run(path, run, overwrite=overwrite, extra=more)
    return written, per_trace


def write_track_run(path, track: SeparationTrack, overwrite: bool = False):
    """The joint run file of the blocks (:func:`write_joint_run`) with /model/separation_track; returns the path
    and every block's result."""
    return write_joint_run(path, track.joint, overwrite=overwrite,
                           more=lambda h5: write_track(h5["model"].create_group("separation_track"), track))


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

"""The run records of a joint fit and of a separation track.

:func:`joint_run_data` (:func:`joint_record`) is a joint fit's run record: the first trace's in the single-trace layout
(:func:`afmid.runfile.run_data`; ``afmid report`` renders it: the first trace's plots, the shared parameters) with
every trace's row and per-period forces (``/joint``: file, SHA-256, separation and its 1 sigma, cv error and noise
floor; docs/file-formats.md, "`/joint` — several traces"); :func:`track_run` is a separation track's: its blocks'
joint record with the track (``/model/separation_track``, :func:`track_record`). :func:`afmid.runfile.write_run` writes either from
the record alone. They sit in the run files' layer, above the fit (docs/architecture.md, Layers): the fit
(:mod:`afmid.fit.joint`, :mod:`afmid.fit.joint_output`, :mod:`afmid.fit.separation_track`) computes, this module
records.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmid.config import dump_config
from afmid.fit.joint import JointResult
from afmid.fit.joint_output import JOINT_LAYOUT, trace_result
from afmid.fit.pipeline import FitResult
from afmid.fit.separation_track import SeparationTrack
from afmid.runfile import TRACK_KEYS, RunData, run_data, write_run


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


def track_record(track: SeparationTrack) -> dict:
    """A separation track as its run record holds it (:attr:`afmid.runfile.RunData.separation_track`, SI): the
    blocks' middle times, sample ranges, d and 1 sigma, the bandwidth, how d moved within a block and, when it
    moved, each block's per-period offsets."""
    moved = bool(track.period_offsets) and track.within_block != "constant"
    record = {"time": track.time, "first_sample": track.first_sample, "stop_sample": track.stop_sample,
              "separation": track.separation, "separation_error": track.sigma, "bandwidth": float(track.bandwidth),
              "within_block": track.within_block,
              "period_offsets": [np.asarray(o, dtype=float) for o in track.period_offsets] if moved else None}
    return {key: record[key] for key in TRACK_KEYS}


def track_run(track: SeparationTrack, name: str = "fit") -> tuple[RunData, list[FitResult]]:
    """A separation track's run record: the joint record of its blocks (:func:`joint_record`: block 0's in the
    single-trace layout, every block in ``/joint``) with the track (:func:`track_record`); and every block's
    result."""
    run, per_block = joint_record(track.joint, name)
    run.separation_track = track_record(track)
    return run, per_block


def write_track_run(path, track: SeparationTrack, overwrite: bool = False) -> tuple[Path, list[FitResult]]:
    """Write a separation track's run file from its record (:func:`track_run`); returns the path and every
    block's result."""
    run, per_block = track_run(track)
    return write_run(path, run, overwrite=overwrite), per_block


"""The diagnosis of a separation track's run: the candidates are refitted on the track's first block with its d
and per-period offsets, not on the whole record under one d (afmid.diagnosis.diagnose.track_block_preparation)."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from afmid.config import build_config
from afmid.diagnosis.diagnose import track_block_preparation
from afmid.errors import InputError
from afmid.fit.prepare import prepare
from afmid.fit.separation_track import SeparationTrack, cut_block
from afmid.io.trace import check_trace
from afmid.preprocess.instrument import from_config as instrument_from_config
from afmid.joint_runfile import track_record
from afmid.runfile import first_track_block, read_separation_track, write_separation_track
from afmid.simulate.driver import simulate

RAW = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
       "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
       "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 0, "seed": 0},
       "simulate": {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "periods": 40,
                    "samples_per_period": 100, "steps_per_period": 1000, "setpoint": 0.85,
                    "noise": {"detector_rms": 1e-12}, "seed": 5}}


def test_the_track_file_keeps_each_blocks_period_offsets(tmp_path):
    """/model/separation_track holds the periods' offsets block after block with their counts (m, units); the run
    reader splits them per block again and gives the first block's range and offsets."""
    offsets = [np.linspace(-5e-12, 5e-12, 19), np.linspace(3e-12, -3e-12, 21)]
    track = SeparationTrack(time=np.array([1e-4, 3e-4]), first_sample=np.array([0, 2000]),
                            stop_sample=np.array([2000, 4000]), separation=np.array([8.1e-9, 7.9e-9]),
                            sigma=np.array([3e-11, 3e-11]), bandwidth=2500.0, joint=None, period_offsets=offsets,
                            within_block="rows")
    with h5py.File(tmp_path / "track.h5", "w") as h5:
        write_separation_track(h5.create_group("separation_track"), track_record(track))
    with h5py.File(tmp_path / "track.h5", "r") as h5:
        group = h5["separation_track"]
        assert group["period_offsets"].attrs["units"] == "m"
        np.testing.assert_array_equal(group["period_offset_counts"][...], [19, 21])
        read = read_separation_track(group)
    for mine, stored in zip(offsets, read["period_offsets"], strict=True):  # float64 through HDF5: the same bits
        np.testing.assert_array_equal(stored, mine)
    block = first_track_block(read)
    assert (block["first_sample"], block["stop_sample"]) == (0, 2000)
    np.testing.assert_array_equal(block["period_offsets"], offsets[0])


def test_a_tracks_diagnosis_prepares_its_first_block_with_its_offsets(tmp_path):
    """The preparation the diagnosis refits on is the first block's (its periods, not the record's), its
    trajectory moved by the stored offsets (the library sees z = d + offset - x); offsets that do not match the
    block's periods are a one-line InputError naming the dataset."""
    config = build_config(copy.deepcopy(RAW))
    record = simulate(config)
    checked = check_trace(record, config)
    plain = prepare(check_trace(cut_block(checked, 0, 2000), config), config.fit, instrument_from_config(config))
    n = plain.blocks.n_blocks
    assert n < prepare(checked, config.fit, instrument_from_config(config)).blocks.n_blocks
    offsets = np.linspace(-20e-12, 20e-12, n)
    run = SimpleNamespace(path=tmp_path / "run.h5",
                          track_block={"first_sample": 0, "stop_sample": 2000, "period_offsets": offsets})
    moved = track_block_preparation(run, record, config)
    assert moved.blocks.n_blocks == n
    np.testing.assert_allclose(moved.X_traj[:, 0], plain.X_traj[:, 0] - offsets, rtol=0, atol=1e-18)
    np.testing.assert_array_equal(moved.Y, plain.Y)  # the equation's rows are the block's own
    run.track_block["period_offsets"] = offsets[:-1]
    with pytest.raises(InputError, match="period_offsets"):
        track_block_preparation(run, record, config)

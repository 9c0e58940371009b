"""``fit.separation_track``: a record cut into blocks of whole periods, fitted as a joint fit (one force law, a
separation per block), the track written to /model/separation_track."""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest

from afmid.config import build_config
from afmid.errors import ConfigError
from afmid.fit.separation_track import block_periods_for, cut_blocks, fit_separation_track, write_track_run
from afmid.io.trace import check_trace
from afmid.simulate.driver import simulate

RAW = {"cantilever": {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 250.0, "tip_radius": 1e-8},
       "drive": {"frequency": 3e5, "free_amplitude": 1e-8}, "sample": {"a0": 0.165e-9, "separation": 8.5e-9},
       "model": {"effects": ["dmt"]}, "fit": {"bootstrap": 10, "seed": 0},
       "simulate": {"model": "dmt", "parameters": {"E_star": 2e9, "hamaker": 5e-20}, "periods": 240,
                    "samples_per_period": 100, "steps_per_period": 2000, "setpoint": 0.85,
                    "noise": {"thermal": True, "detector_rms": 1e-12}, "seed": 61}}
#: No feedback: the piezo holds still and d(t) drops by the step, 0.4 nm, mid-record (120 periods = 0.4 ms in,
#: at 4 um/s: 1.6 nm of travel), over 0.1 nm of travel (~8 periods).
STEP_SCAN = {"speed": 4e-6, "start": -1.6e-9, "step": {"height": 0.4e-9, "position": 0.0, "width": 0.1e-9}}


def configs(scan=STEP_SCAN, periods=240, bandwidth=2500.0):
    raw = copy.deepcopy(RAW)
    raw["simulate"].update(periods=periods, scan=scan)
    fit_raw = copy.deepcopy(raw)
    del fit_raw["sample"]["separation"]
    fit_raw["fit"]["separation_track"] = {"bandwidth": bandwidth}
    return build_config(raw), build_config(fit_raw)


def test_blocks_are_whole_periods_and_carry_their_truth():
    simulated, _ = configs(periods=40)
    trace = simulate(simulated)
    blocks = cut_blocks(trace, 12)
    assert [b.n_samples for b in blocks] == [1200, 1200, 1600]  # the rest joins the last block
    assert [b.first_sample for b in blocks] == [0, 1200, 2400]
    d = trace.truth.tracks["rest_separation"][0]
    for block in blocks:
        part = slice(block.first_sample, block.first_sample + block.n_samples)
        np.testing.assert_array_equal(block.deflection, trace.deflection[part])
        np.testing.assert_array_equal(block.truth.force, trace.truth.force[part])
        assert block.truth.extra["separation"] == pytest.approx(d[part].mean(), rel=1e-12)
    assert block_periods_for(2500.0, 3e5) == 60


def test_a_track_needs_blocks_long_enough_and_an_unknown_separation():
    simulated, fitting = configs(periods=40, bandwidth=6000.0)  # 25-period blocks
    trace = check_trace(simulate(simulated), fitting)
    with pytest.raises(ConfigError, match="fit.separation_track.bandwidth"):
        fit_separation_track(fitting, trace, 6000.0)
    with pytest.raises(ConfigError, match="one block"):
        fit_separation_track(fitting, trace, 2500.0)  # 60-period blocks in 40 periods
    with pytest.raises(ConfigError, match="sample.separation"):
        fit_separation_track(simulated, trace, 2500.0)


@pytest.mark.slow
def test_a_step_in_d_is_tracked_block_by_block(tmp_path):
    """Four 60-period blocks over a 0.4 nm drop of d: each block's d within 2 sigma of its mean truth
    (or 3 sigma for the block holding the edge, whose d is a mixture), and one force law for all."""
    simulated, fitting = configs()
    trace = check_trace(simulate(simulated), fitting)
    track = fit_separation_track(fitting, trace, 2500.0)
    d = trace.truth.tracks["rest_separation"][0]
    truth = np.array([d[a:b].mean() for a, b in zip(track.first_sample, track.stop_sample)])
    z = (track.separation - truth) / track.sigma
    assert track.separation.size == 4
    assert np.all(np.abs(z) <= 2.0), (z, track.sigma)
    assert track.separation[0] - track.separation[-1] == pytest.approx(0.4e-9, abs=3 * np.hypot(*track.sigma[[0, -1]]))
    path, _ = write_track_run(tmp_path / "run.h5", track)
    with h5py.File(path, "r") as h5:
        group = h5["model/separation_track"]
        assert group["separation"].attrs["units"] == "m" and group["separation_error"].attrs["units"] == "m"
        assert group["time"].attrs["units"] == "s" and group.attrs["bandwidth"] == 2500.0
        np.testing.assert_array_equal(group["separation"][...], track.separation)

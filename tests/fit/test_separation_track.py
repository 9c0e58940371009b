"""``fit.separation_track``: a record cut into blocks of whole periods, fitted as a joint fit (one force law, a
separation per block), the track written to /model/separation_track."""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest
import yaml

from afmid.config import build_config
from afmid.errors import ConfigError
from afmid.fit.period_separation import block_means
from afmid.fit.separation_track import block_periods_for, cut_blocks, fit_separation_track
from afmid.io.trace import check_trace, read_truth, write_trace_file
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


def rough_feedback_track(seed: int, periods: int, bandwidth: float):
    """A rough surface scanned under the amplitude feedback (simulation seed ``seed``) and its track fitted with
    ``within_block: rows`` and no bootstrap: (trace, track)."""
    simulated, fitting = configs(scan=FEEDBACK_ROUGH, periods=periods, bandwidth=bandwidth)
    raw = simulated.model_dump(mode="json", exclude_none=True)
    raw["simulate"]["seed"] = seed
    trace = simulate(build_config(raw))
    fit_raw = fitting.model_dump(mode="json", exclude_none=True)
    fit_raw["fit"]["bootstrap"] = 0
    fitting = build_config(fit_raw)
    return trace, fit_separation_track(fitting, check_trace(trace, fitting), bandwidth, within_block="rows")


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


def _files(tmp_path, periods=240, given_separation=False):
    simulated, fitting = configs(periods=periods)
    trace_path = write_trace_file(tmp_path / "scan.h5", simulate(simulated), "")
    raw = fitting.model_dump(mode="json", exclude_none=True)
    raw["data"] = {"path": str(trace_path)}
    if given_separation:
        raw["sample"]["separation"] = 8e-9
    config = tmp_path / "track.yaml"
    config.write_text(yaml.safe_dump(raw))
    return trace_path, config


def test_a_track_with_a_given_separation_is_one_line(tmp_path, run_cli):
    _, config = _files(tmp_path, periods=130, given_separation=True)
    out_path = tmp_path / "run.h5"
    code, out, err = run_cli("fit", config, "-o", out_path)
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code in (1, 2) and len(lines) == 1 and "Traceback" not in err, err
    assert "sample.separation" in lines[0] and not out_path.exists()


@pytest.mark.slow
def test_a_step_in_d_is_tracked_block_by_block(tmp_path, run_cli):
    """``afmid fit`` with fit.separation_track on 240 periods over a 0.4 nm drop of d (4 blocks of 60 periods):
    each block's d within 2 sigma of its mean truth, the track in /model/separation_track with units."""
    trace_path, config = _files(tmp_path)
    run = tmp_path / "run.h5"
    code, out, err = run_cli("fit", config, "-o", run)
    assert code == 0, err
    assert "separation track at 2500 Hz (4 blocks" in out
    d = read_truth(trace_path).tracks["rest_separation"][0]
    with h5py.File(run, "r") as h5:
        group = h5["model/separation_track"]
        assert group["separation"].attrs["units"] == "m" and group["separation_error"].attrs["units"] == "m"
        assert group["time"].attrs["units"] == "s" and group.attrs["bandwidth"] == 2500.0
        separation, sigma = group["separation"][...], group["separation_error"][...]
        first, stop = group["first_sample"][...], group["stop_sample"][...]
        assert h5["joint"].attrs["n_traces"] == 4
    truth = np.array([d[a:b].mean() for a, b in zip(first, stop)])
    z = (separation - truth) / sigma
    assert np.all(np.abs(z) <= 2.0), (z, sigma)
    assert separation[0] - separation[-1] == pytest.approx(0.4e-9, abs=3 * np.hypot(sigma[0], sigma[-1]))


def test_within_block_is_constant_unless_asked_and_checked():
    _, fitting = configs(periods=40)
    assert fitting.fit.separation_track.within_block == "constant"
    raw = fitting.model_dump(mode="json", exclude_none=True)
    raw["fit"]["separation_track"]["within_block"] = "mean_force"
    assert build_config(raw).fit.separation_track.within_block == "mean_force"
    raw["fit"]["separation_track"]["within_block"] = "sometimes"
    with pytest.raises(ConfigError, match="within_block"):
        build_config(raw)


def test_the_run_file_says_how_d_moved_within_a_block(tmp_path):
    """/model/separation_track records ``within_block`` beside the blocks' d and their units."""
    from afmid.fit.separation_track import SeparationTrack
    from afmid.joint_runfile import track_record
    from afmid.runfile import write_separation_track

    track = SeparationTrack(time=np.array([1e-4, 3e-4]), first_sample=np.array([0, 6000]),
                            stop_sample=np.array([6000, 12000]), separation=np.array([8.1e-9, 7.9e-9]),
                            sigma=np.array([3e-11, 3e-11]), bandwidth=2500.0, joint=None,
                            within_block="mean_force")
    with h5py.File(tmp_path / "track.h5", "w") as h5:
        write_separation_track(h5.create_group("separation_track"), track_record(track))
    with h5py.File(tmp_path / "track.h5", "r") as h5:
        group = h5["separation_track"]
        assert group.attrs["within_block"] == "mean_force"
        np.testing.assert_array_equal(group["separation"][...], track.separation)
        assert group["separation"].attrs["units"] == "m"


FEEDBACK_ROUGH = {"speed": 4e-6, "rough": {"rms": 0.5e-9, "correlation_length": 5e-9},
                  "feedback": {"gain": 6000.0, "bandwidth": 10e3}}


@pytest.mark.slow
def test_a_rough_surface_under_feedback_is_tracked_with_rows():
    """A rough surface (0.5 nm rms, 5 nm correlation) scanned under an amplitude feedback, 120 periods, 2 blocks
    of 60 (seed 91, not one the method was measured on), ``within_block: rows``: every block's d within 2 sigma
    of its mean truth and the law's force within 2 % of the peak (RMS over the samples at the true z). With the
    per-period d from the mean force alone, such records came out with every block 42-101 pm low and E* 7-15 %
    soft (docs/lab/2026-11-29-scanning-record.md)."""
    trace, track = rough_feedback_track(seed=91, periods=120, bandwidth=2500.0)
    d = trace.truth.tracks["rest_separation"][0]
    truth = np.array([d[a:b].mean() for a, b in zip(track.first_sample, track.stop_sample)])
    z = (track.separation - truth) / track.sigma
    assert np.all(np.abs(z) <= 2.0), (z, track.sigma)
    for block, first, stop, found in zip(track.joint.traces, track.first_sample, track.stop_sample,
                                         track.period_offsets):
        # Each period's d within the block: held per block it errs by the offsets' own sd; from the mean force
        # alone by about as much (6-9 pm against a true sd of 5-8 pm on such records).
        per_period = block_means(block.prep, d[first:stop])
        expected = per_period - per_period.mean()
        assert np.sqrt(np.mean((found - expected) ** 2)) < 0.5 * np.std(expected), (found, expected)
    e_star = track.joint.quantities["E_star"]["value"]
    hamaker = track.joint.quantities["hamaker"]["value"]
    radius, a0 = 1e-8, 0.165e-9
    separation = d - trace.deflection
    far = np.maximum(separation, a0)
    force = np.where(separation >= a0, -hamaker * radius / (6 * far**2),
                     -hamaker * radius / (6 * a0**2)
                     + 4 / 3 * e_star * np.sqrt(radius) * np.maximum(a0 - separation, 0) ** 1.5)
    error = np.sqrt(np.mean((force - trace.truth.force) ** 2)) / np.max(np.abs(trace.truth.force))
    assert error <= 0.02, (error, e_star)


def test_the_read_outs_carry_the_track_s_added_level_sigma(tmp_path):
    """The track raises each block's d sigma beyond the joint fit's (the offsets' share, the floor at the
    record's bound); E*'s 1 sigma gains the common level's added sigma times E*'s change with the level, in
    quadrature, and says so in its ``error_separation_track``. A rough surface under feedback, 60 periods in two
    blocks of 30 (``within_block: rows``: the offsets' share is never zero), seed 97."""
    from afmid.fit.forces import read_out
    from afmid.fit.joint import stack
    from afmid.fit.regression import combine, subset_fit
    from afmid.fit.system import build_system
    trace, track = rough_feedback_track(seed=97, periods=60, bandwidth=5000.0)
    joint = track.joint
    joint_sigma = np.array([t.separation.sigma for t in joint.traces])
    added = np.sqrt(np.mean(np.maximum(track.sigma**2 - joint_sigma**2, 0.0)))
    assert added > 0.0, (track.sigma, joint_sigma)  # the track widened d: there is something to carry

    def e_star_at(shift):
        systems = [build_system(t.prep, joint.library, dict(t.params, d=t.params["d"] + shift)) for t in joint.traces]
        coef, _ = subset_fit(combine(stack(systems, len(joint.library)).T_blocks), joint.selected)
        return read_out(joint.library, coef, None, dict(joint.traces[0].params, d=joint.traces[0].params["d"] + shift),
                        joint.selected, joint.traces[0].prep.trace)["E_star"]["value"]

    q = joint.quantities["E_star"]
    central = e_star_at(0.0)
    assert central == pytest.approx(q["value"], rel=1e-9)  # the value itself is not moved
    sides = [e_star_at(sign * added) for sign in (1, -1)]
    expected_share = max(abs(s - central) for s in sides)
    slope_share = 0.5 * abs(sides[0] - sides[1])  # |dE*/dlevel| * added, central difference
    assert expected_share > 0
    share = q.get("error_separation_track", 0.0)  # its name in the run file's attributes too
    # The share is the larger one-sided change (the same refit, so equal to rounding of the arithmetic) and not
    # below the linear one; the 1 sigma holds the joint fit's and the share in quadrature.
    assert share == pytest.approx(expected_share, rel=1e-6)
    assert share >= slope_share * (1 - 1e-9)
    joint_part = q["error"] ** 2 - share ** 2
    assert joint_part > 0
    assert q["error"] ** 2 >= joint_part + slope_share**2 * (1 - 1e-9)
    half_width = 0.5 * (q["ci_high"] - q["ci_low"])
    assert half_width >= 1.96 * share * (1 - 1e-9)
    from afmid.joint_runfile import write_track_run
    from afmid.runfile import load_run

    path, _ = write_track_run(tmp_path / "track_run.h5", track)
    with h5py.File(path, "r") as h5:
        assert h5["model/parameters/E_star"].attrs["error_separation_track"] == share
    assert load_run(path).quantities["E_star"]["error_separation_track"] == share

"""A separation track through the front door: ``afmid.ForceModel(separation_track={...}).fit(record)`` is ``afmid
fit`` of ``fit.separation_track`` (the same run file, dataset by dataset; the command prints the fit's text), its
record holds the track (``Fit.separation_track``: SI, with units), ``save`` writes ``/model/separation_track`` from
the record and ``afmid.load`` gives the same fit back; bad requests get one-line errors."""

from __future__ import annotations

import copy
import json

import h5py
import numpy as np
import pytest
import yaml

import afmid
from afmid.errors import ConfigError
from tests.cli.test_run_data import _file_differences
from tests.fit.test_separation_track import FEEDBACK_ROUGH, RAW

#: Blocks of 30 drive periods at 300 kHz (f / (2 bandwidth)), the fewest a block may hold: 60 periods give two.
TRACK = {"bandwidth": 5000.0}
#: The fit's keys beside the track: a short bootstrap, so the intervals' branch is written too.
FIT = {"bootstrap": 4, "seed": 0}
A0 = RAW["sample"]["a0"]


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 60-period record of a rough surface scanned under an amplitude feedback (d moves by tens of pm), written
    as a trace file, and the run config of its track."""
    from afmid.io.trace import write_trace_file

    folder = tmp_path_factory.mktemp("track_front_door")
    raw = copy.deepcopy(RAW)
    raw["simulate"].update(periods=60, scan=FEEDBACK_ROUGH, seed=91)
    path = write_trace_file(folder / "scan.h5", afmid.simulate_trace(raw), "")
    # the lever and drive frequency are the trace file's, as for afmid.read: the two stored configs are alike
    config = {"data": {"path": str(path)}, "sample": {"a0": A0}, "model": {"effects": ["dmt"]},
              "fit": {**FIT, "separation_track": TRACK}}
    config_path = folder / "track.yaml"
    config_path.write_text(yaml.safe_dump(config))
    return folder, path, config_path


@pytest.fixture(scope="module")
def track_fit(scan):
    _, path, _ = scan
    return afmid.ForceModel(["dmt"], a0=A0, fit=FIT, separation_track=TRACK).fit(afmid.read(path))


def test_a_track_is_afmid_fit_of_a_separation_track_config(scan, track_fit, run_cli):
    """The front door and ``afmid fit`` run the same track on the same record: the same run file (every dataset and
    attribute, provenance and the stored config's way of giving the lever aside), and the command prints the fit's
    text: the record's read-out, then the blocks' d(t)."""
    folder, _, config_path = scan
    code, out, err = run_cli("fit", config_path, "-o", folder / "cli.h5")
    assert code == 0, err
    saved = track_fit.save(folder / "front_door.h5")
    assert _file_differences(folder / "cli.h5", saved) == ["@config", "/joint@config"]
    # The stored configs say how each was asked for: the command's leaves the lever and drive frequency to the trace
    # file, the front door's gives the trace's values; nothing else differs.
    stored = []
    for path in (folder / "cli.h5", saved):
        with h5py.File(path, "r") as h5:
            raw = yaml.safe_load(h5.attrs["config"])
        assert raw["fit"]["separation_track"] == {**TRACK, "within_block": "constant"}
        raw.pop("cantilever"), raw["drive"].pop("frequency")
        stored.append(raw)
    assert stored[0] == stored[1]
    assert out.strip() == track_fit.text().strip()
    assert "separation track at 5000 Hz (2 blocks, one force law):" in out
    assert f"wrote {folder / 'cli.h5'}: 2 blocks, one force law; terms: " in err
    assert track_fit.summary_line() == afmid.load(folder / "cli.h5").summary_line()


def test_the_fits_record_holds_the_track(track_fit):
    """``Fit.separation_track``: two blocks of 30 periods at 100 samples each, their middle times, d and 1 sigma in
    SI with units; the blocks are the joint record's rows, block 0's is the rest of the record."""
    track = track_fit.separation_track
    assert len(track) == 2 and track.bandwidth == TRACK["bandwidth"] and track.within_block == "constant"
    assert track.period_offsets is None  # d held per block
    np.testing.assert_array_equal(track.first_sample, [0, 3000])
    np.testing.assert_array_equal(track.stop_sample, [3000, 6000])
    # each block's middle: 1500 and 4500 samples at 30 MS/s (100 per period of 300 kHz), exact in binary to 1 ulp
    np.testing.assert_allclose(track.time, [50e-6, 150e-6], rtol=1e-15, atol=0)
    assert track.UNITS["separation"] == "m" and track.UNITS["time"] == "s" and track.UNITS["bandwidth"] == "Hz"
    rows = track_fit.joint
    assert [row["separation"] for row in rows] == list(track.separation)
    assert track_fit.run.separation == track.separation[0]
    assert np.all(track.sigma > 0)
    assert [d["block"] for d in track.to_dicts()] == [0, 1]
    lines = track.text().splitlines()
    assert lines[0] == "separation track at 5000 Hz (2 blocks, one force law):"
    for line, d, s in zip(lines[1:], track.separation, track.sigma, strict=True):
        assert f"d = {d * 1e9:.3f} ± {s * 1e9:.3f} nm (1σ)" in line


def test_the_read_outs_show_the_track_s_share_of_their_one_sigma(track_fit, tmp_path):
    """The track widened the blocks' d sigma (the floor at the record's bound), so every read-out carries a share
    of its 1 sigma (``error_separation_track``). The fit's text names it beside the statistical part (the 1 sigma
    beyond the share, in quadrature); the parameter table's ``sigma_separation_track`` and summary.json's
    ``error_separation_track`` hold it, the same after save and load; the report's table and terminal cells name
    it. Each number is the formatted value of the record's own, so 2 significant digits agree exactly."""
    from afmid.quantity_text import format_value
    from afmid.report.page import quantity_cell
    from afmid.report.story import run_entry

    quantities = track_fit.run.quantities
    assert quantities["E_star"]["error_separation_track"] > 0
    again = afmid.load(track_fit.save(tmp_path / "track.h5"))
    entry = run_entry(tmp_path / "track.h5", again.run, {"error_fold_sd": 0.0, "error_spread_kind": ""})
    text = track_fit.text()
    for name, q in quantities.items():
        share, unit = q["error_separation_track"], q["unit"]
        statistical = np.sqrt(q["error"] ** 2 - share**2)
        line = next(line for line in text.splitlines() if line.strip().startswith(f"{name} = "))
        assert (f"; of the 1σ, in quadrature: statistical {format_value(statistical, unit, 2)}, separation track "
                f"{format_value(share, unit, 2)};") in line, line
        assert track_fit.parameters[name].sigma_separation_track == share
        assert again.parameters[name].sigma_separation_track == share
        summary = entry["parameters"][name]
        assert summary["error_separation_track"] == share
        assert summary["error_statistical"] == pytest.approx(statistical, rel=1e-12)
        assert summary["error"] ** 2 == pytest.approx(summary["error_statistical"] ** 2 + share**2, rel=1e-12)
        for cell in (quantity_cell(q), quantity_cell(summary)):
            assert f"/ track {format_value(share, unit, 2)} in quadrature)" in cell, cell
    assert np.isnan(track_fit.parameters["d"].sigma_separation_track)  # an estimated nonlinear row: not split


def test_the_track_s_share_is_a_column_of_to_pandas(track_fit):
    pandas = pytest.importorskip("pandas")
    quantities = track_fit.run.quantities
    frame = track_fit.parameters.to_pandas()
    assert isinstance(frame, pandas.DataFrame)
    assert frame.loc["E_star", "sigma_separation_track"] == quantities["E_star"]["error_separation_track"]


def test_save_and_load_give_the_track_back(track_fit, tmp_path):
    again = afmid.load(track_fit.save(tmp_path / "track.h5"))
    mine, read = track_fit.separation_track, again.separation_track
    for name in ("time", "first_sample", "stop_sample", "separation", "sigma"):
        assert np.array_equal(getattr(mine, name), getattr(read, name)), name  # through HDF5: the same bits
    assert (read.bandwidth, read.within_block, read.period_offsets) == (mine.bandwidth, mine.within_block, None)
    assert again.text() == track_fit.text() and again.parameters == track_fit.parameters
    with h5py.File(tmp_path / "track.h5", "r") as h5:
        group = h5["model/separation_track"]
        assert all(group[name].attrs["units"] == unit for name, unit in
                   {"time": "s", "separation": "m", "separation_error": "m", "first_sample": "1"}.items())


def test_bad_track_requests_get_one_line_errors(track_fit, scan):
    record = afmid.read(scan[1])
    with pytest.raises(ConfigError, match="fitted on one record"):
        afmid.ForceModel(["dmt"], separation_track=TRACK).fit([record, record])
    with pytest.raises(ConfigError, match="given twice"):
        afmid.ForceModel(["dmt"], fit={"separation_track": TRACK}, separation_track=TRACK)
    with pytest.raises(ConfigError, match="fit.separation_track.bandwidth"):
        afmid.ForceModel(["dmt"], separation_track={"bandwidth": -1.0})
    with pytest.raises(ConfigError, match="leave sample.separation out"):
        afmid.ForceModel(["dmt"], separation=8e-9, separation_track=TRACK).fit(record)
    assert "separation_track=5000 Hz (constant within a block)" in repr(afmid.ForceModel.of(track_fit))


def _without_seconds(details: dict) -> dict:
    """A diagnosis's answer without its timings (each refit's seconds differ from run to run)."""
    text = json.dumps(details, sort_keys=True, default=str)
    data = json.loads(text)
    data.pop("seconds", None)
    for entry in data.get("tried", []) + data.get("suggestions", []) + data.get("undecided", []):
        entry.pop("seconds", None)
    return data


@pytest.mark.slow
def test_a_tracks_diagnosis_in_memory_is_its_run_files(track_fit, tmp_path, monkeypatch):
    """``Fit.diagnose()`` of a track in memory is ``afmid report``'s diagnosis of its run file (the candidates
    refitted on block 0 with its d held, the record re-read from the input file): the same answer; ``save()`` after
    it keeps the answer, which the loaded fit reuses without a refit; ``report()`` after it writes the folder."""
    from afmid.diagnosis.refit_count import refits_made

    monkeypatch.setenv("AFMID_DIAGNOSIS_CACHE", "off")
    undiagnosed = track_fit.save(tmp_path / "undiagnosed.h5")
    made = track_fit.diagnose()
    track_fit.report(tmp_path / "report")
    assert (tmp_path / "report" / "report.html").is_file()
    share = track_fit.run.quantities["E_star"]["error_separation_track"]
    summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert summary["runs"][-1]["parameters"]["E_star"]["error_separation_track"] == share > 0
    page = (tmp_path / "report" / "report.html").read_text()
    assert "the track's share (shown as track)" in page and " / track " in page
    from_file = afmid.load(undiagnosed).diagnose()
    assert _without_seconds(from_file.details) == _without_seconds(made.details)
    assert made.verdict and made.details["tried"]
    before = refits_made()
    kept = afmid.load(track_fit.save(tmp_path / "diagnosed.h5")).diagnose()
    assert refits_made() == before and kept.details == made.details


def test_a_track_of_several_files_is_one_line(scan, tmp_path, run_cli):
    """``afmid fit`` of ``fit.separation_track`` with ``data.paths``: one line naming data.path, exit 2, no file."""
    _, path, config_path = scan
    raw = yaml.safe_load(config_path.read_text())
    raw["data"] = {"paths": [str(path), str(path)]}
    config = tmp_path / "paths.yaml"
    config.write_text(yaml.safe_dump(raw))
    code, out, err = run_cli("fit", config, "-o", tmp_path / "run.h5")
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "data.path: a separation track is fitted on one record" in lines[0] and not (tmp_path / "run.h5").exists()


def test_a_damaged_track_group_is_one_input_error(track_fit, tmp_path):
    """A run file whose /model/separation_track lost its bandwidth or a dataset: one InputError naming it; one
    without ``within_block`` (written before d could move within a block) reads as held per block."""
    from afmid.errors import InputError

    saved = track_fit.save(tmp_path / "track.h5")
    with h5py.File(saved, "a") as h5:
        del h5["model/separation_track"].attrs["within_block"]
    assert afmid.load(saved).separation_track.within_block == "constant"
    with h5py.File(saved, "a") as h5:
        del h5["model/separation_track"].attrs["bandwidth"]
    with pytest.raises(InputError, match="separation_track@bandwidth: missing attribute 'bandwidth'"):
        afmid.load(saved)
    with h5py.File(saved, "a") as h5:
        h5["model/separation_track"].attrs["bandwidth"] = TRACK["bandwidth"]
        del h5["model/separation_track/separation_error"]
    with pytest.raises(InputError, match="missing /model/separation_track/separation_error"):
        afmid.load(saved)

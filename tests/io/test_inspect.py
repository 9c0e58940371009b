"""``afmid inspect FILE`` and ``afmid init-config --from FILE``.

The files are small synthetic tapping traces (a drive sinusoid plus a few
harmonics of a repulsive contact) written in the test; the example data in
data/ are covered by tests/io/test_example_data.py.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml

from afmid.config import build_config, load_config, template_text
from afmid.io.inspect import describe, inspect_file, prefill_config
from afmid.io.trace import load_trace

# floating-point results compared; blas_sensitive: make test-kernels runs these again (BLAS/LAPACK on the path)
pytestmark = [pytest.mark.numerics, pytest.mark.blas_sensitive]

RATE = 3e7  # Hz
SPP = 100


def motion(periods=20, noise=1e-12, seed=0) -> np.ndarray:
    """Deflection, m: 10 nm at 300 kHz with the harmonics a repulsive contact at the top gives."""
    phase = 2 * np.pi * np.arange(periods * SPP) / SPP
    x = 10e-9 * np.cos(phase)
    for n, amp in ((2, 30e-12), (3, 12e-12), (4, 6e-12), (5, 3e-12), (6, 1.5e-12)):
        x += amp * np.cos(n * phase)  # in phase at the top: a repulsive pulse at the closest approach
    return x + noise * np.random.default_rng(seed).standard_normal(x.size)


def write_csv(path, x, time=True, header="deflection_nm"):
    t = np.arange(x.size) / RATE
    rows = [f"time_s,{header}" if time else header]
    rows += [f"{ti!r},{xi * 1e9!r}" if time else repr(xi * 1e9) for ti, xi in zip(t.tolist(), x.tolist())]
    path.write_text("\n".join(rows) + "\n")
    return path


def field(text: str, name: str) -> str:
    match = re.search(rf"^{re.escape(name)}:\s+(.*)$", text, re.M)
    assert match, f"no {name!r} line in:\n{text}"
    return match[1]


def test_inspect_a_csv_with_a_time_column(tmp_path):
    path = write_csv(tmp_path / "trace.csv", motion())
    text = inspect_file(path)
    assert field(text, "format").startswith("csv (")
    assert field(text, "channels") == "2: time_s, deflection_nm"
    assert field(text, "reading") == "'deflection_nm', time from 'time_s'"
    assert field(text, "samples") == "2000"
    assert field(text, "sample rate").startswith("30 MHz (derived:uniform time channel 'time_s')")
    assert field(text, "units").startswith("nm (file:column name 'deflection_nm')")
    assert field(text, "oscillation").startswith("300 kHz, 100.00 samples per period, 20.0 periods")
    assert field(text, "amplitude").startswith("10 nm")
    assert re.match(r"1(\.0\d)? pm rms \(0\.2\d+ fm/sqrt\(Hz\)\)", field(text, "noise floor"))
    assert re.match(r"5 of 2\.\.4\d above the noise \(n = 2, 3, 4, 5, 6\)", field(text, "harmonics"))
    assert field(text, "interaction").startswith("contact: the force turns repulsive at the closest approach")
    assert "defects: none found" in text
    assert "  data.time_column: time_s\n" in text and "  data.sample_rate: 3.0e+07\n" in text


def test_inspect_without_rate_or_units_still_measures_the_oscillation(tmp_path):
    path = tmp_path / "bare.npy"
    np.save(path, motion())
    text = inspect_file(path)
    assert field(text, "sample rate") == ("unknown: the file does not say; pass --sample-rate or set "
                                          "data.sample_rate")
    assert field(text, "units").startswith("unknown: the file does not say; set data.units")
    assert field(text, "oscillation").startswith("100.00 samples per period, 20.0 periods")
    assert "  data.sample_rate: null  # REQUIRED\n" in text and "  data.units: null  # REQUIRED\n" in text
    with_rate = inspect_file(path, sample_rate=3e7)
    assert field(with_rate, "sample rate").startswith("30 MHz (command line: --sample-rate)")
    assert field(with_rate, "oscillation").startswith("300 kHz")


def test_inspect_lists_the_defects(tmp_path):
    x = motion()
    x[500:540] = np.nan
    x = np.minimum(x, 0.95 * np.nanmax(x))
    text = inspect_file(write_csv(tmp_path / "bad.csv", x))
    assert field(text, "analysed") == ("samples 540-1999 (the longest stretch without NaN/inf; the signal checks "
                                       "below count samples from 540)")
    assert "  error: nan: 40 NaN/inf samples in the deflection (first at sample 500)" in text
    assert "  error: clipping: the deflection is clipped: flat tops at the maximum 9.5" in text


def test_inspect_a_file_with_several_channels_and_choosing_one(tmp_path, run_cli):
    path = tmp_path / "multi.npz"
    np.savez(path, amplitude_nm=np.ones(2000), phase=np.zeros(2000), sample_rate=RATE)
    text = inspect_file(path)
    assert field(text, "reading").startswith("nothing: the file has 2 channels; choose one with data.column")
    assert field(text, "reading").endswith("; pass --column")
    code, out, err = run_cli("inspect", path, "--column", "amplitude_nm")
    assert code == 0, err
    assert field(out, "reading") == "'amplitude_nm'"
    assert "error: no_oscillation: the deflection is constant" in out
    text = prefill_config(path, template_text())  # no default channel: the first one, marked CHECK
    assert re.search(r"^  column: amplitude_nm +# CHECK: the file has several channels: amplitude_nm, phase", text, re.M)
    assert yaml.safe_load(text)["data"]["sample_rate"] == RATE and yaml.safe_load(text)["data"]["units"] == "nm"


def test_inspect_cli_errors_are_one_line(tmp_path, run_cli):
    code, _, err = run_cli("inspect", tmp_path / "missing.csv")
    assert code == 1 and err == f"afmid: error: {tmp_path / 'missing.csv'}: data.path: file not found\n"
    path = write_csv(tmp_path / "trace.csv", motion())
    code, _, err = run_cli("inspect", path, "--column", "deflecton_nm")
    assert code == 1 and "no channel 'deflecton_nm' (did you mean 'deflection_nm'?)" in err


def test_prefill_keeps_the_template_and_fills_the_data_section(tmp_path):
    path = write_csv(tmp_path / "trace.csv", motion())
    text = prefill_config(path, template_text(), config_dir=tmp_path)
    # Every comment line of the template is still there, in order.
    template_comments = [line for line in template_text().splitlines() if line.lstrip().startswith("#")]
    lines = text.splitlines()
    positions = [lines.index(c) for c in template_comments]
    assert positions == sorted(positions)
    raw = yaml.safe_load(text)
    assert raw["data"] == {"path": "trace.csv", "format": "csv", "column": "deflection_nm", "time_column": "time_s",
                           "sample_rate": 3e7, "units": "nm", "positive": "toward_sample"}
    assert raw["drive"]["frequency"] == pytest.approx(3e5, rel=1e-6)
    assert "# CHECK the cantilever values: they are the template's examples, not read from trace.csv" in text
    assert re.search(r"^  format: csv {2,}# csv: from the suffix '.csv'", text, re.M)
    cfg = build_config(raw, base_dir=tmp_path)
    trace = load_trace(cfg)
    np.testing.assert_allclose(trace.deflection, motion(), rtol=1e-12, atol=1e-24)


def test_prefill_from_an_afmid_trace_file_copies_the_calibration(tmp_path, make_trace):
    from afmid.io.trace import write_trace_file

    path = write_trace_file(tmp_path / "t.h5", make_trace(), "{}")
    out = tmp_path / "configs"
    out.mkdir()
    text = prefill_config(path, template_text(), config_dir=out)
    raw = yaml.safe_load(text)
    assert raw["data"]["path"] == "../t.h5" and raw["data"]["units"] == "m" and raw["data"]["column"] == "/deflection"
    assert raw["cantilever"] == {"spring_constant": 40.0, "resonance_frequency": 3e5, "quality_factor": 150.0,
                                 "tip_radius": 1e-8}
    assert raw["drive"] == {"frequency": 3e5}
    assert "  spring_constant: 40.0        # from the trace file" in text
    assert "The file is SIMULATED (ground truth in /truth, model dmt)" in text
    (out / "run.yaml").write_text(text)
    trace = load_trace(load_config(out / "run.yaml"))
    assert trace.overridden == []


def test_init_config_from_cli_writes_a_loadable_config(tmp_path, run_cli):
    write_csv(tmp_path / "data.csv", motion(), time=False)
    out = tmp_path / "nested" / "run.yaml"
    out.parent.mkdir()
    code, _, err = run_cli("init-config", "--from", tmp_path / "data.csv", "-o", out)
    assert code == 0, err
    text = out.read_text()
    raw = yaml.safe_load(text)
    assert raw["data"]["path"] == "../data.csv"
    assert raw["data"]["sample_rate"] is None and "# REQUIRED: Hz; the file does not say" in text
    text = text.replace("sample_rate: null", "sample_rate: 3.0e+7", 1)
    out.write_text(text)
    trace = load_trace(load_config(out))
    assert trace.sample_rate == 3e7 and trace.n_samples == 2000
    code, stdout, _ = run_cli("init-config", "--from", tmp_path / "data.csv")
    assert code == 0 and yaml.safe_load(stdout)["data"]["path"] == str(tmp_path / "data.csv")


def test_prefill_records_the_defects_and_a_flipped_sign(tmp_path):
    path = tmp_path / "flipped.mat"
    from scipy.io import savemat

    savemat(path, {"defl_nm": -motion() * 1e9, "sample_rate": RATE})
    summary = describe(path)
    assert summary.analysis.flipped
    text = prefill_config(path, template_text())
    assert "# afmid inspect: warning: sign: the tip-sample interaction happens at the most negative deflection" in text
    raw = yaml.safe_load(text)
    assert raw["data"]["positive"] == "away_from_sample"
    assert raw["data"]["units"] == "nm" and raw["data"]["sample_rate"] == 3e7


def test_volts_ask_for_invols(tmp_path):
    path = write_csv(tmp_path / "volts.csv", motion() / 50e-9 * 1e-9, header="deflection_V")
    text = prefill_config(path, template_text())
    assert re.search(r"^  invols: null +# REQUIRED for units V: m/V", text, re.M)
    assert "set data.invols (m/V) to convert to metres" in inspect_file(path)


@pytest.mark.parametrize("rate", [float("nan"), float("inf"), -3e7, 0.0])
def test_a_sample_rate_option_that_is_not_a_positive_number_is_refused(tmp_path, rate):
    """``afmid inspect --sample-rate nan`` printed 'nan Hz' (issue 32); now one line naming the option."""
    from afmid.errors import ConfigError

    path = tmp_path / "t.csv"
    write_csv(path, motion(), time=False)
    with pytest.raises(ConfigError) as info:
        inspect_file(path, sample_rate=rate)
    assert info.value.key == "--sample-rate"
    assert f"{rate:g} is not a sample rate: expected a positive number of Hz" in info.value.message

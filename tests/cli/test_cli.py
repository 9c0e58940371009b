"""The command line: help stays light, sub-commands answer, the effect catalog, and the fit command's plumbing.

The fit itself is stubbed (``afmid.fit.pipeline.run_fit`` / ``afmid.runfile.write_run``): these tests
check what the CLI passes on (layered config, --set, --add/--remove), how it
reports warnings, interruptions and success, not the identification.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from afmid.physics.effects import EFFECTS, MODELS

SUBCOMMANDS = ["simulate", "fit", "batch", "report", "effects", "init-config", "inspect", "coverage"]


# --------------------------------------------------------------------------- help
def test_help_does_not_import_numba_or_other_heavy_modules():
    script = textwrap.dedent(
        f"""
        import sys
        from click.testing import CliRunner
        from afmid.cli import cli
        runner = CliRunner()
        for args in [["--help"]] + [[name, "--help"] for name in {SUBCOMMANDS!r}]:
            result = runner.invoke(cli, args)
            assert result.exit_code == 0, (args, result.output)
            assert "Usage:" in result.output, args
        heavy = [m for m in ("numba", "h5py", "matplotlib", "scipy") if m in sys.modules]
        assert not heavy, heavy
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_help_lists_every_subcommand(run_cli):
    code, out, err = run_cli("--help")
    assert code == 0 and err == ""
    for name in SUBCOMMANDS:
        assert f"  {name} " in out


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_subcommand_help(run_cli, name):
    code, out, _ = run_cli(name, "--help")
    assert code == 0
    assert out.startswith(f"Usage: afmid {name} ")


def test_version(run_cli):
    from afmid import __version__

    code, out, _ = run_cli("--version")
    assert code == 0 and out.strip() == f"afmid, version {__version__}"


def test_usage_errors_exit_2(run_cli):
    code, _, err = run_cli("no-such-command")
    assert code == 2 and "No such command" in err and "Traceback" not in err
    assert err.count("\n") == 1 and err.startswith("afmid: error: ") and "see 'afmid --help'" in err
    code, _, err = run_cli("inspect", "x.csv", "--sample-rate", "abc")
    assert code == 2 and err == ("afmid: error: Invalid value for '--sample-rate': 'abc' is not a valid float. "
                                 "(see 'afmid inspect --help')\n")
    code, _, err = run_cli("fit")
    assert code == 2 and "Missing argument 'CONFIG'" in err
    code, _, err = run_cli("fit", "run.yaml")
    assert code == 2 and "Missing option '-o'" in err


def test_batch_usage_errors_exit_2(run_cli, tmp_path):
    out = tmp_path / "out"
    code, _, err = run_cli("batch", "-o", out)
    assert code == 2 and err.startswith("afmid: error: give a CONFIG with --inputs or --manifest, or run configs ")
    assert len(err.splitlines()) == 1
    code, _, err = run_cli("batch", "run.yaml", "--configs", "configs/*.yaml", "-o", out)
    assert code == 2 and "--configs: runs each config on its own data: give it without CONFIG" in err
    code, _, err = run_cli("batch", "--inputs", "traces/*.csv", "-o", out)
    assert code == 2 and "--inputs: needs a CONFIG" in err
    code, _, err = run_cli("batch", "--configs", str(tmp_path / "none" / "*.yaml"), "-o", out)
    assert code == 1 and "--configs: no files match" in err
    code, out_text, _ = run_cli("batch", "--help")
    assert "--configs GLOB" in out_text and "--inputs GLOB" in out_text
    assert not out.exists()


def test_console_script_exit_code(tmp_path):
    script = Path(sys.executable).with_name("afmid")
    if not script.exists():
        pytest.skip("afmid console script not installed in this environment")
    result = subprocess.run([str(script), "fit", str(tmp_path / "nope.yaml"), "-o", str(tmp_path / "o.h5")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr == f"afmid: error: {tmp_path / 'nope.yaml'}: config file not found\n"


# --------------------------------------------------------------------------- effects
def test_effects_lists_all_twelve_and_the_tip_shapes(run_cli):
    code, out, _ = run_cli("effects")
    assert code == 0
    catalog, tips = out.split("\nTip shapes (cantilever.tip_shape")
    names = [line.split(":")[0] for line in catalog.splitlines() if line and not line.startswith(" ")]
    assert names == EFFECTS.names()
    assert len(names) == 12
    assert set(names) == {"dmt", "lennard_jones", "jkr", "viscoelastic", "exponential_damping", "electrostatic",
                          "capillary", "hydration", "squeeze_film", "contact_damping", "double_layer",
                          "standard_linear_solid"}
    assert "force (repulsive +):" in out and "param E_star [Pa]" in out
    shapes = [line.split(":")[0] for line in tips.splitlines()[1:] if line and not line.startswith(" ")]
    assert shapes == ["sphere", "cone", "pyramid", "flat_punch"]


def test_effects_json(run_cli):
    code, out, _ = run_cli("effects", "--json")
    assert code == 0
    records = json.loads(out)
    assert [r["name"] for r in records] == EFFECTS.names()
    for r in records:
        assert r["formula"] and r["references"]
        assert all(p["unit"] is not None and len(p["range"]) == 2 for p in r["parameters"])
        assert all(t["coefficient_unit"] for t in r["terms"])
    code, out, _ = run_cli("effects", "--json", "viscoelastic")
    assert [r["name"] for r in json.loads(out)] == ["viscoelastic"]


def test_effects_models(run_cli):
    code, out, _ = run_cli("effects", "--models")
    assert code == 0
    names = [line.split(":")[0] for line in out.splitlines() if line and not line.startswith(" ")]
    assert names == MODELS.names() and {"dmt", "lennard_jones", "jkr", "dmt_viscoelastic"} <= set(names)
    assert out.count("  effects: ") == len(MODELS)
    code, out, _ = run_cli("effects", "--models", "--json")
    assert {r["name"]: r["effects"] for r in json.loads(out)}["dmt_viscoelastic"] == ["dmt", "viscoelastic"]


def test_effects_unknown_name(run_cli):
    code, out, err = run_cli("effects", "viscoelastc")
    assert code == 2 and out == ""
    assert err.startswith("afmid: error: unknown effect 'viscoelastc' (did you mean 'viscoelastic'?); allowed: ")
    assert len(err.splitlines()) == 1


# --------------------------------------------------------------------------- fit plumbing (fit stubbed)
class _StubResult:
    """The pipeline's result of the stubbed fit: only its trace (the fitted trace, afmid.api.Fit.trace)."""

    def __init__(self, trace):
        self.prep = types.SimpleNamespace(trace=trace)


def _stub_record(config):
    """The run record of the stubbed fit (afmid.runfile.RunData's fields that afmid fit's shell and the printed
    read-out read): one term ``stub`` selected, no read-outs (nothing to judge), an error at its floor, no
    warnings."""
    return types.SimpleNamespace(
        config=config, path=Path("stub.h5"), effects=[], terms=["stub"], expressions=["1"], units=["N"],
        selected=np.ones(1, dtype=bool), selected_terms=["stub"], coefficients=np.zeros(1), errors=np.zeros(1),
        cantilever={}, quantities={}, nonlinear={}, cv_error=0.0, cv_error_noise_floor=1.0,
        cv_error_floor_dof=math.nan, cv_error_folds=np.zeros(0), model_limited=False, n_periods=None,
        warnings=[], implausible=[], force_calibration_uncertainty=0.0, force_separation_uncertainty=math.nan,
        force_statistical_uncertainty=math.nan, force_selection_uncertainty=math.nan,
        force_total_uncertainty=math.nan, inclusion=np.ones(1), selection_path={}, joint=None, separation_track=None)


@pytest.fixture
def stub_fit(monkeypatch):
    """Replace the fit with: load the trace (the real loader), write a tiny run file atomically."""
    import afmid.fit.pipeline
    import afmid.runfile
    from afmid.config import dump_config
    from afmid.io.trace import atomic_hdf5, check_output_path, load_trace

    seen: dict = {}

    def run_fit(config, progress=False, trace=None):
        seen["config"] = config
        seen["trace"] = load_trace(config)
        if "raise" in seen:
            raise seen["raise"]
        return _StubResult(seen["trace"])

    def run_data(result, config, name="fit"):
        return _stub_record(config)

    def write_run(path, run, overwrite=False):
        path = check_output_path(path, overwrite)
        with atomic_hdf5(path, "afmid-run", dump_config(run.config), {}) as h5:
            h5.attrs["stub"] = True
        return path

    monkeypatch.setattr(afmid.fit.pipeline, "run_fit", run_fit)
    monkeypatch.setattr(afmid.runfile, "run_data", run_data)
    monkeypatch.setattr(afmid.runfile, "write_run", write_run)
    return seen


def test_fit_passes_the_layered_config_on(tmp_path, write_csv, write_config, pinned_config, run_cli, stub_fit,
                                          temp_leftovers):
    write_csv()
    cfg = write_config(pinned_config())
    out = tmp_path / "run1.h5"
    code, _, err = run_cli("fit", cfg, "-o", out, "--set", "cantilever.quality_factor=200", "--set", "fit.bootstrap=0",
                           "--add", "viscoelastic")
    assert code == 0, err
    config = stub_fit["config"]
    assert config.cantilever.quality_factor == 200 and config.fit.bootstrap == 0
    assert config.cantilever.spring_constant == 40.0  # from the YAML
    assert config.fit.folds == 5  # default
    assert config.model.effects == ["dmt", "viscoelastic"]
    assert stub_fit["trace"].cantilever.quality_factor == 200
    assert f"wrote {out}: cv_error 0.0000; terms: stub" in err
    stored = yaml.safe_load(h5py.File(out, "r").attrs["config"])
    assert stored["cantilever"]["quality_factor"] == 200 and stored["model"]["effects"] == ["dmt", "viscoelastic"]
    assert temp_leftovers(tmp_path) == []

    # The same output again: refused; with --overwrite: replaced. --remove and --add together.
    code, _, err = run_cli("fit", cfg, "-o", out)
    assert code == 1 and "output exists" in err
    code, _, err = run_cli("fit", cfg, "-o", out, "--overwrite", "--remove", "dmt", "--add", "jkr")
    assert code == 0, err
    assert stub_fit["config"].model.effects == ["jkr"]


def test_low_sample_rate_warns_and_carries_on(tmp_path, write_csv, write_config, pinned_config, run_cli, stub_fit):
    write_csv(samples_per_period=10, periods=6)
    cfg = pinned_config()
    cfg["data"]["sample_rate"] = 3e6
    out = tmp_path / "out.h5"
    code, _, err = run_cli("fit", write_config(cfg), "-o", out)
    assert code == 0, err
    warnings = [line for line in err.splitlines() if line.startswith("afmid: warning: ")]
    assert len(warnings) == 1
    assert "only 10.0 samples per drive period (< 20)" in warnings[0]
    assert "afmid: error" not in err and out.exists()


def test_quiet_keeps_warnings_and_drops_progress(tmp_path, write_csv, write_config, pinned_config, run_cli, stub_fit):
    write_csv(samples_per_period=10, periods=6)
    cfg = pinned_config()
    cfg["data"]["sample_rate"] = 3e6
    code, _, err = run_cli("-q", "fit", write_config(cfg), "-o", tmp_path / "out.h5")
    assert code == 0
    assert "samples per drive period" in err and "wrote" not in err


def test_interrupt_leaves_no_output(tmp_path, write_csv, write_config, pinned_config, run_cli, stub_fit,
                                    temp_leftovers):
    write_csv()
    stub_fit["raise"] = KeyboardInterrupt()
    out = tmp_path / "out.h5"
    code, _, err = run_cli("fit", write_config(pinned_config()), "-o", out)
    assert code == 130
    assert err.strip() == "afmid: interrupted; no partial output was written"  # click prints a newline first
    assert not out.exists() and temp_leftovers(tmp_path) == []


def test_internal_errors_are_not_disguised(tmp_path, write_csv, write_config, pinned_config, run_cli, stub_fit):
    """Only AfmidError is a user error; anything else is a bug and must keep its traceback."""
    write_csv()
    stub_fit["raise"] = ZeroDivisionError("bug")
    with pytest.raises(ZeroDivisionError):
        run_cli("fit", write_config(pinned_config()), "-o", tmp_path / "out.h5")
    assert not (tmp_path / "out.h5").exists()

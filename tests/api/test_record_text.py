"""A fit prints from its run record: the text of the record (``RunReadout`` of ``run_data``) is the pipeline's own
text, line for line, the read-outs and nonlinear parameters in the fit's order (effect by effect as the library
lists them, each effect's quantities as the catalog declares them), though the record keeps them by name as the
file does; and a fit saved and loaded prints the same. Fits of the demo's LDPE-like trace (24 periods) with the
effects in a non-alphabetical order, a decay length, and an estimated separation."""

from __future__ import annotations

import copy

import pytest

from afmid.config import build_config
from tests.fit.test_declared_drive import demo_raw, simulated

#: (effects, separation estimated): each a case whose printed order the file's order (by name) would change.
CASES = [(["viscoelastic", "dmt", "electrostatic"], False), (["jkr", "hydration"], False),
         (["dmt", "capillary"], True)]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("record_text")
    raw = demo_raw(folder, periods=24)
    simulated(folder, raw)
    return folder, raw


def _parameter_names(text: str) -> list[str]:
    """The names of the printed physical and nonlinear parameters, in order."""
    lines = text.splitlines()
    start = lines.index("physical parameters:") + 1
    names = []
    for line in lines[start:]:
        if not line.startswith("  "):
            break
        names.append(line.split()[0].rstrip(":"))
    return names


@pytest.mark.parametrize("effects, estimated", CASES, ids=["+".join(c[0]) for c in CASES])
def test_the_records_text_is_the_fits_text(demo, effects, estimated):
    import afmid
    from afmid.api.fit import Fit
    from afmid.api.readout import RunReadout
    from afmid.fit.pipeline import run_fit
    from afmid.report.fit_text import fit_text
    from afmid.runfile import run_data

    folder, raw = demo
    raw = copy.deepcopy(raw)
    raw["model"] = {"effects": effects}
    raw["fit"]["bootstrap"] = 8
    if estimated:
        raw["sample"]["separation"] = None
    config = build_config(raw, source=folder / "fit.yaml", base_dir=folder)
    result = run_fit(config)
    record = run_data(result, config)
    assert list(record.quantities) == sorted(record.quantities)  # the record keeps them by name, as the file
    own = fit_text(result)
    assert fit_text(RunReadout(record)) == own
    names = _parameter_names(own)
    assert names != sorted(names) and names[: len(result.quantities)] == list(result.quantities)
    fitted = Fit(result, config)
    assert fitted.text() == own
    assert fitted.summary_line() == result.summary_line()
    assert fitted.warnings == [str(w) for w in result.warnings]
    saved = fitted.save(folder / f"{'_'.join(effects)}.h5", overwrite=True)
    assert afmid.load(saved).text() == own
    # verbose (``afmid fit -v``): the candidate supports from the record, made and loaded alike
    verbose = fit_text(result, verbose=True)
    assert "selection: criterion bic" in verbose and "ΔBIC" in verbose
    assert fitted.text(verbose=True) == verbose == afmid.load(saved).text(verbose=True)
    if estimated:
        assert "d" in result.nonlinear and list(result.nonlinear)[0] == "d"


def test_verbose_text_under_aicc_is_the_fits_and_needs_the_stored_aicc(demo):
    """With ``fit.selection: aicc`` the candidates are ranked by their AICc, which the record keeps
    (``/diagnostics/path/aicc``): the record's verbose text is the pipeline's, before and after the file; a file
    without it (an older afmid's) refuses verbose text in one line and still prints the rest."""
    import h5py

    import afmid
    from afmid.api.fit import Fit
    from afmid.errors import ConfigError
    from afmid.fit.pipeline import run_fit
    from afmid.report.fit_text import fit_text

    folder, raw = demo
    raw = copy.deepcopy(raw)
    raw["model"] = {"effects": ["dmt", "viscoelastic"]}
    raw["fit"].update(bootstrap=0, selection="aicc")
    config = build_config(raw, source=folder / "fit.yaml", base_dir=folder)
    result = run_fit(config)
    verbose = fit_text(result, verbose=True)
    assert "selection: criterion aicc" in verbose and "ΔAICC" in verbose
    fitted = Fit(result, config)
    saved = fitted.save(folder / "aicc.h5", overwrite=True)
    loaded = afmid.load(saved)
    assert fitted.text(verbose=True) == verbose == loaded.text(verbose=True)
    with h5py.File(saved, "r") as h5:
        assert h5["diagnostics/path/aicc"].attrs["units"] == "1"
        assert list(h5["diagnostics/path/aicc"][()]) == [c.aicc for c in result.selection.candidates]
    older = folder / "aicc_older.h5"
    older.write_bytes(saved.read_bytes())
    with h5py.File(older, "r+") as h5:
        del h5["diagnostics/path/aicc"]
    old = afmid.load(older)
    assert old.text() == fitted.text()
    with pytest.raises(ConfigError, match="keeps no candidate supports with their criterion values"):
        old.text(verbose=True)

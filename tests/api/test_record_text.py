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
    if estimated:
        assert "d" in result.nonlinear and list(result.nonlinear)[0] == "d"

"""A short run config for tests that need a real run file quickly (tests/report/test_export.py,
test_report_browser.py): the user config configs/dmt_viscoelastic.yaml at 12 periods, 10 bootstrap draws,
its trace at ``trace.h5`` beside it."""

from __future__ import annotations

from pathlib import Path

from repo_paths import REPO_ROOT


def short_dmt_viscoelastic_config(folder: Path) -> Path:
    """Write ``folder/short.yaml`` and return its path."""
    text = (REPO_ROOT / "configs" / "dmt_viscoelastic.yaml").read_text()
    assert "periods: 50 " in text  # the edit below must change something
    config = folder / "short.yaml"
    config.write_text(text.replace("periods: 50 ", "periods: 12 ") + "\ndata: {path: trace.h5}\nfit: {bootstrap: 10}\n")
    return config

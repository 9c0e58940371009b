"""Screenshots of the demo's own reports in headless Chromium, with issue 33's points checked in their DOM.

``make screenshots`` runs ``make demo demo-map`` and then this test with ``AFMID_DEMO_SCREENSHOTS=1``; it reads
the pages those targets wrote (``AFMID_DEMO_DIR``, default demo_output; ``AFMID_DEMO_MAP_DIR``, default
demo_map_output) and writes ``demo_report.png``, ``demo_map_report.png`` and ``demo_map_explorer.png`` into
``AFMID_SCREENSHOT_DIR`` (default screenshots/), and ``demo_map_visco_report.png`` of the map refitted with
viscoelastic. Chromium runs offline as in test_report_browser.py.

Checked, in the DOM Chromium builds from each page (``--dump-dom``, or a probe script put into a copy of it):

- the demo report (run1 fitted with [dmt], run2 with the effect its diagnosis named): each run of the loop has
  its evidence block, "Where the model fails" and "Effects tried" with its own figures, decoded by the browser;
- no parameter the catalog declares in seconds is shown in nm: every "NAME = VALUE UNIT" of such a parameter in
  the pages' text ends in a time unit, and at least one is shown (the demo's effects tried list the standard
  linear solid's relaxation_time), so the check cannot pass on a page that shows none;
- the map page's first section is the missing-effect map: its first heading is "Which effect is missing where",
  and a figure follows it before the next heading;
- the map's values per group say "not selected" exactly where no pixel of the group selected a parameter's term,
  and "selected at K of N pixels" where only some did, K and N counted from the result file (an unselected term
  reads 0: afmid.report.map_values), on the [dmt] page and on the page of the map refitted with viscoelastic
  (report_visco), where the elastic matrix's viscosity cell must carry one of the two (measured: selected at 1 of
  24 pixels; no demo group selects a term at none of its pixels, so the demo shows no "not selected" cell);
- the explorer: clicking another pixel of the missing-effect map changes the curve shown to that pixel's inverted
  force, read from the result file (the click script of test_map_explorer_browser.py).
"""

from __future__ import annotations

import html
import json
import os
import re
from html.parser import HTMLParser
from pathlib import Path

import h5py
import numpy as np
import pytest
from repo_paths import REPO_ROOT

from tests.report.test_map_explorer_browser import CLICK_SCRIPT
from tests.report.test_report_browser import browser, console_lines, probe, run_browser  # noqa: F401 (fixture)

#: The screenshot tests read the demo's outputs: only with them (the controls of the checks run always).
NEEDS_DEMO = pytest.mark.skipif(os.environ.get("AFMID_DEMO_SCREENSHOTS") != "1",
                                reason="needs `make demo demo-map` outputs: run `make screenshots` "
                                       "(AFMID_DEMO_SCREENSHOTS=1)")


def _folder(variable: str, default: str) -> Path:
    path = Path(os.environ.get(variable, default))
    return path if path.is_absolute() else REPO_ROOT / path


DEMO = _folder("AFMID_DEMO_DIR", "demo_output")
DEMO_MAP = _folder("AFMID_DEMO_MAP_DIR", "demo_map_output")
SHOTS = _folder("AFMID_SCREENSHOT_DIR", "screenshots")
#: Display units a time can be shown in (afmid.quantity_text: s -> µs, and the prefixes around it).
TIME_UNITS = ("s", "ms", "µs", "ns", "ps")


class _Sections(HTMLParser):
    """A page's text, its sections in order (heading text, tags seen before the next heading) and its tables (rows
    of cell texts)."""

    def __init__(self):
        super().__init__()
        self.sections: list[tuple[str, list[str]]] = []
        self.text: list[str] = []
        self.tables: list[list[list[str]]] = []
        self._in_heading = False
        self._skip = 0  # inside <script> / <style>
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style"):
            self._skip += 1
            return
        if tag == "h2":
            self._in_heading = True
            self.sections.append(("", []))
        elif self.sections:
            self.sections[-1][1].append(tag)
        if tag == "table":
            self.tables.append([])
        elif tag == "tr" and self.tables:
            self.tables[-1].append([])
        elif tag in ("td", "th") and self.tables and self.tables[-1]:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("script", "style"):
            self._skip -= 1
        elif tag == "h2":
            self._in_heading = False
        elif tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None

    def handle_data(self, data):
        if self._skip:
            return
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)
        if self._in_heading:
            heading, tags = self.sections[-1]
            self.sections[-1] = (heading + data, tags)


def _rendered(browser, page: Path, profile: Path) -> _Sections:  # noqa: F811
    done = run_browser(browser, profile, "--virtual-time-budget=15000", "--dump-dom", page.as_uri())
    assert done.returncode == 0 and "</html>" in done.stdout, done.stderr[-2000:]
    parsed = _Sections()
    parsed.feed(done.stdout)
    return parsed


def _screenshot(browser, page: Path, name: str, size: tuple[int, int], profile: Path) -> Path:  # noqa: F811
    """``page`` as Chromium shows it in a window of ``size`` (width, height), kept as SHOTS/name; not blank."""
    import matplotlib.image

    SHOTS.mkdir(parents=True, exist_ok=True)
    shot = SHOTS / name
    done = run_browser(browser, profile, f"--window-size={size[0]},{size[1]}", "--hide-scrollbars",
                       "--virtual-time-budget=20000", f"--screenshot={shot}", page.as_uri())
    assert done.returncode == 0 and console_lines(done.stderr) == [], done.stderr[-2000:]
    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (size[1], size[0])
    grey = pixels[..., :3].mean(axis=2)
    assert np.std(grey) > 0.05 and np.mean(grey < 0.5) > 0.005  # text and figures, not an empty white page
    return shot


def _time_parameters() -> set[str]:
    from afmid.physics.effects import EFFECTS

    return {p.name for e in EFFECTS for p in e.parameters if p.unit == "s"}


def _time_values_shown(text: str) -> list[tuple[str, str]]:
    """Every ``NAME = VALUE UNIT`` of a time parameter in ``text``: (name, unit word after the number)."""
    names = "|".join(sorted(map(re.escape, _time_parameters())))
    number = r"[-+]?[0-9][0-9.]*(?:e[-+]?[0-9]+)?(?:\s*±\s*[0-9][0-9.]*(?:e[-+]?[0-9]+)?)?"
    return re.findall(rf"\b({names})\s*=\s*\(?{number}\)?\s*([^\s,;()]+)", text)


@pytest.fixture(scope="module")
def pages() -> dict[str, Path]:
    found = {"report": DEMO / "report" / "report.html", "map": DEMO_MAP / "report_dmt" / "report.html",
             "explorer": DEMO_MAP / "report_dmt" / "explorer.html", "result": DEMO_MAP / "dmt.h5",
             "visco": DEMO_MAP / "report_visco" / "report.html", "visco_result": DEMO_MAP / "visco.h5"}
    missing = [str(p) for p in found.values() if not p.is_file()]
    assert not missing, f"run `make demo demo-map` first (or `make screenshots`): missing {missing}"
    return found


@pytest.mark.slow
@NEEDS_DEMO
def test_the_demo_report_carries_each_runs_evidence_and_no_time_in_nm(pages, browser, tmp_path):  # noqa: F811
    found = probe(browser, pages["report"], tmp_path / "probe")
    assert found["errors"] == [], found["errors"]
    summary = json.loads((pages["report"].parent / "summary.json").read_text(encoding="utf-8"))
    runs = [Path(r["run"]).name for r in summary["runs"]]
    evidence = found["evidence"]
    assert [e["run"] for e in evidence] == runs and len(runs) == 2, evidence
    for e in evidence:
        assert e["headings"] == [f"Where the model fails ({e['run']})", f"Effects tried ({e['run']})"], e
        assert len(e["figures"]) == 2 and all(f["width"] > 0 for f in e["figures"]), e
    assert evidence[0]["open"] is True  # run1 ([dmt]) is model-limited: its case is open
    page = _rendered(browser, pages["report"], tmp_path / "dom")
    shown = _time_values_shown(" ".join(page.text))
    assert shown, "the demo report shows no time parameter: the check below would pass vacuously"
    assert all(unit in TIME_UNITS for _, unit in shown), shown
    _screenshot(browser, pages["report"], "demo_report.png", (1200, 2400), tmp_path / "shot")


def _group_cells(page: _Sections) -> list[dict[str, str]]:
    """The map page's values per group: one {column: cell} per group row ("group 1", ...)."""
    for table in page.tables:
        if table and table[0][:2] == ["group", "verdict"]:
            return [dict(zip(table[0], row)) for row in table[1:] if row and row[0].startswith("group ")]
    return []


def _selection_words(result: Path, group: int, name: str) -> tuple[int, int]:
    """(pixels of ``group`` whose ``name`` read-out is non-zero, fitted pixels of the group), from the result file:
    an unselected term reads 0 (afmid.report.map_values), the group's label is its number - 1."""
    with h5py.File(result, "r") as h5:
        labels, status, value = (h5["maps"][n][...] for n in ("group", "status", name))
    members = (labels == group - 1) & (status < 2)
    return int(np.sum(members & np.isfinite(value) & (value != 0))), int(members.sum())


def _check_selection_cells(page: _Sections, result: Path, names: list[str]) -> list[str]:
    """Each group's cell of each parameter says "not selected" when no pixel of the group selected its term, "selected
    at K of N pixels" when some did, neither when all did; returns the cells of the first two kinds."""
    cells = _group_cells(page)
    assert cells, "no table of values per group on the map page"
    flagged = []
    for row in cells:
        group = int(row["group"].split()[1])
        for name in names:
            cell = row[name]
            chosen, pixels = _selection_words(result, group, name)
            if chosen == 0:
                assert cell == "not selected", (row["group"], name, cell)
            elif chosen < pixels:
                assert cell.endswith(f"; selected at {chosen} of {pixels} pixels"), (row["group"], name, cell)
            else:
                assert "selected" not in cell, (row["group"], name, cell)
            if chosen < pixels:
                flagged.append(f"{row['group']} {name}: {cell}")
    return flagged


def _parameter_names(result: Path) -> list[str]:
    """The map's physical parameters: every map with a 1-sigma map beside it, but the separation (always fitted)."""
    with h5py.File(result, "r") as h5:
        return [n for n in h5["maps"] if f"{n}_sigma" in h5["maps"] and n != "separation"]


@pytest.mark.slow
@NEEDS_DEMO
def test_the_demo_map_page_opens_with_the_missing_effect_map(pages, browser, tmp_path):  # noqa: F811
    page = _rendered(browser, pages["map"], tmp_path / "dom")
    headings = [h.strip() for h, _ in page.sections]
    assert headings and headings[0] == "Which effect is missing where", headings
    assert "img" in page.sections[0][1], page.sections[0]  # the map itself, before the next heading
    _check_selection_cells(page, pages["result"], _parameter_names(pages["result"]))
    shown = _time_values_shown(" ".join(page.text))
    assert all(unit in TIME_UNITS for _, unit in shown), shown
    _screenshot(browser, pages["map"], "demo_map_report.png", (1300, 1400), tmp_path / "shot")


@pytest.mark.slow
@NEEDS_DEMO
def test_the_refitted_demo_map_says_where_viscosity_was_not_selected(pages, browser, tmp_path):  # noqa: F811
    """The map refitted with viscoelastic (report_visco): the elastic matrix has no viscous term to select, so its
    viscosity cell must say where the term was (not) selected instead of showing a plain value for the group."""
    page = _rendered(browser, pages["visco"], tmp_path / "dom")
    assert [h.strip() for h, _ in page.sections][0] == "Which effect is missing where"
    flagged = _check_selection_cells(page, pages["visco_result"], _parameter_names(pages["visco_result"]))
    assert any(" viscosity: " in f for f in flagged), flagged
    _screenshot(browser, pages["visco"], "demo_map_visco_report.png", (1300, 1400), tmp_path / "shot")


def _inverted_force(result: Path, pixel: int, cols: int) -> np.ndarray:
    """The approach branch of a pixel's stored inverted force in nN, rounded as the page rounds it (4 digits)."""
    row, col = divmod(pixel, cols)
    with h5py.File(result, "r") as h5:
        force = np.asarray(h5["pixel_curves/force_inverted"][row, col, 0], dtype=float) * 1e9
    return np.array([float(f"{v:.4g}") for v in force])


@pytest.mark.slow
@NEEDS_DEMO
def test_a_click_in_the_demo_map_explorer_changes_the_curve(pages, browser, tmp_path):  # noqa: F811
    """The explorer opens on the pixel with the largest error; a click on the pixel whose curve differs most from
    it (a mouse click at its place, then plotly's click event) shows that pixel's curve and diagnosis."""
    page = pages["explorer"].read_text(encoding="utf-8")
    data = json.loads(html.unescape(re.search(r'id="afmid-explorer-data">(.*?)</script>', page, flags=re.S)
                                    .group(1)).replace("<\\/", "</"))
    start, cols = data["start"], data["cols"]
    assert len(data["pixels"]) == 36 and cols == 6  # the demo map, 6 x 6, drawn without a stride
    fitted = [i for i, p in enumerate(data["pixels"]) if p["curves"] is not None]
    curves = {i: _inverted_force(pages["result"], i, cols) for i in fitted}
    # the pixel whose curve differs most from the one shown first: a click there must visibly change the curve
    target = max((i for i in fitted if i != start), key=lambda i: np.max(np.abs(curves[i] - curves[start])))
    assert np.max(np.abs(curves[target] - curves[start])) > 0.05  # nN: two curves a reader tells apart
    head = re.search(r"<head[^>]*>", page, flags=re.I)
    click = CLICK_SCRIPT.replace("TARGET_PIXEL", str(target))
    report_line = "document.body.appendChild(pre);"
    assert report_line in click  # the screenshot's copy clicks the same but prints no probe output on the page
    copy, quiet = (pages["explorer"].with_name(f"{stem}-explorer.html") for stem in ("probe", "probe-quiet"))
    copy.write_text(page[:head.end()] + click + page[head.end():], encoding="utf-8")
    quiet.write_text(page[:head.end()] + click.replace(report_line, "") + page[head.end():], encoding="utf-8")
    try:
        done = run_browser(browser, tmp_path / "profile", "--window-size=1300,1100", "--virtual-time-budget=20000",
                           "--dump-dom", copy.as_uri())
        # the page after the click, as a user sees the pixel it pinned
        _screenshot(browser, quiet, "demo_map_explorer.png", (1300, 1100), tmp_path / "shot")
    finally:
        copy.unlink()
        quiet.unlink()
    found = re.search(r'<pre id="afmid-probe">(.*?)</pre>', done.stdout, flags=re.S)
    assert found, f"the probe did not report (chromium exit {done.returncode}): {done.stderr[-2000:]}"
    out = json.loads(html.unescape(found.group(1)))
    assert out["errors"] == [], out["errors"]
    assert out["before"]["pixel"] == str(start)
    np.testing.assert_allclose(out["before"]["y"], curves[start], rtol=0, atol=1e-12)
    row, col = divmod(target, cols)
    for key in ("after_mouse", "after_click"):  # the user's click, then plotly's own click event
        state = out[key]
        assert state["pixel"] == str(target), (key, state["pixel"])
        np.testing.assert_allclose(state["y"], curves[target], rtol=0, atol=1e-12, err_msg=key)
        assert f"pixel (row {row}, col {col})" in state["panel"], key


def test_the_checks_catch_a_time_in_nm_and_a_wrong_selection_cell(tmp_path):
    """Controls: a relaxation time written in nm is caught, one in µs passes; a group cell that shows a value where
    the file says the term was never selected fails the check."""
    bad = _time_values_shown("standard_linear_solid: relaxation_time = 104000 nm, E_star = 2 GPa")
    assert bad == [("relaxation_time", "nm")]
    assert _time_values_shown("relaxation_time = 104 ± 3 µs") == [("relaxation_time", "µs")]
    result = tmp_path / "result.h5"
    with h5py.File(result, "w") as h5:
        h5["maps/group"] = np.array([[[0, 0], [1, 1]]])
        h5["maps/status"] = np.zeros((1, 2, 2), dtype=np.int8)
        h5["maps/viscosity"] = np.array([[[0.0, 0.0], [40.0, 0.0]]])
    page = _Sections()
    page.feed("<table><tr><th>group</th><th>verdict</th><th>viscosity</th></tr>"
              "<tr><td>group 1</td><td>-</td><td>not selected</td></tr>"
              "<tr><td>group 2</td><td>-</td><td>40 Pa s (16-84 %: 40 .. 40); selected at 1 of 2 pixels</td></tr></table>")
    assert len(_check_selection_cells(page, result, ["viscosity"])) == 2
    wrong = _Sections()
    wrong.feed("<table><tr><th>group</th><th>verdict</th><th>viscosity</th></tr>"
               "<tr><td>group 1</td><td>-</td><td>0 Pa s (16-84 %: 0 .. 0)</td></tr></table>")
    with pytest.raises(AssertionError):
        _check_selection_cells(wrong, result, ["viscosity"])

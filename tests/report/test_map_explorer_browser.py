"""The map report and its explorer in a real browser, offline (issue 33): Debian's headless Chromium as in
test_report_browser.py (network cut: every name resolves to nothing, every request goes to a closed port).

The map: tests/configs/map_small.yaml (3x3 pixels, a soft domain), fitted by ``afmid map``, reported. A script put
into a copy of explorer.html (the only change) waits until plotly has drawn the pixel shown first, records its
curve and diagnosis, then clicks another pixel of the missing-effect map: first with mouse events at that pixel's
place on the page (what a user does), then, as plotly's own event, ``plotly_click`` on that pixel; after each it
records the curve and diagnosis again. Checked: plotly.js is inlined (no script loaded from anywhere), no error,
the click changed the shown pixel, its curve (the inverted force) and its diagnosis to the clicked pixel's, read
from the result file. Screenshots of report.html and of the explorer after the click (tmp folder; also copied to
``AFMID_SCREENSHOT_DIR`` when set) must hold text and figures, not a blank page.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from repo_paths import TEST_CONFIGS

from afmid.cli import main
from tests.report.test_report_browser import browser, console_lines, run_browser  # noqa: F401  (the fixture)

#: Put into a copy of explorer.html: TARGET_PIXEL (index into the page's pixels) is clicked; the states before and
#: after go into a <pre> of the DOM that --dump-dom prints.
CLICK_SCRIPT = r"""<script>
window.__afmidErrors = [];
window.addEventListener("error", function (e) { window.__afmidErrors.push(String(e.message || (e.target && e.target.src))); }, true);
(function () {
  var original = console.error;
  console.error = function () { window.__afmidErrors.push(Array.prototype.join.call(arguments, " ")); return original.apply(console, arguments); };
})();
function afmidState() {
  var curve = document.getElementById("afmid-curve");
  return {pixel: curve.getAttribute("data-pixel"), y: curve.data && curve.data.length ? curve.data[0].y : null,
          panel: document.getElementById("afmid-diagnosis").textContent,
          marker: (function () { var m = document.getElementById("afmid-maps"); var t = m.data[m.data.length - 1]; return [t.x[0], t.y[0]]; })()};
}
function afmidReport(out) {
  out.errors = window.__afmidErrors;
  var pre = document.createElement("pre"); pre.id = "afmid-probe"; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
}
window.addEventListener("load", function () {
  var out = {};
  var wait = setInterval(function () {
    var curve = document.getElementById("afmid-curve");
    if (!curve || !curve.getAttribute("data-pixel")) return;
    clearInterval(wait);
    out.before = afmidState();
    var D = JSON.parse(document.getElementById("afmid-explorer-data").textContent);
    var target = TARGET_PIXEL, row = Math.floor(target / D.cols), col = target % D.cols;
    var maps = document.getElementById("afmid-maps");
    // A user's click: mouse events at the centre of that pixel on the first map's drag layer.
    var xa = maps._fullLayout.xaxis, ya = maps._fullLayout.yaxis;
    var box = maps.querySelector(".nsewdrag").getBoundingClientRect();
    var px = box.left + xa.l2p(D.pixels[target].x), py = box.top + ya.l2p(D.pixels[target].y);
    var layer = document.elementFromPoint(px, py);
    ["mousemove", "mousedown", "mouseup", "click"].forEach(function (type) {
      layer.dispatchEvent(new MouseEvent(type, {bubbles: true, cancelable: true, clientX: px, clientY: py, view: window, buttons: type === "mousedown" ? 1 : 0}));
    });
    setTimeout(function () {
      out.after_mouse = afmidState();
      // Leave the maps: the clicked pixel stays shown (pinned) only if the click registered.
      maps.emit("plotly_unhover", {});
      out.after_unhover = afmidState();
      // plotly's own event for the start pixel, then for the target again: the shown curve follows each.
      maps.emit("plotly_click", {points: [{pointIndex: [Math.floor(D.start / D.cols), D.start % D.cols]}]});
      out.back_to_start = afmidState();
      maps.emit("plotly_click", {points: [{pointIndex: [row, col]}]});
      out.after_click = afmidState();
      out.target = target;
      afmidReport(out);
    }, 500);
  }, 100);
});
</script>"""


@pytest.fixture(scope="module")
def map_report(tmp_path_factory, browser) -> Path:  # noqa: F811  (the browser fixture)
    folder = tmp_path_factory.mktemp("map_browser")
    config = TEST_CONFIGS / "map_small.yaml"
    assert main(["-q", "simulate", str(config), "-o", str(folder / "map.h5")]) == 0
    assert main(["-q", "map", str(config), "--input", str(folder / "map.h5"), "-o", str(folder / "result.h5"),
                 "-j", "1"]) == 0
    assert main(["-q", "report", str(folder / "result.h5"), "-o", str(folder / "rep")]) == 0
    return folder


def _pixel_truth(result: Path, row: int, col: int) -> np.ndarray:
    """The approach branch of the pixel's stored inverted force, nN, as the page rounds it (4 digits)."""
    with h5py.File(result, "r") as h5:
        force = np.asarray(h5["pixel_curves/force_inverted"][row, col, 0], dtype=float) * 1e9
    return np.array([float(f"{v:.4g}") for v in force])


def _screenshot_is_not_blank(shot: Path, size: tuple[int, int]) -> None:
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == size
    grey = pixels[..., :3].mean(axis=2)
    assert np.std(grey) > 0.05 and np.mean(grey < 0.5) > 0.005  # text and figures, not an empty white page
    # Coloured maps and curves, not only black text: the palest colour drawn, "nothing missing" (#c7e9c0), has a
    # channel spread of 0.16; the first screen holds at least a 200 x 200 pixel map (2 % of it).
    colour = np.ptp(pixels[..., :3], axis=2)
    assert np.mean(colour > 0.1) > 0.02


def _keep(shot: Path) -> None:
    target = os.environ.get("AFMID_SCREENSHOT_DIR")
    if target:
        Path(target).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(target) / shot.name)


@pytest.mark.slow
def test_clicking_a_pixel_shows_its_curve_and_diagnosis_offline(map_report, browser, tmp_path):  # noqa: F811
    rep = map_report / "rep"
    page = (rep / "explorer.html").read_text(encoding="utf-8")
    assert not re.search(r"<script[^>]+\bsrc\s*=", page, flags=re.I)  # plotly.js inlined: nothing to fetch
    assert "plotly" in page.lower() and len(page) > 1_000_000
    data = json.loads(html.unescape(re.search(r'id="afmid-explorer-data">(.*?)</script>', page, flags=re.S)
                                    .group(1)).replace("<\\/", "</"))
    start, cols = data["start"], data["cols"]
    target = (start + 4) % len(data["pixels"])  # another pixel (3x3: never the start)
    copy = rep / "probe-explorer.html"
    head = re.search(r"<head[^>]*>", page, flags=re.I)
    copy.write_text(page[:head.end()] + CLICK_SCRIPT.replace("TARGET_PIXEL", str(target)) + page[head.end():],
                    encoding="utf-8")
    shot = tmp_path / "map_explorer.png"
    try:
        done = run_browser(browser, tmp_path / "profile", "--window-size=1300,1100", "--virtual-time-budget=20000",
                           "--dump-dom", copy.as_uri())
        shown = run_browser(browser, tmp_path / "profile2", "--window-size=1300,1100", "--hide-scrollbars",
                            "--virtual-time-budget=20000", f"--screenshot={shot}", copy.as_uri())
    finally:
        copy.unlink()
    found = re.search(r'<pre id="afmid-probe">(.*?)</pre>', done.stdout, flags=re.S)
    assert found, f"the probe did not report (chromium exit {done.returncode}): {done.stderr[-2000:]}"
    out = json.loads(html.unescape(found.group(1)))
    assert out["errors"] == [], out["errors"]
    before = out["before"]
    assert before["pixel"] == str(start)
    row, col = divmod(target, cols)
    truth = _pixel_truth(map_report / "result.h5", row, col)
    start_truth = _pixel_truth(map_report / "result.h5", *divmod(start, cols))
    np.testing.assert_allclose(before["y"], start_truth, rtol=0, atol=1e-12)
    assert np.max(np.abs(truth - start_truth)) > 0.05  # two pixels whose curves differ visibly (nN)
    for key in ("after_mouse", "after_unhover", "after_click"):  # the user's click pins the pixel
        state = out[key]
        assert state["pixel"] == str(target), (key, state["pixel"])
        np.testing.assert_allclose(state["y"], truth, rtol=0, atol=1e-12, err_msg=key)
        assert f"pixel (row {row}, col {col})" in state["panel"] and state["marker"] != before["marker"], key
    assert out["back_to_start"]["pixel"] == str(start)
    assert f"pixel (row {row}, col {col})" not in before["panel"]
    assert shown.returncode == 0 and console_lines(shown.stderr) == [], shown.stderr[-2000:]
    _screenshot_is_not_blank(shot, (1100, 1300))
    _keep(shot)


@pytest.mark.slow
def test_the_map_report_screenshot_opens_with_the_missing_effect_map(map_report, browser, tmp_path):  # noqa: F811
    shot = tmp_path / "map_report.png"
    done = run_browser(browser, tmp_path / "profile", "--window-size=1300,1400", "--hide-scrollbars",
                       "--virtual-time-budget=15000", f"--screenshot={shot}", (map_report / "rep" / "report.html").as_uri())
    assert done.returncode == 0 and console_lines(done.stderr) == [], done.stderr[-2000:]
    _screenshot_is_not_blank(shot, (1400, 1300))
    _keep(shot)

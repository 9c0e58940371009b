"""The map explorer's page without a browser (afmid.report.map_explorer, issue 33): a large map is strided to at
most MAX_PIXELS pixels, a result without groups or curves still gets a page that says what is missing, and each
pixel's numbers are the file's, in nm and nN."""

from __future__ import annotations

import html
import json
import math
import re

import h5py
import numpy as np

from afmid.io.files import FORMAT_VERSION
from afmid.maps.pixel_curves import CURVE_POINTS, CURVES, write_pixel_curves
from afmid.report.map_explorer import MAX_PIXELS, write_explorer
from afmid.report.maps import read_map_result
from afmid.report.map_values import selected_maps


def _result(path, rows: int, cols: int, curves: bool) -> None:
    """A hand-made map result: E* rising along the columns, every pixel ok, dmt's two terms selected."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as h5:
        h5.attrs["format"] = "afmid-map-result"
        h5.attrs["format_version"] = FORMAT_VERSION  # as every afmid file (afmid.io.files.check_format_version)
        h5.attrs["rows"], h5.attrs["cols"] = rows, cols  # afmid.report.map_result.check_layout reads them
        maps = h5.create_group("maps")

        def put(name, data, unit, **attrs):
            ds = maps.create_dataset(name, data=data)
            ds.attrs["units"] = unit
            for k, v in attrs.items():
                ds.attrs[k] = v

        e_star = np.tile(np.linspace(0.3e9, 2e9, cols), (rows, 1))
        put("E_star", e_star, "Pa", effect="dmt")
        put("E_star_sigma", 0.01 * e_star, "Pa", meaning="1 sigma")
        put("separation", np.full((rows, cols), 8e-9), "m")
        put("separation_sigma", np.full((rows, cols), 1e-11), "m")
        put("cv_error", 0.1 + 0.01 * rng.random((rows, cols)), "1")
        put("cv_error_noise_floor", np.full((rows, cols), 0.1), "1")
        put("status", np.zeros((rows, cols), np.int8), "1")
        put("selected", np.full((rows, cols), 3, np.int64), "1")
        maps.create_dataset("message", data=np.full((rows, cols), "", dtype=object), dtype=h5py.string_dtype())
        maps["message"].attrs["units"] = "1"
        h5.create_dataset("model/terms", data=np.array([b"dmt.vdw", b"dmt.hertz"]))
        h5.create_dataset("x", data=np.arange(cols) * 20e-9)
        if curves:
            n = rows * cols
            z = np.tile(np.linspace(-1e-9, 20e-9, CURVE_POINTS), (n, 1))
            force = np.repeat(e_star.reshape(n, 1, 1) * 1e-18, 2, axis=1) * np.ones((n, 2, CURVE_POINTS))
            data = {"separation": z, **{name: force for name in CURVES if name != "separation"}}
            write_pixel_curves(h5, data, (rows, cols))


def _page_data(page: str) -> dict:
    found = re.search(r'id="afmid-explorer-data">(.*?)</script>', page, flags=re.S)
    return json.loads(found.group(1).replace("<\\/", "</"))


def test_a_large_map_is_strided_and_each_pixel_holds_its_own_numbers(tmp_path):
    rows, cols = 130, 100  # 13000 pixels: every 2nd row and column (65 x 50 = 3250 <= 4096)
    path = tmp_path / "result.h5"
    _result(path, rows, cols, curves=True)
    result = read_map_result(path)
    name = write_explorer(tmp_path, path, result, None, selected_maps(path, ["E_star"]), ["E_star"])
    page = (tmp_path / name).read_text(encoding="utf-8")
    data = _page_data(page)
    stride = math.ceil(math.sqrt(rows * cols / MAX_PIXELS))
    assert stride == 2 and data["cols"] == 50 and len(data["pixels"]) == 65 * 50 <= MAX_PIXELS
    assert f"every {stride}th row and column" in page
    pixel = data["pixels"][3 * 50 + 7]  # row 6, col 14 of the map
    assert "pixel (row 6, col 14)" in html.unescape(pixel["html"])
    e_star = np.linspace(0.3e9, 2e9, cols)[14]
    assert pixel["curves"]["inv"][0][0] == float(f"{e_star * 1e-18 * 1e9:.4g}")  # N -> nN, 4 digits
    assert pixel["curves"]["z"][-1] == 20.0  # m -> nm
    assert f"{e_star * 1e-6:.4g} ± " in html.unescape(pixel["html"])
    assert len(page.encode()) < 16e6, len(page.encode())  # plotly.js (~4.7 MB) and ~2.2 kB per pixel: 12.2 MB


def test_a_result_without_curves_or_groups_says_so(tmp_path):
    path = tmp_path / "old.h5"
    _result(path, 3, 3, curves=False)
    result = read_map_result(path)
    page = (tmp_path / write_explorer(tmp_path, path, result, None, selected_maps(path, ["E_star"]),
                                      ["E_star"])).read_text(encoding="utf-8")
    data = _page_data(page)
    assert "written without the pixels' force curves" in page
    assert all(p["curves"] is None for p in data["pixels"]) and len(data["pixels"]) == 9

"""The force band's words beside the verdict (afmid.report.story.band_words / force_band)."""

from __future__ import annotations

import math

from afmid.report.story import band_words


def _entry(total, separation, estimated=True, value=8.476e-9, error=2.97e-11):
    fraction = (separation / total) ** 2 if estimated else None
    return {"force_band": {"total": total, "separation": separation if estimated else None,
                           "separation_fraction": fraction},
            "separation": {"value": value, "error": error if estimated else 0.0, "estimated": estimated}}


def test_an_estimated_separation_is_named_with_its_share_of_the_variance():
    words = band_words(_entry(0.0116, 0.0112))
    # (0.0112 / 0.0116)^2 = 0.932: 93 % of the variance
    assert words == ("force known to 1.2 % of the peak (1σ), 93 % of its variance from the estimated separation "
                     "8.476 ± 0.030 nm (1σ)")


def test_a_given_separation_is_said_to_be_given():
    words = band_words(_entry(0.02, math.nan, estimated=False, value=8.0e-9))
    assert words.startswith("force known to 2 % of the peak (1σ), the separation 8") and words.endswith(" given")


def test_a_run_without_a_band_gives_no_words():
    assert band_words({"force_band": {"total": None}}) == ""
    assert band_words({}) == ""


def test_the_report_of_a_fit_with_the_separation_estimated_states_its_band(tmp_path):
    """A full fit (bootstrap on, separation estimated) of a small DMT trace: summary.json carries the band and the
    separation with its 1 sigma as the run file holds them, and the verdict box and the terminal say them."""
    import json

    import afmid

    trace = afmid.simulate_trace({
        "cantilever": {"spring_constant": 40.0, "resonance_frequency": 3.0e5, "quality_factor": 250.0,
                       "tip_radius": 10e-9},
        "drive": {"frequency": 3.0e5, "free_amplitude": 10e-9},
        "sample": {"separation": 8.5e-9},
        "simulate": {"model": "dmt", "periods": 30, "seed": 21,
                     "parameters": {"E_star": 2.0e9, "hamaker": 5.0e-20},
                     "noise": {"detector_rms": 2.0e-12}},
    })
    fit = afmid.ForceModel(effects=["dmt"], fit={"bootstrap": 20}).fit(trace)
    text = fit.report(tmp_path / "report")
    run = json.loads((tmp_path / "report" / "summary.json").read_text())["runs"][0]
    band, sep = run["force_band"], run["separation"]
    assert sep["estimated"] is True and sep["unit"] == "m" and abs(sep["value"] - 8.5e-9) < 5 * sep["error"]
    assert 0 < band["separation"] <= band["total"] and 0 < band["separation_fraction"] <= 1
    # the total is the shares in quadrature (afmid.fit.force_band): the arithmetic, to rounding of the file
    shares = [band[k] or 0.0 for k in ("separation", "statistical", "selection", "calibration")]
    assert math.isclose(band["total"], math.sqrt(sum(s * s for s in shares)), rel_tol=1e-9)
    words = band_words(run)
    assert "from the estimated separation" in words
    page = (tmp_path / "report" / "report.html").read_text(encoding="utf-8")
    assert words[1:] in page and words in text

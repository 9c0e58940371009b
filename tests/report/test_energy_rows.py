"""The report's energy rows say what each depends on (afmid/report/energy_rows.py)."""

from __future__ import annotations

from afmid.report.energy_rows import energy_caveat, energy_rows, inverted_force_name


def test_each_row_says_what_it_depends_on():
    energy = {"inverted": 1.0, "energy_balance": 1.0, "model": 1.0, "drive_work": 10.0, "truth": 1.0}
    fitted = energy_rows(energy, calibrated=False)
    assert [key for *_, key, _ in fitted] == ["inverted", "energy_balance", "model", "truth"]
    assert "fitted drive" in fitted[0][0] and all("on the model" in row[1] for row in fitted[:2])
    assert all(sigma is None for *_, sigma in fitted)
    calibrated = energy_rows(dict(energy, drive_calibration_sigma=0.1), calibrated=True)
    assert "calibrated drive" in calibrated[0][0] and all("calibrated drive" in row[1] for row in calibrated[:2])
    assert [sigma for *_, sigma in calibrated] == ["drive_calibration_sigma"] * 2 + [None, None]
    assert "model" not in calibrated[0][1].replace("force model", "")
    assert energy_rows(dict(energy, drive_calibration_sigma=0.0), calibrated=True)[0][3] is None


def test_the_caveat_and_the_name_follow_the_drive():
    assert inverted_force_name(True) != inverted_force_name(False)
    assert "drive.phase" in energy_caveat(False) and "pulls the fitted drive" in energy_caveat(False)
    assert "do not depend on the force model" in energy_caveat(True)

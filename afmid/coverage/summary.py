"""The coverage of many draws, per quantity: how often |z| <= 1 and <= 2 (a 1-sigma error bar that is honest
covers 68.3 % and 95.4 %), with a binomial interval on each fraction, the rms z, the median |z|, the draws
beyond 5 sigma that no flag warned of, and the worst draws with their seeds; and the table ``afmid coverage``
prints.

The interval on a fraction k / n is Wilson's score interval at 95 % (scipy.stats.binomtest): at n = 50 an
honest 68 % is seen anywhere in about [0.55, 0.80], so 60 % is no evidence of a problem at that n.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afmid.coverage.compare import FORCE_CURVE, SEPARATION

#: The fraction of a normal variable within 1 and 2 sigma (erf(1 / sqrt 2), erf(2 / sqrt 2)).
EXPECTED_1 = math.erf(1 / math.sqrt(2))
EXPECTED_2 = math.erf(2 / math.sqrt(2))
#: |z| above this in a number that carries no flag is what the coverage run counts as "confidently wrong".
CONFIDENTLY_WRONG = 5.0
#: Worst draws listed per quantity.
WORST = 3


def binomial_interval(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Wilson's score interval of a fraction k / n at ``level`` (NaN, NaN when n = 0)."""
    if n <= 0:
        return math.nan, math.nan
    from scipy.stats import binomtest

    ci = binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


@dataclass
class QuantitySummary:
    """One quantity over the draws: counts over the draws with a finite z (``n``)."""

    name: str
    unit: str
    n: int  # draws with a finite z
    flagged: int  # of those, with any flag
    missing: int  # fitted draws without a finite z (not determined, no sigma, no truth)
    within_1: int
    within_2: int
    in_ci95: int  # truth inside the reported 95 % interval
    n_ci95: int  # draws with a 95 % interval
    rms_z: float
    median_abs_z: float
    beyond_5_unflagged: int
    worst: list[tuple[int, int, float]] = field(default_factory=list)  # (draw, seed, z), largest |z| first

    def fraction(self, count: int) -> float:
        return count / self.n if self.n else math.nan

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        for key, count in (("within_1", self.within_1), ("within_2", self.within_2)):
            low, high = binomial_interval(count, self.n)
            out[f"{key}_fraction"] = self.fraction(count)
            out[f"{key}_interval95"] = [low, high]
        out["in_ci95_fraction"] = self.in_ci95 / self.n_ci95 if self.n_ci95 else math.nan
        out["worst"] = [{"draw": d, "seed": s, "z": z} for d, s, z in self.worst]
        return out


def quantity_names(draws: list[dict]) -> list[str]:
    """The quantities of the fitted draws: the separation first, the read-outs in order of appearance, the force
    curve last."""
    names: list[str] = []
    for one in draws:
        for name in one.get("numbers", {}):
            if name not in names:
                names.append(name)
    middle = [n for n in names if n not in (SEPARATION, FORCE_CURVE)]
    return [n for n in (SEPARATION,) if n in names] + middle + [n for n in (FORCE_CURVE,) if n in names]


def _with_nan(number: dict) -> dict:
    """A draw's record with null (NaN in a JSON file) read back as NaN."""
    return {k: (math.nan if v is None and k in ("estimate", "sigma", "truth", "z") else v) for k, v in number.items()}


def summarize(draws: list[dict], unflagged_only: bool = False) -> list[QuantitySummary]:
    """Per quantity over the fitted draws (status ok); ``unflagged_only``: over the numbers no flag marked. The
    draws as :func:`afmid.coverage.task.run_draw` returns them, or as read back from the JSON output."""
    fitted = [d for d in draws if d["status"] == "ok"]
    out = []
    for name in quantity_names(fitted):
        rows = [(d["index"], d["seed"], _with_nan(d["numbers"][name])) for d in fitted if name in d["numbers"]]
        if unflagged_only:
            rows = [r for r in rows if not r[2]["flags"]]
        finite = [r for r in rows if math.isfinite(r[2]["z"])]
        z = np.array([r[2]["z"] for r in finite], dtype=float)
        ci = [r[2]["in_ci95"] for r in finite if r[2].get("in_ci95") is not None]
        order = sorted(finite, key=lambda r: -abs(r[2]["z"]))
        unit = rows[0][2]["unit"] if rows else ""
        out.append(QuantitySummary(
            name=name, unit=unit, n=len(finite), flagged=sum(bool(r[2]["flags"]) for r in finite),
            missing=len(fitted) - len(finite) if not unflagged_only else len(rows) - len(finite),
            within_1=int(np.sum(np.abs(z) <= 1)), within_2=int(np.sum(np.abs(z) <= 2)),
            in_ci95=int(sum(ci)), n_ci95=len(ci),
            rms_z=float(np.sqrt(np.mean(z**2))) if z.size else math.nan,
            median_abs_z=float(np.median(np.abs(z))) if z.size else math.nan,
            beyond_5_unflagged=sum(abs(r[2]["z"]) > CONFIDENTLY_WRONG and not r[2]["flags"] for r in finite),
            worst=[(i, s, float(r["z"])) for i, s, r in order[:WORST]]))
    return out


def _fraction_cell(count: int, n: int) -> str:
    if n == 0:
        return "-"
    low, high = binomial_interval(count, n)
    return f"{count / n:.2f} [{low:.2f}, {high:.2f}]"


def table_text(summaries: list[QuantitySummary], title: str) -> str:
    """The coverage table as ``afmid coverage`` prints it (one row per quantity)."""
    width = max([18] + [len(s.name) for s in summaries])
    header = (f"{'quantity':<{width}} {'n':>4} {'flag':>4} {'miss':>4}  {'|z|<=1 (68 %)':<18} {'|z|<=2 (95 %)':<18} "
              f"{'in 95% CI':>9} {'rms z':>6} {'med|z|':>6} {'>5 unfl':>7}  worst (draw/seed: z)")
    lines = [title, header]
    for s in summaries:
        ci = f"{s.in_ci95 / s.n_ci95:.2f}" if s.n_ci95 else "-"
        worst = ", ".join(f"#{d}/{seed}: {z:+.2f}" for d, seed, z in s.worst)
        lines.append(f"{s.name:<{width}} {s.n:>4} {s.flagged:>4} {s.missing:>4}  {_fraction_cell(s.within_1, s.n):<18} "
                     f"{_fraction_cell(s.within_2, s.n):<18} {ci:>9} {s.rms_z:>6.2f} {s.median_abs_z:>6.2f} "
                     f"{s.beyond_5_unflagged:>7}  {worst}")
    return "\n".join(lines)

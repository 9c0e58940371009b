"""The small result types of the Python front door: the parameter table, the force curve, the diagnosis.

Plain containers of a run's values (SI, the unit beside each number); they import nothing heavy, so
``afmid.api`` stays cheap to import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from afmid.quantity_text import format_measurement, format_value

#: The kind of interval of every ``sigma`` in the table: one standard deviation.
ONE_SIGMA = "1 sigma"


def data_frame(table: str, rows: list[dict], columns, index: str):
    """``rows`` as a :class:`pandas.DataFrame` with ``columns``, indexed by ``index``: the tables' ``to_pandas``.
    pandas is optional for afmid: without it, one ImportError naming ``table`` and its ``to_dicts()``."""
    try:
        import pandas
    except ImportError:
        raise ImportError(f"{table}.to_pandas needs pandas, which is not installed (pip install pandas); "
                          f"{table}.to_dicts() gives the same rows as plain dicts") from None
    return pandas.DataFrame(rows, columns=list(columns)).set_index(index)


@dataclass(frozen=True)
class Parameter:
    """One physical read-out of a fit: ``value`` and ``sigma`` (1 sigma) in ``unit`` (SI), its 95 % interval
    ``ci95`` (low, high; NaN where the run has none), the ``effect`` it belongs to and ``flags``: ``model-limited``
    (the fit's error stands above its noise floor: biased beyond its error bar), ``undetermined`` (its term was not
    selected: no value), ``undecided`` (the data cannot decide on a term; in the error bar), ``implausible``
    (outside the range a physical sample can have) and ``estimated`` (a nonlinear parameter from its profile).
    ``sigma_separation_track`` is the part of ``sigma`` (``unit``, in quadrature) a separation track added after its
    joint fit (the run file's ``error_separation_track``): 0 where none was added, NaN for an estimated nonlinear
    parameter (not split)."""

    name: str
    value: float
    sigma: float
    unit: str
    ci95: tuple[float, float] = (math.nan, math.nan)
    effect: str = ""
    flags: tuple[str, ...] = ()
    interval: str = ONE_SIGMA
    sigma_separation_track: float = 0.0

    def __str__(self) -> str:
        if "undetermined" in self.flags:
            text = f"{self.name}: not determined"
        elif math.isfinite(self.sigma):
            text = f"{self.name} = {format_measurement(self.value, self.sigma, self.unit)}"
        else:
            text = f"{self.name} = {format_value(self.value, self.unit, significant=4)} (no error bar)"
        shown = [f for f in self.flags if f != "undetermined"]
        return text + (f" [{', '.join(shown)}]" if shown else "")


def quantity_flags(q: dict) -> tuple[str, ...]:
    """The flags of a run's read-out (a ``quantities`` entry of :class:`afmid.runfile.RunData`)."""
    flags = []
    if q.get("model_limited"):
        flags.append("model-limited")
    if q.get("determined", True) is False:
        flags.append("undetermined")
    if q.get("undecided"):
        flags.append("undecided")
    if not q.get("plausible", True):
        flags.append("implausible")
    return tuple(flags)


class Parameters:
    """A fit's physical parameters as a table: rows of :class:`Parameter` by name (``table["E_star"].value``),
    iterable in the run file's order; :meth:`to_pandas` gives a DataFrame when pandas is installed."""

    COLUMNS = ("name", "value", "sigma", "interval", "ci95_low", "ci95_high", "unit", "effect", "flags",
               "sigma_separation_track")

    def __init__(self, rows: list[Parameter]):
        self._rows = {row.name: row for row in rows}

    @classmethod
    def of_run(cls, run) -> "Parameters":
        """The table of a run (:class:`afmid.runfile.RunData`): its read-outs, then its estimated nonlinear
        parameters (the rest separation ``d``, decay lengths) with their profile's 1 sigma."""
        # Here, not at the top: the fit stage's module loads numba and scipy, and a run is read by then anyway.
        from afmid.fit.uncertainty import TRACK_LEVEL_ERROR

        rows = [Parameter(name, q["value"], q["error"], q["unit"], (q["ci_low"], q["ci_high"]), q["effect"],
                          quantity_flags(q), sigma_separation_track=q.get(TRACK_LEVEL_ERROR, 0.0))
                for name, q in run.quantities.items()]
        rows += [Parameter(name, q["value"], q["error"], q["unit"], flags=("estimated",),
                           sigma_separation_track=math.nan)
                 for name, q in run.nonlinear.items() if name not in run.quantities]
        return cls(rows)

    def __getitem__(self, name: str) -> Parameter:
        try:
            return self._rows[name]
        except KeyError:
            raise KeyError(f"no parameter {name!r}; the fit has {', '.join(self._rows) or 'none'}") from None

    def __contains__(self, name: str) -> bool:
        return name in self._rows

    def __iter__(self):
        return iter(self._rows.values())

    def __len__(self) -> int:
        return len(self._rows)

    def __eq__(self, other) -> bool:
        return isinstance(other, Parameters) and _same_rows(list(self), list(other))

    def names(self) -> list[str]:
        return list(self._rows)

    def to_dicts(self) -> list[dict]:
        """One dict per row with the :attr:`COLUMNS` (SI; flags joined by ``;``)."""
        return [{"name": r.name, "value": r.value, "sigma": r.sigma, "interval": r.interval, "ci95_low": r.ci95[0],
                 "ci95_high": r.ci95[1], "unit": r.unit, "effect": r.effect, "flags": ";".join(r.flags),
                 "sigma_separation_track": r.sigma_separation_track}
                for r in self]

    def to_pandas(self):
        """The table as a :class:`pandas.DataFrame` indexed by name (needs pandas, which afmid does not require)."""
        return data_frame("Parameters", self.to_dicts(), self.COLUMNS, "name")

    def __repr__(self) -> str:
        if not self._rows:
            return "Parameters(none)"
        return "Parameters (± 1σ):\n" + "\n".join(f"  {row}" for row in self)


def _same_rows(a: list[Parameter], b: list[Parameter]) -> bool:
    """Equal rows; NaN equals NaN (an interval the run does not have is NaN in both)."""
    def key(r: Parameter):
        return (r.name, r.unit, r.effect, r.flags, r.interval)

    def numbers(r: Parameter):
        return np.array([r.value, r.sigma, *r.ci95, r.sigma_separation_track], dtype=float)

    return len(a) == len(b) and all(key(x) == key(y) and np.array_equal(numbers(x), numbers(y), equal_nan=True)
                                    for x, y in zip(a, b))


@dataclass(frozen=True)
class ForceCurve:
    """A fit's force against separation over one drive period, averaged over the periods at equal drive phase (SI).

    ``phase`` (rad), ``separation`` z (m), ``force`` the identified model's force on the tip (N, positive =
    repulsive), ``force_sigma`` its 1-sigma band (N: the fit's total relative uncertainty times the peak |force|;
    NaN where the fit computed none), ``force_inverted`` the force from the cantilever equation on the harmonics
    above the noise (N) with ``force_inverted_sigma`` the 1-sigma of that period mean (N), ``approaching`` True
    where the separation decreases, and ``periods`` the number of periods averaged."""

    phase: np.ndarray
    separation: np.ndarray
    force: np.ndarray
    force_sigma: np.ndarray
    force_inverted: np.ndarray
    force_inverted_sigma: np.ndarray
    approaching: np.ndarray
    periods: int

    def __repr__(self) -> str:
        return (f"ForceCurve({self.phase.size} phase points, {self.periods} periods; separation "
                f"{format_value(float(np.min(self.separation)), 'm')} to {format_value(float(np.max(self.separation)), 'm')}, "
                f"peak force {format_value(float(np.max(self.force)), 'N')})")


@dataclass(frozen=True, eq=False)
class SeparationTrackTable:
    """A separation track (``fit.separation_track``: one record cut into blocks of whole drive periods, one force law,
    a rest separation per block), SI as the run file's ``/model/separation_track`` holds it: per block its middle
    ``time`` (s, from the record's first sample), its rest ``separation`` d and that d's ``sigma`` (m, 1 sigma), its
    samples ``first_sample`` to ``stop_sample`` (one past its last) of the checked record; the track's
    ``bandwidth`` (Hz), ``within_block`` (how d moved inside a block: constant, mean_force or rows) and, when it
    moved, ``period_offsets``: per block each period's d relative to the block's (m)."""

    time: np.ndarray
    separation: np.ndarray
    sigma: np.ndarray
    first_sample: np.ndarray
    stop_sample: np.ndarray
    bandwidth: float
    within_block: str
    period_offsets: tuple[np.ndarray, ...] | None = None
    interval: str = ONE_SIGMA

    #: The unit of each column (and of the bandwidth), SI.
    UNITS: ClassVar[dict[str, str]] = {"time": "s", "separation": "m", "sigma": "m", "first_sample": "1",
                                       "stop_sample": "1", "bandwidth": "Hz", "period_offsets": "m"}
    COLUMNS: ClassVar[tuple[str, ...]] = ("block", "time", "separation", "sigma", "interval", "first_sample",
                                          "stop_sample")

    @classmethod
    def of_run(cls, run) -> "SeparationTrackTable | None":
        """The track of a run record (:attr:`afmid.runfile.RunData.separation_track`); None for a run without."""
        track = run.separation_track
        if track is None:
            return None
        offsets = track["period_offsets"]
        return cls(track["time"], track["separation"], track["separation_error"], track["first_sample"],
                   track["stop_sample"], float(track["bandwidth"]), track["within_block"],
                   None if offsets is None else tuple(offsets))

    def __len__(self) -> int:
        return len(self.separation)

    def to_dicts(self) -> list[dict]:
        """One dict per block with the :attr:`COLUMNS` (SI, :attr:`UNITS`)."""
        return [{"block": i, "time": float(t), "separation": float(d), "sigma": float(s), "interval": self.interval,
                 "first_sample": int(a), "stop_sample": int(b)}
                for i, (t, d, s, a, b) in enumerate(zip(self.time, self.separation, self.sigma, self.first_sample,
                                                        self.stop_sample))]

    def to_pandas(self):
        """The blocks as a :class:`pandas.DataFrame` indexed by block (needs pandas, which afmid does not require)."""
        return data_frame("SeparationTrackTable", self.to_dicts(), self.COLUMNS, "block")

    def text(self) -> str:
        """The track as ``afmid fit`` prints it: one line per block, its time in ms and d ± 1σ in nm."""
        lines = [f"separation track at {self.bandwidth:g} Hz ({len(self)} blocks, one force law):"]
        for t, d, s in zip(self.time, self.separation, self.sigma):
            lines.append(f"  t = {t * 1e3:8.3f} ms: d = {d * 1e9:.3f} ± {s * 1e9:.3f} nm (1σ)")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.text()


@dataclass
class Diagnosis:
    """Where a fit fails and which catalog effect is missing (:func:`afmid.diagnosis.diagnose.suggest`).

    ``missing_effect``: the data show physics the model lacks; ``suggestions``: the accepted effects, best first
    (names for :meth:`afmid.api.ForceModel.add`); ``verdict`` and ``description`` in words; ``details`` the whole
    answer (every candidate tried, its ΔBIC, error after, fitted values)."""

    missing_effect: bool
    suggestions: list[str]
    verdict: str
    description: str
    details: dict = field(repr=False)

    @classmethod
    def of(cls, answer: dict) -> "Diagnosis":
        diagnosis = answer.get("diagnosis") or {}
        return cls(bool(answer.get("missing_effect", False)), [s["effect"] for s in answer.get("suggestions", [])],
                   diagnosis.get("verdict") or answer.get("note", ""), diagnosis.get("description", ""), answer)

    @property
    def suggested(self) -> str | None:
        """The best suggested effect, or None."""
        return self.suggestions[0] if self.suggestions else None

    def text(self) -> str:
        lines = [self.verdict or ("missing effect" if self.missing_effect else "no effect is missing")]
        if self.description:
            lines.append(f"residual: {self.description}")
        lines += [f"suggested: {s['effect']}: {s['evidence']}" for s in self.details.get("suggestions", [])]
        return "\n".join(lines)

    def print(self) -> None:
        print(self.text())

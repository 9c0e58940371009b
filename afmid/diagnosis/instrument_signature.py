"""Recognising an undeclared instrument in a fit's residual: a detector low-pass or a second eigenmode.

A detector low-pass G (not declared in ``data.detector``) leaves, at drive harmonics n >= 2, a model-free
force G_n F_n instead of F_n: the residual against the model force M_n ~ F_n is (G_n - 1) M_n, a phase lag
growing with n (-i sqrt(2) n f / f_c for a 2-pole Butterworth) and a roll-off (-n^2 (f / f_c)^2). A second
flexural mode (not declared in ``cantilever.higher_modes``) adds H_2 / H_1 (n) M_n: a resonance at the harmonic
f_2 / f. :func:`screen` fits both shapes to the per-harmonic residual of the fit (weighted by its noise, the
scale fitted by least squares, f_2 on a grid); only when one explains most of a significant residual are
candidate instruments refitted (:func:`check`): a short search over the bandwidth or f_2 by refits with the
candidate declared (minimising the cross-validated error), kept when it lowers the BIC by ``bic_evidence`` and
brings the cross-validated error to the noise level or removes 80 % of its excess over it. The diagnosis
(:mod:`afmid.diagnosis.diagnose`, only when no sample effect explains the data, or when the misfit is not significant
but the low-pass shape stands out: :func:`detector_stands_out`) then names the instrument instead of a sample effect.

The refits assume, for the mode, the modal stiffness fitted by the screen and Q_2 = :data:`MODE_Q_RATIO` Q_1
(Q_2 matters only within f_2 / Q_2 of the resonance); for the detector a 2-pole Butterworth or a first-order
low-pass, whichever fits better. What is reported is the frequency (and the family); the user declares the
instrument from its calibration.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from afmid.preprocess.instrument import Detector, Instrument, Mode

log = logging.getLogger(__name__)

#: The screen fires when a shape removes at least this much chi-square (whitened units) ...
SCREEN_CHI2 = 25.0
#: ... for the low-pass shape (2 real parameters): this much. Under the null (no detector) the removed chi-square
#: is at most chi2(2): measured on 12 clean traces of an ideal instrument, d unknown (hidden_clean variants a-c,
#: seeds 61-363), mean 1.30 (chi2(2): 2; the fit's own force law absorbs part of the shape), largest 5.8; the
#: scale's upper 95 % bound from 12 traces is 1.13, and chi2(2) exceeds 13.8 with probability 1e-3:
#: 1.13 x 13.8 = 15.6. A screen that fires only opens the refits: what names a detector is their BIC and error
#: (:func:`check`), which named none of the same clean traces with the screen forced open (scripts/
#: instrument_null.py). The second-mode shape keeps SCREEN_CHI2: its statistic is a maximum over ~3000 trial f_2
#: (3.9-12.6 on the same traces), not a chi2(2).
DETECTOR_SCREEN_CHI2 = 16.0
#: ... and this fraction of the residual chi-square above its expectation.
SCREEN_FRACTION = 0.3
#: Q_2 / Q_1 assumed by the refits of a second-mode candidate.
MODE_Q_RATIO = 3.0
#: Refits per golden-section search (over log bandwidth or f_2).
SEARCH_REFITS = 7
#: ... or leave at most this fraction of the error in excess of the floor (the candidate's f_2, k_2 come from a
#: short search: near a harmonic a few % off leave part of a large residual).
EXCESS_LEFT = 0.2
#: A candidate that leaves at most this fraction of the excess error is named when it beats every tried sample
#: effect (a sample effect may be missing as well: the verdict says a residual remains).
MOST_LEFT = 0.5
#: Refits of the final joint (f_2, k_2) polish of a second-mode candidate (Nelder-Mead).
POLISH_REFITS = 20
#: The refitted candidate must bring the cross-validated error within this factor of its noise floor.
EXPLAINS_FACTOR = 1.3


@dataclass
class Screen:
    """The residual shapes' fits: chi-square removed and the parameters they suggest."""

    chi2: float  # residual chi-square over harmonics 2..K (whitened)
    dof: int
    detector_chi2: float  # chi-square removed by the low-pass shape
    detector_bandwidth: float  # Hz, from its phase-lag coefficient (2-pole Butterworth)
    mode_chi2: float  # chi-square removed by the best second-mode shape
    mode_frequency: float  # Hz
    mode_stiffness: float  # N/m

    def fires(self, removed: float, threshold: float = SCREEN_CHI2) -> bool:
        excess = max(self.chi2 - self.dof, 0.0)
        return removed >= threshold and removed >= SCREEN_FRACTION * excess

    @property
    def detector_fires(self) -> bool:
        return self.fires(self.detector_chi2, DETECTOR_SCREEN_CHI2)

    @property
    def mode_fires(self) -> bool:
        return self.fires(self.mode_chi2) and math.isfinite(self.mode_frequency)


@dataclass
class Finding:
    kind: str  # "second_eigenmode" or "detector_bandwidth"
    instrument: Instrument  # the candidate that explains the residual
    frequency: float  # Hz: f_2 or the bandwidth
    delta_bic: float
    error_after: float
    noise_floor_after: float
    explains: bool = True  # the error falls to the noise level (else: most of its excess removed)
    evidence: "ModeEvidence | None" = None  # a second mode's spectral peak and beam-theory consistency
    #: False for a second mode the screen saw but that was not searched (:func:`lever_mode_within_reach`): its
    #: frequency and stiffness are the screen's (the residual's shape fitted with the force law held fixed),
    #: ``screen_share`` the part of the harmonics' residual chi-square that shape takes; no refit, so
    #: ``delta_bic``, ``error_after`` and ``noise_floor_after`` are NaN.
    searched: bool = True
    screen_share: float = math.nan

    @property
    def supported(self) -> bool:
        """A second mode is named only with a peak in the spectrum at f_2 and a lever's f_2 / f_1 and k_2 / k_1."""
        return self.evidence is None or self.evidence.supports

    @property
    def text(self) -> str:
        if not self.searched:
            return (f"the residual has the shape of a second eigenmode near {_hz(self.frequency)} (with the force "
                    f"law held fixed, that shape takes {100 * self.screen_share:.0f} % of the harmonics' residual "
                    f"chi-square) but no mode was searched, as no lever's second mode lies within "
                    f"{MODE_SEARCH_REACH:g} drive frequency of it: {self.evidence.against()}")
        if not self.supported:
            return (f"a second eigenmode near {_hz(self.frequency)} would fit the residual (ΔBIC "
                    f"{self.delta_bic:.0f}) but is not suggested: {self.evidence.against()}")
        more = "" if self.explains else "; a residual remains: declare it and diagnose again"
        return self._text() + more

    def _text(self) -> str:
        if self.kind == "second_eigenmode":
            return (f"instrument: second eigenmode near {_hz(self.frequency)} (not a sample effect; declare "
                    "cantilever.higher_modes from the lever's calibration)")
        det = self.instrument.detector
        shape = "2-pole" if det.order == 2 else f"{det.order}-pole"
        return (f"instrument: detector bandwidth near {_hz(self.frequency)} (a {shape} low-pass lags and "
                "attenuates the harmonics; not a sample effect; declare data.detector)")

    def record(self) -> dict:
        out = {"kind": self.kind, "frequency": self.frequency, "instrument": self.instrument.describe(),
               "delta_bic": self.delta_bic, "error_after": self.error_after,
               "noise_floor_after": self.noise_floor_after, "searched": self.searched, "text": self.text}
        if not self.searched:
            out["screen_share"] = self.screen_share
        if self.evidence is not None:
            out["evidence"] = dataclasses.asdict(self.evidence)
        return out


def _hz(f: float) -> str:
    return f"{f / 1e6:.2g} MHz" if f >= 1e6 else f"{f / 1e3:.3g} kHz"


#: Beam theory of a uniform rectangular lever: f_2 / f_1 = (4.694 / 1.875)^2 = 6.27 and, with equal modal masses,
#: k_2 / k_1 = (f_2 / f_1)^2 = 39.3. A tip mass, a taper or a V shape moves f_2 / f_1 within this range (the accepted
#: tolerance for real levers; the diagnosis tests' levers: 6.27 and 5.6).
MODE_RATIO_RANGE = (5.5, 7.0)
#: ... and k_2 / (k_1 (f_2 / f_1)^2) (the ratio of the modal masses) within this factor of 1.
MODAL_MASS_FACTOR = 2.0
#: How far from the screen's f_2 the mode search can end, in drive frequencies: its first golden section spans
#: +-0.5 f around it, the zoom 0.05 f more, the joint polish moves by steps of 0.02 f (POLISH_REFITS of them at most).
#: When no frequency within this reach is a lever's (MODE_RATIO_RANGE), whatever the search ends on is refused by
#: :attr:`ModeEvidence.beam_consistent`: the search is not run (on the HSDC record, f2/f1 3.4: ~20 refits in each of
#: two passes and 5 separation searches, half the report's time).
MODE_SEARCH_REACH = 1.0
#: The spectrum: Hann-windowed segments of this many drive periods, half overlapping (a resolution of f / 16).
SPECTRUM_PERIODS = 16
#: A peak counts when a noise spectrum exceeds it with this probability among the bins searched (Bonferroni).
PEAK_FALSE_ALARM = 1e-3
#: The peak is searched within this fraction of f_2 (the candidate's f_2 comes from a short search), the floor
#: over the bins within FLOOR_SPAN of f_2 outside that window; bins within HARMONIC_GUARD bins of a drive harmonic
#: are left out of both (the lines and their window leakage).
PEAK_WINDOW = 0.05
FLOOR_SPAN = 0.25
HARMONIC_GUARD = 3
#: A second mode between harmonics n and n + 1 amplifies both: :func:`harmonic_bump` at least this much counts as
#: a peak among the drive harmonics (measured: 32 and 20 for the diagnosis tests' modes at 6.27 f and 5.6 f,
#: 0.6-1.1 at the same places without a mode, 0.43 on the Bruker HSDC record at its phantom 3.77 f; plain
#: contact spectra stay below 9 anywhere, RESONANCE_BUMP's note).
HARMONIC_BUMP_EVIDENCE = 10.0


@dataclass
class ModeEvidence:
    """What speaks for a second mode at ``frequency`` beyond the residual: a spectral peak, beam theory."""

    frequency: float  # Hz
    ratio: float  # f_2 / f_1
    stiffness_ratio: float  # k_2 / k_1
    peak: float  # largest spectral density within PEAK_WINDOW of f_2, off the harmonics (m^2/Hz)
    floor: float  # median spectral density around it (m^2/Hz)
    needed: float  # peak / floor that noise exceeds with PEAK_FALSE_ALARM
    segments: int  # independent spectral segments averaged
    bump: float = math.nan  # the drive harmonics bracketing f_2 against those two away (harmonic_bump)

    @property
    def spectral(self) -> bool:
        """A peak at f_2: off the harmonics (the mode's own, thermally or irregularly driven, response) or among
        them (the impacts drive it at the harmonics on either side, which stand out of their neighbours)."""
        off_harmonics = self.floor > 0 and self.peak >= self.needed * self.floor
        return off_harmonics or self.bump >= HARMONIC_BUMP_EVIDENCE

    @property
    def beam_consistent(self) -> bool:
        masses = self.stiffness_ratio / self.ratio**2
        return (MODE_RATIO_RANGE[0] <= self.ratio <= MODE_RATIO_RANGE[1]
                and 1 / MODAL_MASS_FACTOR <= masses <= MODAL_MASS_FACTOR)

    @property
    def supports(self) -> bool:
        return self.spectral and self.beam_consistent

    def against(self) -> str:
        """Why it is not a lever's second mode (one clause per missing piece of evidence)."""
        parts = []
        if not self.spectral:
            lines = (f"; the drive harmonics around it stand {self.bump:.2g}x out of their neighbours, a resonance "
                     f"{HARMONIC_BUMP_EVIDENCE:g}x" if math.isfinite(self.bump) else "")
            if self.segments == 0:  # spectral_peak found no bins to judge: none off the harmonics, or too short
                off = (f"off the drive harmonics the spectrum has no bins to judge within {100 * PEAK_WINDOW:g} % of "
                       "it")
            else:
                off = (f"off the drive harmonics, the largest within {100 * PEAK_WINDOW:g} % of it is "
                       f"{self.peak / max(self.floor, 1e-300):.3g}x the local floor of {math.sqrt(self.floor):.2g} "
                       f"m/sqrt(Hz), a peak needs {self.needed:.2g}x")
            parts.append(f"the spectrum shows no peak there ({off}{lines})")
        if not self.beam_consistent:
            parts.append(f"f2/f1 = {self.ratio:.3g} and k2/k1 = {self.stiffness_ratio:.3g} are not a lever's "
                         f"(beam theory: f2/f1 {MODE_RATIO_RANGE[0]:g}-{MODE_RATIO_RANGE[1]:g}, 6.27 for a "
                         f"rectangular lever, k2/k1 ~ (f2/f1)^2 = {self.ratio**2:.3g})")
        return " and ".join(parts) + ": declaring it would turn a misfit into plausible-looking numbers"


def mode_evidence(trace, drive_frequency: float, mode: Mode) -> ModeEvidence:
    """The spectral and beam-theory evidence for ``mode`` (a candidate second mode) in ``trace``'s deflection."""
    cantilever = trace.cantilever
    ratio = mode.resonance_frequency / cantilever.resonance_frequency
    stiffness = mode.spring_constant / cantilever.spring_constant
    peak, floor, needed, segments = spectral_peak(trace.deflection, trace.sample_rate, drive_frequency,
                                                  mode.resonance_frequency)
    from afmid.io.trace_analysis import DETECT_SIGMA, analyse

    analysis = analyse(trace.deflection, cycles_per_sample=drive_frequency / trace.sample_rate)
    bump = math.nan if analysis is None else harmonic_bump(
        analysis.harmonic_amplitudes(), DETECT_SIGMA * analysis.harmonic_sigma(), analysis.above_noise,
        mode.resonance_frequency / drive_frequency)
    return ModeEvidence(mode.resonance_frequency, ratio, stiffness, peak, floor, needed, segments, bump)


def harmonic_bump(amplitudes: np.ndarray, floor: np.ndarray, above_noise: list[int], at: float) -> float:
    """The product, for the two drive harmonics n, n + 1 bracketing ``at`` (f_2 / f), of each one's amplitude over
    the geometric mean of the harmonics two away (the statistic of
    :func:`afmid.preprocess.instrument.harmonic_resonance` at f_2), those taken at least at their noise ``floor``
    (a harmonic lost in the noise can only lower the product); NaN unless n and n + 1 stand above the noise."""
    n = int(math.floor(at))
    A = np.asarray(amplitudes, dtype=float)
    if n < 3 or n + 3 >= A.size or not {n, n + 1} <= set(above_noise):
        return math.nan
    low = np.maximum(A, np.asarray(floor, dtype=float))
    return float(np.prod([A[k] / math.sqrt(low[k - 2] * low[k + 2]) for k in (n, n + 1)]))


def spectral_peak(x: np.ndarray, sample_rate: float, drive_frequency: float, frequency: float
                  ) -> tuple[float, float, float, int]:
    """(peak, floor, needed ratio, segments): the one-sided spectral density of ``x`` (Welch: Hann segments of
    :data:`SPECTRUM_PERIODS` drive periods, half overlapping) at its largest within :data:`PEAK_WINDOW` of
    ``frequency`` and its median within :data:`FLOOR_SPAN` outside that window, bins near drive harmonics left
    out; ``needed`` the ratio a noise bin exceeds with :data:`PEAK_FALSE_ALARM` shared among the searched bins
    (an average of m independent segments is Gamma(m, 1/m) distributed). Zeros when the record is too short."""
    from scipy.special import gammainccinv

    length = int(round(SPECTRUM_PERIODS * sample_rate / drive_frequency))
    x = np.asarray(x, dtype=float) - float(np.mean(x))
    if x.size < 2 * length or length < 16:
        return 0.0, 0.0, math.inf, 0
    window = np.hanning(length)
    starts = range(0, x.size - length + 1, length // 2)
    power = np.zeros(length // 2 + 1)
    for start in starts:
        segment = x[start:start + length]
        segment = segment - segment.mean()
        power += np.abs(np.fft.rfft(segment * window)) ** 2
    density = power * 2.0 / (len(starts) * sample_rate * float(window @ window))
    bins = np.fft.rfftfreq(length, 1.0 / sample_rate)
    step = bins[1]
    harmonic = np.abs(bins / drive_frequency - np.round(bins / drive_frequency)) * drive_frequency
    off = harmonic > HARMONIC_GUARD * step
    searched = off & (np.abs(bins - frequency) <= max(PEAK_WINDOW * frequency, step))
    around = off & ~searched & (np.abs(bins - frequency) <= FLOOR_SPAN * frequency)
    if not searched.any() or around.sum() < 8:
        return 0.0, 0.0, math.inf, 0
    independent = max(x.size // length, 1)  # half-overlapping Hann segments add little beyond these
    needed = float(gammainccinv(independent, PEAK_FALSE_ALARM / int(searched.sum()))) / independent
    return float(density[searched].max()), float(np.median(density[around])), needed, independent


def harmonic_residual(result) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(harmonics n, residual R_n, model M_n, sigma_n) of a FitResult, complex per harmonic n >= 1.

    R is the window mean of the weak-form model-free force minus the model force, M the model's, sigma the
    noise of a window mean (the rows' predicted noise / sqrt(windows)); a harmonic's cos and sin rows form
    a - i b.
    """
    prep, system, coef = result.prep, result.system, result.coef
    p = system.theta.shape[2]
    free = (prep.Y - np.einsum("wkm,m->wk", prep.nuisance, coef[p:])).mean(axis=0)
    model = np.einsum("wkm,m->wk", system.theta, coef[:p]).mean(axis=0)
    sigma = prep.row_sigma / math.sqrt(prep.Y.shape[0])
    K = (free.size - 1) // 2
    n = np.arange(1, K + 1)

    def pairs(v):
        return v[1::2] - 1j * v[2::2]

    return n, pairs(free - model), pairs(model), 0.5 * (sigma[1::2] + sigma[2::2])


def _removed(R: np.ndarray, basis: list[np.ndarray], sigma: np.ndarray) -> tuple[float, np.ndarray]:
    """Chi-square removed from R by the best real combination of complex ``basis`` vectors (weighted)."""
    A = np.stack([np.concatenate([b.real, b.imag]) / np.concatenate([sigma, sigma]) for b in basis], axis=1)
    y = np.concatenate([R.real, R.imag]) / np.concatenate([sigma, sigma])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(y @ y - np.sum((y - A @ coef) ** 2)), coef


def _harmonics_above_first(result):
    n, R, M, sigma = harmonic_residual(result)
    keep = n >= 2
    return n[keep], R[keep], M[keep], np.maximum(sigma[keep], 1e-300)


def _detector_shape(n, R, M, sigma, drive_frequency: float) -> tuple[float, float, float]:
    """(residual chi-square, chi-square the low-pass shape removes, the bandwidth its lag suggests, Hz)."""
    chi2 = float(np.sum(np.abs(R) ** 2 / sigma**2))  # real and imaginary parts
    det_removed, (a, _b) = _removed(R, [-1j * n * M, -(n**2) * M], sigma)
    # 2-pole Butterworth: G - 1 ~ -i sqrt(2) n f / f_c - n^2 (f / f_c)^2.
    return chi2, det_removed, (math.sqrt(2.0) * drive_frequency / a if a > 0 else math.inf)


def detector_stands_out(result, drive_frequency: float, declared: Instrument) -> bool:
    """The low-pass shape alone passes the screen in the residual of ``result`` (no detector declared).

    The diagnosis asks this also when the fit's overall misfit is not significant: a detector at 10 f lags the
    harmonics and the force law, the separation and the drive phase absorb most of it, so the whole chi-square
    (~120 degrees of freedom) may stay within its noise while the shape (2 parameters) stands out (measured: an
    undeclared 2-pole detector at 10 f, reduced chi-square 0.985, the shape removes 17 units, force error 16.5 %).
    """
    if declared.detector is not None:
        return False
    n, R, M, sigma = _harmonics_above_first(result)
    chi2, removed, _ = _detector_shape(n, R, M, sigma, drive_frequency)
    return Screen(chi2, int(2 * n.size), removed, math.nan, 0.0, math.nan, math.nan).detector_fires


def screen(result, cantilever, drive_frequency: float) -> Screen:
    """Fit the low-pass and the second-mode shapes to the residual of ``result`` (harmonics 2..K)."""
    n, R, M, sigma = _harmonics_above_first(result)
    chi2, det_removed, bandwidth = _detector_shape(n, R, M, sigma, drive_frequency)
    f0, k1, Q1 = cantilever.resonance_frequency, cantilever.spring_constant, cantilever.quality_factor
    r = n * drive_frequency / f0
    h1_inverse = 1.0 - r**2 + 1j * r / Q1  # k1 / H_1 ... divided by k1
    best = (0.0, math.nan, math.nan)
    for ratio in np.arange(2.2, n[-1] + 0.5, 0.02):  # f_2 / f
        f2 = ratio * drive_frequency
        q = n / ratio
        shape = h1_inverse / (1.0 - q**2 + 1j * q / (MODE_Q_RATIO * Q1))  # (H_2 / H_1) * k2 / k1
        removed, (scale,) = _removed(R, [shape * M], sigma)
        if scale > 0 and removed > best[0]:
            best = (removed, f2, k1 / scale)
    return Screen(chi2, int(2 * n.size), det_removed, bandwidth, best[0], best[1], best[2])


def lever_mode_within_reach(mode_frequency: float, resonance_frequency: float, drive_frequency: float) -> bool:
    """Whether the mode search started at ``mode_frequency`` (Hz, the screen's f_2) can end on a lever's second mode:
    some f_2 within :data:`MODE_SEARCH_REACH` drive frequencies of it has f_2 / f_1 in :data:`MODE_RATIO_RANGE`
    (f_1 = ``resonance_frequency``). Outside, :class:`ModeEvidence` refuses whatever the search finds."""
    reach = MODE_SEARCH_REACH * drive_frequency
    low, high = (mode_frequency - reach) / resonance_frequency, (mode_frequency + reach) / resonance_frequency
    return high >= MODE_RATIO_RANGE[0] and low <= MODE_RATIO_RANGE[1]


def unsearched_mode(screened: Screen, trace, drive_frequency: float) -> Finding | None:
    """The second mode the screen fitted to the residual when it fired but the search was not run (no lever's mode
    within its reach, :func:`lever_mode_within_reach`), with its evidence (:func:`mode_evidence`) saying why it is
    not a lever's; None otherwise."""
    cantilever = trace.cantilever
    if not screened.mode_fires or lever_mode_within_reach(screened.mode_frequency, cantilever.resonance_frequency,
                                                         drive_frequency):
        return None
    mode = Mode(float(screened.mode_frequency), MODE_Q_RATIO * cantilever.quality_factor,
                float(screened.mode_stiffness))
    return Finding("second_eigenmode", Instrument(None, (mode,)), mode.resonance_frequency, math.nan, math.nan,
                   math.nan, explains=False, evidence=mode_evidence(trace, drive_frequency, mode), searched=False,
                   screen_share=screened.mode_chi2 / max(screened.chi2, 1e-300))


def _golden(objective, lo: float, hi: float, evaluations: int) -> tuple[float, float]:
    """Minimum of ``objective`` on [lo, hi] by golden-section search with ``evaluations`` calls."""
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = objective(c), objective(d)
    for _ in range(max(evaluations - 2, 0)):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = objective(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = objective(d)
    return (c, fc) if fc < fd else (d, fd)


def _best_seen(cache: dict, part: str) -> Instrument:
    """The refitted instrument with the lowest cross-validated error among those whose ``part`` was searched."""
    searched = [(float(r.cv_error), i) for i, r in cache.items()
                if r is not None and getattr(i, part) and (part != "higher_modes" or len(i.higher_modes) > 0)]
    return min(searched, key=lambda item: item[0])[1]


@dataclass(frozen=True)
class _RefitNumbers:
    """What the instrument search reads of one refit. Not the fit itself: each refit holds its own preparation of
    the record (the instrument undone per harmonic), and the ~100 refits of a search on a 5e5-sample record kept
    alive together held ~5 GB."""

    cv_error: float
    cv_error_noise_floor: float
    bic: float  # the selected model's BIC
    n_rows: int

    @classmethod
    def of(cls, result) -> "_RefitNumbers":
        return cls(float(result.cv_error), float(result.cv_error_noise_floor), float(result.selection.best.bic),
                   int(result.system.n_rows))


def check(base_result, screened: Screen, cantilever, drive_frequency: float, declared: Instrument, refit,
          base_bic: float, bic_evidence: float, searched: list | None = None) -> Finding | None:
    """An undeclared instrument that explains the residual of ``base_result``, or None.

    ``screened``: :func:`screen` of ``base_result``. ``refit(instrument)`` -> FitResult of the same model on the
    trace prepared with ``instrument`` declared; ``declared`` is what the config declares already (its parts are
    not searched again). ``searched`` (a list) receives the best candidate instrument of each kind the screen let
    through, named or not.
    """
    from afmid.diagnosis.forked_work import in_order

    s = screened
    cache: dict = {}

    def fitted(instrument: Instrument, seen: dict):
        """The refit's numbers with ``instrument`` declared, from ``seen`` (the search's refits) when made before."""
        key = instrument
        if key not in seen:
            try:
                seen[key] = _RefitNumbers.of(refit(instrument))
            except Exception as exc:  # a candidate that cannot be fitted is no candidate
                log.debug("instrument refit with %s failed: %s", instrument.describe(), exc)
                seen[key] = None
        return seen[key]

    def error_of(instrument: Instrument, seen: dict) -> float:
        """The search's objective: the cross-validated force error (not the BIC: each candidate reweights the
        rows by its own noise gains, so BICs of different candidates are not comparable within a search)."""
        result = fitted(instrument, seen)
        return math.inf if result is None or not math.isfinite(result.cv_error) else float(result.cv_error)

    top = drive_frequency * (base_result.prep.blocks.K + 0.5)

    def detector_search(seen: dict) -> tuple:
        # The fit absorbs much of a lag into a wrong force law, so the screen's bandwidth is no guide: search
        # from 1.5 f to the highest harmonic (a 2-pole Butterworth, the usual anti-alias filter).
        def make(log_bw):
            return Instrument(Detector(float(10**log_bw), "butterworth", 2), declared.higher_modes)
        _golden(lambda v: error_of(make(v), seen), math.log10(1.5 * drive_frequency), math.log10(top),
                SEARCH_REFITS + 2)
        best_detector = _best_seen(seen, "detector")
        return ("detector_bandwidth", best_detector, best_detector.detector.bandwidth), seen

    def mode_search(seen: dict) -> tuple:
        f0, k1 = cantilever.resonance_frequency, cantilever.spring_constant

        def make_mode(f2, k2):
            mode = Mode(float(f2), MODE_Q_RATIO * cantilever.quality_factor, float(k2))
            return Instrument(declared.detector, declared.higher_modes + (mode,))
        # f_2 first with the stiffness of equal modal masses (k_2 = k_1 (f_2 / f_1)^2, a uniform lever), then
        # the stiffness: the screen's stiffness comes from a biased model force.
        # The BIC is sharp near a harmonic (H_2 there moves by ~25 % per 1 % of f_2): the best refit seen (the
        # screen's estimate and three searches) is kept, not the last search's end point.
        span = 0.5 * drive_frequency
        if math.isfinite(s.mode_stiffness):
            error_of(make_mode(s.mode_frequency, s.mode_stiffness), seen)  # the screen's own estimate
        _golden(lambda f: error_of(make_mode(f, k1 * (f / f0) ** 2), seen), s.mode_frequency - span,
                s.mode_frequency + span, SEARCH_REFITS)
        mode = _best_seen(seen, "higher_modes").higher_modes[-1]
        k_guess = math.log10(mode.spring_constant)
        _golden(lambda v: error_of(make_mode(mode.resonance_frequency, 10**v), seen), k_guess - 0.5, k_guess + 0.5,
                SEARCH_REFITS)
        mode = _best_seen(seen, "higher_modes").higher_modes[-1]
        _golden(lambda f: error_of(make_mode(f, mode.spring_constant), seen),
                mode.resonance_frequency - 0.05 * drive_frequency, mode.resonance_frequency + 0.05 * drive_frequency,
                SEARCH_REFITS - 2)
        # Then both together from the best seen (the valley runs along k_2 (1 - (n / r_2)^2) = const).
        from scipy.optimize import minimize

        mode = _best_seen(seen, "higher_modes").higher_modes[-1]
        start = np.array([mode.resonance_frequency / drive_frequency, math.log10(mode.spring_constant)])
        minimize(lambda p: error_of(make_mode(p[0] * drive_frequency, 10 ** p[1]), seen), start,
                 method="Nelder-Mead",
                 options={"maxfev": POLISH_REFITS, "initial_simplex": [start, start + [0.02, 0], start + [0, 0.03]]})
        best_mode = _best_seen(seen, "higher_modes")
        return ("second_eigenmode", best_mode, best_mode.higher_modes[-1].resonance_frequency), seen

    searches = []
    if declared.detector is None and s.detector_fires:
        searches.append(detector_search)
    if s.mode_fires and lever_mode_within_reach(s.mode_frequency, cantilever.resonance_frequency, drive_frequency):
        searches.append(mode_search)
    # The two searches refit different instruments (a detector, a mode): apart, each with its own refits, on two
    # cores (afmid.diagnosis.forked_work). Not when modes are declared: a detector candidate then carries them, and
    # the mode search's best seen (in order, after the detector's refits) may be one of those.
    apart = not declared.higher_modes
    found = in_order(lambda search: search({} if apart else cache), searches, None if apart else 1)
    candidates = []
    for candidate, seen in found:
        cache.update(seen)
        candidates.append(candidate)
    if searched is not None:
        searched.extend(instrument for _, instrument, _ in candidates)
    best = None
    for kind, instrument, frequency in candidates:
        result = fitted(instrument, cache)
        if result is None:
            continue
        delta = result.bic + 2.0 * math.log(max(result.n_rows, 2)) - base_bic
        floor = result.cv_error_noise_floor
        excess_before = math.sqrt(max(base_result.cv_error**2 - floor**2, 0.0))
        excess_after = math.sqrt(max(result.cv_error**2 - floor**2, 0.0))
        explains = result.cv_error <= EXPLAINS_FACTOR * floor or excess_after <= EXCESS_LEFT * excess_before
        most = excess_after <= MOST_LEFT * excess_before
        log.debug("instrument candidate %s: ΔBIC %.0f, error %.3g (floor %.3g)", instrument.describe(), delta,
                 result.cv_error, result.cv_error_noise_floor)
        if not (delta <= -bic_evidence and (explains or most)):
            continue
        evidence = None
        if kind == "second_eigenmode":
            evidence = mode_evidence(base_result.prep.trace, drive_frequency, instrument.higher_modes[-1])
            log.debug("second-mode evidence: %s", evidence)
        found = Finding(kind, instrument, frequency, delta, result.cv_error, result.cv_error_noise_floor, explains,
                        evidence)
        # a supported candidate before any unsupported one; then the lower BIC
        if best is None or (found.supported, -delta) > (best.supported, -best.delta_bic):
            best = found
    return best


def undeclared(config, prepared, base_result, base_bic: float, trials: list, fit_quick, bic_evidence: float,
               bic_distinct: float, separation_free: bool = False) -> Finding | None:
    """The diagnosis's hook: an undeclared detector or eigenmode that explains the residual of ``base_result``
    (the fit of ``config`` on ``prepared``), or None.

    ``trials`` are the diagnosis's candidate effects (``delta_bic``, ``significant``). A candidate instrument
    that brings the error to the noise level must beat every accepted effect by ``bic_distinct``; one that only
    removes most of the excess error (a sample effect may be missing too) must beat every tried effect by it.
    ``fit_quick(config, prepared)`` refits without error bars.

    ``separation_free``: the run estimated the rest separation (``config`` holds its estimate). That estimate
    belongs to the run's model without the instrument, and an undeclared instrument pulls it far (a second
    mode at 6.27 f moved it by 5 nm, to the edge of the search): refitted at it, no candidate explains the
    residual. So when the first search names nothing that explains, the separation is estimated again with
    each kind's best candidate declared (the fit's own profile over its whole range, :func:`reprofiled`) and
    the search runs again at that separation. What that second search finds is kept only when it explains the
    residual (its error at the noise level): the separation was re-estimated for the candidate, one more
    freedom given to it, and a candidate that still leaves most of a residual is a stand-in (on the HSDC record's
    second half a detector near 251 kHz took half the excess error there and none elsewhere on the record).
    """
    from afmid.preprocess.instrument import from_config

    screened = screen(base_result, prepared.trace.cantilever, prepared.drive.frequency)
    log.debug("instrument screen: %s", screened)

    def search(trial_config, searched=None):
        return check(base_result, screened, prepared.trace.cantilever, prepared.drive.frequency, from_config(config),
                     _refit(trial_config, prepared, fit_quick), base_bic, bic_evidence, searched)

    searched: list = []
    try:
        finding = search(config, searched)
        if separation_free and (finding is None or not finding.explains or not finding.supported):
            separation = reprofiled(config, prepared, _variants(searched, prepared.drive.frequency), fit_quick)
            if separation is not None and separation > 0:  # a separation not above zero places no surface
                trial_config = copy.deepcopy(config)
                trial_config.sample.separation = separation
                again = search(trial_config)
                log.debug("instrument search again at d = %.4g nm: %s", 1e9 * separation, again)
                if again is not None and again.explains and (finding is None or (again.supported, -again.delta_bic)
                                                             > (finding.supported, -finding.delta_bic)):
                    finding = again
    finally:
        if prepared.before_instrument is not None:  # the hypotheses' shared trajectory and columns: done with
            prepared.before_instrument.forget_tip_side()
    if finding is None:
        # A resonance's shape where no lever has its second mode: not searched, and said so (it has no BIC to weigh
        # against the sample effects, and is never named).
        return unsearched_mode(screened, prepared.trace, prepared.drive.frequency)
    rivals = [t.delta_bic for t in trials if t.significant or not finding.explains]
    return finding if finding.delta_bic < min(rivals, default=math.inf) - bic_distinct else None


def _refit(config, prepared, fit_quick):
    """refit(instrument): ``config``'s fit on the trace prepared with ``instrument`` declared. The candidates differ
    only in the instrument: each preparation starts from ``prepared``'s instrument-free part (the detrended record,
    its blocks and windows, the views' block series and residual spectrum, the rows' noise probe), made once."""
    from afmid.fit.prepare import with_instrument

    def refit(instrument: Instrument):
        return fit_quick(config, with_instrument(prepared, config.fit, instrument))

    return refit


#: The second pass (separation re-estimated) tries second modes at the first search's f_2 and this far on
#: either side, in units of the drive frequency: at the wrong separation the search may end on the wrong side
#: of a harmonic (measured: 5.8 f found for a mode at 6.27 f), where the response differs most.
REPROFILE_MODE_OFFSETS = (-0.4, -0.2, 0.0, 0.2, 0.4)


def _variants(searched: list, drive_frequency: float) -> list:
    """The instruments the separation is re-estimated with: each searched candidate, a second mode also at
    f_2 + REPROFILE_MODE_OFFSETS f (the stiffness of equal modal masses scaled with f_2^2)."""
    out = []
    for instrument in searched:
        if not instrument.higher_modes:
            out.append(instrument)
            continue
        mode = instrument.higher_modes[-1]
        for offset in REPROFILE_MODE_OFFSETS:
            f2 = mode.resonance_frequency + offset * drive_frequency
            moved = Mode(f2, mode.quality_factor, mode.spring_constant * (f2 / mode.resonance_frequency) ** 2)
            out.append(Instrument(instrument.detector, instrument.higher_modes[:-1] + (moved,)))
    return out


def reprofiled(config, prepared, instruments: list, fit_quick) -> float | None:
    """The rest separation (m) the fit estimates (its own search over its whole range, ``sample.separation``
    absent) with the one of ``instruments`` declared whose fit has the lowest cross-validated error; None when
    no such fit succeeds."""
    from afmid.diagnosis.forked_work import in_order

    free = copy.deepcopy(config)
    free.sample.separation = None
    refit = _refit(free, prepared, fit_quick)

    def estimated(instrument: Instrument) -> tuple[float, float] | None:
        """(cross-validated error, separation estimate in m) of the fit with ``instrument``; None without one."""
        try:
            result = refit(instrument)
        except Exception as exc:  # a candidate that cannot be fitted gives no separation
            log.debug("separation with %s not estimated: %s", instrument.describe(), exc)
            return None
        estimate = result.nonlinear.get("d")
        log.debug("separation with %s: %s (error %.3g)", instrument.describe(), estimate and estimate.value,
                  result.cv_error)
        if estimate is None or not math.isfinite(estimate.value):
            return None
        return float(result.cv_error), float(estimate.value)

    best = (math.inf, None)
    # Independent fits, shared with a forked child (afmid.diagnosis.forked_work); the best chosen here, in order.
    for found in in_order(estimated, instruments):
        if found is not None and found[0] < best[0]:
            best = found
    return best[1]


def name_instrument(summary: dict, finding: Finding) -> dict:
    """The diagnosis ``summary`` (afmid.diagnosis.diagnose.suggest) with the instrument named instead of sample effects:
    the verdict is the finding's text, no effect is suggested (the candidates stay in ``tried``). A second mode
    without the evidence (:class:`ModeEvidence`) is not named: the verdict says why, and nothing else changes."""
    diagnosis = dict(summary["diagnosis"])
    if not finding.supported:
        diagnosis.update(verdict=f"{diagnosis['verdict']}; {finding.text}", instrument_rejected=finding.record())
        return {**summary, "diagnosis": diagnosis}
    diagnosis.update(verdict=f"{finding.text} ({'ΔBIC'} {finding.delta_bic:.0f}, error -> {finding.error_after:.3g}, "
                             f"floor {finding.noise_floor_after:.3g})",
                     instrument=finding.record(), explained_by_catalog=False,
                     error_after=finding.error_after, delta_bic_after=finding.delta_bic)
    return {**summary, "missing_effect": True, "diagnosis": diagnosis, "suggestions": []}

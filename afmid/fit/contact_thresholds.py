"""Where a force that forms at contact switches taps on: each tap's contact threshold in the rest separation.

A gate declared to form at contact (:attr:`afmid.physics.effect_types.StateGate.forms_at_contact`: a meniscus, a
JKR neck) switches on in a tap when the tip's separation z = d - x reaches a0 there, i.e. when the rest
separation d is at most a0 + (that tap's largest deflection). On an orbit whose taps differ (a grazing tip, a
period-n orbit) the set of taps with a neck therefore changes at each of these thresholds, and a fit's residual
against d is piecewise smooth between them with steps at them: the valley where the neck forms on the record's
own taps can be as narrow as the spread of the taps' peaks (measured: ~10 pm on a grazing meniscus orbit whose
taps differ by 20 pm), which a grid 0.5 nm apart zoomed on its lowest point cannot find. A search of d evaluates
one separation inside each interval between consecutive thresholds (:func:`contact_trial_separations`) besides
its own grid. Lengths in m.
"""

from __future__ import annotations

import numpy as np

from afmid.fit.prepare import Prepared, fine_chunks

#: At most this many intervals between thresholds are tried per search: thresholds closer than their spread over
#: this many are merged (a record built up from rest has taps over nanometres; its intervals are then sampled).
CONTACT_TRIALS_MAX = 64


def tap_peaks(prep: Prepared) -> np.ndarray:
    """The largest deflection of each tap (one per period, in time order), m, on the fine grid the library's
    gates are scanned on (:func:`afmid.fit.prepare.fine_chunks`: the smoothed trajectory ``X_traj``), so that a
    threshold a0 + peak is where the library's gate, not the raw record's, starts to switch on. A block of several
    periods (``fit.periods_per_block``) is cut into that many equal parts, one tap each."""
    blocks = prep.blocks
    per_block = max(1, int(round(blocks.L * blocks.dt * blocks.omega / (2 * np.pi))))
    peaks = np.full((blocks.n_blocks, per_block), -np.inf)
    # The chunks the library's evaluations use (overlap 1: the fine grid a diagnosis keeps holds these); a block
    # repeated as the next chunk's overlap gets the same values twice.
    for first, x, _, _ in fine_chunks(prep, overlap=1):
        for j, part in enumerate(np.array_split(x, per_block, axis=1)):
            peaks[first:first + part.shape[0], j] = part.max(axis=1)
    return peaks.ravel()


def contact_thresholds(prep: Prepared, a0: float) -> np.ndarray:
    """The distinct rest separations a0 + (a tap's largest deflection), m, ascending: at each, one more tap
    reaches contact as d decreases (none where no tap is on the fine grid's chunks)."""
    peaks = tap_peaks(prep)
    return np.unique(a0 + peaks[np.isfinite(peaks)])


def contact_trial_separations(thresholds: np.ndarray, low: float, high: float, resolution: float) -> np.ndarray:
    """One rest separation inside each interval between consecutive ``thresholds`` (its middle) that lies in
    [``low``, ``high``], m, ascending; and one on each outer side of the outermost thresholds, half the adjacent
    interval away (every tap with a neck below the lowest, none above the highest).

    Thresholds closer than ``resolution`` (m: the search's last step, below which it resolves nothing) are
    merged, and further while more than :data:`CONTACT_TRIALS_MAX` trials would remain; a single threshold gives
    the points ``resolution`` either side of it."""
    t = np.sort(np.asarray(thresholds, dtype=float))
    t = t[np.isfinite(t)]
    if t.size == 0:
        return np.zeros(0)
    spacing = max(resolution, (t[-1] - t[0]) / CONTACT_TRIALS_MAX)
    kept = [t[0]]
    for value in t[1:]:
        if value - kept[-1] >= spacing:
            kept.append(value)
    kept = np.array(kept)
    if kept.size == 1:
        trials = np.array([kept[0] - resolution, kept[0] + resolution])
    else:
        middles = 0.5 * (kept[1:] + kept[:-1])
        trials = np.concatenate([[kept[0] - 0.5 * (kept[1] - kept[0])], middles,
                                 [kept[-1] + 0.5 * (kept[-1] - kept[-2])]])
    return trials[(trials >= low) & (trials <= high)]

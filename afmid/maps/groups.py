"""Pixels of a force map grouped by their residual signature and their parameters.

Each fitted pixel (ok or suspect) is described by a few features, each in units of the smallest difference that
means something (so that a feature that only carries noise does not weigh as much as one that tells phases apart,
as it would when every feature were scaled to unit variance):

- the residual's size: log10 of the cross-validated error over its noise floor (1 where it is below the floor)
  and log10 of the residual's signal-to-noise ratio (:data:`SNR_NOISE` where below: noise), in units of
  log10 FLOOR_FACTOR (the model-limited factor of afmid.fit.uncertainty: a smaller ratio is not told apart);
- its character: the share of the part that reverses with the direction of motion (0..1; 0.5, i.e. neutral, where
  neither part stands above the noise), in units of :data:`SHARE_UNIT`;
- the parameters: the value of each parameter map (its median where the pixel has none; linear, not log: a
  parameter at zero within its noise, e.g. the viscosity of an elastic phase, would spread over decades in log),
  in units of its median 1-sigma error bar over the pixels (its spread over the pixels when there is none);
  a parameter map correlated beyond :data:`SAME_INFORMATION` with an earlier one (a read-out of the same
  coefficient, e.g. the adhesion force and the surface energy from the Hamaker constant) is left out.

The groups are k-means clusters (Lloyd's algorithm, k-means++ starts with a fixed seed, the best of
:data:`STARTS` runs). k is chosen by the data: the k of 2 .. :data:`MAX_GROUPS` with the largest mean silhouette
(Rousseeuw, J. Comput. Appl. Math. 20, 53 (1987)), taken only when that silhouette is at least
:data:`MIN_SILHOUETTE` ("a reasonable structure" on Kaufman & Rousseeuw's scale); otherwise every pixel is one group.
Groups are numbered by size, the largest first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Most groups a map is cut into (a few explainable groups, not a segmentation).
MAX_GROUPS = 4
#: Mean silhouette a split needs to be taken (0.51-0.70: "a reasonable structure has been found").
MIN_SILHOUETTE = 0.5
#: k-means runs from different k-means++ starts per k (the one with the least within-group scatter is kept).
STARTS = 5
#: A residual snr up to this counts as noise (afmid.diagnosis.localize: a part is significant above 3x its noise).
SNR_NOISE = 3.0
#: The unit of the dissipative share (a quarter of the way from conservative to dissipative).
SHARE_UNIT = 0.25
#: Parameter maps correlated beyond this over the fitted pixels carry the same information: the first one is kept.
SAME_INFORMATION = 0.99
#: At most this many pixels enter the silhouette (a random subset of a large map: the pairwise distances).
SILHOUETTE_SAMPLE = 1500


@dataclass
class Grouping:
    """The groups of a map: ``labels`` (rows, cols; -1 where the pixel was not fitted), the silhouette of the chosen
    split (NaN for one group), the features' names and the fitted pixels' scaled features (n_fitted, features) with
    their flat pixel indices."""

    labels: np.ndarray
    silhouette: float
    feature_names: list[str]
    features: np.ndarray
    pixels: np.ndarray
    centres: np.ndarray

    @property
    def n_groups(self) -> int:
        return int(self.labels.max()) + 1 if (self.labels >= 0).any() else 0


def features(maps: dict[str, np.ndarray], parameter_names: list[str], fitted: np.ndarray
             ) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The fitted pixels' features (n_fitted, n_features), unscaled, their names and their units (see the module
    docstring). ``maps``: name -> flat array over the pixels (NAME_sigma: the 1-sigma map of parameter NAME);
    ``fitted``: bool over the pixels."""
    from afmid.fit.uncertainty import FLOOR_FACTOR

    ratio = maps["cv_error"] / maps["cv_error_noise_floor"]
    # Below the floor and below 3x the noise nothing is there to tell apart: those pixels share one value (the
    # noise would otherwise split a phase at its noise level into groups that differ by chance).
    columns = {"log10 error / floor (from 1)": np.log10(np.clip(ratio, 1.0, None)),
               f"log10 residual snr (from {SNR_NOISE:g})": np.log10(np.clip(maps["residual_snr"], SNR_NOISE, None))}
    share = np.where(maps["residual_character"] > 0, maps["residual_dissipative_share"], 0.5)
    columns["dissipative share"] = np.where(np.isfinite(share), share, 0.5)
    units = [np.log10(FLOOR_FACTOR), np.log10(FLOOR_FACTOR), SHARE_UNIT]
    parameter_columns: list[str] = []
    for name in parameter_names:
        values = maps[name]
        if not np.isfinite(values[fitted]).any():
            continue
        column = np.where(np.isfinite(values), values, np.nanmedian(values[fitted]))
        if not any(_same_information(column[fitted], columns[other][fitted]) for other in parameter_columns):
            columns[name] = column
            parameter_columns.append(name)
            sigma = maps.get(f"{name}_sigma", np.full(column.size, np.nan))[fitted]
            sigma = sigma[np.isfinite(sigma) & (sigma > 0)]
            units.append(float(np.median(sigma)) if sigma.size else float(np.std(column[fitted])))
    names = list(columns)
    table = np.stack([np.where(np.isfinite(columns[n]), columns[n], 0.0)[fitted] for n in names], axis=1)
    return table, names, np.asarray(units, float)


def _same_information(a: np.ndarray, b: np.ndarray) -> bool:
    """Two parameter maps that are (nearly) proportional over the pixels: read-outs of one coefficient (the
    adhesion force and the surface energy from the Hamaker constant), counted once."""
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return False
    return abs(float(np.corrcoef(a, b)[0, 1])) > SAME_INFORMATION


def scaled(table: np.ndarray, units: np.ndarray) -> np.ndarray:
    """Each feature minus its mean, in its unit (a feature constant to rounding, or without a unit: zero)."""
    centred = table - table.mean(axis=0)
    spread = np.abs(centred).max(axis=0) if table.shape[0] else np.zeros(table.shape[1])
    constant = spread <= 1e-12 * np.maximum(np.abs(table).max(axis=0, initial=0.0), 1e-300)
    usable = np.isfinite(units) & (units > 0) & ~constant
    return np.where(usable, centred / np.where(usable, units, 1.0), 0.0)


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means from a k-means++ start: (labels, centres)."""
    n = x.shape[0]
    centres = [x[rng.integers(n)]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
        total = d2.sum()
        centres.append(x[rng.choice(n, p=d2 / total)] if total > 0 else x[rng.integers(n)])
    centres = np.asarray(centres, float)
    labels = np.full(n, -1)
    for _ in range(iterations):
        new = np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            if np.any(labels == j):
                centres[j] = x[labels == j].mean(axis=0)
    return labels, centres


def silhouette(x: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette of a split (a pixel alone in its group counts 0)."""
    d = np.sqrt(((x[:, None, :] - x[None]) ** 2).sum(-1))
    groups = np.unique(labels)
    if groups.size < 2:
        return float("nan")
    s = np.zeros(x.shape[0])
    for i in range(x.shape[0]):
        own = labels == labels[i]
        if own.sum() < 2:
            continue
        a = d[i, own].sum() / (own.sum() - 1)
        b = min(d[i, labels == g].mean() for g in groups if g != labels[i])
        s[i] = (b - a) / max(a, b) if max(a, b) > 0 else 0.0
    return float(s.mean())


def group_pixels(maps: dict[str, np.ndarray], parameter_names: list[str], fitted: np.ndarray, shape: tuple[int, int],
                 seed: int = 0) -> Grouping:
    """Group the fitted pixels (see the module docstring). ``maps``: name -> flat arrays over the pixels."""
    pixels = np.flatnonzero(fitted)
    if pixels.size == 0:
        return Grouping(np.full(shape, -1), float("nan"), [], np.zeros((0, 0)), pixels, np.zeros((0, 0)))
    table, names, units = features(maps, parameter_names, fitted)
    x = scaled(table, units)
    labels_flat = np.full(fitted.size, -1)
    best_labels, best_centres, best_score = np.zeros(pixels.size, int), x.mean(axis=0, keepdims=True), float("nan")
    rng = np.random.default_rng([seed, 14, 3])
    sample = (np.arange(pixels.size) if pixels.size <= SILHOUETTE_SAMPLE
              else np.sort(rng.choice(pixels.size, SILHOUETTE_SAMPLE, replace=False)))
    for k in range(2, min(MAX_GROUPS, pixels.size - 1) + 1):
        runs = [kmeans(x, k, rng) for _ in range(STARTS)]
        labels, centres = min(runs, key=lambda r: float(((x - r[1][r[0]]) ** 2).sum()))
        score = silhouette(x[sample], labels[sample])
        if score >= MIN_SILHOUETTE and not score <= best_score:
            best_labels, best_centres, best_score = labels, centres, score
    # Number the groups by size, the largest first (ties: the lower old number first).
    order = sorted(range(best_centres.shape[0]), key=lambda g: (-int(np.sum(best_labels == g)), g))
    renumber = np.empty(len(order), int)
    renumber[order] = np.arange(len(order))
    labels_flat[pixels] = renumber[best_labels]
    return Grouping(labels_flat.reshape(shape), best_score, names, x, pixels, best_centres[order])


def representatives(grouping: Grouping, group: int, n: int) -> np.ndarray:
    """Up to ``n`` flat pixel indices of ``group`` nearest its centre in the scaled features (nearest first)."""
    members = np.flatnonzero(grouping.labels.ravel()[grouping.pixels] == group)
    distance = ((grouping.features[members] - grouping.centres[group]) ** 2).sum(axis=1)
    return grouping.pixels[members[np.argsort(distance, kind="stable")[:n]]]

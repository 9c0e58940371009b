"""Pixels of a force map grouped by their residual signature and their parameters (issue 14 part 3).

Each fitted pixel (ok or suspect) is described by a few features, each scaled to unit standard deviation over the
fitted pixels:

- the residual's size: log10 of the cross-validated error over its noise floor, and log10 of the residual's
  signal-to-noise ratio (afmid.maps.residual);
- its character: the share of the part that reverses with the direction of motion (0..1; 0.5, i.e. neutral, where
  neither part stands above the noise);
- the parameters: log10 |value| of each parameter map (its median where the pixel has none).

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
             ) -> tuple[np.ndarray, list[str]]:
    """The fitted pixels' features (n_fitted, n_features), unscaled, and their names (see the module docstring).
    ``maps``: name -> flat array over the pixels; ``fitted``: bool over the pixels."""
    ratio = maps["cv_error"] / maps["cv_error_noise_floor"]
    columns = {"log10 error / floor": np.log10(np.clip(ratio, 1e-3, None)),
               "log10 residual snr": np.log10(np.clip(maps["residual_snr"], 1e-3, None))}
    share = np.where(maps["residual_character"] > 0, maps["residual_dissipative_share"], 0.5)
    columns["dissipative share"] = np.where(np.isfinite(share), share, 0.5)
    for name in parameter_names:
        values = np.abs(maps[name])
        logged = np.log10(np.where(values > 0, values, np.nan))
        if not np.isfinite(logged[fitted]).any():
            continue
        columns[f"log10 |{name}|"] = np.where(np.isfinite(logged), logged, np.nanmedian(logged[fitted]))
    names = list(columns)
    table = np.stack([np.where(np.isfinite(columns[n]), columns[n], 0.0)[fitted] for n in names], axis=1)
    return table, names


def scaled(table: np.ndarray) -> np.ndarray:
    """Each feature minus its mean over its standard deviation (a constant feature: zero)."""
    sd = table.std(axis=0)
    return (table - table.mean(axis=0)) / np.where(sd > 0, sd, 1.0)


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
    table, names = features(maps, parameter_names, fitted)
    x = scaled(table)
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

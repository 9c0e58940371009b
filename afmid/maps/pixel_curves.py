"""Each pixel's force curve, kept in the map result for the map explorer.

At fit time a pixel's period curves are already evaluated for its residual signature (:mod:`afmid.maps.residual`:
the model and inverted forces on the fit's phase grid, averaged over the settled periods). This module resamples
that period average onto a coarse separation grid, per branch (approach: the separation falls; retraction: it
rises), and :func:`write_pixel_curves` stores it under ``/pixel_curves`` of the result file:

- ``separation`` (rows, cols, :data:`CURVE_POINTS`), m: z_k = z_min + (z_max - z_min) u_k^2 with u_k uniform on
  [0, 1]: dense near the turn at the sample, where the contact forces change fastest (with a 30 nm swing the
  first 6 points lie within 1 nm of z_min);
- ``force_inverted``, ``force_inverted_sigma`` (1 sigma of the period average), ``force_model`` (full bandwidth)
  and ``residual`` (inverted minus the model on the same harmonics, as afmid.diagnosis.localize compares them):
  (rows, cols, 2, :data:`CURVE_POINTS`) in N (positive = repulsive), branch 0 approach, 1 retraction.

Why stored rather than recomputed by the report: the result keeps each pixel's read-outs, not its coefficients,
drive and prepared trace; recomputing a pixel's curves means preparing its trace and refitting it (seconds per
pixel), while here they cost one interpolation of arrays already in memory. Size: 288 float32 values per pixel,
1.2 kB (75 MB for a 256 x 256 map); float32 keeps 7 digits, far below the noise of a period average.
"""

from __future__ import annotations

import numpy as np

#: Separation points per branch.
CURVE_POINTS = 32
BRANCHES = ("approach", "retraction")
#: name -> (unit, meaning) of the datasets of /pixel_curves (the per-branch ones are (rows, cols, 2, CURVE_POINTS)).
CURVES = {
    "separation": ("m", "separation grid of the pixel's curves: z_min + (z_max - z_min) u^2, u uniform on [0, 1]"),
    "force_inverted": ("N", "inverted force (drive minus the lever's own terms), period average at equal phase; "
                            "branch 0 approach, 1 retraction; positive = repulsive"),
    "force_inverted_sigma": ("N", "1 sigma of the period average of the inverted force (period-to-period spread "
                                  "over the square root of the periods)"),
    "force_model": ("N", "the pixel's fitted force law at full bandwidth along the same orbit"),
    "residual": ("N", "inverted minus the model on the same harmonics (what afmid.diagnosis.localize breaks down)"),
}
GROUP = "pixel_curves"
#: The keys of a chunk's result (afmid.maps.task) and saved chunk (afmid.maps.run) that hold the curves.
CHUNK_KEYS = tuple(f"curve_{name}" for name in CURVES)


def grid(z_min: float, z_max: float) -> np.ndarray:
    """The separation grid (m) of one pixel: :data:`CURVE_POINTS` points, quadratic in u (dense near z_min)."""
    u = np.linspace(0.0, 1.0, CURVE_POINTS)
    return z_min + (z_max - z_min) * u**2


def empty_curves() -> dict:
    """The curves of a pixel that was not fitted (NaN)."""
    out = {"separation": np.full(CURVE_POINTS, np.nan)}
    out.update({name: np.full((2, CURVE_POINTS), np.nan) for name in CURVES if name != "separation"})
    return out


def pixel_curves(z: np.ndarray, zdot: np.ndarray, per_phase: dict) -> dict:
    """Resample period-averaged curves on the phase grid onto the pixel's separation grid, per branch.

    ``z``, ``zdot``: the period-averaged separation (m) and its rate (m/s) at each phase point; ``per_phase``:
    name -> the period-averaged curve (N) at the same points, for the names of :data:`CURVES` but the separation.
    """
    out = empty_curves()
    finite = np.isfinite(z)
    if finite.sum() < 4:
        return out
    z_grid = grid(float(np.min(z[finite])), float(np.max(z[finite])))
    out["separation"] = z_grid
    for b, branch in enumerate((zdot < 0, zdot >= 0)):
        sel = branch & finite
        if sel.sum() < 2:
            continue
        order = np.argsort(z[sel])
        zs = z[sel][order]
        for name, curve in per_phase.items():
            # Outside the branch's own span (its ends sit a phase step from the turns) the end value is held.
            out[name][b] = np.interp(z_grid, zs, np.asarray(curve)[sel][order])
    return out


def collect(results: list[dict | None]) -> dict:
    """The curves of a chunk's pixels (None: not fitted) as arrays (pixels first), under :data:`CHUNK_KEYS`."""
    filled = [r if r is not None else empty_curves() for r in results]
    return {f"curve_{name}": np.stack([r[name] for r in filled]) if filled
            else np.zeros((0, *empty_curves()[name].shape)) for name in CURVES}


def merge_chunks(chunks: list[dict]) -> dict:
    """The curves of every pixel (row-major) from the chunks' results in pixel order."""
    return {name: np.concatenate([c[f"curve_{name}"] for c in chunks]) for name in CURVES}


def write_pixel_curves(h5, curves: dict, shape: tuple[int, int]) -> None:
    """``/pixel_curves`` of a map result from the pixels' curves (pixels first, row-major), as float32."""
    from afmid.io.trace import write_dataset

    group = h5.create_group(GROUP)
    group.attrs["branches"] = ", ".join(f"{i}: {name}" for i, name in enumerate(BRANCHES))
    for name, (unit, meaning) in CURVES.items():
        data = np.asarray(curves[name], dtype=np.float32)
        write_dataset(group, name, data.reshape(*shape, *data.shape[1:]), unit, meaning=meaning)


def read_pixel_curves(path) -> dict | None:
    """The /pixel_curves of a map result (SI arrays, float64), None for a result written without them."""
    import h5py

    with h5py.File(path, "r") as h5:
        if GROUP not in h5:
            return None
        group = h5[GROUP]
        return {name: np.asarray(group[name][()], dtype=float) for name in CURVES if name in group}

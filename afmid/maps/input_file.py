"""Reading a force map: a deflection trace per pixel, ``(rows, cols, samples)``.

Two layouts: an HDF5 file with the dataset ``/deflection`` (attributes ``units``, ``sample_rate`` on the dataset or
the root, the cantilever and drive as root attributes ``spring_constant``, ``resonance_frequency``,
``quality_factor``, ``tip_radius``, ``drive_frequency``; optional ``/x``, ``/y`` pixel coordinates in m), or a
NumPy ``.npy`` file of that shape read as a memory map (everything else from the config). Values in the config
override the file's, as for a trace. A pixel's trace is read on its own (:func:`read_pixels`), so a worker holds
one chunk of pixels, never the map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afmid.errors import ConfigError, InputError
from afmid.io.files import check_format_version, check_input_file
from afmid.io.trace import Cantilever, Trace, check_trace

#: Metres per unit of the deflection samples (V and raw are converted with data.invols / data.scale).
UNIT_SCALE = {"m": 1.0, "nm": 1e-9, "pm": 1e-12, "um": 1e-6}
CANTILEVER_KEYS = ("spring_constant", "resonance_frequency", "quality_factor", "tip_radius")
HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf")


@dataclass
class MapSource:
    """What a map file holds besides the traces (read once, in the main process and in each worker)."""

    path: Path
    rows: int
    cols: int
    samples: int
    sample_rate: float
    units: str
    cantilever: Cantilever
    drive_frequency: float
    x: np.ndarray | None = None  # m, (cols,) or (rows, cols)
    y: np.ndarray | None = None
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def n_pixels(self) -> int:
        return self.rows * self.cols


def _is_hdf5(path: Path) -> bool:
    return path.suffix.lower() in HDF5_SUFFIXES


def _attrs(path: Path) -> tuple[tuple[int, ...], dict, dict, np.ndarray | None, np.ndarray | None]:
    """Shape, dataset attributes, root attributes and the x/y coordinates of a map file."""
    if not _is_hdf5(path):
        if path.suffix.lower() != ".npy":
            raise InputError(f"a map is an HDF5 file with /deflection or a .npy array, got suffix {path.suffix!r}",
                             file=path, key="--input")
        try:
            values = np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise InputError(f"not a readable .npy array ({exc})", file=path, key="--input") from None
        if values.dtype.kind not in "fiu":
            raise InputError(f"the map must hold numbers, got dtype {values.dtype}", file=path, key="--input")
        return tuple(values.shape), {}, {}, None, None
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            if "deflection" not in h5 or not isinstance(h5["deflection"], h5py.Dataset):
                raise InputError("no dataset /deflection (rows, cols, samples) in the map", file=path,
                                 key="/deflection")
            ds = h5["deflection"]
            if ds.dtype.kind not in "fiu":
                raise InputError(f"/deflection must hold numbers, got dtype {ds.dtype}", file=path, key="/deflection")
            coords = {}
            for name in ("x", "y"):
                coords[name] = np.asarray(h5[name][()], dtype=float) if name in h5 else None
            return tuple(ds.shape), dict(ds.attrs), dict(h5.attrs), coords["x"], coords["y"]
    except OSError as exc:
        raise InputError(f"not a readable HDF5 file ({exc})", file=path, key="--input") from None


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def open_map(path: str | Path, config) -> MapSource:
    """Check a map file and merge its metadata with ``config`` (config values win)."""
    path = check_input_file(Path(path), what="map file", key="--input")
    shape, ds_attrs, root, x, y = _attrs(path)
    if len(shape) != 3 or min(shape) < 1:
        raise InputError(f"the map must have shape (rows, cols, samples), got {shape}", file=path, key="/deflection")
    if _text(root.get("format", "")) == "afmid-map":  # afmid's own map file (afmid simulate): a version it reads
        check_format_version(root, path)
    for axis, values, length, what in (("x", x, shape[1], "column"), ("y", y, shape[0], "row")):
        if values is not None and values.shape != (length,):  # the result's axes would be drawn from it
            raise InputError(f"has shape {values.shape}, expected ({length},): one position per {what} of "
                             f"/deflection", file=path, key=f"/{axis}")
    sources: dict[str, str] = {}

    def merged(key: str, from_config, *names):
        if from_config is not None:
            sources[key] = f"config:{key}"
            return from_config
        for attrs in (ds_attrs, root):
            for name in names:
                if name in attrs:
                    sources[key] = "file"
                    value = attrs[name]
                    return _text(value) if isinstance(value, (bytes, str)) else float(value)
        return None

    rate = merged("data.sample_rate", config.data.sample_rate, "sample_rate")
    if rate is None or not np.isfinite(rate) or rate <= 0:
        raise ConfigError("the map file states no sample rate; set data.sample_rate (Hz)", file=config.source,
                          key="data.sample_rate")
    units = merged("data.units", config.data.units, "units")
    if units is None:
        raise ConfigError("the map file does not state the deflection units; set data.units",
                          file=config.source, key="data.units")
    if units not in UNIT_SCALE and units not in ("V", "raw"):
        raise InputError(f"cannot convert deflection units {units!r}; set data.units", file=path, key="data.units")
    values = {}
    for key in CANTILEVER_KEYS:
        values[key] = merged(f"cantilever.{key}", getattr(config.cantilever, key), key)
    for key in CANTILEVER_KEYS[:3]:
        if values[key] is None or not np.isfinite(values[key]) or values[key] <= 0:
            raise ConfigError("required (the map file does not state it), a positive number", file=config.source,
                              key=f"cantilever.{key}")
    radius = values.pop("tip_radius")
    cantilever = Cantilever(tip_radius=None if radius is None or not np.isfinite(radius) else float(radius),
                            **{k: float(v) for k, v in values.items()})
    drive = merged("drive.frequency", config.drive.frequency, "drive_frequency")
    if drive is None or not np.isfinite(drive) or drive <= 0:
        raise ConfigError("required (the map file does not state it), Hz", file=config.source, key="drive.frequency")
    return MapSource(path, shape[0], shape[1], shape[2], float(rate), str(units), cantilever, float(drive), x, y,
                     sources)


def read_pixels(source: MapSource, first: int, stop: int) -> np.ndarray:
    """The raw samples of pixels ``first`` to ``stop`` (flat, row-major), shape (stop - first, samples)."""
    rows = range(first // source.cols, (stop - 1) // source.cols + 1)
    if _is_hdf5(source.path):
        import h5py

        with h5py.File(source.path, "r") as h5:
            block = h5["deflection"][rows.start:rows.stop]
    else:
        block = np.load(source.path, mmap_mode="r", allow_pickle=False)[rows.start:rows.stop]
    flat = np.asarray(block, dtype=np.float64).reshape(-1, source.samples)
    offset = rows.start * source.cols
    return flat[first - offset:stop - offset]


def pixel_trace(source: MapSource, raw: np.ndarray, config, pixel: int) -> Trace:
    """One pixel's trace in SI, positive toward the sample, checked as a loaded trace is (defects raise)."""
    data = config.data
    values = raw - data.offset
    if source.units in UNIT_SCALE:
        values = values * UNIT_SCALE[source.units]
    elif source.units == "V":
        if data.invols is None:
            raise ConfigError("units V needs data.invols (m/V)", file=config.source, key="data.invols")
        values = values * data.invols
    else:
        if data.scale is None:
            raise ConfigError("units raw needs data.scale (m per count)", file=config.source, key="data.scale")
        values = values * data.scale
    if data.positive == "away_from_sample":
        values = -values
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise InputError(f"pixel {divmod(pixel, source.cols)}: {bad} of {values.size} samples are NaN or infinite",
                         file=source.path, key="/deflection")
    trace = Trace(deflection=np.ascontiguousarray(values), sample_rate=source.sample_rate,
                  cantilever=source.cantilever, drive_frequency=source.drive_frequency, path=source.path,
                  sources=dict(source.sources), drive_force_amplitude=config.drive.force_amplitude)
    return check_trace(trace, config)

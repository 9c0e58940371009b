"""HDF5 files, including afmid's own trace files (root attribute ``format: afmid-trace``).

- Channel: any dataset path ('/deflection', 'deflection', '/AFM/z'); by default
  '/deflection', else the one dataset named 'deflection' in a group, else the
  only 1-D numeric dataset that is not a time axis.
- Units: the dataset's ``units`` attribute, else a unit in its name.
- Sample rate: an attribute ``sample_rate`` (Hz) or ``dt``/``time_step`` (s) on
  the dataset, else on its enclosing groups up to the root.
- Metadata: root and dataset attributes; for afmid trace files also the
  attributes of ``/cantilever`` and ``/drive`` and the paths of the ``/truth``
  datasets (not loaded).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmid.io.files import check_format_version
from afmid.io.readers.base import (
    RawTrace,
    Reader,
    as_samples,
    check_array_size,
    choose_channels,
    not_readable,
    plain,
    rate_from_fields,
    settle_rate,
    split_units,
    time_axis,
)

TRACE_FORMAT = "afmid-trace"


def _open(path: Path):
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise not_readable("HDF5", path, exc) from None


def _datasets(h5) -> dict[str, object]:
    """Every dataset by absolute path, in file order."""
    import h5py

    found: dict[str, object] = {}

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            found["/" + name] = obj

    h5.visititems(visit)
    return found


def _is_channel(dataset) -> bool:
    """Numeric with one axis longer than 1: what can be read as a trace."""
    return dataset.dtype.kind in "iuf" and sum(n > 1 for n in dataset.shape) == 1


def _attrs(obj) -> dict:
    return {str(k): plain(v) for k, v in obj.attrs.items()}


def _read_dataset(dataset, path: Path) -> np.ndarray:
    # A dataset may claim any size without storing it (unwritten chunks read as the fill value).
    check_array_size(dataset.shape, dataset.dtype, file=path, channel=dataset.name)
    try:
        return dataset[()]
    except OSError as exc:  # a truncated file can open and then fail on the data
        raise not_readable("HDF5", path, exc) from None


def _units(dataset) -> str | None:
    units = plain(dataset.attrs.get("units"))
    return units.strip() if isinstance(units, str) and units.strip() else None


def _stated_rate(dataset, path: Path) -> tuple[float, str] | None:
    """Sample rate stated on the dataset, else on the nearest enclosing group."""
    obj = dataset
    while True:
        location = obj.name.rstrip("/") + "/attrs/{}"
        stated = rate_from_fields(_attrs(obj), location.format, file=path)
        if stated or obj.name == "/":
            return stated
        obj = obj.parent


def _absolute(wanted: str | int | None, datasets: dict) -> str | int | None:
    """A dataset path given without its leading '/' ('AFM/z'), made absolute."""
    if isinstance(wanted, str) and not wanted.startswith("/") and "/" + wanted in datasets:
        return "/" + wanted
    return wanted


def _afmid_metadata(h5, datasets: dict) -> dict:
    """The parts of an afmid trace file that describe the experiment (layout: afmid.io.trace)."""

    def group_attrs(name: str) -> dict:
        return _attrs(h5[name]) if name in h5 else {}

    truth = [name for name in datasets if name.startswith("/truth/")]
    return {
        "format": TRACE_FORMAT,
        "root": _attrs(h5),
        "cantilever": group_attrs("cantilever"),
        "drive": group_attrs("drive"),
        "truth_datasets": truth,
    }


def list_channels(path: Path) -> list[str]:
    """Paths of the datasets that can be read as a trace (numeric, 1-D)."""
    with _open(path) as h5:
        return [name for name, ds in _datasets(h5).items() if _is_channel(ds)]


def read(path: Path, channel: str | None = None, time_channel: str | None = None) -> RawTrace:
    """Read one dataset (file units) and optionally a time dataset (s)."""
    with _open(path) as h5:
        if plain(h5.attrs.get("format")) == TRACE_FORMAT:  # afmid's own trace: a newer one is refused, named
            check_format_version(h5.attrs, path)
        datasets = _datasets(h5)
        names = list(datasets)
        channels = [name for name, ds in datasets.items() if _is_channel(ds)]
        if channel is None and "/deflection" in datasets:
            channel = "/deflection"
        index, t_index = choose_channels(
            names, _absolute(channel, datasets), _absolute(time_channel, datasets), file=path, listed=channels
        )
        name = names[index]
        dataset = datasets[name]
        values = as_samples(_read_dataset(dataset, path), file=path, channel=name)
        source = {"values": f"file:{name}"}

        units = _units(dataset)
        if units:
            source["units"] = f"file:{name}/attrs/units"
        else:
            units = split_units(name)[1]
            if units:
                source["units"] = f"file:dataset name {name!r}"

        time = t_name = None
        if t_index is not None:
            t_name = names[t_index]
            t_units = _units(datasets[t_name]) or split_units(t_name)[1]
            time = time_axis(_read_dataset(datasets[t_name], path), t_units, file=path, channel=t_name)
            source["time"] = f"file:{t_name}" + ("" if t_units else " (taken as s)")
        sample_rate = settle_rate(_stated_rate(dataset, path), time, t_name, source)

        if plain(h5.attrs.get("format")) == TRACE_FORMAT:
            metadata = _afmid_metadata(h5, datasets)
        else:
            metadata = {"root": _attrs(h5)}
        metadata["dataset"] = _attrs(dataset)
    return RawTrace(values, time, sample_rate, units, name, channels, metadata, source)


READER = Reader(
    name="hdf5",
    title="HDF5 dataset (any path; afmid trace files with their metadata)",
    suffixes=(".h5", ".hdf5", ".hdf"),
    read=read,
    list_channels=list_channels,
    extra=None,
    references=(
        "The HDF Group, HDF5 File Format Specification, https://docs.hdfgroup.org/hdf5/develop/_f_m_t3.html",
        "h5py, https://docs.h5py.org",
    ),
)

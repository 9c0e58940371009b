"""MATLAB ``.mat`` files: v4/v5/v7 via scipy, v7.3 (HDF5-based) via h5py.

Channels are numeric arrays addressed by a dotted path through structs and
cell arrays, as Zurich Instruments LabOne exports them:
``dev1234.demods.sample.x``. A struct or cell array with one element is
stepped through without an index; with several, the path takes a 0-based
index (``dev1234.demods.1.sample.x``). Run ``afmid inspect`` to list the paths.

Scalars are not channels but metadata; top-level scalars ``sample_rate`` (Hz)
or ``dt``/``time_step`` (s) set the sample rate. MAT files carry no units,
except in a variable name such as ``deflection_nm``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

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

_VERSIONS = {0: "4", 1: "5", 2: "7.3"}


def _join(prefix: str, part: str) -> str:
    return f"{prefix}.{part}" if prefix else part


def _version(path: Path) -> str:
    from scipy.io.matlab import matfile_version

    try:
        major, _ = matfile_version(str(path))
    except Exception as exc:  # scipy raises several types for a file that is not a MAT file
        raise not_readable("MATLAB", path, exc) from None
    return _VERSIONS.get(major, str(major))


# --------------------------------------------------------------------------- v4 to v7 (scipy)
def _v5_leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted path, value) of every leaf of ``loadmat(simplify_cells=True)`` output."""
    if isinstance(node, dict):
        for key, child in node.items():
            if not prefix and key.startswith("__"):  # __header__, __version__, __globals__
                continue
            yield from _v5_leaves(child, _join(prefix, key))
    elif isinstance(node, list) or (isinstance(node, np.ndarray) and node.dtype == object):
        # Cell arrays: numbered in MATLAB's column-major order, as in v7.3 files.
        items = list(node.ravel(order="F")) if isinstance(node, np.ndarray) else node
        if len(items) == 1:
            yield from _v5_leaves(items[0], prefix)
        else:
            for i, item in enumerate(items):
                yield from _v5_leaves(item, _join(prefix, str(i)))
    else:
        yield prefix, node


# --------------------------------------------------------------------------- v7.3 (HDF5)
def _h5_leaves(h5, node, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted path, dataset) of every leaf; structs are groups, struct/cell arrays hold references."""
    import h5py

    if isinstance(node, h5py.Group):
        for key in node:
            if key.startswith("#"):  # '#refs#', '#subsystem#': MATLAB's internal storage
                continue
            yield from _h5_leaves(h5, node[key], _join(prefix, key))
    elif h5py.check_dtype(ref=node.dtype) is not None:
        # Stored transposed, so C order here is MATLAB's column-major element order.
        refs = [ref for ref in np.ravel(node[()]) if ref]
        if len(refs) == 1:
            yield from _h5_leaves(h5, h5[refs[0]], prefix)
        else:
            for i, ref in enumerate(refs):
                yield from _h5_leaves(h5, h5[ref], _join(prefix, str(i)))
    else:
        yield prefix, node


def _h5_value(dataset, path: Path) -> Any:
    """A v7.3 dataset as MATLAB meant it: char arrays as text, empty arrays as empty."""
    matlab_class = plain(dataset.attrs.get("MATLAB_class"))
    if dataset.attrs.get("MATLAB_empty"):  # the data of an empty array are its dimensions
        return np.empty(0)
    check_array_size(dataset.shape, dataset.dtype, file=path, channel=dataset.name.lstrip("/").replace("/", "."))
    try:
        data = dataset[()]
    except OSError as exc:
        raise not_readable("MATLAB 7.3 (HDF5)", path, exc) from None
    if matlab_class == "char":
        return "".join(chr(c) for c in np.ravel(data))
    if matlab_class == "logical":
        data = data.astype(bool)
    # Squeezed like scipy's squeeze_me: MATLAB has no 1-D arrays or scalars, only matrices.
    return np.squeeze(data)


# --------------------------------------------------------------------------- both versions
def _is_channel(leaf: Any) -> bool:
    """Numeric with one axis longer than 1 (known without reading an HDF5 dataset)."""
    attrs = getattr(leaf, "attrs", None)
    if attrs is not None:
        if plain(attrs.get("MATLAB_class")) in ("char", "logical") or attrs.get("MATLAB_empty"):
            return False
        dtype, shape = leaf.dtype, leaf.shape
    else:
        array = np.asarray(leaf)
        dtype, shape = array.dtype, array.shape
    return dtype.kind in "iuf" and sum(n > 1 for n in shape) == 1


def _is_scalar(leaf: Any) -> bool:
    """Settings and labels (single numbers, text): metadata rather than channels."""
    attrs = getattr(leaf, "attrs", None)
    if attrs is not None:
        return plain(attrs.get("MATLAB_class")) == "char" or (not attrs.get("MATLAB_empty") and leaf.size <= 1)
    return isinstance(leaf, str) or np.size(leaf) == 1


@contextmanager
def _leaves(path: Path) -> Iterator[tuple[dict[str, Any], Callable[[Any], Any], str]]:
    """(dotted path -> leaf, function reading a leaf's value, MAT version), for either file version."""
    version = _version(path)
    if version != "7.3":
        from scipy.io import loadmat

        try:
            tree = loadmat(str(path), simplify_cells=True)
        except Exception as exc:  # scipy's parser fails in many ways on a damaged file
            raise not_readable("MATLAB", path, exc) from None
        yield dict(_v5_leaves(tree)), lambda leaf: leaf, version
        return
    import h5py

    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        raise not_readable("MATLAB 7.3 (HDF5)", path, exc) from None
    with h5:
        yield dict(_h5_leaves(h5, h5)), lambda dataset: _h5_value(dataset, path), version


def list_channels(path: Path) -> list[str]:
    """Dotted paths of the 1-D numeric arrays."""
    with _leaves(path) as (leaves, _, _):
        return [name for name, leaf in leaves.items() if _is_channel(leaf)]


def read(path: Path, channel: str | None = None, time_channel: str | None = None) -> RawTrace:
    """Read one variable (file units) by dotted path, and optionally a time variable (s)."""
    with _leaves(path) as (leaves, value, version):
        names = list(leaves)
        channels = [name for name in names if _is_channel(leaves[name])]
        index, t_index = choose_channels(names, channel, time_channel, file=path, listed=channels)
        name = names[index]
        values = as_samples(value(leaves[name]), file=path, channel=name)
        units = split_units(name)[1]
        source = {"values": f"file:{name}"}
        if units:
            source["units"] = f"file:variable name {name!r}"

        time = t_name = None
        if t_index is not None:
            t_name = names[t_index]
            t_units = split_units(t_name)[1]
            time = time_axis(value(leaves[t_name]), t_units, file=path, channel=t_name)
            source["time"] = f"file:{t_name}" + ("" if t_units else " (taken as s)")

        scalars = {key: plain(value(leaf)) for key, leaf in leaves.items() if _is_scalar(leaf)}

    top_level = {key: v for key, v in scalars.items() if "." not in key}
    stated = rate_from_fields(top_level, lambda key: f"variable {key!r}", file=path)
    sample_rate = settle_rate(stated, time, t_name, source)
    return RawTrace(values, time, sample_rate, units, name, channels, {"version": version, "scalars": scalars}, source)


READER = Reader(
    name="mat",
    title="MATLAB MAT-file (v5/v7 and v7.3; LabOne struct exports)",
    suffixes=(".mat",),
    read=read,
    list_channels=list_channels,
    extra=None,
    references=(
        "MathWorks, MAT-File Format (v5), https://www.mathworks.com/help/pdf_doc/matlab/matfile_format.pdf",
        "scipy.io.loadmat, https://docs.scipy.org/doc/scipy/reference/generated/scipy.io.loadmat.html",
        "Zurich Instruments, LabOne User Manual: data export to MATLAB, https://docs.zhinst.com",
    ),
)

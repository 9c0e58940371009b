"""Reading a force-map result (``afmid map``'s ``RESULT.h5``) for the report: its layout and version checked first.

A result is afmid's own file, but it may come from a newer afmid, be cut short by a tool, or be edited by hand.
Before anything is drawn, :func:`read_map_result` checks, each failure one :class:`afmid.errors.InputError`
naming the file and the dataset or attribute:

- ``format`` is ``afmid-map-result`` and ``format_version`` one this afmid reads (a newer one is refused with
  its number, :func:`afmid.runcheck.check_version`);
- the ``rows`` / ``cols`` attributes are positive whole numbers;
- ``/maps`` holds the maps the report draws (:data:`REQUIRED_MAPS`), and every map is ``rows x cols``;
- ``/x`` holds ``cols`` and ``/y`` ``rows`` positions (the axes of every map image);
- the groups' tables (``/groups``) have one entry per group.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmid.errors import InputError
from afmid.runcheck import check_version

MAP_RESULT_FORMAT = "afmid-map-result"
#: The maps :func:`afmid.report.maps.make_map_report` draws or counts whatever the model was.
REQUIRED_MAPS = ("status", "message", "separation", "separation_sigma", "cv_error", "cv_error_noise_floor")
#: The tables of ``/groups``, one entry per group, when the result has groups.
GROUP_TABLES = ("verdict", "effects", "sentence", "pixels", "fraction", "error_over_floor", "diagnosed")


def _whole(attrs, name: str, path: Path) -> int:
    value = attrs.get(name)
    try:
        number = int(value)
    except (TypeError, ValueError):
        number = None
    if number is None or number < 1 or number != value:
        raise InputError(f"must be a positive whole number (pixels), got {value!r}", file=path, key=name)
    return number


def check_layout(h5, path: Path) -> tuple[int, int]:
    """InputError unless the open map result ``h5`` (of file ``path``) is laid out as afmid writes it (see the
    module's docstring); returns (rows, cols)."""
    import h5py

    if h5.attrs.get("format") != MAP_RESULT_FORMAT:
        raise InputError(f"not a map result (format {h5.attrs.get('format')!r})", file=path, key="format")
    check_version(h5.attrs, path)
    rows, cols = _whole(h5.attrs, "rows", path), _whole(h5.attrs, "cols", path)
    if not isinstance(h5.get("maps"), h5py.Group):
        raise InputError("missing: the result holds no maps (damaged or not written by afmid map)", file=path,
                         key="/maps")
    for name in REQUIRED_MAPS:
        if not isinstance(h5["maps"].get(name), h5py.Dataset):
            raise InputError("missing: every map result has it (damaged, or edited by hand)", file=path,
                             key=f"/maps/{name}")
    for name, item in h5["maps"].items():
        shape = getattr(item, "shape", None)
        if shape != (rows, cols):
            raise InputError(f"has shape {shape}, expected the map's (rows, cols) = ({rows}, {cols})", file=path,
                             key=f"/maps/{name}")
    for axis, length in (("x", cols), ("y", rows)):
        if axis in h5:
            shape = getattr(h5[axis], "shape", None)
            if shape != (length,):
                raise InputError(f"has shape {shape}, expected ({length},): one position per "
                                 f"{'column' if axis == 'x' else 'row'} of the map", file=path, key=f"/{axis}")
    if isinstance(h5.get("groups"), h5py.Group) and "verdict" in h5["groups"]:
        count = h5["groups/verdict"].shape[:1]
        for name in GROUP_TABLES:
            if getattr(h5["groups"].get(name), "shape", None) != count:
                raise InputError(f"expected one entry per group ({count[0] if count else 0})", file=path,
                                 key=f"/groups/{name}")
    return rows, cols


def read_map_result(path: Path) -> dict:
    """The maps of result ``path`` (name -> (values, units, meaning)), its root attributes and its pixel size (m,
    None when it has no ``/x``), after :func:`check_layout`. A file HDF5 cannot read is one InputError."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            check_layout(h5, Path(path))
            maps = {name: (ds[()], str(ds.attrs.get("units", "")), str(ds.attrs.get("meaning", "")))
                    for name, ds in h5["maps"].items()}
            attrs = {k: h5.attrs[k] for k in h5.attrs}
            pixel_size = None
            if "x" in h5 and h5["x"].size > 1:
                x = np.asarray(h5["x"][()]).ravel()
                pixel_size = float(abs(x[1] - x[0]))
    except (OSError, KeyError, TypeError, ValueError) as exc:  # h5py: an unreadable object or chunk
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"damaged map result: cannot read its contents ({first})", file=path) from None
    return {"maps": maps, "attrs": attrs, "pixel_size": pixel_size}

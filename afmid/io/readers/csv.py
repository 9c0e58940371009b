"""Delimited text: CSV, TSV, whitespace-separated columns.

The structure (delimiter, header, where the numbers start) is detected from
the first lines; the numbers are then parsed by ``np.loadtxt``, whose C parser
(numpy >= 1.23) reads 10^6 rows in about a second. Only if that fails is the
file scanned line by line, to say which value in which row is wrong.

Layout rules:

- lines starting with ``#`` or ``%`` and blank lines are skipped;
- the delimiter is the first of tab, ``;``, ``,`` that occurs on every sampled
  row, else runs of whitespace;
- the first row is a header if any of its fields is not a number; failing
  that, a comment line right above the data with one name per column (as
  ``np.savetxt(header=...)`` writes it) names the columns;
- ``key: value`` or ``key = value`` comment lines before the data are kept in
  ``metadata['header_fields']``; ``sample_rate`` (Hz) or ``dt``/``time_step`` (s)
  among them set the sample rate;
- units come from the column name: ``deflection_nm``, ``deflection [nm]``,
  ``time (s)``;
- numbers written with decimal commas are refused, not guessed at: rows of
  ``1,234`` values separated by tabs, ``;`` or spaces, and a lone ``a,b`` per
  row when a leading zero after the comma, an exponent or ``-0,`` shows it is
  no pair of integers (a headerless file of two integer columns is still read).

Columns are chosen by name or by 0-based index (an int or a digit string).
Files without a header name their columns '0', '1', ...
"""

from __future__ import annotations

import contextlib
import csv as _csv
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afmid.errors import InputError
from afmid.io.files import safe_excerpt
from afmid.io.readers.base import (
    COLUMN_KEY,
    RawTrace,
    Reader,
    check_array_size,
    choose_channels,
    quoted,
    rate_from_fields,
    settle_rate,
    split_units,
    time_axis,
)

_COMMENTS = ("#", "%")
_DELIMITERS = ("\t", ";", ",")
_SAMPLE_ROWS = 50  # rows inspected to detect the layout
_ENCODING_PROBE = 1 << 16  # bytes inspected to choose the text encoding
_FIELD_LINE = re.compile(r"^[#%]+\s*(?P<key>[A-Za-z][\w .-]*?)\s*[:=]\s*(?P<value>.*?)\s*$")
_DECIMAL_COMMA = re.compile(r"^[-+]?\d+,\d*(?:[eE][-+]?\d+)?$")
_DECIMAL_COMMA_NUMBER = r"[-+]?\d+,\d+(?:[eE][-+]?\d+)?"
#: A row of decimal-comma numbers, separated by tabs, semicolons or spaces (or one number alone).
_DECIMAL_COMMA_ROW = re.compile(rf"^{_DECIMAL_COMMA_NUMBER}(?:\s*[;\t ]\s*{_DECIMAL_COMMA_NUMBER})*$")
#: In "a,b" alone, what an integer pair never is: a fraction with a leading zero ("0,05"), an exponent ("1,5e-09"),
#: a signed zero before the comma ("-0,5").
_DECIMAL_COMMA_EVIDENCE = re.compile(r"^(?:[-+]0,\d+|[-+]?\d+,0\d+|[-+]?\d+,\d+[eE][-+]?\d+)$")
_VALUE_CHARS = 20  # longest excerpt of a bad value in a message
_DELIMITER_NAMES = {"\t": "tab", ";": "semicolon", ",": "comma", None: "whitespace"}


@dataclass
class _Layout:
    """What the first lines of a file say about its structure."""

    encoding: str
    delimiter: str | None  # None: runs of whitespace
    quoted: bool  # fields are enclosed in double quotes
    comment: tuple[str, ...]  # comment characters to pass to np.loadtxt
    names: list[str]
    header: str | None  # 'row', 'comment' or None (columns named by index)
    data_start: int  # 0-based line number of the first data row
    row_chars: float = 1.0  # mean length of the sampled data rows, with the line end (to estimate the row count)
    fields: dict[str, str] = field(default_factory=dict)
    field_lines: dict[str, int] = field(default_factory=dict)  # key -> 1-based line number


def _encoding(path: Path) -> str:
    """UTF-16 if marked so (Windows 'Unicode text' exports), else UTF-8 if the start decodes as such, else Latin-1."""
    with open(path, "rb") as fh:
        probe = fh.read(_ENCODING_PROBE)
    if probe.startswith((b"\xff\xfe", b"\xfe\xff")):
        return "utf-16"
    if b"\0" in probe:
        raise InputError("not a text file (it holds binary data); is the format right?", file=path, key="data.format")
    if probe.startswith(b"\xef\xbb\xbf"):
        return "utf-8-sig"
    try:
        probe.decode("utf-8")
    except UnicodeDecodeError as exc:
        # A multi-byte character cut by the end of the probe is not an error.
        if exc.start < len(probe) - 3:
            return "latin-1"
    return "utf-8"


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        tokens = line.split()
        # Keep a bracketed unit with its name: 'deflection [nm]' is one header field.
        merged: list[str] = []
        for token in tokens:
            if merged and token[:1] in "[(":
                merged[-1] += " " + token
            else:
                merged.append(token)
        return merged
    return [f.strip() for f in next(_csv.reader([line], delimiter=delimiter))]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _sniff_delimiter(rows: list[str]) -> str | None:
    # Present on every row is enough: a ragged row must still split on the
    # file's delimiter, so that it can be reported as ragged.
    for delimiter in _DELIMITERS:
        if all(delimiter in row for row in rows):
            return delimiter
    return None


def _require_numbers(path: Path, rows: list[tuple[int, str]], delimiter: str | None) -> None:
    """Refuse a file none of whose first rows holds a number: not a data table (``/etc/passwd``, a key file).

    Messages about such a file never quote it: only files that look like data
    have their column names (and short excerpts of bad values) shown.
    """
    for _, text in rows:
        if any(_is_number(f) or _DECIMAL_COMMA.match(f) for f in _split(text, delimiter)):
            return
    raise InputError(
        f"not a table of numbers: none of its first {len(rows)} rows holds a number; is the file a trace?",
        file=path,
    )


def _refuse_decimal_commas(path: Path, rows: list[tuple[int, str]]) -> None:
    """Refuse a file whose numbers are written with decimal commas (a header row above them allowed).

    Split on its commas, a headerless single-column file "1,234" read as two integer columns, and the integer
    part was fitted as the trace. Values separated by tabs, semicolons or spaces make the comma a
    decimal comma without doubt; "a,b" alone only with evidence an integer pair never shows
    (:data:`_DECIMAL_COMMA_EVIDENCE`), so a headerless file of two integer columns is still read.
    """
    data = [text for _, text in rows]
    if data and not _DECIMAL_COMMA_ROW.match(data[0]):
        data = data[1:]  # a header
    if not data or not all(_DECIMAL_COMMA_ROW.match(text) for text in data):
        return
    separated = any(re.search(r"[;\t ]", text) for text in data)
    if separated or any(_DECIMAL_COMMA_EVIDENCE.match(text) for text in data):
        raise InputError(f"the numbers are written with decimal commas ({_excerpt(data[0])}), but afmid reads '.' "
                         "as the decimal separator and ',' as a delimiter; export with '.' as the decimal separator",
                         file=path, key=COLUMN_KEY)


def _layout(path: Path) -> _Layout:
    encoding = _encoding(path)
    preamble: list[tuple[int, str]] = []  # comment lines before the first row
    rows: list[tuple[int, str]] = []
    seen: set[str] = set()  # comment characters in use
    with open(path, encoding=encoding, errors="replace") as fh:
        for number, line in enumerate(fh):
            text = line.strip()
            if not text:
                continue
            if text.startswith(_COMMENTS):
                seen.add(text[0])
                if not rows:
                    preamble.append((number, text))
                continue
            rows.append((number, text))
            if len(rows) > _SAMPLE_ROWS:
                break
    if not rows:
        raise InputError("no data rows (empty, or only comments)", file=path)
    _refuse_decimal_commas(path, rows)

    delimiter = _sniff_delimiter([text for _, text in rows[1:]] or [rows[0][1]])
    if len(rows) > 1:  # a single row is a header without data, reported below
        _require_numbers(path, rows, delimiter)
    has_quotes = any('"' in text for _, text in rows)
    first = _split(rows[0][1], delimiter)
    # Decimal-comma numbers are not a header; they fail later with a hint.
    header = "row" if any(not (_is_number(f) or _DECIMAL_COMMA.match(f)) for f in first) else None
    data_rows = rows[1:] if header else rows
    if not data_rows:
        raise InputError("no data rows, only a header", file=path)
    n_columns = len(_split(data_rows[0][1], delimiter))
    names = [str(i) for i in range(n_columns)]
    if header:
        if len(first) != n_columns:
            raise InputError(
                f"the header (line {rows[0][0] + 1}) has {len(first)} names but the first data row has "
                f"{n_columns} values ({_DELIMITER_NAMES[delimiter]}-separated)",
                file=path,
            )
        names = [name or str(i) for i, name in enumerate(first)]
    elif preamble and preamble[-1][0] == rows[0][0] - 1:
        candidate = _split(preamble[-1][1].lstrip("#%").strip(), delimiter)
        if len(candidate) == n_columns and not any(_is_number(f) for f in candidate):
            names, header = candidate, "comment"

    fields: dict[str, str] = {}
    field_lines: dict[str, int] = {}
    for number, text in preamble:
        match = _FIELD_LINE.match(text)
        if match:
            key = re.sub(r"[\s.-]+", "_", match["key"].strip().lower())
            fields[key], field_lines[key] = match["value"], number + 1

    # One comment character keeps np.loadtxt on its fast path (two take twice as
    # long), and with quote handling it accepts only one.
    used = tuple(c for c in _COMMENTS if c in seen) or _COMMENTS[:1]
    return _Layout(
        encoding=encoding,
        delimiter=delimiter,
        quoted=has_quotes,
        comment=used[:1] if has_quotes else used,
        names=names,
        header=header,
        data_start=data_rows[0][0],
        row_chars=sum(len(text) + 1 for _, text in data_rows) / len(data_rows),
        fields=fields,
        field_lines=field_lines,
    )


def _bad_value(path: Path, layout: _Layout, columns: list[int]) -> InputError:
    """Find the first unparsable value in ``columns`` and describe it (slow; error path only)."""
    row = 0
    with open(path, encoding=layout.encoding, errors="replace") as fh:
        for number, line in enumerate(fh):
            if number < layout.data_start:
                continue
            text = line.split(layout.comment[0], 1)[0] if layout.quoted else re.split(r"[#%]", line, maxsplit=1)[0]
            text = text.strip()
            if not text:
                continue
            row += 1
            values = _split(text, layout.delimiter)
            where = f"row {row} (line {number + 1})"
            for column in columns:
                name = layout.names[column]
                if column >= len(values):
                    return InputError(
                        f"{where} has {len(values)} values, too few for column {quoted(name)} (number {column})",
                        file=path,
                        key=COLUMN_KEY,
                    )
                value = values[column]
                if not _is_number(value) or "_" in value:  # float() accepts '1_000', np.loadtxt does not
                    hint = ""
                    if _DECIMAL_COMMA.match(value):
                        hint = "; decimal commas are not supported, export with '.' as the decimal separator"
                    what = "an empty value" if not value else f"{_excerpt(value)}, not a number"
                    return InputError(f"column {quoted(name)}: {what} at {where}{hint}", file=path, key=COLUMN_KEY)
    return InputError("the numbers could not be parsed", file=path, key=COLUMN_KEY)


def _excerpt(value: str) -> str:
    """A bad value for a message: quoted, printable ASCII, at most 20 characters (the policy of afmid.io.files)."""
    return repr(safe_excerpt(value, _VALUE_CHARS))


def _load(path: Path, layout: _Layout, columns: list[int]) -> np.ndarray:
    """The given columns as a (rows, len(columns)) float64 array."""

    def load(comments: tuple[str, ...]) -> np.ndarray:
        with open(path, encoding=layout.encoding, errors="replace") as fh:
            return np.loadtxt(
                fh,
                dtype=np.float64,
                delimiter=layout.delimiter,
                comments=comments,
                quotechar='"' if layout.quoted else None,
                skiprows=layout.data_start,
                usecols=columns,
                ndmin=2,
            )

    try:
        return load(layout.comment)
    except ValueError:
        pass
    if not layout.quoted and layout.comment != _COMMENTS:
        # A comment style first used past the sampled rows: retry with both.
        with contextlib.suppress(ValueError):
            return load(_COMMENTS)
    raise _bad_value(path, layout, columns)


def list_channels(path: Path) -> list[str]:
    """Column names (header names, or '0', '1', ... without a header)."""
    return list(_layout(path).names)


def read(path: Path, channel: str | int | None = None, time_channel: str | int | None = None) -> RawTrace:
    """Read one column (file units) and optionally a time column (converted to s)."""
    layout = _layout(path)
    names = layout.names
    index, time_index = choose_channels(names, channel, time_channel, file=path, positional=True)
    columns = [index] if time_index is None else [index, time_index]
    estimated_rows = path.stat().st_size / layout.row_chars
    check_array_size((round(estimated_rows), len(columns)), np.float64, file=path, channel=names[index])
    data = _load(path, layout, columns)

    name = names[index]
    units = split_units(name)[1] if layout.header else None
    source = {"values": f"file:column {name!r}"}
    if units:
        source["units"] = f"file:column name {name!r}"
    time = time_name = None
    if time_index is not None:
        time_name = names[time_index]
        time_units = split_units(time_name)[1] if layout.header else None
        time = time_axis(data[:, 1], time_units, file=path, channel=time_name)
        source["time"] = f"file:column {time_name!r}" + ("" if time_units else " (taken as s)")
    stated = rate_from_fields(layout.fields, lambda key: f"comment line {layout.field_lines[key]} ({key})", file=path)
    return RawTrace(
        values=np.ascontiguousarray(data[:, 0]),
        time=time,
        sample_rate=settle_rate(stated, time, time_name, source),
        units=units,
        channel=name,
        channels=list(names),
        metadata={
            "delimiter": _DELIMITER_NAMES[layout.delimiter],
            "header": layout.header,
            "header_fields": dict(layout.fields),
        },
        source=source,
    )


READER = Reader(
    name="csv",
    title="Delimited text (CSV, TSV, whitespace columns)",
    suffixes=(".csv", ".txt", ".dat", ".tsv"),
    read=read,
    list_channels=list_channels,
    extra=None,
    references=(
        "RFC 4180, Common Format and MIME Type for CSV Files, https://www.rfc-editor.org/rfc/rfc4180",
        "numpy.loadtxt, https://numpy.org/doc/stable/reference/generated/numpy.loadtxt.html",
    ),
)

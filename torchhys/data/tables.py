"""One data file's columns, read and checked: a CSV file or an NPZ file's arrays
(:func:`torchhys.data.files.read_recordings` cuts them into recordings).

CSV files are read as spreadsheets and loggers write them:

* text in UTF-8, with or without a byte-order mark (Excel's "CSV UTF-8"), or in the
  ``encoding`` given (``"latin-1"``, ``"cp1252"``, ...);
* fields separated by ``,``, ``;`` or a tab, found from the first lines (the one that gives
  every line the same number of fields, more than one; ``,`` first), or by the ``delimiter``
  given;
* numbers with a decimal point, or with a decimal comma (``decimal=","``: ``1,5`` is 1.5;
  the fields are then separated by ``;`` or a tab);
* an optional header row, ``#`` comment lines before the data, and blank lines (or lines of
  empty fields) anywhere, which are skipped.

Every problem is reported as a :class:`DataFileError` (a ``ValueError``) that names the
file, the column and, where it applies, the row (0-based data row; for CSV files also the
1-based line of the file) or the recording: a row with more or fewer fields than the
header, text that is not in the file's encoding, a value that is not a finite number.
"""

from __future__ import annotations

import codecs
import csv
import io
import math
import re
from array import array
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "DECIMALS", "DELIMITERS", "Column", "DataFileError", "RecordingId", "check_text_options",
    "recording_id",
]

DELIMITERS = (",", ";", "\t")
"""The delimiters a CSV file is sniffed for, in order of preference."""
DECIMALS = (".", ",")
"""The decimal marks of numbers in a CSV file."""
_DELIMITER_NAMES = {"tab": "\t", "\\t": "\t", "comma": ",", "semicolon": ";"}

Column = str | int
"""A column by header name (CSV) / array key (NPZ), or by 0-based index."""
RecordingId = int | str
"""A recording's id: its run-column value (an int when the value is integral, else the text
as written), or the file's index in the list of files when each file is one recording."""


class DataFileError(ValueError):
    """A problem in a data file, naming the file, the column and the row."""


def recording_id(value: object) -> RecordingId:
    """The id of a run-column value: an int when it is an integral number, else its text
    (``3``, ``3.0`` and ``"3"`` are all ``3``; ``"A"`` stays ``"A"``)."""
    if isinstance(value, (bool, np.bool_)):
        return str(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    text = str(value).strip()
    try:
        number = float(text)
    except ValueError:
        return text
    return int(number) if number.is_integer() else text


def check_text_options(encoding: object, delimiter: object, decimal: object, *,
                       prefix: str = "") -> str | None:
    """Check the CSV options ``encoding``, ``delimiter`` and ``decimal`` (see
    :func:`read_recordings`) and return the delimiter as a character (``"tab"`` and the two
    characters ``\\t`` are a tab) or None (sniffed).

    Raises:
        ValueError: a bad value; the message names the option as ``prefix + name`` (e.g.
            ``data.decimal``).
    """
    if decimal not in DECIMALS:
        raise ValueError(f"{prefix}decimal must be '.' or ',', got {decimal!r}")
    if encoding is not None:
        if not isinstance(encoding, str):
            raise ValueError(f"{prefix}encoding must be the name of a text encoding "
                             f"(utf-8, latin-1, cp1252, ...) or null, got {encoding!r}")
        try:
            codecs.lookup(encoding)
        except LookupError:
            raise ValueError(f"{prefix}encoding {encoding!r} is not a known text encoding; "
                             "use e.g. utf-8, latin-1 or cp1252") from None
    if delimiter is None:
        return None
    if isinstance(delimiter, str):
        delimiter = _DELIMITER_NAMES.get(delimiter.lower(), delimiter)
    if (not isinstance(delimiter, str) or len(delimiter) != 1 or delimiter.isalnum()
            or delimiter in '"\r\n.+-#'):
        raise ValueError(f"{prefix}delimiter must be one character such as ',', ';' or a tab "
                         f"('\\t' or 'tab'), or null to sniff it, got {delimiter!r}")
    if delimiter == decimal:
        raise ValueError(f"{prefix}delimiter {delimiter!r} cannot also be the decimal mark "
                         f"({prefix}decimal {decimal!r}): files with decimal commas separate "
                         "their fields with ';' or a tab")
    return delimiter


_ZIP = b"PK\x03\x04"
"""The first bytes of a zip file: an .xlsx (or .ods) spreadsheet."""
_OLE2 = bytes.fromhex("d0cf11e0a1b11ae1")
"""The first bytes of an OLE2 compound file: an .xls spreadsheet."""


def _decode(path: Path, encoding: str | None) -> str:
    """The text of a file: UTF-8 with an optional byte-order mark, or ``encoding``."""
    data = path.read_bytes()
    if data.startswith((_ZIP, _OLE2)):
        kind = "an .xlsx (zip)" if data.startswith(_ZIP) else "an .xls (OLE2)"
        raise DataFileError(
            f"{path}: the file is {kind} spreadsheet, not CSV text (whatever its name); "
            "save it from the spreadsheet as CSV (File > Save As > CSV UTF-8)")
    skip = 0
    if encoding is None and data.startswith(codecs.BOM_UTF8):
        skip = len(codecs.BOM_UTF8)
    try:
        text = data[skip:].decode(encoding or "utf-8")
    except UnicodeDecodeError as exc:
        start = exc.start + skip
        line = data.count(b"\n", 0, start) + 1
        if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
            fix = "it starts with a UTF-16 byte-order mark: set encoding='utf-16'"
        elif encoding is None or codecs.lookup(encoding).name == "utf-8":
            fix = ("the file is not UTF-8; give its encoding: encoding='latin-1' "
                   "(data.encoding: latin-1), or 'cp1252' for a file from Windows")
        else:
            fix = ("give the file's encoding: encoding='latin-1' (data.encoding: latin-1) "
                   "reads any bytes")
        raise DataFileError(
            f"{path}: byte {start} (line {line}) is {data[start:exc.end]!r}, which is not "
            f"{encoding or 'utf-8'} text ({exc.reason}); {fix}"
        ) from None
    return text[1:] if text.startswith("\ufeff") else text


def _blank(row: list[str]) -> bool:
    """A row of only empty (or whitespace) fields."""
    return all(not f.strip() for f in row)


def _sniff(lines: list[str], decimal: str) -> tuple[str, bool]:
    """The delimiter of the first data lines (comments and blank lines left out), and whether
    it gives them all the same number of fields, more than one."""
    candidates = [d for d in DELIMITERS if d != decimal]
    counts = {}
    for d in candidates:
        rows = [r for r in csv.reader(lines, delimiter=d) if not _blank(r)]
        counts[d] = [len(r) for r in rows]
    for d in candidates:
        if counts[d] and len(set(counts[d])) == 1 and counts[d][0] > 1:
            return d, True
    # none consistent: the one that splits the first line (the header) most
    best = max(candidates, key=lambda d: counts[d][0] if counts[d] else 0)
    return best, False


def _looks_decimal_comma(fields: list[str], expected: int) -> bool:
    """More fields than expected, all of them whole numbers: ``1,5`` read as ``1`` and
    ``5``."""
    return len(fields) > expected and all(
        re.fullmatch(r"[+-]?\d+([eE][+-]?\d+)?", f.strip()) for f in fields if f.strip())


_DECIMAL_OPTION = "set decimal=',' (data.decimal: ',')"
_DECIMAL_HINT = (f"{_DECIMAL_OPTION} and separate the fields with ';' (the delimiter such "
                 "files normally use)")


def _lines_of(text: str) -> Iterator[str]:
    """The lines of ``text`` with their line ends, as ``io.StringIO(text, newline="")`` gives
    them, without its copy of the text (a line ends at ``\\n``; text with a lone ``\\r``
    goes through StringIO)."""
    if text.count("\r") != text.count("\r\n"):
        yield from io.StringIO(text, newline="")
        return
    start, end = 0, len(text)
    while start < end:
        stop = text.find("\n", start)
        stop = end if stop < 0 else stop + 1
        yield text[start:stop]
        start = stop


class _Csv(NamedTuple):
    """A CSV file parsed: header names (``str(index)`` without a header), every column as
    float64 (NaN where a field is not a number), the 1-based line of each data row, and what
    reading the fields again needs (:func:`_fields`)."""

    names: list[str]
    values: np.ndarray
    """(rows, columns) float64."""
    lines: np.ndarray
    text: str
    delimiter: str
    header: bool


def _data_rows(table: _Csv) -> Iterator[list[str]]:
    """The data rows of a parsed file again, as lists of fields (for ids and messages): the
    rows :func:`_read_csv` kept, in order."""
    started = False
    for row in csv.reader(_lines_of(table.text), delimiter=table.delimiter):
        if _blank(row) or not started and row[0].lstrip().startswith("#"):
            continue
        if not started:
            started = True
            if table.header:
                continue
        yield row


def _read_csv(path: Path, encoding: str | None, delimiter: str | None,
              decimal: str) -> _Csv:
    """Parse a CSV file (see the module docstring) into float64 columns, checking that every
    row has the header's number of fields."""
    text = _decode(path, encoding)
    if delimiter is None:
        sample = []
        for raw in _lines_of(text):
            if raw.strip() and not raw.lstrip().startswith("#"):
                sample.append(raw)
                if len(sample) == 50:
                    break
        delimiter, consistent = _sniff(sample, decimal)
        commas = [len(r) for r in csv.reader(sample) if not _blank(r)]
        if decimal == "," and not consistent and commas and commas[0] > 1:
            fix = ("leave decimal '.' for a file with decimal points" if len(set(commas)) == 1
                   else "save the file with ';' between the fields")
            raise DataFileError(
                f"{path}: the fields are separated by ',', which decimal=',' (data.decimal) "
                f"makes the decimal mark; {fix}"
            )
    reader = csv.reader(_lines_of(text), delimiter=delimiter)
    values, lines = array("d"), array("q")
    names: list[str] | None = None
    has_header = underscores = False
    what, n = "", 0
    last = 0
    try:
        for row in reader:
            line, last = last + 1, reader.line_num
            if names is None:
                if not row or row[0].lstrip().startswith("#") or _blank(row):
                    continue
                head = [c.strip() for c in row]
                has_header = not all(_is_number(c, decimal) for c in head)
                names = head if has_header else [str(i) for i in range(len(head))]
                what, n = ("the header" if has_header else "the first row"), len(names)
                # float() reads 1_000 as 1000: rows are checked for '_' where the data has any
                underscores = text.count("_") > sum(c.count("_") for c in row) * has_header
                if has_header:
                    continue
            elif _blank(row):
                continue
            if len(row) != n:
                hint = ""
                if decimal == "." and delimiter == "," and _looks_decimal_comma(row, n):
                    hint = (f"; the file looks like it uses decimal commas ('1,5' split into "
                            f"'1' and '5'): {_DECIMAL_HINT}")
                raise DataFileError(
                    f"{path}: line {line}: expected {n} fields as {what}, got {len(row)} "
                    f"(delimiter {delimiter!r}){hint}"
                )
            values.extend(_numbers(row, decimal, underscores))
            lines.append(line)
    except csv.Error as exc:
        raise DataFileError(f"{path}: line {reader.line_num}: {exc}") from None
    if names is None:
        raise DataFileError(f"{path}: the file holds no data rows")
    table = np.frombuffer(values, dtype=np.float64).reshape(-1, n) if n else np.zeros((0, 0))
    return _Csv(names, table, np.frombuffer(lines, dtype=np.int64), text, delimiter,
                has_header)


def _numbers(row: list[str], decimal: str, underscores: bool) -> list[float]:
    """The numbers of a row's fields, NaN for a field that is not one (:func:`_number`;
    ``underscores``: the row may hold ``_``, which float() would take)."""
    try:
        if underscores and any("_" in f for f in row):
            raise ValueError
        if decimal == ",":
            return [float(f.replace(",", ".")) for f in row]
        return list(map(float, row))
    except ValueError:
        return [_number(f.strip(), decimal) for f in row]


def as_column(column: Column, names: list[str]) -> Column:
    """A column as the file's ``names`` read it: an integer, or a string of digits (as the
    command line gives ``--data.input_column 2``), names the column of that name where the
    header has one, else it is a 0-based index; any other string is a name."""
    if isinstance(column, str) and re.fullmatch(r"\d+", column.strip()):
        return column if column in names else int(column)
    if isinstance(column, int) and not isinstance(column, bool) and str(column) in names:
        return str(column)
    return column


def _index(path: Path, names: list[str], column: Column, role: str) -> int:
    column = as_column(column, names)
    if isinstance(column, int) and not isinstance(column, bool):
        if not 0 <= column < len(names):
            raise DataFileError(
                f"{path}: column index {column} ({role}) is out of range: the file has "
                f"{len(names)} columns {names}"
            )
        return column
    if column not in names:
        raise DataFileError(
            f"{path}: column {column!r} ({role}) not found; the file's columns are {names}"
        )
    where = [i for i, name in enumerate(names) if name == column]
    if len(where) > 1:
        raise DataFileError(
            f"{path}: column {column!r} ({role}) is the name of {len(where)} columns (indices "
            f"{where}); rename them in the header, or give the column by its index"
        )
    return where[0]


class _Table:
    """The columns of one CSV or NPZ file, by name or index (CSV: read with ``encoding``,
    ``delimiter`` (None: sniffed) and ``decimal``, see :func:`read_recordings`)."""

    def __init__(self, path: Path, encoding: str | None = None, delimiter: str | None = None,
                 decimal: str = ".") -> None:
        if not path.is_file():
            raise DataFileError(f"{path}: no such file")
        self.path = path
        self.decimal = decimal
        self._csv: _Csv | None = None
        self._arrays: dict[str, np.ndarray] | None = None
        suffix = path.suffix.lower()
        if suffix == ".csv":
            self._csv = _read_csv(path, encoding, delimiter, decimal)
            self.names = self._csv.names
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                self._arrays = {k: np.asarray(data[k]) for k in data.keys()}
            self.names = list(self._arrays)
        else:
            raise DataFileError(f"{path}: unknown file type {suffix!r}; use .csv or .npz")

    def line(self, row: int) -> str:
        """`` (line N)`` of a data row in a CSV file, ``""`` in an NPZ file."""
        return "" if self._csv is None else f" (line {int(self._csv.lines[row])})"

    def _texts(self, idx: int) -> list[str]:
        """The stripped texts of a CSV file's column ``idx``, read again from the text."""
        return [r[idx].strip() for r in _data_rows(self._csv)]

    def _text(self, idx: int, row: int) -> str:
        """The stripped text of one field of a CSV file."""
        for i, r in enumerate(_data_rows(self._csv)):
            if i == row:
                return r[idx].strip()
        raise AssertionError(f"row {row} not found")

    def _raw(self, column: Column, role: str) -> tuple[str, np.ndarray]:
        """The column's name and its values (NPZ)."""
        path = self.path
        keys = self.names
        column = as_column(column, keys)
        if isinstance(column, str) and column in keys:
            arr = self._arrays[column]
            if arr.ndim != 1:
                raise DataFileError(
                    f"{path}: array {column!r} ({role}) must be one-dimensional, got shape "
                    f"{arr.shape}"
                )
            return column, arr
        if isinstance(column, int) and not isinstance(column, bool) and len(keys) == 1:
            table = self._arrays[keys[0]]
            if table.ndim != 2 or not 0 <= column < table.shape[1]:
                raise DataFileError(
                    f"{path}: column index {column} ({role}) needs a 2-D array with more "
                    f"than {column} columns; array {keys[0]!r} has shape {table.shape}"
                )
            return f"{keys[0]}[:, {column}]", table[:, column]
        raise DataFileError(
            f"{path}: column {column!r} ({role}) not found; the file's arrays are {keys}"
        )

    def column(self, column: Column, role: str) -> np.ndarray:
        """A column of finite numbers, float64, (rows,)."""
        if self._csv is not None:
            idx = _index(self.path, self.names, column, role)
            name, out = self.names[idx], np.ascontiguousarray(self._csv.values[:, idx])
            bad = np.flatnonzero(~np.isfinite(out))
            if bad.size:
                i = int(bad[0])
                text = self._text(idx, i)
                fix = "remove or fill the row"
                if self.decimal == "." and re.fullmatch(r"[+-]?\d*,\d+([eE][+-]?\d+)?", text):
                    fix = f"the file looks like it uses decimal commas: {_DECIMAL_OPTION}"
                elif "_" in text and _is_number(text.replace("_", ""), self.decimal):
                    fix = "write numbers without '_' between the digits (1000, not 1_000)"
                raise DataFileError(
                    f"{self.path}: column {name!r} ({role}), row {i}{self.line(i)}: "
                    f"{repr(text) if text else 'an empty cell'} is not a finite number; {fix}"
                )
            return out
        name, raw = self._raw(column, role)
        if not (np.issubdtype(raw.dtype, np.floating) or np.issubdtype(raw.dtype, np.integer)):
            raise DataFileError(f"{self.path}: column {name!r} ({role}) must hold real "
                                f"numbers, got dtype {raw.dtype}")
        try:
            out = np.asarray(raw, dtype=np.float64)
        except ValueError as exc:
            raise DataFileError(
                f"{self.path}: column {name!r} ({role}) is not numeric: {exc}"
            ) from None
        bad = np.flatnonzero(~np.isfinite(out))
        if bad.size:
            i = int(bad[0])
            raise DataFileError(
                f"{self.path}: column {name!r} ({role}), row {i}: {raw[i]} is not a finite "
                f"number ({bad.size} such rows); remove or fill them"
            )
        return out

    def ids(self, column: Column, role: str) -> list[RecordingId]:
        """A column of recording ids (see :func:`recording_id`), (rows,)."""
        if self._csv is not None:
            idx = _index(self.path, self.names, column, role)
            name, raw = self.names[idx], self._texts(idx)
        else:
            name, raw = self._raw(column, role)
        for i, v in enumerate(raw):
            if isinstance(v, str) and not v:
                raise DataFileError(
                    f"{self.path}: column {name!r} ({role}), row {i}{self.line(i)}: empty "
                    "value; every row needs its recording id"
                )
        if self._csv is not None and self.decimal == ",":
            raw = [v.replace(",", ".") if _is_number(v, ",") else v for v in raw]
        return [recording_id(v) for v in raw]


def _is_number(text: str, decimal: str) -> bool:
    if "_" in text:  # float() reads 1_000 as 1000
        return False
    try:
        float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        return False
    return True


def _number(text: str, decimal: str = ".") -> float:
    """The number a CSV field holds (``decimal=","``: ``1,5`` is 1.5), NaN if none (and for
    ``1_000``, which float() would read as 1000)."""
    if "_" in text:
        return math.nan
    try:
        return float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        return math.nan

"""One data file's columns, read and checked: a CSV file or an NPZ file's arrays
(:func:`torchhys.training.files.read_recordings` cuts them into recordings).

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
from pathlib import Path

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


def _decode(path: Path, encoding: str | None) -> str:
    """The text of a file: UTF-8 with an optional byte-order mark, or ``encoding``."""
    data = path.read_bytes()
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


def _read_csv(path: Path, encoding: str | None, delimiter: str | None,
              decimal: str) -> tuple[list[str], list[list[str]], list[int]]:
    """Header names (``str(index)`` without a header), data rows (each with the header's
    number of fields) and the 1-based line of each data row."""
    text = _decode(path, encoding)
    if delimiter is None:
        sample = []
        for raw in io.StringIO(text, newline=""):
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
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    rows, lines = [], []
    last = 0
    try:
        for row in reader:
            line, last = last + 1, reader.line_num
            if rows or (row and not row[0].lstrip().startswith("#")):
                if not _blank(row):
                    rows.append(row)
                    lines.append(line)
    except csv.Error as exc:
        raise DataFileError(f"{path}: line {reader.line_num}: {exc}") from None
    if not rows:
        raise DataFileError(f"{path}: the file holds no data rows")
    head = [c.strip() for c in rows[0]]
    has_header = not all(_is_number(c, decimal) for c in head)
    names = head if has_header else [str(i) for i in range(len(head))]
    what = "the header" if has_header else "the first row"
    for row, line in zip(rows, lines, strict=True):
        if len(row) != len(names):
            hint = ""
            if decimal == "." and delimiter == "," and _looks_decimal_comma(row, len(names)):
                hint = (f"; the file looks like it uses decimal commas ('1,5' split into '1' "
                        f"and '5'): {_DECIMAL_HINT}")
            raise DataFileError(
                f"{path}: line {line}: expected {len(names)} fields as {what}, got "
                f"{len(row)} (delimiter {delimiter!r}){hint}"
            )
    if has_header:
        rows, lines = rows[1:], lines[1:]
    return names, rows, lines


def _index(path: Path, names: list[str], column: Column, role: str) -> int:
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
    return names.index(column)


class _Table:
    """The columns of one CSV or NPZ file, by name or index (CSV: read with ``encoding``,
    ``delimiter`` (None: sniffed) and ``decimal``, see :func:`read_recordings`)."""

    def __init__(self, path: Path, encoding: str | None = None, delimiter: str | None = None,
                 decimal: str = ".") -> None:
        if not path.is_file():
            raise DataFileError(f"{path}: no such file")
        self.path = path
        self.decimal = decimal
        suffix = path.suffix.lower()
        if suffix == ".csv":
            self.names, self._rows, self._lines = _read_csv(path, encoding, delimiter, decimal)
            self._arrays: dict[str, np.ndarray] | None = None
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                self._arrays = {k: np.asarray(data[k]) for k in data.keys()}
            self.names = list(self._arrays)
        else:
            raise DataFileError(f"{path}: unknown file type {suffix!r}; use .csv or .npz")

    def line(self, row: int) -> str:
        """`` (line N)`` of a data row in a CSV file, ``""`` in an NPZ file."""
        return "" if self._arrays is not None else f" (line {self._lines[row]})"

    def _raw(self, column: Column, role: str) -> tuple[str, list[str] | np.ndarray]:
        """The column's name and its values (CSV: the stripped texts)."""
        path = self.path
        if self._arrays is None:
            idx = _index(path, self.names, column, role)
            return self.names[idx], [r[idx].strip() for r in self._rows]
        keys = self.names
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
        name, raw = self._raw(column, role)
        if self._arrays is None:
            out = np.array([_number(v, self.decimal) for v in raw], dtype=np.float64)
        else:
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
            value = (repr(raw[i]) if raw[i] else "an empty cell") if self._arrays is None \
                else raw[i]
            more = f" ({bad.size} such rows)" if self._arrays is not None else ""
            fix = "remove or fill the row" if self._arrays is None else "remove or fill them"
            if (self._arrays is None and self.decimal == "."
                    and re.fullmatch(r"[+-]?\d*,\d+([eE][+-]?\d+)?", raw[i])):
                fix = f"the file looks like it uses decimal commas: {_DECIMAL_OPTION}"
            raise DataFileError(
                f"{self.path}: column {name!r} ({role}), row {i}{self.line(i)}: {value} is "
                f"not a finite number{more}; {fix}"
            )
        return out

    def ids(self, column: Column, role: str) -> list[RecordingId]:
        """A column of recording ids (see :func:`recording_id`), (rows,)."""
        name, raw = self._raw(column, role)
        for i, v in enumerate(raw):
            if isinstance(v, str) and not v:
                raise DataFileError(
                    f"{self.path}: column {name!r} ({role}), row {i}{self.line(i)}: empty "
                    "value; every row needs its recording id"
                )
        if self._arrays is None and self.decimal == ",":
            raw = [v.replace(",", ".") if _is_number(v, ",") else v for v in raw]
        return [recording_id(v) for v in raw]


def _is_number(text: str, decimal: str) -> bool:
    try:
        float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        return False
    return True


def _number(text: str, decimal: str = ".") -> float:
    """The number a CSV field holds (``decimal=","``: ``1,5`` is 1.5), NaN if none."""
    try:
        return float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        return math.nan

"""Reading recorded (command, response) data from CSV and NPZ files, with checks.

Every problem is reported as a :class:`DataFileError` (a ``ValueError``) that names the
file, the column and, where it applies, the row (0-based data row; for CSV files also the
1-based line of the file).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = ["Column", "DataFileError", "Record", "read_record"]

Column = str | int
"""A column by header name (CSV) / array key (NPZ), or by 0-based index."""


class DataFileError(ValueError):
    """A problem in a data file, naming the file, the column and the row."""


class Record(NamedTuple):
    """Columns of a recorded experiment, each a float64 array of shape (time,)."""

    x: np.ndarray
    """The inverse model's input (the plant's response)."""
    y: np.ndarray
    """The inverse model's target (the command that produced the response)."""
    t: np.ndarray | None
    """Sample times, strictly increasing, or None."""


def _read_csv(path: Path) -> tuple[list[str], list[list[str]], int]:
    """Header names (``str(index)`` without a header), data rows, line of the first row."""
    with path.open(newline="") as fh:
        rows = [r for r in csv.reader(fh)]
    first = 0
    while first < len(rows) and (not rows[first] or rows[first][0].lstrip().startswith("#")):
        first += 1
    if first == len(rows):
        raise DataFileError(f"{path}: the file holds no data rows")
    head = [c.strip() for c in rows[first]]
    try:
        [float(c) for c in head]
        has_header = False
    except ValueError:
        has_header = True
    names = head if has_header else [str(i) for i in range(len(head))]
    data_start = first + 1 if has_header else first
    return names, rows[data_start:], data_start + 1


def _csv_column(path: Path, names: list[str], rows: list[list[str]], line0: int,
                column: Column, role: str) -> np.ndarray:
    idx = _index(path, names, column, role)
    out = np.empty(len(rows))
    for i, row in enumerate(rows):
        raw = row[idx].strip() if idx < len(row) else ""
        try:
            value = float(raw)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise DataFileError(
                f"{path}: column {names[idx]!r} ({role}), row {i} (line {line0 + i}): "
                f"{raw or 'empty value'!r} is not a finite number; remove or fill the row"
            )
        out[i] = value
    return out


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


def _npz_column(path: Path, data: np.lib.npyio.NpzFile, column: Column, role: str) -> np.ndarray:
    keys = list(data.keys())
    if isinstance(column, str) and column in keys:
        arr, name = np.asarray(data[column], dtype=np.float64), column
        if arr.ndim != 1:
            raise DataFileError(
                f"{path}: array {column!r} ({role}) must be one-dimensional, got shape "
                f"{arr.shape}"
            )
    elif isinstance(column, int) and not isinstance(column, bool) and len(keys) == 1:
        table = np.asarray(data[keys[0]], dtype=np.float64)
        if table.ndim != 2 or not 0 <= column < table.shape[1]:
            raise DataFileError(
                f"{path}: column index {column} ({role}) needs a 2-D array with more than "
                f"{column} columns; array {keys[0]!r} has shape {table.shape}"
            )
        arr, name = table[:, column], f"{keys[0]}[:, {column}]"
    else:
        raise DataFileError(
            f"{path}: column {column!r} ({role}) not found; the file's arrays are {keys}"
        )
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise DataFileError(
            f"{path}: column {name!r} ({role}), row {int(bad[0])}: {arr[bad[0]]} is not a "
            f"finite number ({bad.size} such rows); remove or fill them"
        )
    return arr


def read_record(
    path: str | Path, *, input_column: Column, target_column: Column,
    time_column: Column | None = None, min_samples: int = 2,
) -> Record:
    """Read and check a recorded experiment.

    Args:
        path: a ``.csv`` file (comma separated; an optional header row; lines starting with
            ``#`` before the data are skipped) or a ``.npz`` file (one 1-D array per column,
            or a single 2-D array addressed by column index).
        input_column: column of the inverse model's input (the plant's response).
        target_column: column of the inverse model's target (the command).
        time_column: optional column of sample times, which must strictly increase.
        min_samples: fewest rows accepted.

    Returns:
        :class:`Record` of float64 arrays, shape (time,).

    Raises:
        DataFileError: missing file or column, a non-finite or empty value, non-increasing
            time, too few rows; the message names the file, the column and the row.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path}: no such file")
    suffix = path.suffix.lower()
    roles = {"input_column": input_column, "target_column": target_column}
    if time_column is not None:
        roles["time_column"] = time_column
    if suffix == ".csv":
        names, rows, line0 = _read_csv(path)
        cols = {r: _csv_column(path, names, rows, line0, c, r) for r, c in roles.items()}
        lines = [f" (line {line0 + i})" for i in range(len(rows))]
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            cols = {r: _npz_column(path, data, c, r) for r, c in roles.items()}
        lines = [""] * len(cols["input_column"])
    else:
        raise DataFileError(f"{path}: unknown file type {suffix!r}; use .csv or .npz")
    lengths = {r: len(v) for r, v in cols.items()}
    if len(set(lengths.values())) != 1:
        raise DataFileError(f"{path}: columns differ in length: {lengths}")
    n = lengths["input_column"]
    if n < min_samples:
        raise DataFileError(
            f"{path}: column {input_column!r} (input_column) holds {n} rows, at least "
            f"{min_samples} are needed (row {n} is missing)"
        )
    t = cols.get("time_column")
    if t is not None:
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise DataFileError(
                f"{path}: column {time_column!r} (time_column), row {i}{lines[i]}: time "
                f"{t[i]!r} does not increase (previous row {t[i - 1]!r}); sort the file or "
                "remove repeated samples"
            )
    return Record(cols["input_column"], cols["target_column"], t)

"""Reading recorded (command, response) data from CSV and NPZ files, with checks: the
recordings of one file or several (:func:`read_recordings`), each file read as
:mod:`torchhys.data.tables` reads it (CSV text as spreadsheets and loggers write it).

Every problem is reported as a :class:`DataFileError` (a ``ValueError``) that names the
file, the column and, where it applies, the row (0-based data row; for CSV files also the
1-based line of the file) or the recording: a row with more or fewer fields than the
header, text that is not in the file's encoding, a value that is not a finite number.
"""

from __future__ import annotations

import errno
import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from torchhys.data.tables import (
    Column,
    DataFileError,
    RecordingId,
    _Table,
    check_text_options,
)

__all__ = ["Record", "Recording", "check_condition_columns", "read_record", "read_recordings",
           "resolve_path", "watch_files"]


class Record(NamedTuple):
    """Columns of a recorded experiment, each a float64 array of shape (time,)."""

    x: np.ndarray
    """The inverse model's input (the plant's response)."""
    y: np.ndarray
    """The inverse model's target (the command that produced the response)."""
    t: np.ndarray | None
    """Sample times, strictly increasing, or None."""


class Recording(NamedTuple):
    """One recording: a run of a file (its rows of one run-column value) or a whole file.

    Each recording starts from its own initial state: models run it from a fresh state.
    """

    id: RecordingId
    """Run-column value, or the file's index in the list of files."""
    label: str
    """Where it comes from, for messages: ``"log.csv: recording 3"``, or the file name."""
    x: np.ndarray
    """The inverse model's input, float64, (time,)."""
    y: np.ndarray
    """The inverse model's target, float64, (time,)."""
    t: np.ndarray | None
    """Sample times (strictly increasing within the recording), or None."""
    conditions: np.ndarray | None = None
    """The operating conditions (``condition_columns``), float64, (time, n), or None."""



def _runs(table: _Table, ids: list[RecordingId], column: Column) -> list[tuple[int, int]]:
    """``[start, end)`` rows of each run of equal ids; the rows of one id must be contiguous."""
    bounds, seen = [], set()
    for i, rid in enumerate(ids):
        if i and rid == ids[i - 1]:
            continue
        if rid in seen:
            raise DataFileError(
                f"{table.path}: column {column!r} (run_column), row {i}{table.line(i)}: "
                f"recording {rid!r} starts again after other recordings; the rows of a "
                f"recording must be contiguous (sort the file by {column!r})"
            )
        seen.add(rid)
        if bounds:
            bounds[-1] = (bounds[-1][0], i)
        bounds.append((i, len(ids)))
    return bounds


def _check_time(table: _Table, t: np.ndarray, start: int, column: Column) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = start + int(bad[0]) + 1
        raise DataFileError(
            f"{table.path}: column {column!r} (time_column), row {i}{table.line(i)}: time "
            f"{float(t[i - start]):.10g} does not increase (previous row "
            f"{float(t[i - start - 1]):.10g}); sort the file, remove repeated samples, or "
            "leave time_column out (null: the models use the order of the rows, not the times)"
        )


def _file_recordings(
    table: _Table, roles: dict[str, Column], run_column: Column | None, index: int | None,
    min_samples: int, condition_columns: Sequence[Column] = (),
) -> list[Recording]:
    """The recordings of one file; ``index``: its place in a list of files (None: alone)."""
    path = table.path
    cols = {r: table.column(c, r) for r, c in roles.items()}
    for k, c in enumerate(condition_columns):
        cols[f"condition_columns[{k}]"] = table.column(c, f"condition_columns[{k}]")
    conds = (np.stack([cols[f"condition_columns[{k}]"] for k in range(len(condition_columns))],
                      -1) if condition_columns else None)
    lengths = {r: len(v) for r, v in cols.items()}
    if len(set(lengths.values())) != 1:
        raise DataFileError(f"{path}: columns differ in length: {lengths}")
    n = lengths["input_column"]
    if run_column is None:
        ids, runs = None, [(0, n)]
    else:
        ids = table.ids(run_column, "run_column")
        if len(ids) != n:
            lengths["run_column"] = len(ids)
            raise DataFileError(f"{path}: columns differ in length: {lengths}")
        runs = _runs(table, ids, run_column)
    out = []
    for a, b in runs:
        if ids is not None:
            rid, label = ids[a], f"{path}: recording {ids[a]!r}"
        else:
            rid, label = (index or 0), str(path) if index is None else f"{path} (recording {index})"
        if b - a < min_samples:
            where = (f"{label} (rows {a}..{b - 1}) holds {b - a} samples" if ids is not None
                     else f"{path}: column {roles['input_column']!r} (input_column) holds "
                          f"{b - a} data row{'s' * (b - a != 1)}")
            raise DataFileError(f"{where}, at least {min_samples} are needed")
        t = cols.get("time_column")
        if t is not None:
            _check_time(table, t[a:b], a, roles["time_column"])
        out.append(Recording(rid, label, cols["input_column"][a:b], cols["target_column"][a:b],
                             None if t is None else t[a:b],
                             None if conds is None else conds[a:b]))
    return out


def read_recordings(
    path: str | Path | Sequence[str | Path], *, input_column: Column, target_column: Column,
    time_column: Column | None = None, run_column: Column | None = None, min_samples: int = 2,
    encoding: str | None = None, delimiter: str | None = None, decimal: str = ".",
    condition_columns: Sequence[Column] | None = None,
) -> list[Recording]:
    """Read and check recorded experiments: one file or several, each whole or split into
    recordings by a run column.

    Args:
        path: a ``.csv`` or ``.npz`` file (as in :func:`read_record`), or a list of them with
            the same columns.
        input_column: column of the inverse model's input (the plant's response).
        target_column: column of the inverse model's target (the command).
        time_column: optional column of sample times, which must strictly increase within
            each recording.
        run_column: optional column of recording ids (run or sequence numbers, or names):
            consecutive rows with the same id form one recording. Ids must be unique across
            the files. Without it each file is one recording, with id its index in ``path``.
        min_samples: fewest rows of a recording.
        encoding: the text encoding of CSV files (``"latin-1"``, ``"cp1252"``, ...); None:
            UTF-8, with or without a byte-order mark.
        delimiter: the character between the fields of CSV files (``","``, ``";"``, a tab,
            also written ``"tab"`` or ``"\\t"``); None: sniffed from the first lines among
            ``,``, ``;`` and tab (the one that gives every line the same number of fields,
            more than one; ``,`` first, never the decimal mark).
        decimal: the decimal mark of numbers in CSV files, ``"."`` or ``","`` (``1,5`` is
            1.5; the delimiter is then ``;`` or a tab).
        condition_columns: optional columns of measured operating conditions (a coil
            voltage, a supply pressure, a temperature), constant within a recording or
            varying sample by sample: each recording's ``conditions`` (time, n).

    Returns:
        The recordings in the order of the files and of their rows, each with float64 arrays
        of shape (time,) (the conditions (time, n)).

    Raises:
        ValueError: an empty list of files; input_column equal to target_column; a bad
            ``encoding``, ``delimiter`` or ``decimal``.
        DataFileError: a missing file or column, files with different columns, text that
            is not in the encoding, a row with more or fewer fields than the header (with
            a hint when the numbers look like they have decimal commas), a non-finite or
            empty value, non-increasing time, a recording whose rows are not contiguous or
            whose id another file also uses, too few rows, a column name that the header
            gives to several columns, a spreadsheet file saved under a ``.csv`` name, a
            symbolic link loop, a file that changed since this command first read it
            (:func:`watch_files`); the message names the file, the column and the row (and
            the line) or the recording.
    """
    delimiter = check_text_options(encoding, delimiter, decimal)
    conds = check_condition_columns(condition_columns, input_column, target_column,
                                    time_column, run_column)
    if str(input_column) == str(target_column):
        raise ValueError(
            f"input_column (data.input_column) and target_column (data.target_column) are both "
            f"{input_column!r}: the input (the plant's response) and the target (the command) "
            "are two columns of the file")
    paths = [path] if isinstance(path, (str, Path)) else list(path)
    if not paths:
        raise ValueError("path must name a file or a non-empty list of files, got []")
    from torchhys.datasets import shipped_path  # a config's examples/data/... outside a checkout

    paths = [shipped_path(p) or p for p in paths]
    options = (input_column, target_column, time_column, run_column, min_samples, encoding,
               delimiter, decimal, conds)
    for p in paths:
        resolve_path(p)
    try:  # the files as they are now: a file written again is read again
        key = (*options, *((str(Path(p).resolve()), *_stat(Path(p))) for p in paths))
        hash(key)
    except (OSError, TypeError):  # a missing file: read (and report) it below
        key = None
    if _FIRST is not None:
        for p in paths:
            _check_unchanged(Path(p))
    recordings = _READ.get(key) if key is not None else None
    if recordings is None:
        recordings = _read(paths, *options)
        if _FIRST is not None and key is not None:  # not written while it was read either
            for p, (_, mtime, size) in zip(paths, key[len(options):], strict=True):
                _check_unchanged(Path(p), (mtime, size))
        if key is not None:
            _READ.clear()  # the last file read only (a fit reads it once per candidate run)
            _READ[key] = recordings
    return [r._replace(x=r.x.copy(), y=r.y.copy(), t=None if r.t is None else r.t.copy(),
                       conditions=None if r.conditions is None else r.conditions.copy())
            for r in recordings]


def check_condition_columns(columns: object, *others: Column | None) -> tuple[Column, ...]:
    """``condition_columns`` as a tuple of columns (names or indices; None: none).

    Raises:
        ValueError: not a list of column names or indices, a column listed twice or also
            the input, target, time or run column."""
    if columns is None:
        return ()
    if isinstance(columns, (str, int)) or not isinstance(columns, Sequence) or not all(
            isinstance(c, (str, int)) and not isinstance(c, bool) for c in columns):
        raise ValueError(f"condition_columns (data.condition_columns) must be a list of column "
                         f"names or indices, e.g. [voltage_V], got {columns!r}")
    names = [str(c) for c in columns]
    taken = {str(o) for o in others if o is not None}
    for c in names:
        if names.count(c) > 1 or c in taken:
            why = "twice" if names.count(c) > 1 else (
                "which is also the input, target, time or run column")
            raise ValueError(f"condition_columns (data.condition_columns) lists {c!r} {why}: "
                             "each condition is a column of its own")
    return tuple(columns)


_READ: dict[tuple, list[Recording]] = {}
"""The recordings of the last files read, by path, modification time, size and options:
model selection builds a datamodule for every candidate and fold, and the files are parsed
once (each caller gets copies of the arrays)."""


_FIRST: dict[str, tuple[int, int, str]] | None = None
"""While a command runs (:func:`watch_files`): each data file's modification time, size and
content digest at its first read; None: not watched."""


def watch_files(on: bool = True) -> None:
    """Start (``on``) or stop watching the data files: while watched, a file read again (a
    model selection reads it for every candidate and fold, and for the final fit) must hold
    what it held at its first read, or :func:`read_recordings` raises a
    :class:`DataFileError` naming it. The command line watches for the whole of a command
    (the processes of ``model.select_jobs`` inherit what the command read first)."""
    global _FIRST
    _FIRST = {} if on else None


def _stat(path: Path) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_mtime_ns, st.st_size


def _digest(path: Path) -> str:
    h = hashlib.blake2b(digest_size=20)
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def resolve_path(path: str | Path) -> Path:
    """``Path(path).resolve()``, or a :class:`DataFileError` naming a symbolic link that
    leads back to itself (a loop) where it cannot be resolved."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:  # RuntimeError: a loop, Python < 3.13
        if "loop" in str(exc).lower() or getattr(exc, "errno", None) == errno.ELOOP:
            raise DataFileError(f"{path}: a symbolic link that leads back to itself (a "
                                "loop); point the path at the data file") from None
        raise


def _check_unchanged(path: Path, read_at: tuple[int, int] | None = None) -> None:
    """Record a watched file's first state, or raise if it changed since (``read_at``: the
    modification time and size before a read just made, which must still hold)."""
    try:
        now = _stat(path)
    except OSError:
        return  # missing: the reader reports it
    key = str(path.resolve())
    first = _FIRST.get(key)
    if read_at is not None and now != read_at:
        what = "while it was read"
    elif first is not None and now == first[:2]:
        return
    elif first is None:
        _FIRST[key] = (*now, _digest(path))
        return
    elif _digest(path) == first[2]:
        _FIRST[key] = (*now, first[2])  # touched, same content
        return
    else:
        what = f"after this run first read it ({first[1]} bytes then, {now[1]} now)"
    raise DataFileError(
        f"{path}: the file changed {what}: the run would mix two versions of the data (the "
        "candidates scored on one, the fit on another); wait until its writer has finished "
        "(or copy it) and run again")


def _read(paths: list[str | Path], input_column: Column, target_column: Column,
          time_column: Column | None, run_column: Column | None, min_samples: int,
          encoding: str | None, delimiter: str | None, decimal: str,
          condition_columns: tuple[Column, ...] = ()) -> list[Recording]:
    """:func:`read_recordings` of checked options, uncached."""
    roles = {"input_column": input_column, "target_column": target_column}
    if time_column is not None:
        roles["time_column"] = time_column
    recordings: list[Recording] = []
    first: _Table | None = None
    owner: dict[RecordingId, Path] = {}
    for k, p in enumerate(paths):
        table = _Table(Path(p), encoding, delimiter, decimal)
        if first is None:
            first = table
        elif table.names != first.names:
            raise DataFileError(
                f"{table.path}: columns {table.names} differ from the columns {first.names} "
                f"of {first.path}; every file in path must have the same columns"
            )
        index = None if len(paths) == 1 else k
        for rec in _file_recordings(table, roles, run_column, index, min_samples,
                                    condition_columns):
            if rec.id in owner:
                raise DataFileError(
                    f"{table.path}: recording {rec.id!r} (run_column {run_column!r}) is also "
                    f"in {owner[rec.id]}; recording ids must be unique across the files in "
                    "path: renumber the runs"
                )
            owner[rec.id] = table.path
            recordings.append(rec)
    return recordings


def read_record(
    path: str | Path, *, input_column: Column, target_column: Column,
    time_column: Column | None = None, min_samples: int = 2, encoding: str | None = None,
    delimiter: str | None = None, decimal: str = ".",
) -> Record:
    """Read and check a recorded experiment.

    Args:
        path: a ``.csv`` file (fields separated by ``,``, ``;`` or a tab; an optional
            header row; lines starting with ``#`` before the data, and blank lines, are
            skipped; see :mod:`torchhys.data.tables`) or a ``.npz`` file (one 1-D array per
            column, or a single 2-D array addressed by column index).
        input_column: column of the inverse model's input (the plant's response).
        target_column: column of the inverse model's target (the command).
        time_column: optional column of sample times, which must strictly increase.
        min_samples: fewest rows accepted.
        encoding: the text encoding of a CSV file; None: UTF-8, with or without a
            byte-order mark (as :func:`read_recordings`).
        delimiter: the character between a CSV file's fields; None: sniffed among ``,``,
            ``;`` and tab (as :func:`read_recordings`).
        decimal: the decimal mark of a CSV file's numbers, ``"."`` or ``","``.

    Returns:
        :class:`Record` of float64 arrays, shape (time,).

    Raises:
        ValueError: a bad ``encoding``, ``delimiter`` or ``decimal``.
        DataFileError: missing file or column, text not in the encoding, a row with more
            or fewer fields than the header, a non-finite or empty value, non-increasing
            time, too few rows; the message names the file, the column and the row.
    """
    (rec,) = read_recordings(Path(path), input_column=input_column,
                             target_column=target_column, time_column=time_column,
                             min_samples=min_samples, encoding=encoding, delimiter=delimiter,
                             decimal=decimal)
    return Record(rec.x, rec.y, rec.t)

"""The devices of a fleet: the recordings a fleet run identifies, one per device, each named.

:func:`find_devices` takes a glob (``devices/*.csv``: one file per device, the device named
by the file's stem), a list of files, a mapping of names to files, or one file with a
device column (``device_column``: its rows of each device written to a file of their own,
in the order they come, without that column). :func:`check_columns` reads each device's
header: a file that cannot be read, or whose columns differ from the fleet's (those of most
devices), is a device that fails with its reason; the others are fitted.
"""

from __future__ import annotations

import csv
import glob
import os
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Device", "check_columns", "find_devices", "split_by_column"]

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
"""A device name that is a folder name everywhere (no separators, no leading dot)."""


@dataclass(frozen=True)
class Device:
    """One device of the fleet: its name (its run folder's) and its recording."""

    name: str
    path: Path


def _check_name(name: str, where: str) -> str:
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"{where}: device name {name!r} is not a folder name (letters, digits, "
                         "'.', '_', '+', '-', not starting with '.' or '-')")
    return name


def find_devices(data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, str],
                 *, device_column: str | None = None,
                 split_dir: str | os.PathLike | None = None) -> list[Device]:
    """The fleet's devices, in a stable order (sorted by name, a mapping's in its order).

    Args:
        data: a glob pattern or a file (``devices/*.csv``; each match a device named by its
            stem), a list of files (named by their stems), or a mapping name -> file.
        device_column: one file holding every device: the column naming each row's device
            (the rows of each are written to ``split_dir/<device>.csv``).
        split_dir: where those files go (needed with ``device_column``).

    Raises:
        ValueError: no file matches (naming the pattern), two devices with one name (naming
            it and both files), a name that is not a folder name, ``device_column`` with
            several files or a column the file lacks.
    """
    if isinstance(data, Mapping):
        devices = [Device(_check_name(str(k), "data"), Path(v)) for k, v in data.items()]
    else:
        if isinstance(data, (str, os.PathLike)):
            pattern = os.fspath(data)
            paths = sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
            if not paths:
                raise ValueError(f"data.path {pattern!r} matches no file: give a glob of the "
                                 "devices' recordings (devices/*.csv) or one file with "
                                 "data.device_column")
        elif isinstance(data, Sequence) and data:
            paths = [os.fspath(p) for p in data]
        else:
            raise ValueError(f"data.path must be a glob, a file, a non-empty list of files or a "
                             f"mapping of device names to files, got {data!r}")
        if device_column is not None:
            if len(paths) != 1:
                raise ValueError(f"data.device_column={device_column!r} reads one file holding "
                                 f"every device, but data.path gives {len(paths)}")
            if split_dir is None:
                raise ValueError("device_column needs split_dir (where each device's rows go)")
            return split_by_column(Path(paths[0]), device_column, Path(split_dir))
        devices = [Device(_check_name(Path(p).stem, f"data.path {p}"), Path(p))
                   for p in paths]
    if not devices:
        raise ValueError("the fleet has no device: data names no file")
    seen: dict[str, Path] = {}
    for d in devices:
        if d.name in seen:
            raise ValueError(f"two devices are named {d.name!r} ({seen[d.name]} and {d.path}): "
                             "device names (the files' stems) must differ")
        seen[d.name] = d.path
    return devices if isinstance(data, Mapping) else sorted(devices, key=lambda d: d.name)


def split_by_column(path: Path, column: str, out: Path) -> list[Device]:
    """The devices of one CSV file with a device column: each device's rows, in their order,
    written to ``out/<device>.csv`` with the file's other columns.

    Raises:
        ValueError: the file cannot be read, lacks the column, or has a row without a device
            name or with one that is not a folder name (naming the line).
    """
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"data.path {path}: cannot be read ({err})") from None
    if not rows or column not in rows[0]:
        have = rows[0] if rows else []
        raise ValueError(f"data.device_column={column!r}: {path} has no such column (its "
                         f"columns: {have})")
    header, k = rows[0], rows[0].index(column)
    keep = [i for i in range(len(header)) if i != k]
    groups: dict[str, list[list[str]]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        name = row[k].strip() if k < len(row) else ""
        _check_name(name, f"{path} line {line}, column {column!r}")
        groups.setdefault(name, []).append([row[i] for i in keep if i < len(row)])
    if not groups:
        raise ValueError(f"data.path {path} holds no rows")
    out.mkdir(parents=True, exist_ok=True)
    devices = []
    for name in sorted(groups):
        file = out / f"{name}.csv"
        with file.open("w", newline="") as fh:
            csv.writer(fh).writerows([[header[i] for i in keep], *groups[name]])
        devices.append(Device(name, file))
    return devices


def _header(path: Path) -> tuple[str, ...]:
    """The first row of a CSV file (an NPZ file's array names), or OSError/ValueError."""
    if path.suffix.lower() == ".npz":
        import numpy as np

        with np.load(path) as z:
            return tuple(sorted(z.files))
    with path.open(newline="") as fh:
        first = next(csv.reader(fh), None)
    if not first:
        raise ValueError("it is empty")
    return tuple(c.strip() for c in first)


def check_columns(devices: Sequence[Device]) -> dict[str, str]:
    """The devices that cannot be fitted with the fleet's columns, each with its reason: a
    file that cannot be read, or columns other than those of most devices (the first such
    set of columns on a tie). The others are left to the fit, which checks their data."""
    headers: dict[str, tuple[str, ...]] = {}
    failed: dict[str, str] = {}
    for d in devices:
        try:
            headers[d.name] = _header(d.path)
        except (OSError, ValueError, UnicodeDecodeError) as err:
            failed[d.name] = f"{d.path} cannot be read: {err}"
    if headers:
        counts = Counter(headers.values())
        common = max(counts, key=lambda h: (counts[h], -list(headers.values()).index(h)))
        for name, h in headers.items():
            if h != common:
                failed[name] = (f"its columns {list(h)} differ from the fleet's "
                                f"{list(common)} (most devices')")
    return failed

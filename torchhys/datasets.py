"""The example recordings shipped with torchhys, by name: ``torchhys.datasets.load(name)``.

The files are those of the checkout's ``examples/data`` (``torchhys/example_data`` links that
folder in a checkout; the wheel holds the files there), each with its source and licence in
the folder's README files (:func:`attribution`)::

    import torchhys.datasets as datasets

    datasets.names()                                  # what is shipped
    rec = datasets.load("piezo_micromanipulator")     # columns as float64 numpy arrays
    rec["voltage_V"], rec["displacement_um"]
    print(datasets.attribution("piezo_micromanipulator"))

A config's default ``data.path`` under ``examples/data/`` (``configs/measured.yaml``'s
``examples/data/bouc_wen.csv``) is read from the shipped files where the current folder has
no such file (:func:`shipped_path`), so that ``torchhys fit --config measured`` runs outside a
checkout.
"""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import numpy as np

__all__ = ["FILES", "attribution", "load", "names", "path", "shipped_path"]

FILES = {
    "bouc_wen": "bouc_wen.csv",
    "mnzn_ferrite_bh_loops": "mnzn_ferrite_bh_loops.csv",
    "jamodel_bh_loops": "real/jamodel_bh_loops.csv",
    "mr_damper_labcontrol": "real/mr_damper_labcontrol.csv",
    "piezo_micromanipulator": "real/piezo_micromanipulator.csv",
}
"""The shipped recordings: name -> file under the example data folder."""

_PREFIX = "examples/data/"


def _folder() -> Path:
    """``torchhys/example_data`` (the wheel's files, the checkout's link), else the
    checkout's ``examples/data``."""
    inside = Path(__file__).resolve().parent / "example_data"
    if inside.is_dir():
        return inside
    return Path(__file__).resolve().parents[1] / "examples" / "data"


def names() -> list[str]:
    """The shipped recordings' names."""
    return sorted(FILES)


def path(name: str) -> Path:
    """The file of the shipped recording ``name``; ValueError naming the shipped ones."""
    if name not in FILES:
        raise ValueError(f"no shipped recording {name!r}; shipped: {', '.join(names())}")
    file = _folder() / FILES[name]
    if not file.is_file():
        raise FileNotFoundError(f"the shipped recording {name!r} is missing ({file}): "
                                "reinstall torchhys")
    return file


def load(name: str) -> dict[str, np.ndarray]:
    """The recording ``name``'s columns (header names): float64 numpy arrays, a column of
    text (a material's name) as a str array; lines starting with ``#`` skipped."""
    with path(name).open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(line for line in fh if not line.startswith("#")))
    header, body = rows[0], np.array(rows[1:], dtype=str)
    out = {}
    for i, column in enumerate(header):
        try:
            out[column] = body[:, i].astype(np.float64)
        except ValueError:
            out[column] = body[:, i]
    return out


def attribution(name: str) -> str:
    """The README section of the recording ``name``: what it is, its source and licence
    (the licence texts themselves are at the end of ``real/README.md``)."""
    path(name)  # a shipped name, its file present
    file = FILES[name]
    readme = _folder() / Path(file).parent / "README.md"
    text = readme.read_text(encoding="utf-8")
    base = Path(file).name
    sections = re.split(r"(?m)^(?=## )", text)
    for section in sections:
        if section.startswith("## ") and base in section.splitlines()[0]:
            return section.strip()
    raise ValueError(f"no section of {readme} names {base}")


def shipped_path(file: str | os.PathLike) -> Path | None:
    """The shipped file of a relative ``examples/data/...`` path that does not exist here,
    else None (the path is read as it is)."""
    text = os.fspath(file).replace(os.sep, "/")
    if os.path.isabs(text) or not text.startswith(_PREFIX) or Path(file).exists():
        return None
    candidate = _folder() / text[len(_PREFIX):]
    return candidate if candidate.is_file() else None

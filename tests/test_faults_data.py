"""Fault cases of the data and the configs: memory that user input would make unbounded
(a Preisach fit's n, ``data.repeat``, a YAML alias bomb, a large CSV file) refused with an
estimate or read within a bound, a data file rewritten during a fit detected, and CSV files
that look right but are not (duplicate header names, ``1_000``, a spreadsheet saved as
``.csv``, a symlink loop) refused with one line naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys import fit_preisach
from torchhys._memory import MEMORY_ENV, memory_limit
from torchhys.training import HysteresisDataModule
from torchhys.training.files import DataFileError, read_recordings
from torchhys.training.operators import build_operators


def write_csv(path: Path, rows: int = 200, header: str = "response,command") -> Path:
    """A CSV file of a smooth loop, ``rows`` data rows under ``header``."""
    t = np.linspace(0.0, 2 * np.pi, rows)
    np.savetxt(path, np.c_[np.sin(t) + 0.1 * np.sin(3 * t), np.sin(t)], delimiter=",",
               header=header, comments="")
    return path


# ------------------------------------------------------------------------------------------
# memory estimated before allocating
# ------------------------------------------------------------------------------------------

def test_memory_limit_from_the_environment(monkeypatch) -> None:
    monkeypatch.setenv(MEMORY_ENV, "1.5G")
    assert memory_limit() == int(1.5 * 1024**3)
    monkeypatch.setenv(MEMORY_ENV, "12345")
    assert memory_limit() == 12345
    monkeypatch.setenv(MEMORY_ENV, "lots")
    with pytest.raises(ValueError, match=f"{MEMORY_ENV} must be a size"):
        memory_limit()
    monkeypatch.delenv(MEMORY_ENV)
    assert memory_limit() is None or memory_limit() > 2**20


def test_preisach_family_n_refused_before_training(monkeypatch) -> None:
    """``{fit: preisach, n: 2000}`` (2001000 relays: 10 matrices of 32 TB) is refused when the
    spec is read, with the estimate; a small n under a small limit is refused as well."""
    with pytest.raises(ValueError, match=r"fit 'preisach': n=2000 \(2001000 relays\) needs "
                                         r"about .* TiB.*lower n.*TORCHHYS_MAX_MEMORY"):
        build_operators([{"fit": "preisach", "n": 2000}], {})
    monkeypatch.setenv(MEMORY_ENV, "32M")
    with pytest.raises(ValueError, match=r"n=40 \(820 relays\).*32\.0 MiB \(TORCHHYS_MAX"):
        build_operators([{"fit": "preisach", "n": 40}], {})
    build_operators([{"fit": "preisach", "n": 20}], {})  # 210 relays: 3.5 MB


def test_fit_preisach_n_refused_before_allocating(monkeypatch) -> None:
    monkeypatch.setenv(MEMORY_ENV, "32M")
    x = torch.sin(torch.linspace(0, 6, 100, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"fit_preisach: n=40 \(820 relays\) needs about "
                                         r"51\.\d MiB, more than the memory limit 32\.0 MiB"):
        fit_preisach(x, x, n=40)
    fit_preisach(x, x, n=8)


def test_repeat_refused_with_the_estimate(monkeypatch, tmp_path) -> None:
    """``data.repeat 100000`` on 200 rows (2e7 samples) is refused at setup, before the
    sequences are built, naming the option and the samples."""
    path = write_csv(tmp_path / "d.csv")
    data = HysteresisDataModule(path=str(path), repeat=100_000)
    monkeypatch.setenv(MEMORY_ENV, "4G")
    with pytest.raises(ValueError, match=r"data\.repeat=100000 \(100000 x 200 samples\) "
                                         r"needs about 9\.5 GiB.*lower data\.repeat"):
        data.setup()
    ok = HysteresisDataModule(path=str(path), repeat=3)
    ok.setup()
    assert ok.tensors("train")[0].numel() == 600

"""torchhys.datasets: the shipped example recordings by name, against the files read by
numpy, with their attribution; a config's examples/data path outside a checkout."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import torchhys
import torchhys.datasets as datasets

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(datasets.FILES))
def test_load_equals_the_file_read_by_numpy(name: str) -> None:
    got = datasets.load(name)
    lines = [ln for ln in (ROOT / "examples" / "data" / datasets.FILES[name]).read_text()
             .splitlines() if not ln.startswith("#")]
    table = np.genfromtxt(lines, delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert list(got) == list(table.dtype.names)
    for column in got:
        if table[column].dtype.kind in "iuf":
            np.testing.assert_array_equal(got[column], table[column].astype(np.float64))
            assert got[column].dtype == np.float64
        else:
            assert list(got[column]) == list(table[column]), column
    text = datasets.attribution(name)
    assert text.startswith("## ") and Path(datasets.FILES[name]).name in text.splitlines()[0]


def test_names_path_and_errors() -> None:
    assert datasets.names() == sorted(datasets.FILES)
    assert torchhys.datasets is datasets
    assert datasets.path("bouc_wen").read_bytes() == (ROOT / "examples/data/bouc_wen.csv"
                                                      ).read_bytes()
    with pytest.raises(ValueError, match="no shipped recording 'nope'; shipped: bouc_wen"):
        datasets.load("nope")


def test_a_configs_example_path_outside_a_checkout(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    got = datasets.shipped_path("examples/data/bouc_wen.csv")
    assert got is not None and got.read_bytes() == (ROOT / "examples/data/bouc_wen.csv"
                                                    ).read_bytes()
    assert datasets.shipped_path("examples/data/none.csv") is None
    assert datasets.shipped_path(str(ROOT / "examples/data/bouc_wen.csv")) is None  # absolute
    (tmp_path / "examples/data").mkdir(parents=True)
    (tmp_path / "examples/data/bouc_wen.csv").write_text("time,command,response\n")
    assert datasets.shipped_path(os.path.join("examples", "data", "bouc_wen.csv")) is None

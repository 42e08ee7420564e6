"""benchmarks/bouc_wen_benchmark.py: the saved models reproduce their table rows
(``--evaluate``), and the ``--quick`` mode trains, saves and evaluates (slow)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from _helpers import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bouc_wen_benchmark.npz"
RESULTS = ROOT / "benchmarks" / "results"

pytestmark = pytest.mark.skipif(not DATA.exists(),
                                reason="the benchmark data (../shared/data) is absent")


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bouc_wen_benchmark.py")


def _saved(path: Path) -> dict:
    return torch.load(path, weights_only=True)


def _same_rows(rows: list[dict], files: list[Path]) -> None:
    assert len(rows) == len(files)
    for row, path in zip(rows, files, strict=True):
        saved = _saved(path)
        assert row["label"] == saved["label"]
        for key, value in saved["results"].items():
            assert row["results"][key] == pytest.approx(value, rel=1e-9), (path.name, key)


def test_saved_linear_model_reproduces_its_row(bench) -> None:
    path = RESULTS / "linear.pt"
    rows = bench.main(["--evaluate", str(path)])
    _same_rows(rows, [path])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["feedback-duhem", "grey-box"])
def test_saved_models_reproduce_their_rows(bench, name: str) -> None:
    """The committed models' numbers (docs/bouc-wen.md) from the files alone."""
    path = RESULTS / f"{name}.pt"
    rows = bench.main(["--evaluate", str(path)])
    _same_rows(rows, [path])
    if name == "feedback-duhem":  # the black box beats PNLSS on the multisine test
        assert rows[0]["results"]["multisine"] < bench.PUBLISHED["PNLSS"]


@pytest.mark.slow
def test_quick_mode_trains_saves_and_evaluates(bench, tmp_path: Path) -> None:
    """The quick mode trains every model, saves the rows and evaluates them."""
    rows = bench.main(["--quick", "--save", str(tmp_path)])
    names = [r["label"] for r in rows]
    assert len(rows) == len(bench.MODELS) and names[0] == "linear (order 2)"
    for r in rows:
        assert all(math.isfinite(v) for v in r["results"].values()), r
        assert r["seconds"] > 0
    linear, duhem = rows[0]["results"], rows[1]["results"]
    assert duhem["multisine"] < 0.6 * linear["multisine"]
    files = sorted(tmp_path.glob("*.pt"), key=bench._order)
    assert [f.stem for f in files] == list(bench.MODELS)
    _same_rows(bench.main(["--evaluate", str(tmp_path)]), files)


def test_evaluate_without_models_says_so(bench, tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="no saved models"):
        bench.main(["--evaluate", str(tmp_path)])

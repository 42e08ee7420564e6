"""HysteresisDataModule: simulated and recorded sources, file checks, splits, normalization."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys.data.files import read_record
from torchhys.data.tables import DataFileError
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

EXAMPLE = Path(__file__).resolve().parents[1] / "examples/data/bouc_wen.csv"


def write_csv(path: Path, rows: list[list], header: str = "time,command,response") -> Path:
    lines = [header] + [",".join(str(v) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def good_rows(n: int = 40) -> list[list]:
    t = np.arange(n) * 0.01
    u = np.sin(3 * t)
    return [[f"{a:.2f}", f"{b:.6f}", f"{0.9 * b:.6f}"] for a, b in zip(t, u, strict=True)]


def test_paper_simulation_is_the_default() -> None:
    dm = HysteresisDataModule()
    x, y = dm.train_tensors()
    assert x.shape == y.shape == (1, 2514)
    assert x.dtype == torch.float64
    from torchhys.plants import paper_simulation

    _, xs, hs = paper_simulation(dtype=torch.float64)
    torch.testing.assert_close(x[0], hs)  # model input h = H[x]
    torch.testing.assert_close(y[0], xs)  # target x
    for stage in ("val", "test"):  # the paper reports training MSE: the same record
        xv, yv, warm = dm.tensors(stage)
        assert warm == 0 and torch.equal(xv, hs) and torch.equal(yv, xs)


def test_bouc_wen_simulation() -> None:
    dm = HysteresisDataModule(simulation="bouc_wen", t_end=5.0)
    x, y = dm.train_tensors()
    assert x.shape == (1, 500) and torch.isfinite(x).all()
    assert float(y.abs().max()) == pytest.approx(6.0, rel=1e-6)


@pytest.mark.parametrize("cols", [("response", "command", "time"), (2, 1, 0)])
def test_csv_by_name_and_index(tmp_path: Path, cols: tuple) -> None:
    path = write_csv(tmp_path / "log.csv", good_rows())
    rec = read_record(path, input_column=cols[0], target_column=cols[1], time_column=cols[2])
    assert rec.x.shape == rec.y.shape == rec.t.shape == (40,)
    np.testing.assert_allclose(rec.x, 0.9 * rec.y, atol=1e-6)


def test_csv_without_header(tmp_path: Path) -> None:
    path = tmp_path / "raw.csv"
    path.write_text("\n".join(",".join(r) for r in good_rows()) + "\n")
    rec = read_record(path, input_column=2, target_column=1)
    assert rec.x.shape == (40,) and rec.t is None


def test_npz_arrays_and_table(tmp_path: Path) -> None:
    rows = np.array(good_rows(), dtype=float)
    np.savez(tmp_path / "a.npz", time=rows[:, 0], command=rows[:, 1], response=rows[:, 2])
    np.savez(tmp_path / "b.npz", data=rows)
    a = read_record(tmp_path / "a.npz", input_column="response", target_column="command",
                    time_column="time")
    b = read_record(tmp_path / "b.npz", input_column=2, target_column=1, time_column=0)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.t, b.t)
    for name, bad in (("complex", rows[:, 2] + 1j), ("text", rows[:, 2].astype(str))):
        np.savez(tmp_path / f"{name}.npz", time=rows[:, 0], command=rows[:, 1], response=bad)
        with pytest.raises(DataFileError, match=r"column 'response' \(input_column\) must hold "
                           rf"real numbers, got dtype {bad.dtype}"):
            read_record(tmp_path / f"{name}.npz", input_column="response",
                        target_column="command")


def _problem_csv(tmp_path: Path, kind: str) -> tuple[Path, dict]:
    rows = good_rows()
    cols = dict(input_column="response", target_column="command", time_column="time")
    if kind == "missing column":
        cols["input_column"] = "voltage"
    elif kind == "nan":
        rows[17][2] = "nan"
    elif kind == "empty":
        rows[17][1] = ""
    elif kind == "time":
        rows[12][0] = rows[11][0]
    elif kind == "few":
        rows = rows[:5]
    return write_csv(tmp_path / f"{kind.replace(' ', '_')}.csv", rows), cols


@pytest.mark.parametrize(
    "kind, column, row",
    [("missing column", "voltage", None), ("nan", "response", "row 17 (line 19)"),
     ("empty", "command", "row 17 (line 19)"), ("time", "time", "row 12 (line 14)"),
     ("few", "response", "holds 5 data rows")],
)
def test_csv_problems_name_file_column_row(tmp_path: Path, kind: str, column: str,
                                            row: str | None) -> None:
    path, cols = _problem_csv(tmp_path, kind)
    dm = HysteresisDataModule(path=str(path), split=[0.5, 0.25, 0.25], min_samples=8, **cols)
    with pytest.raises(DataFileError) as err:
        dm.setup("fit")
    msg = str(err.value)
    assert str(path) in msg and repr(column) in msg
    if row is not None:
        assert row in msg


@pytest.mark.parametrize("kind", ["missing", "nan", "time", "few"])
def test_npz_problems_name_file_column_row(tmp_path: Path, kind: str) -> None:
    rows = np.array(good_rows(), dtype=float)
    if kind == "nan":
        rows[23, 2] = np.nan
    elif kind == "time":
        rows[30, 0] = rows[29, 0] - 0.5
    elif kind == "few":
        rows = rows[:3]
    path = tmp_path / f"{kind}.npz"
    np.savez(path, time=rows[:, 0], command=rows[:, 1], response=rows[:, 2])
    col = "current" if kind == "missing" else "response"
    with pytest.raises(DataFileError) as err:
        read_record(path, input_column=col, target_column="command", time_column="time",
                    min_samples=8)
    msg = str(err.value)
    assert str(path) in msg
    expected = {"missing": ("'current'", None), "nan": ("'response'", "row 23"),
                "time": ("'time'", "row 30"), "few": ("'response'", "holds 3 data rows")}[kind]
    assert expected[0] in msg
    if expected[1]:
        assert expected[1] in msg
    if kind == "time":  # the values as numbers, and the way out
        t = rows[:, 0]
        assert f"time {t[30]:.10g} does not increase (previous row {t[29]:.10g})" in msg
        assert "np.float64" not in msg and "leave time_column out" in msg


def test_split_too_small_names_file_and_rows(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "log.csv", good_rows(40))
    dm = HysteresisDataModule(path=str(path), split=[0.9, 0.05, 0.05], min_samples=8,
                              time_column="time")
    with pytest.raises(DataFileError, match=r"log\.csv: the val split holds 2 samples"):
        dm.setup("fit")


@pytest.mark.parametrize("split", ["all", [0.5, 0.6, 0.1], [0.0, 0.5, 0.5], [0.5, 0.5],
                                   [True, 0, 0], [0.5, "0.2", 0.1]])
def test_bad_split(split) -> None:
    with pytest.raises(ValueError, match="split"):
        HysteresisDataModule(split=split)


def test_split_fractions_are_time_ordered_with_warmup() -> None:
    dm = HysteresisDataModule(path=str(EXAMPLE), time_column="time", split=[0.7, 0.2, 0.1])
    dm.setup("fit")
    n = 3000
    assert dm.bounds == {"train": (0, 2100), "val": (2100, 2700), "test": (2700, n)}
    x, y = dm.train_tensors()
    torch.testing.assert_close(x[0], dm.x[:2100])
    xv, yv, warm = dm.tensors("val")
    assert warm == 2100 and xv.shape == (2700,)  # the preceding record, then the split
    xt, _, warm_t = dm.tensors("test")
    assert warm_t == 2700 and xt.shape == (n,)
    batch = next(iter(dm.val_dataloader()))
    assert batch[0].shape == (1, 2700) and int(batch[2]) == 2100


def test_empty_test_split_gives_no_loader() -> None:
    dm = HysteresisDataModule(path=str(EXAMPLE), split=[0.8, 0.2, 0.0])
    dm.setup("fit")
    assert dm.test_dataloader() == []


def test_normalization_is_fit_on_the_training_part_only() -> None:
    dm = HysteresisDataModule(path=str(EXAMPLE), time_column="time", split=[0.5, 0.25, 0.25])
    dm.setup("fit")
    module = InverseHysteresisModule(operator=None, hidden=4)
    trainer = type("T", (), {"datamodule": dm})()
    module._trainer = trainer  # what Trainer attaches; setup only reads the datamodule
    module.setup("fit")
    x, y = dm.train_tensors()
    net = module.net
    assert float(net.out_mean) == pytest.approx(float(y.mean()), rel=1e-6)
    assert float(net.out_std) == pytest.approx(float(y.std()), rel=1e-6)
    assert float(net.in_mean[0]) == pytest.approx(float(x.mean()), rel=1e-6)
    whole = float(dm.y.mean())
    assert not math.isclose(float(net.out_mean), whole, rel_tol=1e-3)
    assert bool(module.normalization_fitted)


def test_the_training_rows_are_padded_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """``train_tensors``, ``train_warmup`` and ``train_mask`` read one stacking of the
    training sequences (the module's set-up reads all three)."""
    import torchhys.training.data as data

    calls = []
    stack = data.stack_sequences
    monkeypatch.setattr(data, "stack_sequences", lambda seqs: calls.append(1) or stack(seqs))
    dm = HysteresisDataModule(t_end=6.3, split=[0.8, 0.2, 0.0], warmup=7)
    x, y = dm.train_tensors()
    assert dm.train_warmup == 7 and dm.train_mask is None and len(calls) == 1
    assert dm.train_tensors()[0] is x and x.shape == (1, dm.batches("train")[0][0].shape[1])

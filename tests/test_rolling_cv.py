"""Rolling-origin cross-validation (``model.select_cv_mode: rolling``): each block of the
training part (or each training recording) after the first is scored by a fit of those
before it only."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from _training_helpers import DROP, LINE, cli, small_config

from torchhys.cli.selection import check_candidates, model_arguments
from torchhys.selection.folds import block_split, fold_masks, rolling_split
from torchhys.training import HysteresisDataModule, InverseHysteresisModule
from torchhys.training.folds import RecordingFold, RollingFold, cv_fold
from torchhys.training.selection import run_selection

ROOT = Path(__file__).resolve().parents[1]
FERRITE = {"path": str(ROOT / "examples/data/mnzn_ferrite_bh_loops.csv"), "input_column": "B_T",
           "target_column": "H_Apm", "run_column": "loop", "split_by": "recording"}


def reference_split(mask: np.ndarray, k: int, fold: int) -> tuple[np.ndarray, np.ndarray]:
    """The rolling cut by a plain loop over rows: numpy's array_split of each row's scored
    indices into k pieces, pieces 0..fold fitted, piece fold + 1 held out."""
    fitted, held = np.zeros_like(mask, dtype=bool), np.zeros_like(mask, dtype=bool)
    for r in range(mask.shape[0]):
        pieces = np.array_split(np.flatnonzero(mask[r]), k)
        for piece in pieces[:fold + 1]:
            fitted[r, piece] = True
        held[r, pieces[fold + 1]] = True
    return fitted, held


@pytest.mark.parametrize("k", [2, 3, 5])
def test_rolling_split_against_a_plain_loop(k: int) -> None:
    """Rows of other lengths, warm-ups and gaps: the cut matches the reference, every
    fitted sample comes before every held-out one, the held-out block is the blocked cut's
    block ``fold + 1``, and the held-out blocks cover every scored sample but block 0."""
    g = torch.Generator().manual_seed(k)
    mask = torch.rand(3, 40, generator=g) > 0.2
    mask[0, :4] = False  # a warm-up
    mask[2, 31:] = False  # a shorter row
    covered = torch.zeros_like(mask)
    for fold in range(k - 1):
        fitted, held = rolling_split(mask.to(torch.uint8), k, fold)
        ref_fitted, ref_held = reference_split(mask.numpy(), k, fold)
        np.testing.assert_array_equal(fitted.numpy(), ref_fitted)
        np.testing.assert_array_equal(held.numpy(), ref_held)
        assert torch.equal(held, block_split(mask, k, fold + 1))
        for got, want in zip(fold_masks(mask, k, fold, rolling=True), (fitted, held),
                             strict=True):
            assert torch.equal(got, want)
        blocked_fit, blocked_held = fold_masks(mask, k, fold)
        assert torch.equal(blocked_held, block_split(mask, k, fold))
        assert torch.equal(blocked_fit, mask & ~blocked_held)
        for r in range(3):
            assert int(fitted[r].nonzero().max()) < int(held[r].nonzero().min())
        assert not (covered & held).any()
        covered |= held
    assert torch.equal(covered, mask & ~block_split(mask, k, 0))


def test_rolling_split_errors() -> None:
    mask = torch.ones(2, 10, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"fold must be in \[0, 2\) \(k - 1 rolling folds of "
                                         r"k=3 blocks\), got 2"):
        rolling_split(mask, 3, 2)
    with pytest.raises(ValueError, match=r"model.select_cv must be an int >= 2, got 1"):
        rolling_split(mask, 1, 0)
    with pytest.raises(ValueError, match=r"row 0 of the data holds 10 scored samples, at "
                                         r"least 12"):
        rolling_split(mask, 6, 0)
    with pytest.raises(ValueError, match=r"mask must have shape \(rows, time\)"):
        rolling_split(mask[0], 3, 0)


@pytest.mark.parametrize("warmup", [0, 7])
def test_rolling_folds_of_a_datamodule(warmup: int) -> None:
    """A :class:`RollingFold` trains on the blocks before its held-out block and lets its
    fits use the warm-up and those blocks only (the later samples run the states but are
    outside the fit mask)."""
    dm = HysteresisDataModule(t_end=6.3, split=[0.8, 0.2, 0.0], warmup=warmup)
    x, y, first, mask = dm.batches("train")[0]
    for j in range(3):
        fold = RollingFold(dm, 4, j)
        fitted, held = reference_split(mask.numpy(), 4, j)
        (tx, _, tw, tmask), = list(fold.train_dataloader())
        (vx, _, _, vmask), = list(fold.val_dataloader())
        assert fold.k == 3 and fold.n_val == held.sum()
        assert torch.equal(tx, x) and torch.equal(vx, x) and torch.equal(tw, first)
        np.testing.assert_array_equal(tmask.numpy(), fitted)
        np.testing.assert_array_equal(vmask.numpy(), held)
        fx, fy = fold.train_tensors()
        assert torch.equal(fx, x) and torch.equal(fy, y) and fold.train_warmup == warmup
        np.testing.assert_array_equal(fold.train_mask.numpy(), fitted | ~mask.numpy())
    with pytest.raises(ValueError, match=r"fold must be in \[0, 3\)"):
        RollingFold(dm, 4, 3)


def test_rolling_recording_folds_train_on_the_recordings_before() -> None:
    dm = HysteresisDataModule(**FERRITE, train_recordings=[0, 1, 3], val_recordings=[],
                              test_recordings=[2])
    x, y, _, mask = dm.batches("train")[0]
    for j in range(2):
        fold = RecordingFold(dm, j, rolling=True)
        (tx, _, _, _), = list(fold.train_dataloader())
        (vx, vy, _, vmask), = list(fold.val_dataloader())
        assert fold.k == 2 and fold.n_val == int(mask[j + 1].sum())
        assert torch.equal(tx, x[:j + 1]) and torch.equal(fold.train_tensors()[1], y[:j + 1])
        assert torch.equal(vx[0], x[j + 1]) and torch.equal(vmask[0], mask[j + 1])
    with pytest.raises(ValueError, match=r"fold must be in \[0, 2\), got 2"):
        RecordingFold(dm, 2, rolling=True)
    assert isinstance(cv_fold(dm, "recording", 1, "rolling"), RecordingFold)
    assert isinstance(cv_fold(dm, 3, 1, "rolling"), RollingFold)
    with pytest.raises(ValueError, match=r"model.select_cv_mode must be one of \['blocked', "
                                         r"'rolling'\], got 'rolled'"):
        cv_fold(dm, 3, 1, "rolled")


# The fold's fits through the module's set-up, on part of the Bouc-Wen example record.
OPERATORS = {
    "stops and drift": [{"fit": "stop_pi", "n_widths": 8}, {"fit": "drift"}],
    "preisach": [{"fit": "preisach", "n": 8}],
    "inverse pi": [{"fit": "pi_nonneg", "n_widths": 6, "direction": "inverse"}],
}


@pytest.mark.parametrize("operator", list(OPERATORS))
def test_a_rolling_fold_never_reads_what_comes_after_its_block(tmp_path: Path,
                                                                operator: str) -> None:
    """Inputs and targets spoiled after fold 1's held-out block change neither the fitted
    operators and normalization nor the predictions on the block; targets spoiled inside
    the fitted blocks do change the fit (the check can fail)."""
    rows = list(csv.DictReader((ROOT / "examples/data/bouc_wen.csv").open()))[:600]
    kw = {"input_column": "response", "target_column": "command", "time_column": "time",
          "split": [0.8, 0.2, 0.0], "warmup": 50}

    def fitted(table: list[dict]) -> tuple[dict, torch.Tensor, torch.Tensor]:
        path = tmp_path / f"rec{len(list(tmp_path.iterdir()))}.csv"
        with path.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
        fold = RollingFold(HysteresisDataModule(path=str(path), **kw), 4, 1)
        torch.manual_seed(0)
        module = InverseHysteresisModule(operator=OPERATORS[operator], hidden=1,
                                         activation="identity").double()
        x, y = fold.train_tensors()
        module.fit_normalization(x, y, warmup=fold.train_warmup, mask=fold.train_mask)
        (vx, _, _, vmask), = list(fold.val_dataloader())
        with torch.no_grad():
            prediction = module(vx)[vmask]
        state = {k: v.clone() for k, v in module.net.state_dict().items()}
        return state, vmask[0], prediction

    clean, held, prediction = fitted(rows)
    end = int(held.nonzero().max()) + 1
    assert 0 < end < 480  # samples of the training part come after the block
    later = [dict(r, command=str(-2 * float(r["command"])), response=str(float(r["response"])
                                                                          * 3 + 1))
             if i >= end else r for i, r in enumerate(rows)]
    other, _, other_prediction = fitted(later)
    for key, value in clean.items():
        assert torch.equal(other[key], value), key
    assert torch.equal(other_prediction, prediction)
    start = int(held.nonzero().min())
    earlier = [dict(r, command=str(float(r["command"]) * 1.5)) if 60 <= i < start else r
               for i, r in enumerate(rows)]
    moved, _, _ = fitted(earlier)
    assert any(not torch.equal(moved[k], v) for k, v in clean.items())


SELECT = {"trainer": {"max_epochs": 10},
          "model": {**LINE, "optimizer_kwargs": {"max_iter": 100, "tolerance_grad": 1.0e-12,
                                                 "tolerance_change": 1.0e-15},
                    "select": [{"operator": None},
                               {"operator": [{"fit": "pi_ls", "n_widths": 8}]}],
                    "select_cv": 3, "select_cv_mode": "rolling"},
          "data": {"dt": 0.05, "t_end": 25.2, "split": [0.6, 0.0, 0.4]}}
"""The sections of :func:`small_config`: the line or the PI operator, by rolling-origin
cross-validation."""


def test_rolling_cross_validation_on_the_command_line(monkeypatch, capsys, tmp_path) -> None:
    """``select_cv: 3, select_cv_mode: rolling``: two folds per candidate; the straight
    line's fold MSEs are those of numpy least squares on the blocks before each held-out
    block, and the pooled MSE weighs them by their samples."""
    cfg = small_config(tmp_path, "rolling.yaml", **SELECT)
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}")
    out = capsys.readouterr().out
    assert "rolling-origin cross-validation on 3 blocks (2 folds)" in out
    with (root / "logs/version_0/selection.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and "fold_3" not in rows[0]
    assert rows[1]["selected"] == "1"  # the PI inverts the paper's PI plant
    x, y, _, mask = (v.numpy() for v in HysteresisDataModule(
        dt=0.05, t_end=25.2, split=[0.6, 0.0, 0.4]).batches("train")[0])
    folds, counts = [], []
    for j in range(2):
        fit, held = reference_split(mask, 3, j)
        k, c = np.polyfit(x[fit], y[fit], 1)
        folds.append(np.mean((k * x[held] + c - y[held]) ** 2))
        counts.append(held.sum())
    line = rows[0]
    assert [float(line[f"fold_{j + 1}"]) for j in range(2)] == pytest.approx(folds, rel=1e-5)
    assert float(line["val_mse"]) == pytest.approx(np.dot(folds, counts) / sum(counts),
                                                   rel=1e-5)
    assert len(list((root / "logs/version_0/selection").rglob("metrics.csv"))) == 4


def test_rolling_mode_errors(monkeypatch, tmp_path) -> None:
    valid = model_arguments(InverseHysteresisModule)
    with pytest.raises(ValueError, match=r"model.select_cv_mode='rolling' needs "
                                         r"model.select_cv"):
        check_candidates([{}], valid, mode="rolling")
    with pytest.raises(ValueError, match=r"model.select_cv_mode must be one of"):
        check_candidates([{}], valid, cv=3, mode="forward")
    with pytest.raises(ValueError, match=r"model.select_cv_mode='rolling' needs "
                                         r"model.select_cv"):
        run_selection([{}], lambda i, fold: None, mode="rolling")
    cfg = small_config(tmp_path, "bad.yaml",
                       **{**SELECT, "model": {**SELECT["model"], "select_cv": DROP}})
    with pytest.raises(ValueError, match=r"model.select_cv_mode='rolling' needs "
                                         r"model.select_cv"):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}")
    assert not list(tmp_path.rglob("metrics.csv"))

"""The memoryless baselines (straight line, polynomial of a chosen degree) against numpy
least squares, and ``torchhys test``'s comparison of the model with them."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tests._training_helpers import DROP, LINE, cli, small_config, trainer
from torchhys.training import HysteresisDataModule, InverseHysteresisModule
from torchhys.training.baselines import fit_polynomial, holdout_mask, max_degree
from torchhys.training.callbacks import BaselineComparison


def _data(seed: int = 0, rows: int = 2, T: int = 200) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(rows, T, generator=g, dtype=torch.float64)
    y = 0.5 - 1.5 * x + 0.3 * x**3 + 0.2 * torch.randn(rows, T, generator=g, dtype=torch.float64)
    return x, y


def _reference_holdout(mask: np.ndarray, share: float = 0.25) -> np.ndarray:
    """The last share of each row's scored samples, by a plain loop."""
    held = np.zeros_like(mask)
    for r in range(mask.shape[0]):
        idx = [t for t in range(mask.shape[1]) if mask[r, t]]
        n = max(1, int(round(share * len(idx))))
        for t in idx[len(idx) - n:]:
            held[r, t] = True
    return held


def test_holdout_is_the_last_quarter_of_each_rows_scored_samples() -> None:
    mask = torch.zeros(3, 20, dtype=torch.bool)
    mask[0, 4:] = True  # warm-up
    mask[1, 2:15] = True  # padded row
    mask[2, ::3] = True  # gaps
    held = holdout_mask(mask)
    np.testing.assert_array_equal(held.numpy(), _reference_holdout(mask.numpy()))
    assert bool((held <= mask).all())
    assert held[0].nonzero().flatten().tolist() == [16, 17, 18, 19]


def test_line_is_numpy_least_squares_on_the_scored_samples() -> None:
    x, y = _data()
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, :20] = False
    y[:, :20] = float("nan")  # unscored samples are never read
    line = fit_polynomial(x, y, mask, degrees=(1,))
    k, b = np.polyfit(x[mask].numpy(), y[mask].numpy(), 1)
    v = torch.linspace(-2, 2, 7, dtype=torch.float64)
    np.testing.assert_allclose(line(v).numpy(), k * v.numpy() + b, rtol=1e-10, atol=1e-12)
    assert line.degree == 1
    # its validation RMSE: fitted before the hold-out, scored on it
    held = torch.from_numpy(_reference_holdout(mask.numpy()))
    fit = mask & ~held
    k0, b0 = np.polyfit(x[fit].numpy(), y[fit].numpy(), 1)
    ref = np.sqrt(np.mean((k0 * x[held].numpy() + b0 - y[held].numpy()) ** 2))
    assert line.validation_rmse == pytest.approx(ref, rel=1e-10)


def test_degree_is_chosen_on_the_holdout() -> None:
    x, y = _data(seed=1)
    mask = torch.ones_like(x, dtype=torch.bool)
    held = torch.from_numpy(_reference_holdout(mask.numpy()))
    fit = mask & ~held
    scores = {}
    for d in range(1, 10):  # numpy's plain polyfit, an independent least-squares solver
        c = np.polyfit(x[fit].numpy(), y[fit].numpy(), d)
        scores[d] = np.sqrt(np.mean((np.polyval(c, x[held].numpy()) - y[held].numpy()) ** 2))
    expected = min(scores, key=scores.get)
    poly = fit_polynomial(x, y)
    assert poly.degree == expected >= 3  # the data are cubic
    assert poly.validation_rmse == pytest.approx(scores[expected], rel=1e-8)
    c = np.polyfit(x.flatten().numpy(), y.flatten().numpy(), expected)
    v = torch.linspace(-2, 2, 9, dtype=torch.float64)
    np.testing.assert_allclose(poly(v).numpy(), np.polyval(c, v.numpy()), rtol=1e-8, atol=1e-8)


def test_polynomial_keeps_the_input_dtype_and_shape() -> None:
    x, y = _data(T=60)
    poly = fit_polynomial(x, y, degrees=(2,))
    v = torch.zeros(2, 3, 4, dtype=torch.float32)
    out = poly(v)
    assert out.shape == v.shape and out.dtype == torch.float32
    # one sequence, (time,)
    assert fit_polynomial(x[0], y[0], degrees=(1,)).degree == 1


@pytest.mark.parametrize(("args", "kwargs", "match"), [
    ((torch.zeros(2, 10), torch.zeros(2, 9)), {}, "x and y must have the same shape"),
    ((torch.zeros(2, 10), torch.zeros(2, 10), torch.ones(2, 9, dtype=torch.bool)), {},
     "mask must have the shape"),
    ((torch.tensor([[0.0, float("nan")] * 10]), torch.zeros(1, 20)), {},
     "x holds NaN or inf"),
    ((torch.zeros(1, 20), torch.tensor([[0.0, float("inf")] * 10])), {},
     "y holds NaN or inf"),
    ((torch.randn(1, 20), torch.randn(1, 20)), {"degrees": (0, 1)}, "degrees"),
    ((torch.randn(1, 20), torch.randn(1, 20)), {"degrees": ()}, "at least one degree"),
    ((torch.randn(1, 12), torch.randn(1, 12)), {}, "degree 9 needs at least 10 scored"),
    ((torch.randn(1, 20), torch.randn(1, 20)), {"validation": 1.0}, "validation"),
    ((torch.randn(20), torch.randn(20), torch.ones(19, dtype=torch.bool)), {},
     r"mask must have the shape of x \(20,\), got \(19,\)"),
])
def test_bad_input_is_a_clear_error(args, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        fit_polynomial(*args, **kwargs)


def test_degrees_must_be_an_iterable() -> None:
    with pytest.raises(TypeError, match="degrees must be an iterable"):
        fit_polynomial(torch.randn(20), torch.randn(20), degrees=5)


def test_max_degree_counts_the_samples_before_the_holdout() -> None:
    mask = torch.zeros(2, 30, dtype=torch.bool)
    mask[0, 10:18] = True  # 8 scored: 2 held out, 6 before
    mask[1, :4] = True  # 4 scored: 1 held out, 3 before
    assert max_degree(mask) == 6 + 3 - 1
    assert max_degree(torch.zeros(1, 5, dtype=torch.bool)) == -1


def test_constant_input_gives_the_mean() -> None:
    y = torch.arange(20.0, dtype=torch.float64)[None]
    poly = fit_polynomial(torch.ones_like(y), y)
    assert float(poly(torch.tensor([3.0]))) == pytest.approx(float(y.mean()))


def test_comparison_scores_the_baselines_on_the_test_split(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.chdir(tmp_path)  # a trainer without a logger draws no report (here, or anywhere)
    torch.manual_seed(0)
    dm = HysteresisDataModule(simulation="paper", t_end=12.6, split=[0.6, 0.2, 0.2], warmup=60)
    module = InverseHysteresisModule(operator="zhao_tan", operator_kwargs={"scale": 1.8},
                                     hidden=6, optimizer="lbfgs")
    comparison = BaselineComparison(max_degree=5)
    t = trainer(max_epochs=3, callbacks=[comparison])
    t.fit(module, datamodule=dm)
    (logged,) = t.test(module, datamodule=dm, verbose=False)
    # the reference: numpy on the stage tensors
    (x, y, _, mask), = dm.batches("train")
    (tx, ty, _, tmask), = dm.batches("test")
    m, tm = mask.numpy().astype(bool), tmask.numpy().astype(bool)
    xs, ys, txs, tys = x.numpy(), y.numpy(), tx.numpy(), ty.numpy()
    held = _reference_holdout(m)
    scores = {}
    for d in range(1, 6):
        c = np.polyfit(xs[m & ~held], ys[m & ~held], d)
        scores[d] = np.mean((np.polyval(c, xs[held]) - ys[held]) ** 2)
    d = min(scores, key=scores.get)
    line = np.mean((np.polyval(np.polyfit(xs[m], ys[m], 1), txs[tm]) - tys[tm]) ** 2)
    poly = np.mean((np.polyval(np.polyfit(xs[m], ys[m], d), txs[tm]) - tys[tm]) ** 2)
    assert logged["test_line_mse"] == pytest.approx(line, rel=1e-6)
    assert logged["test_poly_mse"] == pytest.approx(poly, rel=1e-6)
    assert comparison.results["poly_degree"] == d
    # the model's own test MSE, as the module logs it
    assert comparison.results["test_mse"] == pytest.approx(logged["test_mse"], rel=1e-6)
    assert logged["test_ratio"] == pytest.approx(
        math.sqrt(logged["test_mse"] / min(line, poly)), rel=1e-6)
    assert logged["test_rmse_pct"] == pytest.approx(
        100 * math.sqrt(logged["test_mse"]) / np.ptp(tys[tm]), rel=1e-6)
    assert comparison.report and list(tmp_path.rglob("*.png")) == []


def test_torchhys_test_logs_the_comparison(monkeypatch, tmp_path: Path) -> None:
    config = small_config(
        tmp_path, "c.yaml", trainer={"max_epochs": 10, "check_val_every_n_epoch": DROP},
        model={**LINE, "optimizer_kwargs": {"max_iter": 20, "tolerance_grad": 1.0e-12,
                                            "tolerance_change": 1.0e-15}})
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(config), f"--trainer.default_root_dir={root}")
    ckpt = root / "logs/version_0/checkpoints/last.ckpt"
    cli(monkeypatch, "test", "--config", str(config), f"--trainer.default_root_dir={root}",
        f"--ckpt_path={ckpt}", "--baselines.max_degree=1")
    with (root / "logs/version_1/metrics.csv").open() as fh:
        (row,) = [r for r in csv.DictReader(fh) if r.get("test_ratio")]
    # an affine network of the input is the least-squares line: ratio 1
    assert float(row["test_ratio"]) == pytest.approx(1.0, rel=1e-6)
    # the RMSE, the largest error and the RMSE in % of range beside the MSE, and the figure
    assert float(row["test_rmse"]) == pytest.approx(math.sqrt(float(row["test_mse"])), rel=1e-6)
    assert float(row["test_max_error"]) >= float(row["test_rmse"]) > 0.0
    assert 0.0 < float(row["test_rmse_pct"]) < 100.0
    assert (root / "logs/version_1/test_report.png").stat().st_size > 10_000
    with pytest.raises(ValueError, match="max_degree must be an int >= 1, got 0"):
        cli(monkeypatch, "test", "--config", str(config), f"--trainer.default_root_dir={root}",
            f"--ckpt_path={ckpt}", "--baselines.max_degree=0")


def test_a_short_training_split_caps_the_degree() -> None:
    """8 training samples: 6 before the hold-out determine degrees up to 5, not 9."""
    dm = HysteresisDataModule(simulation="paper", t_end=0.2, split=[0.4, 0.3, 0.3],
                              min_samples=4)
    module = InverseHysteresisModule(operator=None, hidden=1, activation="identity",
                                     optimizer="lbfgs")
    comparison = BaselineComparison()
    t = trainer(max_epochs=1, callbacks=[comparison])
    t.fit(module, datamodule=dm)
    (logged,) = t.test(module, datamodule=dm, verbose=False)
    (_, _, _, mask), = dm.batches("train")
    assert int(mask.sum()) == 8
    assert 1 <= comparison.results["poly_degree"] <= 5
    assert math.isfinite(logged["test_ratio"])


def _recording_files(folder: Path, lengths: list[int]) -> list[str]:
    """Recordings of a backlash-like loop of different lengths, as CSV files."""
    paths = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * 0.01
        command = (1.0 + 0.3 * i) * np.sin(2.0 * t) + 0.2 * np.sin(7.0 * t + i)
        response = np.tanh(command) + 0.1 * np.sign(np.cos(2.0 * t))
        path = folder / f"rec{i}.csv"
        np.savetxt(path, np.column_stack([response, command]), delimiter=",",
                   header="response,command", comments="")
        paths.append(str(path))
    return paths


def test_comparison_on_recordings_of_different_lengths(tmp_path: Path) -> None:
    """Padded rows and per-recording warm-ups: the baselines see exactly the scored samples
    of each recording, read here from the files themselves."""
    lengths = [300, 420, 250, 380, 260]
    paths = _recording_files(tmp_path, lengths)
    warmup = 30
    dm = HysteresisDataModule(path=paths, split_by="recording", train_recordings=[0, 1],
                              val_recordings=[2], test_recordings=[3, 4], warmup=warmup)
    module = InverseHysteresisModule(operator=[{"fit": "plays", "n": 4}], hidden=4,
                                     optimizer="lbfgs")
    comparison = BaselineComparison(max_degree=4)
    t = trainer(max_epochs=2, callbacks=[comparison])
    t.fit(module, datamodule=dm)
    (logged,) = t.test(module, datamodule=dm, verbose=False)
    data = [np.loadtxt(p, delimiter=",", skiprows=1) for p in paths]
    fx = np.concatenate([d[warmup:, 0] for d in data[:2]])
    fy = np.concatenate([d[warmup:, 1] for d in data[:2]])
    tx = np.concatenate([d[warmup:, 0] for d in data[3:]])
    ty = np.concatenate([d[warmup:, 1] for d in data[3:]])
    line = np.mean((np.polyval(np.polyfit(fx, fy, 1), tx) - ty) ** 2)
    # (logged values are float32; the callback keeps float64 ones)
    assert comparison.results["test_line_mse"] == pytest.approx(line, rel=1e-9)
    assert logged["test_line_mse"] == pytest.approx(line, rel=1e-6)
    d = int(comparison.results["poly_degree"])
    poly = np.mean((np.polyval(np.polyfit(fx, fy, d), tx) - ty) ** 2)
    assert comparison.results["test_poly_mse"] == pytest.approx(poly, rel=1e-6)
    assert comparison.results["test_mse"] == pytest.approx(logged["test_mse"], rel=1e-6)


def test_comparison_scores_the_dataloaders_the_test_ran(tmp_path: Path) -> None:
    """``trainer.test(dataloaders=...)`` after a fit: the tested batches, not the
    datamodule's test split; the training part stays the datamodule's."""
    paths = _recording_files(tmp_path, [300, 320, 280, 310])
    dm = HysteresisDataModule(path=paths, split_by="recording", train_recordings=[0, 1],
                              val_recordings=[2], test_recordings=[3], warmup=20)
    module = InverseHysteresisModule(operator=[{"fit": "plays", "n": 3}], hidden=3,
                                     optimizer="lbfgs")
    comparison = BaselineComparison(max_degree=1)
    t = trainer(max_epochs=2, callbacks=[comparison])
    t.fit(module, datamodule=dm)
    (logged,) = t.test(module, dataloaders=dm.val_dataloader(), verbose=False)
    (x, y, _, mask), = dm.batches("train")
    (vx, vy, _, vmask), = dm.batches("val")
    m, v = mask.bool(), vmask.bool()
    k, b = np.polyfit(x[m].numpy(), y[m].numpy(), 1)
    line = np.mean((k * vx[v].numpy() + b - vy[v].numpy()) ** 2)
    assert comparison.results["test_line_mse"] == pytest.approx(line, rel=1e-9)
    assert logged["test_ratio"] == pytest.approx(math.sqrt(logged["test_mse"] / line), rel=1e-6)


def test_comparison_fits_on_every_training_batch(tmp_path: Path) -> None:
    """A datamodule that serves its training recordings as two batches of different lengths:
    the baselines are fitted on the scored samples of both (padding left out)."""
    paths = _recording_files(tmp_path, [300, 420, 260])
    warmup = 25
    dm = HysteresisDataModule(path=paths, split_by="recording", train_recordings=[0, 1],
                              val_recordings=[2], test_recordings=[2], warmup=warmup)
    dm.setup("fit")
    whole = dm.batches("train")

    class TwoBatches(HysteresisDataModule):
        def batches(self, stage: str) -> list:
            if stage != "train":
                return super().batches(stage)
            (x, y, z, mask), = whole
            first = (x[:1, :300], y[:1, :300], z[:1], mask[:1, :300])
            return [first, (x[1:], y[1:], z[1:], mask[1:])]

    split = TwoBatches(path=paths, split_by="recording", train_recordings=[0, 1],
                       val_recordings=[2], test_recordings=[2], warmup=warmup)
    assert split.batches("train")[0][0].shape == (1, 300)  # really two batches
    module = InverseHysteresisModule(operator=None, hidden=1, activation="identity",
                                     optimizer="lbfgs")
    comparison = BaselineComparison(max_degree=3)
    t = trainer(max_epochs=1, callbacks=[comparison])
    t.fit(module, datamodule=dm)
    t.test(module, datamodule=split, verbose=False)
    data = [np.loadtxt(p, delimiter=",", skiprows=1) for p in paths]
    fx = np.concatenate([d[warmup:, 0] for d in data[:2]])
    fy = np.concatenate([d[warmup:, 1] for d in data[:2]])
    tx, ty = data[2][warmup:, 0], data[2][warmup:, 1]
    line = np.mean((np.polyval(np.polyfit(fx, fy, 1), tx) - ty) ** 2)
    assert comparison.results["test_line_mse"] == pytest.approx(line, rel=1e-9)

"""torchhys.training.report.FitReport: after fit, the model on the validation split beside
the baselines, and fit_report.png in the run's folder."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger

from tests._training_helpers import cli, small_config, trainer
from torchhys.training import HysteresisDataModule, InverseHysteresisModule
from torchhys.training.report import FitReport


def _fitted(tmp_path: Path, logger: bool = True) -> tuple:
    torch.manual_seed(0)
    dm = HysteresisDataModule(simulation="paper", t_end=12.6, split=[0.6, 0.2, 0.2], warmup=60)
    module = InverseHysteresisModule(operator="zhao_tan", operator_kwargs={"scale": 1.8},
                                     hidden=6, optimizer="lbfgs")
    report = FitReport(max_degree=3)
    t = trainer(max_epochs=2, callbacks=[report], limit_val_batches=1.0,
                logger=CSVLogger(tmp_path, name="run") if logger else False)
    t.fit(module, datamodule=dm)
    return dm, module, report, t


def test_the_report_scores_the_validation_split_and_draws_it(tmp_path: Path, capsys) -> None:
    dm, module, report, t = _fitted(tmp_path)
    # the model's validation MSE as Lightning's validation loop logs it
    (logged,) = t.validate(module, datamodule=dm, verbose=False)
    assert report.results["val_mse"] == pytest.approx(logged["val_mse"], rel=1e-6)
    # the straight line: numpy least squares on the training split's scored samples
    (x, y, _, mask), = dm.batches("train")
    (vx, vy, _, vmask), = dm.batches("val")
    m, vm = mask.numpy().astype(bool), vmask.numpy().astype(bool)
    coef = np.polyfit(x.numpy()[m], y.numpy()[m], 1)
    line = np.mean((np.polyval(coef, vx.numpy()[vm]) - vy.numpy()[vm]) ** 2)
    assert report.results["val_line_mse"] == pytest.approx(line, rel=1e-6)
    best = min(line, report.results["val_poly_mse"])
    assert report.results["val_ratio"] == pytest.approx(
        math.sqrt(report.results["val_mse"] / best), rel=1e-9)
    assert report.results["val_rmse_pct"] == pytest.approx(
        100 * math.sqrt(logged["val_mse"]) / np.ptp(vy.numpy()[vm]), rel=1e-6)
    assert report.report_path == Path(t.log_dir) / "fit_report.png"
    assert report.report_path.stat().st_size > 10_000
    assert f"in {report.report_path}" in capsys.readouterr().out


def test_without_a_logger_nothing_is_drawn(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _, _, report, _ = _fitted(tmp_path, logger=False)
    assert report.results == {} and report.report_path is None
    assert list(tmp_path.rglob("*.png")) == []


def test_torchhys_fit_writes_the_report_and_says_where(monkeypatch, tmp_path: Path,
                                                       capsys) -> None:
    config = small_config(tmp_path, "c.yaml", fit_report={"enabled": True})
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(config), f"--trainer.default_root_dir={root}")
    png = root / "logs/version_0/fit_report.png"
    assert png.stat().st_size > 10_000
    assert f"torchhys fit: the fitted loop, the validation tracking and error in {png}" \
        in capsys.readouterr().out
    off = tmp_path / "off"
    cli(monkeypatch, "fit", "--config", str(config), f"--trainer.default_root_dir={off}",
        "--fit_report.enabled=false")
    assert list(off.rglob("*.png")) == []

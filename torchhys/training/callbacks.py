"""Callbacks of the ``torchhys`` command."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter

from torchhys._checks import check_int
from torchhys.training.baselines import MAX_DEGREE
from torchhys.training.report import Scored, compare_baselines, draw_report, scored_samples

__all__ = ["BaselineComparison", "PredictionWriter"]


class BaselineComparison(L.Callback):
    """After ``test``: the model beside two memoryless baselines fitted on the same training
    part, a straight line and a polynomial of the input (its degree chosen on the training
    part's time-ordered hold-out, :func:`~torchhys.training.baselines.fit_polynomial`), each
    scored on the samples the test scored. Logged (and so printed in the test table and
    returned by ``trainer.test``):

    - ``test_line_mse``, ``test_poly_mse``: the baselines' test MSE (with operating
      conditions, ``data.condition_columns``, the polynomial is one of the input and the
      conditions: :func:`~torchhys.training.baselines.fit_condition_polynomial`, the
      baseline that sees what the model sees);
    - ``test_ratio``: the model's test RMSE over the better baseline's (below 1: the model
      earns its place; the ``ratio`` of docs/real-data.md; 1 when both are 0);
    - ``test_rmse``, ``test_max_error`` and ``test_rmse_pct``: the model's RMSE, its largest
      error and its RMSE in % of the tested targets' range (target units).

    With ``report`` (the default) it also draws the test (the loop of target and prediction
    against the input, the tracking and the baselines over the samples, the error over time)
    into ``test_report.png`` in the run's log folder and prints where (rank 0, a trainer
    with a logger; needs matplotlib).

    The tested samples are those of the batches the test ran (their scored inputs, targets
    and predictions, as :class:`~torchhys.training.InverseHysteresisModule`'s ``test_step``
    returns them); the training part is the trainer's datamodule's: the rows of every batch
    of ``batches("train")`` (:class:`~torchhys.training.HysteresisDataModule` serves one).
    Without either it does nothing.
    :attr:`results` keeps the logged values, with ``poly_degree`` and the model's
    ``test_mse`` over the same samples.

    On a training split too short for ``max_degree`` (fewer than ``max_degree + 1`` scored
    samples before its hold-out) the degrees are capped at what its samples determine
    (:func:`~torchhys.training.baselines.max_degree`).

    Args:
        max_degree: the highest polynomial degree tried (>= 1; 1: the line twice).
        report: draw ``test_report.png`` (above).
    """

    KEYS = ("input", "target", "prediction")
    """What ``test_step`` returns: the scored samples of the batch, each flat."""

    def __init__(self, max_degree: int = MAX_DEGREE, report: bool = True) -> None:
        self.max_degree = check_int(max_degree, "max_degree", minimum=1)
        self.report = bool(report)
        self.report_path: Path | None = None
        self.results: dict[str, float] = {}
        self._tested: list[Scored] = []

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._tested, self.results = [], {}

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                          outputs: Any, batch: Any, batch_idx: int,
                          dataloader_idx: int = 0) -> None:
        if isinstance(outputs, Mapping) and all(k in outputs for k in self.KEYS):
            self._tested.append(scored_samples(outputs))

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        dm = getattr(trainer, "datamodule", None)
        if not self._tested or dm is None or not hasattr(dm, "batches"):
            return
        comparison = compare_baselines(dm.batches("train"), self._tested, "test",
                                       self.max_degree)
        if comparison is None:
            return
        self.results = dict(comparison.results)
        self.results["poly_degree"] = self.results.pop("test_poly_degree")
        for key in ("test_line_mse", "test_poly_mse", "test_ratio", "test_rmse",
                    "test_max_error", "test_rmse_pct"):
            pl_module.log(key, self.results[key], on_step=False, on_epoch=True, sync_dist=True)
        if self.report and trainer.loggers:  # a run's folder
            folder = Path(trainer.log_dir)  # a broadcast: every rank asks, or rank 0 waits
            if trainer.global_rank == 0:
                self.report_path = draw_report(folder / "test_report.png", comparison, "test")
            if self.report_path is not None:
                print(f"torchhys test: the test's loop, tracking and error in "
                      f"{self.report_path}", flush=True)


class PredictionWriter(BasePredictionWriter):
    """Write ``predict`` results to ``<default_root_dir>/<filename>``.

    Columns: ``sequence`` (the batch row), ``sample``, ``input``, ``target``, ``prediction``
    (physical units), and the operating conditions under their column names where the data
    has them (``data.condition_columns``). Only rank 0 writes.

    Args:
        filename: name of the CSV file under the trainer's ``default_root_dir``.
    """

    def __init__(self, filename: str = "predictions.csv") -> None:
        super().__init__(write_interval="epoch")
        self.filename = filename
        self.path: Path | None = None

    def write_on_epoch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, predictions: Any,
        batch_indices: Any,
    ) -> None:
        if trainer.global_rank != 0:
            return
        loader = trainer.predict_dataloaders
        batches = list(loader) if loader is not None else []
        rows = []
        seq = 0
        n_cond = 0
        for batch, pred in zip(batches, predictions, strict=False):
            x, y = batch[0], batch[1]
            conds = batch[4] if len(batch) == 5 else None
            n_cond = 0 if conds is None else int(conds.shape[-1])
            for r, (xb, yb, pb) in enumerate(zip(x, y, pred.reshape(x.shape), strict=True)):
                n = xb.numel()
                cols = [np.full(n, seq), np.arange(n), xb.double().numpy(),
                        yb.double().numpy(), pb.detach().to(torch.float64).cpu().numpy()]
                if conds is not None:
                    cols += [conds[r, :, k].double().numpy() for k in range(n_cond)]
                rows.append(np.column_stack(cols))
                seq += 1
        if not rows:
            return
        names = list(getattr(getattr(trainer.datamodule, "hparams", None), "condition_columns",
                             None) or []) if n_cond else []
        names = [str(c) for c in names] if len(names) == n_cond else [
            f"condition_{k}" for k in range(n_cond)]
        self.path = Path(trainer.default_root_dir) / self.filename
        self.path.parent.mkdir(parents=True, exist_ok=True)
        replaced = self.path.exists()
        np.savetxt(self.path, np.concatenate(rows), delimiter=",", comments="",
                   header=",".join(["sequence", "sample", "input", "target", "prediction",
                                    *names]),
                   fmt=["%d", "%d", "%.10g", "%.10g", "%.10g"] + ["%.10g"] * n_cond)
        print(f"torchhys predict: wrote {self.path}" + (" (replacing the file that was there)"
                                                        if replaced else ""), flush=True)

"""Callbacks of the ``torchhys`` command."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter

__all__ = ["PredictionWriter"]


class PredictionWriter(BasePredictionWriter):
    """Write ``predict`` results to ``<default_root_dir>/<filename>``.

    Columns: ``sequence`` (the batch row), ``sample``, ``input``, ``target``, ``prediction``
    (physical units). Only rank 0 writes.

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
        for batch, pred in zip(batches, predictions, strict=False):
            x, y = batch[0], batch[1]
            for xb, yb, pb in zip(x, y, pred.reshape(x.shape), strict=True):
                n = xb.numel()
                rows.append(np.column_stack([
                    np.full(n, seq), np.arange(n), xb.double().numpy(), yb.double().numpy(),
                    pb.detach().to(torch.float64).cpu().numpy(),
                ]))
                seq += 1
        if not rows:
            return
        self.path = Path(trainer.default_root_dir) / self.filename
        self.path.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(self.path, np.concatenate(rows), delimiter=",", comments="",
                   header="sequence,sample,input,target,prediction",
                   fmt=["%d", "%d", "%.10g", "%.10g", "%.10g"])

"""The affine readout of a model-selection run solved by least squares, without a Trainer.

The candidates of ``configs/measured.yaml`` are fitted model families read by an affine
network (``hidden: 1, activation: identity``) trained full-batch by L-BFGS: once the
families are fitted, its training is a linear least-squares problem in the normalized
features, which L-BFGS solves in a few steps. Model selection trains such a readout on every
fold of every candidate; :func:`direct_validation` solves it directly instead (one
least-squares solve on the training batch's scored samples) and scores it on the validation
batches as the Trainer's validation does. The chosen candidate's final fit still runs
through the Trainer (its checkpoint and logs).
"""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from torch import Tensor

from torchhys.networks import InverseHysteresisNet
from torchhys.selection.candidates import is_direct, solve_readout, steps_readout
from torchhys.selection.folds import Batch
from torchhys.training.module import InverseHysteresisModule

__all__ = ["direct_validation", "solvable"]


def solvable(module: Any, datamodule: Any, trainer: Any) -> bool:
    """Whether :func:`direct_validation` gives the trained run's result: an
    :class:`InverseHysteresisModule` of an identity-activation network with fixed operators,
    trained full-batch by a closure optimizer (its training a least-squares problem it
    solves), on one device, on a datamodule with ``train_tensors`` and (x, y, warmup, mask)
    batches; its trainer steps the readout at all
    (:func:`~torchhys.selection.candidates.steps_readout`, as ``torchhys fit`` asks)."""
    return (isinstance(module, InverseHysteresisModule)
            and isinstance(module.net, InverseHysteresisNet)
            and is_direct({"activation": module.hparams.get("activation"),
                           "optimizer": module.optimizer_name}, module.net)
            and hasattr(datamodule, "train_tensors")
            and getattr(trainer, "world_size", 1) == 1
            and steps_readout(getattr(trainer, "max_epochs", None),
                              getattr(trainer, "limit_train_batches", None)))


def _batches(loader: Any) -> list[tuple[Tensor, Tensor, Tensor, Tensor | None]]:
    out = []
    for batch in loader or []:
        if not (isinstance(batch, (tuple, list)) and len(batch) in (4, 5)):
            raise ValueError("a direct readout needs (x, y, warmup, mask) batches")
        x, y, _, mask = batch[:4]
        out.append((x, y, mask.to(torch.bool), batch[4] if len(batch) == 5 else None))
    return out


@torch.no_grad()
def direct_validation(module: InverseHysteresisModule, datamodule: L.LightningDataModule,
                      trainer: L.Trainer) -> tuple[float, Tensor]:
    """Fit ``module`` as its training would (the families and the normalization on
    ``datamodule``'s training tensors, then the readout), with the readout solved by least
    squares; its validation MSE and the squared errors of the scored validation samples.

    Raises:
        FitError: a family that cannot be fitted (as the Trainer's run raises it).
    """
    datamodule.setup("fit")
    if str(getattr(trainer, "precision", "")).startswith("64"):
        module.net.double()
    x, y = datamodule.train_tensors()
    module.fit_normalization(x, y, warmup=int(getattr(datamodule, "train_warmup", 0)),
                             mask=getattr(datamodule, "train_mask", None))
    dtype = module.net.in_mean.dtype
    train = _batches(datamodule.train_dataloader())
    if len(train) != 1:
        raise ValueError(f"a direct readout needs one full training batch, got {len(train)}")
    bx, by, mask, bc = train[0]
    solve_readout(module.net, Batch(bx.to(dtype), by.to(dtype), mask, bc))
    errors = []
    for bx, by, mask, bc in _batches(datamodule.val_dataloader()):
        e = (module(bx.to(dtype), target=by.to(dtype), conditions=bc).to(torch.float64)
             - by.to(torch.float64))
        errors.append(e.square()[mask])
    squared = torch.cat(errors) if errors else torch.zeros(0, dtype=torch.float64)
    return float(squared.mean()) if squared.numel() else float("nan"), squared

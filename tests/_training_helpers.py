"""Shared set-up of the training tests."""

from __future__ import annotations

import lightning as L


def trainer(max_epochs: int = 4, **kwargs) -> L.Trainer:
    """A quiet float64 CPU trainer without logger, checkpoints or validation by default."""
    opts = dict(max_epochs=max_epochs, accelerator="cpu", devices=1, logger=False,
                enable_checkpointing=False, enable_progress_bar=False,
                enable_model_summary=False, precision="64-true", num_sanity_val_steps=0,
                limit_val_batches=0)
    opts.update(kwargs)
    return L.Trainer(**opts)

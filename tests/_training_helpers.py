"""Shared set-up of the training tests."""

from __future__ import annotations

import sys

import lightning as L
import pytest
import torch

from torchhys.cli.main import main


def trainer(max_epochs: int = 4, **kwargs) -> L.Trainer:
    """A quiet float64 CPU trainer without logger, checkpoints or validation by default."""
    opts = dict(max_epochs=max_epochs, accelerator="cpu", devices=1, logger=False,
                enable_checkpointing=False, enable_progress_bar=False,
                enable_model_summary=False, precision="64-true", num_sanity_val_steps=0,
                limit_val_batches=0)
    opts.update(kwargs)
    return L.Trainer(**opts)


def cli(monkeypatch: pytest.MonkeyPatch, *args: str) -> None:
    """Run the ``torchhys`` command line with ``args`` (one torch thread). Errors in the
    user's files and options are raised as they are (``TORCHHYS_TRACEBACK=1``), for
    ``pytest.raises``; tests/test_cli_errors.py runs the command as users see it."""
    monkeypatch.setattr(sys, "argv", ["torchhys"])  # no stray pytest arguments
    monkeypatch.setenv("TORCHHYS_TRACEBACK", "1")
    torch.set_num_threads(1)
    main(list(args))

"""Shared set-up of the training tests."""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch
import yaml

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


DROP = object()
"""A value of :func:`small_config`'s sections: the key (or the section) is left out."""

SMALL_CONFIG: dict[str, Any] = {
    "seed_everything": 0,
    "trainer": {"accelerator": "cpu", "devices": 1, "precision": "64-true", "max_epochs": 3,
                "check_val_every_n_epoch": 1000, "enable_progress_bar": False,
                "enable_model_summary": False},
    "model": {"operator": "zhao_tan", "operator_kwargs": {"scale": 1.8}, "hidden": 8,
              "optimizer": "cg", "optimizer_kwargs": {"minstep": 0.0}},
    "data": {"simulation": "paper", "t_end": 6.3, "split": [0.6, 0.2, 0.2]},
    "fit_report": {"enabled": False},
}
"""The small ``torchhys fit`` config of the command-line tests: seeded, float64 on the CPU,
quiet, the paper's simulated plant inverted by a Zhao-Tan operator and 8 sigmoids (CG, one
full batch per epoch), validated only at the end of a short run, without fit_report.png
(tests/test_fit_report.py draws it)."""

LINE: dict[str, Any] = {"operator": None, "operator_kwargs": DROP, "hidden": 1,
                        "activation": "identity", "optimizer": "lbfgs",
                        "optimizer_kwargs": DROP}
"""``model`` overrides for the straight line (an affine network of the input) by L-BFGS."""


def small_config(folder: Path, name: str = "config.yaml", **sections: Any) -> Path:
    """Write :data:`SMALL_CONFIG` with ``sections`` applied to ``folder / name``; its path.

    A dict updates that section of the config key by key, any other value replaces the
    section (``seed_everything``, ``ckpt_path``, ...); :data:`DROP` leaves a key or a
    section out. Paths are written as strings."""
    config = copy.deepcopy(SMALL_CONFIG)
    for section, value in sections.items():
        if isinstance(value, dict) and isinstance(config.get(section), dict):
            config[section].update(value)
        else:
            config[section] = value
    path = Path(folder) / name
    path.write_text(yaml.safe_dump(_without_drops(config), sort_keys=False))
    return path


def _without_drops(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_drops(v) for k, v in value.items() if v is not DROP}
    if isinstance(value, (list, tuple)):
        return [_without_drops(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value

"""The version folder of a ``torchhys fit`` run, reserved before model selection starts:
concurrent runs into the same ``default_root_dir`` keep their tables apart, and the final
fit's logger writes into the folder that holds the table."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

from jsonargparse import Namespace
from lightning.pytorch.utilities import rank_zero_only

__all__ = ["RUN_DIR_ENV", "log_folder", "reserve_run_dir"]

RUN_DIR_ENV = "TORCHHYS_RUN_DIR"
"""The version folder model selection reserved, passed to the processes of other ranks that
the run launches (DDP): they use it instead of reserving their own."""


def log_folder(trainer: Namespace) -> tuple[Path, int | str | None, bool]:
    """Where the run's logger puts its version folders: the parent folder, the version
    its config pins (or None), and whether the logger is one whose version can be pinned
    (the default CSV logger, or a configured CSVLogger or TensorBoardLogger)."""
    root = Path(trainer.get("default_root_dir") or ".")
    logger = trainer.get("logger")
    if logger in (None, True):
        return root / "logs", None, True
    if isinstance(logger, dict | Namespace):
        init = logger.get("init_args") or {}
        if str(logger.get("class_path", "")).endswith(("CSVLogger", "TensorBoardLogger")) \
                and init.get("save_dir"):
            return Path(init["save_dir"]) / (init.get("name") or ""), init.get("version"), True
    return root / "logs", None, False  # no logger or another kind: a folder of its own


def _next_version(parent: Path) -> int:
    """One more than the highest ``version_N`` under ``parent`` (0 if none), as Lightning's
    loggers count."""
    found = [int(p.name[8:]) for p in parent.glob("version_*")
             if p.name[8:].isdigit() and p.is_dir()] if parent.is_dir() else []
    return max(found, default=-1) + 1


def reserve_run_dir(trainer: Namespace) -> tuple[Path, int | str | None]:
    """The run's version folder, created now (``os.mkdir`` of the next free ``version_N``,
    the next one on ``FileExistsError``: concurrent runs get different folders), and the
    version to pin the logger to (None: the logger's own, or no logger to pin)."""
    parent, version, pinnable = log_folder(trainer)
    if version is not None:  # the config pins it: that folder, as the logger would
        folder = parent / (f"version_{version}" if isinstance(version, int) else str(version))
        folder.mkdir(parents=True, exist_ok=True)
    elif rank_zero_only.rank != 0:  # launched by rank 0 (DDP): its folder, none of our own
        inherited = os.environ.get(RUN_DIR_ENV)
        folder = Path(inherited) if inherited else parent / f"version_{_next_version(parent)}"
    else:
        parent.mkdir(parents=True, exist_ok=True)
        n = _next_version(parent)
        while True:
            folder = parent / f"version_{n}"
            try:
                os.mkdir(folder)
                break
            except FileExistsError:
                n += 1
        os.environ[RUN_DIR_ENV] = str(folder)
    if not pinnable:
        return folder, None
    # the final fit's CSV logger finds the folder holding the table: not a previous run's
    warnings.filterwarnings("ignore", "Experiment logs directory .*"
                            f"{re.escape(os.path.join(parent.name, folder.name))} exists")
    suffix = folder.name[8:]
    return folder, int(suffix) if version is None and suffix.isdigit() else None

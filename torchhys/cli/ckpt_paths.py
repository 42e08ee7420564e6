"""The checkpoint a command's ``--ckpt_path`` names, checked before anything is written.

- a local file: read and checked (:func:`~torchhys.checkpoints.read_checkpoint`,
  ``weights_only=True``: no code from the file runs);
- a URL (``http://``, ``file://``, ``s3://`` ...) or Lightning's ``registry:...``: refused,
  one line; torchhys downloads nothing (Lightning's loader would load a URL with
  ``weights_only=False``, running code from the file);
- ``last``: the newest ``last*.ckpt`` of the earlier runs (``checkpoint.dirpath`` where the
  config sets one, else ``<default_root_dir>/logs/version_*/checkpoints`` and
  ``<default_root_dir>/checkpoints``), by modification time, named in a line on stderr;
  none is a one-line error.
  (Lightning's own ``last`` looks in the new run's folder, which is empty.)
- ``best`` and ``hpc``: Lightning's, read by the trainer's checkpoint plugin
  (:class:`~torchhys.training.checkpoint_io.AtomicCheckpointIO`: local files,
  ``weights_only=True``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

from torchhys.checkpoints import CheckpointError, read_checkpoint
from torchhys.cli.quiet import quiet_requested
from torchhys.cli.run_dirs import log_folder

__all__ = ["check_ckpt_path", "last_checkpoint"]

_LIGHTNING = ("best", "hpc")
"""Values Lightning resolves to a local file of the run."""


def last_checkpoint(cfg: Any) -> Path | None:
    """The newest ``last*.ckpt`` of the earlier runs the (subcommand's) config ``cfg`` would
    resume (see the module docstring), or None."""
    dirpath = (cfg.get("checkpoint") or {}).get("dirpath")
    if dirpath:
        folders = [Path(dirpath)]
    else:
        trainer = cfg["trainer"]
        parent = log_folder(trainer)[0]
        folders = [*parent.glob("version_*/checkpoints"),
                   Path(trainer.get("default_root_dir") or ".") / "checkpoints"]
    found = [p for folder in folders if folder.is_dir() for p in folder.glob("last*.ckpt")
             if p.is_file()]
    return max(found, key=lambda p: (p.stat().st_mtime_ns, str(p)), default=None)


def check_ckpt_path(path: Any, cfg: Any) -> str | None:
    """``--ckpt_path`` checked (see the module docstring): the path to use (``last``
    resolved to its file), or None when none is given.

    Raises:
        CheckpointError: a URL or a registry, no earlier ``last.ckpt``, or a file that
            :func:`~torchhys.checkpoints.read_checkpoint` refuses.
    """
    if path is None:
        return None
    text = os.fspath(path)
    if text in _LIGHTNING:
        return text
    if text.lower().startswith("registry"):
        raise CheckpointError(f"--ckpt_path {text}: a model registry is a download; torchhys "
                              "reads checkpoints from local files only (nothing is "
                              "downloaded): download it and give the local file's path")
    if text == "last":
        found = last_checkpoint(cfg)
        if found is None:
            where = (cfg.get("checkpoint") or {}).get("dirpath") or \
                f"{log_folder(cfg['trainer'])[0]}/version_*/checkpoints"
            raise CheckpointError(f"--ckpt_path last: no earlier run's last.ckpt under "
                                  f"{where}; give a checkpoint file, or fit without "
                                  "--ckpt_path to start afresh")
        text = str(found)
        if not quiet_requested():
            print(f"--ckpt_path last: {text}", file=sys.stderr, flush=True)
    read_checkpoint(text, "--ckpt_path")
    return text

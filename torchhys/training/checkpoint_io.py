"""Checkpoint files that are replaced whole or not at all.

Lightning's :class:`~lightning.fabric.plugins.io.TorchCheckpointIO` writes a checkpoint into
a temporary file of the system's temporary folder (``TMPDIR``) and moves it over the old one
with :func:`shutil.move`. When that folder is on another filesystem than the checkpoints (a
``tmpfs`` ``/tmp``, a scratch or network disk for the runs), the move is a copy that first
truncates the old file: a full disk, a quota or a killed process in the middle of the copy
leaves ``last.ckpt`` damaged, and the run cannot be resumed. Nothing is flushed to the disk
before the rename either, so a power cut may leave an empty file.

:class:`AtomicCheckpointIO` writes the new checkpoint to a temporary file in the checkpoint's
own folder, flushes it to the disk (``fsync``), and :func:`os.replace`\\ s it over the old
file (then ``fsync``\\ s the folder): a reader sees the old checkpoint or the new one, never a
part. On any error the temporary file is removed and the old checkpoint is left as it was
(:mod:`torchhys._atomic`, which the exported compensators' files share).
Remote paths (``s3://``, ...) are saved as Lightning saves them; checkpoints are loaded from
local files only, with ``weights_only=True`` (no code from the file runs).

Use it as a trainer plugin: ``Trainer(plugins=[AtomicCheckpointIO()])``, or on the command
line ``--trainer.plugins=torchhys.training.checkpoint_io.AtomicCheckpointIO``.
"""

from __future__ import annotations

import io
import os
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol

from torchhys._atomic import atomic_write_bytes
from torchhys.checkpoints import refuse_url

__all__ = ["AtomicCheckpointIO"]


class AtomicCheckpointIO(TorchCheckpointIO):
    """:class:`~lightning.fabric.plugins.io.TorchCheckpointIO` whose local checkpoint files
    are replaced atomically (:func:`atomic_write_bytes`): the previous checkpoint survives a
    full disk or a killed process during the save. Loading reads local files only, with
    ``weights_only=True`` (:meth:`load_checkpoint`); removing is Lightning's."""

    def load_checkpoint(self, path: Any, map_location: Any = lambda storage, loc: storage,
                        weights_only: bool | None = None) -> dict[str, Any]:
        """The checkpoint in the local file ``path`` (Lightning's read of ``ckpt_path``, of
        ``best`` and ``hpc``), loaded with ``weights_only=True`` whatever ``weights_only``
        asks: no code from the file runs. A URL (``http://``, ``file://``, ``s3://`` ...) is
        refused with a :class:`~torchhys.checkpoints.CheckpointError`: nothing is
        downloaded (Lightning's loader would load a URL with ``weights_only=False``)."""
        refuse_url(path, "ckpt_path")
        if not os.path.isfile(path):
            raise FileNotFoundError(f"Checkpoint file not found: {path}")
        with open(path, "rb") as fh:
            return torch.load(fh, map_location=map_location, weights_only=True)

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any,
                        storage_options: Any | None = None) -> None:
        if not _is_local_file_protocol(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        if storage_options is not None:
            raise TypeError(
                "`Trainer.save_checkpoint(..., storage_options=...)` is not supported by "
                f"{type(self).__name__}"
            )
        local = os.fspath(path)
        if local.startswith("file://"):
            local = local[len("file://"):]
        os.makedirs(os.path.dirname(os.path.abspath(local)), exist_ok=True)
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        atomic_write_bytes(local, buffer.getvalue())

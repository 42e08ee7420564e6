"""The ``torchhys fit`` run's checkpoint: one file, ``last.ckpt``, saved at every save point.

Lightning's :class:`~lightning.pytorch.callbacks.ModelCheckpoint` saves ``last.ckpt`` only
where it saved a top-k checkpoint: without a monitor its top file (``epoch=N-step=M.ckpt``)
is a copy of ``last.ckpt``, two identical files per run, and with ``save_top_k=0`` it writes
``last.ckpt`` only at the end of training (nothing to resume a killed run from).
:class:`RunCheckpoint` with ``save_top_k=0`` (its default) saves ``last.ckpt`` where the
top-k checkpoint would have been saved, and nothing else; ``save_top_k`` >= 1 (with a
``monitor``, to keep the best) is Lightning's behaviour unchanged.
"""

from __future__ import annotations

from typing import Any, Literal

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

__all__ = ["RunCheckpoint"]


class RunCheckpoint(ModelCheckpoint):
    """:class:`~lightning.pytorch.callbacks.ModelCheckpoint` keeping one file per run (the
    module docstring). Its arguments are Lightning's, with ``save_last=True`` and
    ``save_top_k=0`` by default."""

    def __init__(self, *args: Any, save_last: bool | Literal["link"] | None = True,
                 save_top_k: int = 0, **kwargs: Any) -> None:
        super().__init__(*args, save_last=save_last, save_top_k=save_top_k, **kwargs)
        self._last_step_of_last = -1  # the global step last.ckpt was last written at

    def _save_topk_checkpoint(self, trainer: L.Trainer, monitor_candidates: dict) -> None:
        if self.save_top_k == 0 and self.save_last:
            self._save_last_checkpoint(trainer, monitor_candidates)  # the run's one file
            return
        super()._save_topk_checkpoint(trainer, monitor_candidates)

    def _save_last_checkpoint(self, trainer: L.Trainer, monitor_candidates: dict) -> None:
        if self.save_top_k == 0 and self._last_step_of_last == trainer.global_step:
            return  # written a moment ago, as the top-k checkpoint
        super()._save_last_checkpoint(trainer, monitor_candidates)
        if self.save_last:
            self._last_step_of_last = trainer.global_step

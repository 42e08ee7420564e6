"""A ``torchhys`` command stopped by a signal ends with a non-zero status and one line.

- SIGTERM during a fit's training (Lightning stops at the end of the epoch):
  :class:`SigtermCheckpoint` saves ``last.ckpt`` where the run's last save is older than
  the step reached, prints ``torchhys fit: interrupted by SIGTERM after N epochs; last.ckpt
  saved in DIR (resume: --ckpt_path last)`` and makes the exit status 143 (128 + SIGTERM;
  Lightning's own is 0).
- SIGTERM or SIGINT (Ctrl-C) during model selection: :func:`signals_raise` (around the
  command's selection) turns them into :class:`Interrupted`, the processes of
  ``model.select_jobs`` are killed (:mod:`torchhys.selection.jobs`), and the command prints
  ``torchhys fit: interrupted by SIGINT`` (or SIGTERM) and exits with 128 + the signal's
  number (130, 143). A Ctrl-C elsewhere in the command is that line too.
- The processes of ``model.select_jobs`` die with the command's process however it ends
  (SIGKILL included: :func:`~torchhys.selection.jobs.die_with_parent`), and ignore SIGINT
  (a Ctrl-C reaches the whole process group; the command ends them).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_only
from lightning.pytorch.utilities.exceptions import SIGTERMException

__all__ = ["Interrupted", "SigtermCheckpoint", "report_interrupt", "signals_raise"]


class Interrupted(BaseException):
    """The command's process got ``signum`` (SIGTERM, SIGINT): a BaseException, so that no
    handler of errors takes it for one (Lightning's trainer passes it on)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = int(signum)

    @property
    def exit_status(self) -> int:
        """128 + the signal's number, as a shell reports a process the signal ended."""
        return 128 + self.signum


def _raise(signum: int, frame: Any) -> None:  # noqa: ARG001 (a signal handler's arguments)
    raise Interrupted(signum)


@contextlib.contextmanager
def signals_raise(signums: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)
                  ) -> Iterator[None]:
    """While the block runs (in the main thread; elsewhere it changes nothing), the signals
    ``signums`` raise :class:`Interrupted` in the main thread; the previous handlers are
    restored after. A trainer run inside registers its own SIGTERM handler, which calls this
    one too."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise) for s in signums}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class SigtermCheckpoint(Callback):
    """On SIGTERM during a fit (Lightning's ``SIGTERMException``, raised at the end of an
    epoch): ``last.ckpt`` of each ModelCheckpoint with ``save_last`` saved where the last
    save is older than the step reached, one line on stderr, and exit status 143 instead of
    Lightning's 0."""

    def __init__(self) -> None:
        self._saved_step = -1

    def on_save_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict) -> None:
        self._saved_step = trainer.global_step

    def on_exception(self, trainer: Any, pl_module: Any, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException):
            return
        exception.code = 128 + int(signal.SIGTERM)
        if trainer.state.fn != "fit":
            _say(f"torchhys {trainer.state.fn}: interrupted by SIGTERM")
            return
        saved = []
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and cb.dirpath:
                path = os.path.join(cb.dirpath, cb.CHECKPOINT_NAME_LAST + cb.FILE_EXTENSION)
                if self._saved_step != trainer.global_step or not os.path.exists(path):
                    trainer.save_checkpoint(path)
                saved.append(cb.dirpath)
        where = (f"; last.ckpt saved in {saved[0]} (resume: --ckpt_path last)" if saved
                 else "; no checkpoint saved (checkpoint.save_last is off)")
        n = trainer.current_epoch  # the epochs finished, those of resumed runs included
        _say(f"torchhys fit: interrupted by SIGTERM after {n} epoch{'s' * (n != 1)}{where}")


@rank_zero_only
def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def report_interrupt(prog: str, exc: Interrupted | KeyboardInterrupt) -> int:
    """Print ``<prog>: interrupted by SIGINT`` (or the signal of an :class:`Interrupted`) on
    stderr; the exit status, 128 + the signal's number."""
    signum = exc.signum if isinstance(exc, Interrupted) else int(signal.SIGINT)
    print(f"{prog}: interrupted by {signal.Signals(signum).name}", file=sys.stderr, flush=True)
    return 128 + signum

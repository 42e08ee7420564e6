"""``--verbose``: what the command prints besides its own lines.

By default (:func:`default_output`):

- a warning is one line, without the source line Python echoes under it: ``torchhys fit:
  warning: <message>`` for torchhys's own, ``<file>:<line>: <Category>: <message>`` for
  another package's;
- Lightning's tips and its lines about the machine are left out (:data:`HIDDEN_INFO`: the
  "Tip:" lines, "GPU available: ...", "TPU available: ...", "You are using a CUDA device
  ...", "Seed set to ...", a rank's CUDA_VISIBLE_DEVICES and the distributed banner); its
  other lines (the model summary, "`Trainer.fit` stopped: ...") still show;
- a ``FutureWarning`` that Lightning, torchmetrics or jsonargparse raise about the torch
  API they call (a deprecation the user cannot act on) is left out.

Warnings and errors of torchhys, and the other warnings of Lightning and torch, always show.
``--verbose`` (or ``TORCHHYS_VERBOSE=1``, which it sets for the ranks of a multi-process run
and the processes of ``model.select_jobs``) keeps all of it as Lightning and Python print it.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import os
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

__all__ = ["HIDDEN_INFO", "VERBOSE_ENV", "VERBOSE_FLAG", "default_output",
           "format_warning", "verbose_requested"]

VERBOSE_FLAG = "--verbose"
"""The command-line flag."""
VERBOSE_ENV = "TORCHHYS_VERBOSE"
"""The environment variable it sets (everything shown when set to anything but '', '0',
'false' or 'no')."""

HIDDEN_INFO = re.compile(
    r"(\[rank: \d+\] )?(\W*Tip:|(GPU|TPU|HPU|IPU) available:|You are using a CUDA device"
    r"|Seed set to |LOCAL_RANK: \d+ - CUDA_VISIBLE_DEVICES|Initializing distributed:|-{8,}\s*\n"
    r"distributed_backend=)")
"""The beginnings of Lightning's information lines that the default output leaves out (after
a rank's ``[rank: N]``)."""

_THIRD_PARTY = r"(lightning|lightning_utilities|torchmetrics|jsonargparse)(\.|$)"
"""The modules whose ``FutureWarning`` (about the torch API they call) is left out."""

_PACKAGE = str(Path(__file__).resolve().parents[1])
"""torchhys's own folder: a warning raised from a file there is the command's own."""


def verbose_requested() -> bool:
    """Whether everything is shown (``--verbose`` sets ``TORCHHYS_VERBOSE``)."""
    return os.environ.get(VERBOSE_ENV, "").strip().lower() not in ("", "0", "false", "no")


_HELPERS = ("warnings", "lightning_utilities.core.rank_zero", "lightning.fabric.utilities."
            "rank_zero", "lightning.pytorch.utilities.rank_zero", __name__)
"""The modules between the code that raises a warning and its formatting (``warnings`` and
Lightning's ``rank_zero_warn``)."""


def _own(filename: str) -> bool:
    """Whether torchhys raised the warning being formatted: its file is torchhys's, or the
    innermost caller outside :data:`_HELPERS` is (a ``stacklevel`` may name the caller's
    caller, Lightning's code that calls a hook)."""
    if os.path.abspath(filename).startswith(_PACKAGE + os.sep):
        return True
    frame = inspect.currentframe()
    while frame is not None:
        name = str(frame.f_globals.get("__name__", ""))
        if name not in _HELPERS:
            return name == "torchhys" or name.startswith("torchhys.")
        frame = frame.f_back
    return False


def format_warning(prog: str, message: Warning | str, category: type[Warning],
                   filename: str, lineno: int) -> str:
    """A warning on one line, without its source line: ``prog: warning: <message>`` where
    torchhys raised it, ``<file>:<line>: <Category>: <message>`` elsewhere."""
    text = " ".join(str(message).split())
    if _own(filename):
        return f"{prog}: warning: {text}\n"
    return f"{filename}:{lineno}: {category.__name__}: {text}\n"


class _HideInfo(logging.Filter):
    """Drops the records of :data:`HIDDEN_INFO` below WARNING."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.WARNING or not HIDDEN_INFO.match(record.getMessage())


def _lightning_loggers() -> list[logging.Logger]:
    """Lightning's loggers (a filter acts only on the logger a record is made by)."""
    names = {"lightning.pytorch", "lightning.fabric", "lightning.pytorch.utilities.rank_zero",
             "lightning.fabric.utilities.rank_zero", "lightning.fabric.utilities.seed"}
    names.update(n for n in logging.root.manager.loggerDict
                 if n.startswith(("lightning.", "lightning_")))
    return [logging.getLogger(n) for n in sorted(names)]


@contextlib.contextmanager
def default_output(prog: str) -> Iterator[None]:
    """Within: the default output of the module docstring, unless :func:`verbose_requested`;
    the warning format, filters and Lightning's loggers are restored when it ends.

    Args:
        prog: the command's name in its warnings (``torchhys fit``).
    """
    if verbose_requested():
        yield
        return
    hide = _HideInfo()
    loggers = _lightning_loggers()
    saved_format = warnings.formatwarning
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning, module=_THIRD_PARTY)
        warnings.formatwarning = lambda message, category, filename, lineno, line=None: \
            format_warning(prog, message, category, filename, lineno)
        for log in loggers:
            log.addFilter(hide)
        try:
            yield
        finally:
            warnings.formatwarning = saved_format
            for log in loggers:
                log.removeFilter(hide)

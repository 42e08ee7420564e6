"""User errors of the ``torchhys`` commands, reported in one line.

An error caused by the user's files, options or data is printed as one line,
``torchhys fit: error: <message>``, without a traceback, and the command exits with status 2
(:func:`report_user_error`). The user errors (:func:`is_user_error`) are:

- :class:`ValueError`, which includes :class:`torchhys.data.tables.DataFileError`,
  :class:`torchhys.checkpoints.CheckpointError`, :class:`json.JSONDecodeError` and
  :class:`UnicodeDecodeError`;
- :class:`OSError` about a path (its ``filename`` is set, e.g. :class:`FileNotFoundError`
  from ``open``), and :class:`FileNotFoundError` in any case;
- Lightning's ``MisconfigurationException`` (a trainer setting the machine cannot honour;
  looked up only where Lightning is loaded: ``torchhys export`` runs without it);
- a :class:`TypeError` raised while the config is read and its classes are built
  (:func:`config_errors`), not one raised while training.

Any other exception (``IndexError``, ``KeyError``, ``AttributeError``, ``AssertionError``,
``RuntimeError`` from torch ...) is a bug and keeps its traceback. ``--traceback`` on the
command line or ``TORCHHYS_TRACEBACK=1`` in the environment lets user errors propagate too
(the traceback is printed, exit status 1). Errors of the command line's syntax (an unknown
option, a value of the wrong type) are the parsers' own: a usage message and status 2.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator, Sequence

__all__ = [
    "TRACEBACK_ENV", "TRACEBACK_FLAG", "config_errors", "is_user_error", "report_user_error",
    "split_traceback_flag", "traceback_requested",
]

TRACEBACK_FLAG = "--traceback"
"""The command-line flag that shows the traceback of user errors too."""
TRACEBACK_ENV = "TORCHHYS_TRACEBACK"
"""The environment variable that does the same when set to anything but '', '0' or 'false'."""
_MARK = "_torchhys_user_error"
_MISCONFIGURATION = "lightning.fabric.utilities.exceptions"
"""The module of Lightning's ``MisconfigurationException``."""


def traceback_requested(flag: bool = False) -> bool:
    """Whether user errors show their traceback: ``flag`` (``--traceback``) or the
    environment's ``TORCHHYS_TRACEBACK``."""
    env = os.environ.get(TRACEBACK_ENV, "").strip().lower()
    return flag or env not in ("", "0", "false", "no")


def split_traceback_flag(argv: Sequence[str]) -> tuple[list[str], bool]:
    """``argv`` without ``--traceback``, and whether it was there."""
    args = [a for a in argv if a != TRACEBACK_FLAG]
    return args, len(args) != len(argv)


def is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is caused by the user's files, options or data (see the module
    docstring), rather than by a bug."""
    if getattr(exc, _MARK, False) or isinstance(exc, (ValueError, FileNotFoundError)):
        return True
    if isinstance(exc, OSError):
        return exc.filename is not None
    lightning = sys.modules.get(_MISCONFIGURATION)  # raised only where Lightning is loaded
    return lightning is not None and isinstance(exc, lightning.MisconfigurationException)


@contextlib.contextmanager
def config_errors() -> Iterator[None]:
    """Mark a :class:`TypeError` raised inside as a user error (reading the config and
    building its classes: a value of the wrong kind)."""
    try:
        yield
    except TypeError as exc:
        setattr(exc, _MARK, True)
        raise


def message(exc: BaseException) -> str:
    """The error's message on one line (an OSError as ``path: reason``)."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(line.strip() for line in text.splitlines() if line.strip())


def report_user_error(prog: str, exc: BaseException, traceback: bool = False) -> bool:
    """Print ``prog: error: <message>`` on stderr and return True when ``exc`` is a user
    error and no traceback is asked for (``traceback`` or ``TORCHHYS_TRACEBACK``); else
    return False: the caller re-raises it."""
    if traceback_requested(traceback) or not is_user_error(exc):
        return False
    print(f"{prog}: error: {message(exc)}", file=sys.stderr, flush=True)
    return True

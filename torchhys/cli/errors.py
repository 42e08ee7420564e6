"""User errors of the ``torchhys`` commands, reported in one line, and the checked read of a
checkpoint file.

An error caused by the user's files, options or data is printed as one line,
``torchhys fit: error: <message>``, without a traceback, and the command exits with status 2
(:func:`report_user_error`). The user errors (:func:`is_user_error`) are:

- :class:`ValueError`, which includes :class:`torchhys.data.files.DataFileError`,
  :class:`CheckpointError`, :class:`json.JSONDecodeError` and :class:`UnicodeDecodeError`;
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
import pickle
import re
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "CheckpointError", "TRACEBACK_ENV", "TRACEBACK_FLAG", "config_errors", "is_user_error",
    "read_checkpoint", "refuse_url", "report_user_error", "split_traceback_flag",
    "traceback_requested",
]

TRACEBACK_FLAG = "--traceback"
"""The command-line flag that shows the traceback of user errors too."""
TRACEBACK_ENV = "TORCHHYS_TRACEBACK"
"""The environment variable that does the same when set to anything but '', '0' or 'false'."""
_MARK = "_torchhys_user_error"
_MISCONFIGURATION = "lightning.fabric.utilities.exceptions"
"""The module of Lightning's ``MisconfigurationException``."""


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used, naming the file and what was expected."""


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


_EXPECTED = "expected a checkpoint written by torchhys fit (<run>/checkpoints/last.ckpt)"
_ZIP, _PICKLE = b"PK\x03\x04", b"\x80"
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.-]+:/")
"""A URL's scheme (``http://``, ``file://``, ``s3://``; ``http:/`` once a :class:`Path` has
folded the slashes); one letter is a Windows drive (``C:/``), not a scheme."""


def refuse_url(path: str | os.PathLike, option: str = "--ckpt") -> None:
    """Raise a :class:`CheckpointError` if ``path`` is a URL (any scheme, ``file://``
    included): checkpoints are read from local files only, nothing is downloaded (a loader
    of remote files may run code from them)."""
    text = os.fspath(path)
    if _URL.match(text):
        raise CheckpointError(f"{option} {text} is a URL: torchhys reads checkpoints from "
                              "local files only (nothing is downloaded); download it and "
                              "give the local file's path")


def read_checkpoint(path: str | Path, option: str = "--ckpt", *,
                    lightning: bool = True) -> dict[str, Any]:
    """The dict saved in the checkpoint file ``path`` (``torch.load`` with
    ``weights_only=True`` on the CPU: no code from the file is run).

    Args:
        path: the file.
        option: the option that named it, for messages (``--ckpt``, ``--ckpt_path``).
        lightning: a Lightning checkpoint (a dict with ``state_dict``) is required; False:
            a plain ``torch.save``d state dict (names to tensors) is accepted too.

    Raises:
        CheckpointError: a URL (:func:`refuse_url`), no such file, not a PyTorch file,
            damaged or truncated, or not a dict of the expected kind; the message names the
            file and what was expected.
    """
    import torch

    refuse_url(path, option)
    expected = _EXPECTED + ("" if lightning else " or a torch.save'd state dict of a network")
    where = f"{option} {path}"
    file = Path(path)
    if not file.exists():
        raise CheckpointError(f"{where} does not exist; {expected}")
    if not file.is_file():
        raise CheckpointError(f"{where} is not a file; {expected}")
    with file.open("rb") as fh:
        head = fh.read(24)
    if not head:
        raise CheckpointError(f"{where} is empty; {expected}")
    if not head.startswith((_ZIP, _PICKLE)):
        start = head.decode("utf-8", "replace").split("\n")[0]
        raise CheckpointError(f"{where} is not a PyTorch file (it starts with {start!r}); "
                              f"{expected}")
    try:
        ckpt = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 (whatever the loader meets in a damaged file)
        if isinstance(exc, pickle.UnpicklingError) and "weights only" in str(exc).lower():
            what = "holds objects other than tensors and plain containers"
        else:
            what = "is damaged or truncated"
        # the loader's first sentence: its advice is about trusting the file, not fixing it
        first = re.split(r"(?<=\.)\s", (str(exc).strip() or type(exc).__name__))[0]
        first = first.splitlines()[0][:120]
        raise CheckpointError(f"{where} {what} ({type(exc).__name__}: {first}); "
                              f"{expected}") from exc
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{where} holds a {type(ckpt).__name__}, not a dict; {expected}")
    if "state_dict" in ckpt:
        if not isinstance(ckpt["state_dict"], dict):
            raise CheckpointError(f"{where}: its 'state_dict' is a "
                                  f"{type(ckpt['state_dict']).__name__}, not a dict; {expected}")
    elif lightning:
        keys = ", ".join(map(repr, list(ckpt)[:5])) or "none"
        raise CheckpointError(f"{where} has no 'state_dict' (keys: {keys}); {expected}")
    elif not all(isinstance(v, torch.Tensor) for v in ckpt.values()):
        raise CheckpointError(f"{where} holds neither a 'state_dict' nor tensors only; "
                              f"{expected}")
    return ckpt

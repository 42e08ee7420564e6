"""Loggers of ``torchhys fit|validate|test|predict`` by a short name.

``--trainer.logger csv`` and ``--trainer.logger tensorboard`` (or ``=csv``, any case) stand
for Lightning's :class:`~lightning.pytorch.loggers.CSVLogger` and
:class:`~lightning.pytorch.loggers.TensorBoardLogger` (:func:`expand_logger_names`, before
the command's parser reads the arguments). Either logger, so named on the command line (or
by its class path there), writes where the default logger does,
``<default_root_dir>/logs/version_<N>``, unless a ``--trainer.logger.save_dir`` follows: its
``save_dir`` is :data:`ROOT_DIR` until the config is read (:func:`prepare_loggers`).

TensorBoard's logger needs the ``tensorboard`` package (or ``tensorboardX``), which no extra
of torchhys installs: where neither is found the command says so in one line (``pip install
tensorboard``) instead of a traceback at the end of the parse. A config file names a logger
by its class path with ``init_args`` (the short names are for the command line).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from typing import Any

__all__ = ["LOGGERS", "ROOT_DIR", "check_logger_package", "expand_logger_names", "prepare_loggers"]

LOGGERS = {
    "csv": "lightning.pytorch.loggers.CSVLogger",
    "tensorboard": "lightning.pytorch.loggers.TensorBoardLogger",
}
"""The short names of ``--trainer.logger`` and the class each stands for."""

ROOT_DIR = "<default_root_dir>"
"""The ``save_dir`` of a logger named on the command line, until :func:`prepare_loggers`
puts ``trainer.default_root_dir`` in its place."""

_PACKAGES = {"TensorBoardLogger": (("tensorboard", "tensorboardX"), "pip install tensorboard")}
"""Logger class -> the packages it can write with (any one), and how to install one."""

_FLAG = "--trainer.logger"
_DEFAULT_NAME = "lightning_logs"
"""Lightning's default ``name`` of both loggers: the command's default logger's is ``logs``."""


def _found(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a finder that refuses it; a broken sys.modules entry
        return False


def check_logger_package(class_path: str) -> None:
    """Raise a one-line :class:`ValueError` when the logger ``class_path`` needs a package
    that is not installed (TensorBoard's)."""
    packages, install = _PACKAGES.get(str(class_path).rpartition(".")[2], ((), ""))
    if packages and not any(_found(p) for p in packages):
        raise ValueError(f"trainer.logger {class_path} needs the {packages[0]} package, which "
                         f"is not installed: {install} (or choose --trainer.logger csv)")


def expand_logger_names(argv: Sequence[str]) -> list[str]:
    """``argv`` with the short name of ``--trainer.logger NAME`` (``--trainer.logger=NAME``)
    replaced by its class path (:data:`LOGGERS`) and ``--trainer.logger.save_dir`` set to
    :data:`ROOT_DIR` after it (a later ``save_dir`` wins); the class path of either logger
    gets the ``save_dir`` too; any other value is left as it is.

    Raises:
        ValueError: the logger needs a package that is not installed (one line, naming it).
    """
    out: list[str] = []
    args = list(argv)
    i = 0
    while i < len(args):
        arg = args[i]
        if arg == _FLAG and i + 1 < len(args):
            value, taken = args[i + 1], 2
        elif arg.startswith(_FLAG + "="):
            value, taken = arg.split("=", 1)[1], 1
        else:
            out.append(arg)
            i += 1
            continue
        class_path = LOGGERS.get(value.strip().lower(), value.strip())
        if class_path in LOGGERS.values():
            check_logger_package(class_path)
            out += [f"{_FLAG}={class_path}", f"{_FLAG}.save_dir={ROOT_DIR}"]
        else:
            out += args[i:i + taken]
        i += taken
    return out


def prepare_loggers(logger: Any, root: str) -> None:
    """Put the default logger's place (``save_dir`` ``root``, and ``name`` ``logs`` where
    it is Lightning's default ``lightning_logs``) in a CSV or TensorBoard logger of the
    parsed config whose ``save_dir`` is :data:`ROOT_DIR` (or None), in place; check the
    package any logger needs (:func:`check_logger_package`). ``logger`` is the
    ``trainer.logger`` value: a class path with ``init_args``, a list of them, or anything
    else (left alone)."""
    for one in logger if isinstance(logger, list) else [logger]:
        if not hasattr(one, "get") or not isinstance(one.get("class_path"), str):
            continue
        class_path = one["class_path"]
        check_logger_package(class_path)
        if class_path not in LOGGERS.values():
            continue
        init = one.get("init_args")
        if init is None:
            continue
        if init.get("save_dir") in (None, ROOT_DIR):
            init["save_dir"] = root
            if init.get("name") == _DEFAULT_NAME:
                init["name"] = "logs"

"""Operators from other modules and packages for the ``torchhys`` command.

``--import MODULE`` (repeatable, on every subcommand) imports a module before the config is
read, so that an operator it registers with :func:`torchhys.operator.register_operator` can
be named in ``model.operator``; installed packages declare theirs as entry points of the
group ``torchhys.operators`` (:func:`torchhys.operator.load_entry_points`), loaded when a
name is first looked up.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Sequence

__all__ = ["IMPORT_ENV", "IMPORT_FLAG", "import_modules", "split_import_flags"]

IMPORT_ENV = "TORCHHYS_IMPORT"
"""The modules of ``--import``, comma separated, passed to the processes of a
multi-process run (their command lines are the parent's without ``--import``)."""
IMPORT_FLAG = "--import"


def split_import_flags(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """``argv`` without ``--import MODULE`` / ``--import=MODULE`` (repeatable), and the
    modules in order.

    Raises:
        ValueError: ``--import`` without a module name.
    """
    args, modules, it = [], [], iter(argv)
    for a in it:
        if a == IMPORT_FLAG:
            module = next(it, None)
            if module is None or module.startswith("-"):
                raise ValueError("--import needs a module name, e.g. --import my_operators")
            modules.append(module)
        elif a.startswith(IMPORT_FLAG + "="):
            modules.append(a.split("=", 1)[1])
        else:
            args.append(a)
    return args, modules


def import_modules(modules: Sequence[str]) -> None:
    """Import each module (by its dotted name, found on ``sys.path`` with the current folder
    first), so that the operators it registers (:func:`torchhys.operator.register_operator`)
    can be named in the config.

    Raises:
        ValueError: a module that cannot be imported, naming it and the reason.
    """
    for module in modules:
        if "" not in sys.path and os.getcwd() not in sys.path:
            sys.path.insert(0, os.getcwd())
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 (whatever importing the user's module raises)
            raise ValueError(f"--import {module}: {type(exc).__name__}: {exc}") from exc

"""Operators from other modules and packages for the ``torchhys`` command.

``--import MODULE`` (repeatable, on every subcommand) imports a module before the config is
read, so that an operator it registers with :func:`torchhys.registry.register_operator` can
be named in ``model.operator``; installed packages declare theirs as entry points of the
group ``torchhys.operators`` (:func:`torchhys.registry.load_entry_points`), loaded when a
name is first looked up.

``--import`` adds nothing to ``sys.path``: a module is found where Python finds it (the
installed packages, ``PYTHONPATH``). ``--import-path DIR`` (repeatable) adds a folder, after
the installed packages, so that no file in it replaces an installed package of the same
name; a module in the working folder needs ``--import-path .``. ``TORCHHYS_IMPORT``
(modules, comma separated) and ``TORCHHYS_IMPORT_PATH`` (folders, separated by
``os.pathsep``) stand for the options when the command line has none (the command sets them
for the processes of a multi-process run, whose command lines lack the options).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Sequence
from pathlib import Path

__all__ = ["IMPORT_ENV", "IMPORT_FLAG", "IMPORT_PATH_ENV", "IMPORT_PATH_FLAG", "add_import_paths",
           "import_modules", "modules_from_env", "paths_from_env", "split_import_flags",
           "split_import_path_flags"]

IMPORT_ENV = "TORCHHYS_IMPORT"
"""The modules of ``--import``, comma separated, when the command line has none (the
command sets it for the processes of a multi-process run)."""
IMPORT_PATH_ENV = "TORCHHYS_IMPORT_PATH"
"""The folders of ``--import-path``, separated by ``os.pathsep``, when the command line has
none (the command sets it, as absolute paths, for the processes of a multi-process run)."""
IMPORT_FLAG = "--import"
IMPORT_PATH_FLAG = "--import-path"


def _split(argv: Sequence[str], flag: str, needs: str) -> tuple[list[str], list[str]]:
    args, values, it = [], [], iter(argv)
    for a in it:
        if a == flag:
            value = next(it, None)
            if value is None or value.startswith("-"):
                raise ValueError(f"{flag} needs {needs}")
            values.append(value)
        elif a.startswith(flag + "="):
            values.append(a.split("=", 1)[1])
        else:
            args.append(a)
    return args, values


def split_import_flags(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """``argv`` without ``--import MODULE`` / ``--import=MODULE`` (repeatable), and the
    modules in order.

    Raises:
        ValueError: ``--import`` without a module name.
    """
    return _split(argv, IMPORT_FLAG, "a module name, e.g. --import my_operators")


def split_import_path_flags(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """``argv`` without ``--import-path DIR`` / ``--import-path=DIR`` (repeatable), and the
    folders in order.

    Raises:
        ValueError: ``--import-path`` without a folder.
    """
    return _split(argv, IMPORT_PATH_FLAG, "a folder, e.g. --import-path .")


def modules_from_env() -> list[str]:
    """The modules of ``TORCHHYS_IMPORT``."""
    return [m for m in os.environ.get(IMPORT_ENV, "").split(",") if m]


def paths_from_env() -> list[str]:
    """The folders of ``TORCHHYS_IMPORT_PATH``."""
    return [p for p in os.environ.get(IMPORT_PATH_ENV, "").split(os.pathsep) if p]


def add_import_paths(paths: Sequence[str]) -> list[str]:
    """Append each folder (made absolute) to ``sys.path`` unless it is there: after the
    installed packages, so that a file in it never replaces one of them. Returns the
    absolute folders.

    Raises:
        ValueError: a folder that does not exist, naming it.
    """
    folders = []
    for path in paths:
        folder = Path(path).expanduser().resolve()
        if not folder.is_dir():
            raise ValueError(f"{IMPORT_PATH_FLAG} {path}: no such folder")
        if str(folder) not in sys.path:
            sys.path.append(str(folder))
        folders.append(str(folder))
    return folders


def import_modules(modules: Sequence[str], paths: Sequence[str] = ()) -> None:
    """Import each module by its dotted name, as Python finds it (``sys.path``: nothing is
    added to it but the folders of ``paths``, appended by :func:`add_import_paths`), so that
    the operators it registers (:func:`torchhys.registry.register_operator`) can be named in
    the config.

    Raises:
        ValueError: a folder of ``paths`` that does not exist, or a module that cannot be
            imported, naming it and the reason (and ``--import-path .`` where the module is
            a file of the working folder, which is not searched).
    """
    add_import_paths(paths)
    for module in modules:
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 (whatever importing the user's module raises)
            raise ValueError(f"{IMPORT_FLAG} {module}: {type(exc).__name__}: {exc}"
                             f"{_cwd_hint(module, exc)}") from exc


def _cwd_hint(module: str, exc: Exception) -> str:
    """The hint for a module that is not found but lies in the working folder."""
    top = module.split(".")[0]
    if not isinstance(exc, ModuleNotFoundError) or exc.name != top:
        return ""
    here = Path.cwd()
    if not ((here / f"{top}.py").is_file() or (here / top).is_dir()):
        return ""
    return (f" ({top} is in the working folder, which {IMPORT_FLAG} does not search: add "
            f"{IMPORT_PATH_FLAG} .)")

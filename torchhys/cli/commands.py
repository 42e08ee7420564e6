"""The ``torchhys`` commands that one run of Lightning or the exporter answers (all but
``fleet``: :mod:`torchhys.cli.main`, the console script's entry point, dispatches it).

``torchhys fit|validate|test|predict`` are a LightningCLI (:mod:`torchhys.cli.train`), which
needs the ``train`` extra (Lightning, jsonargparse, torchmetrics, matplotlib): without it
they say which extra to install, in one line on stderr, and exit with status 2, instead of
failing with a traceback on an import. ``torchhys export`` (:mod:`torchhys.cli.export`)
reads a checkpoint as a spec plus weights and needs none of them.

The options of the command itself are taken out here, before a subcommand reads the rest:
``--import MODULE`` and ``--import-path DIR`` (:mod:`torchhys.cli.plugins`), ``--threads N``
(:mod:`torchhys.cli.threads`), ``--quiet`` (:mod:`torchhys.cli.quiet`), ``--verbose``
(:mod:`torchhys.cli.verbose`), ``--traceback`` (:mod:`torchhys.cli.errors`), ``--help-all``
(:mod:`torchhys.cli.help`).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from typing import NoReturn

from torchhys.cli.errors import (
    TRACEBACK_ENV,
    TRACEBACK_FLAG,
    report_user_error,
    split_traceback_flag,
)
from torchhys.cli.help import split_help_all_flag
from torchhys.cli.info import INFO_COMMANDS, info_main
from torchhys.cli.plugins import (
    IMPORT_ENV,
    IMPORT_PATH_ENV,
    add_import_paths,
    import_modules,
    modules_from_env,
    paths_from_env,
    split_import_flags,
    split_import_path_flags,
)
from torchhys.cli.quiet import QUIET_ENV, QUIET_FLAG, quiet_requested
from torchhys.cli.threads import THREADS_ENV, choose_threads, split_threads_flag
from torchhys.cli.verbose import VERBOSE_ENV, VERBOSE_FLAG, default_output

__all__ = ["COMMANDS", "INSTALL_TRAIN", "TRAIN_PACKAGES", "main", "missing_train_packages",
           "training_commands"]

TRAIN_PACKAGES = ("lightning", "jsonargparse", "torchmetrics", "matplotlib")
"""Top-level modules of the ``train`` extra (``pip install "torchhys[train]"``)."""

INSTALL_TRAIN = 'pip install "torchhys[train]"'

COMMANDS = ("fit", "validate", "test", "predict", "export")
"""The subcommands: LightningCLI's four, and ``export`` (and ``fleet``, a fit per device:
:mod:`torchhys.cli.fleet`)."""


def missing_train_packages() -> list[str]:
    """The modules of :data:`TRAIN_PACKAGES` that cannot be found (without importing them)."""
    missing = []
    for name in TRAIN_PACKAGES:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a finder that refuses it; a broken sys.modules entry
            found = False
        if not found:
            missing.append(name)
    return missing


def _refuse(missing: list[str]) -> NoReturn:
    print(f"torchhys: error: the torchhys command needs the training extra: {INSTALL_TRAIN} "
          f"(missing: {', '.join(missing)})", file=sys.stderr)
    raise SystemExit(2)


def training_commands() -> Callable[..., None]:
    """:func:`torchhys.cli.train.run`, or the one line that names the extra (SystemExit)."""
    missing = missing_train_packages()
    if missing:
        _refuse(missing)
    try:
        from torchhys.cli.train import run
    except ModuleNotFoundError as exc:
        # a package the extra pulls in (a dependency of Lightning, say) is missing
        top = (exc.name or "").split(".")[0]
        if not top or top == "torchhys":
            raise
        _refuse([top])
    return run


def main(argv: list[str] | None = None) -> None:
    """Run the ``torchhys`` command.

    An error caused by the user's files, options or data is printed as one line,
    ``torchhys fit: error: <message>``, and exits with status 2; a bug keeps its traceback;
    ``--traceback`` (anywhere in ``argv``) or ``TORCHHYS_TRACEBACK=1`` shows the traceback
    of user errors too (:mod:`torchhys.cli.errors`).

    ``--import MODULE`` (repeatable, any subcommand) imports a module before the config is
    read: an operator it registers can be named in ``model.operator``
    (:func:`~torchhys.cli.plugins.import_modules`; nothing is added to ``sys.path`` but
    the folders of ``--import-path DIR``). ``--threads N`` (or
    ``TORCHHYS_THREADS``) sets torch's threads, one by default
    (:mod:`torchhys.cli.threads`). ``--verbose`` (or ``TORCHHYS_VERBOSE``) keeps Lightning's
    tips and Python's warning format (:mod:`torchhys.cli.verbose`); ``--help-all`` shows
    every option where ``--help`` shows the most used (:mod:`torchhys.cli.help`).

    Args:
        argv: command-line arguments without the program name (``sys.argv[1:]`` if None).

    The environment variables it sets for the processes of a multi-process run
    (``TORCHHYS_QUIET``, ``TORCHHYS_VERBOSE``, ``TORCHHYS_THREADS``, ``TORCHHYS_IMPORT``,
    ``TORCHHYS_IMPORT_PATH``, ``TORCHHYS_TRACEBACK``) are restored when it returns.

    Raises:
        SystemExit: 2 on a user error, and when a package of the ``train`` extra is missing
            for a training command (after printing ``torchhys: error: the torchhys command
            needs the training extra: ...`` on stderr); as LightningCLI exits (usage
            errors, ``--help``); ``export``'s status.
    """
    saved = {k: os.environ.get(k)
             for k in (QUIET_ENV, VERBOSE_ENV, THREADS_ENV, IMPORT_ENV, IMPORT_PATH_ENV,
                       TRACEBACK_ENV)}
    try:
        _main(argv)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _main(argv: list[str] | None) -> None:
    args, traceback = split_traceback_flag(sys.argv[1:] if argv is None else argv)
    if args and args[0] in INFO_COMMANDS:  # --version, configs: no extra, nothing read
        raise SystemExit(info_main(args))
    try:
        args, modules = split_import_flags(args)
        args, paths = split_import_path_flags(args)
        args, threads = split_threads_flag(args)
        args, help_all = split_help_all_flag(args)
        export = bool(args) and args[0] == "export"
        run = None if export else training_commands()
        if QUIET_FLAG in args:  # no progress lines (the ranks of a multi-process run too)
            args = [a for a in args if a != QUIET_FLAG]
            os.environ[QUIET_ENV] = "1"
        if VERBOSE_FLAG in args:  # Lightning's tips, warnings' source lines (the ranks too)
            args = [a for a in args if a != VERBOSE_FLAG]
            os.environ[VERBOSE_ENV] = "1"
        sub = next((a for a in args if a in COMMANDS), None)
        # an explicit choice is passed to the ranks of a multi-process run as the variable
        if threads is not None:
            os.environ[THREADS_ENV] = str(threads)
        choose_threads(threads, f"torchhys {sub}" if sub else "torchhys",
                       say=sub is not None and "--help" not in args and "-h" not in args
                       and not quiet_requested())
        paths = add_import_paths(paths or paths_from_env())
        modules = modules or modules_from_env()
        import_modules(modules)
    except Exception as exc:
        if not report_user_error(f"torchhys {args[0] if args else ''}".strip(), exc,
                                 traceback):
            raise
        raise SystemExit(2) from None
    if modules:
        os.environ[IMPORT_ENV] = ",".join(modules)  # for the ranks of a multi-process run
    if paths:
        os.environ[IMPORT_PATH_ENV] = os.pathsep.join(paths)
    with default_output(f"torchhys {sub}" if sub else "torchhys"):
        if run is None:
            from torchhys.cli.export import main as export_main

            raise SystemExit(export_main(args[1:] + [TRACEBACK_FLAG] * traceback))
        run(args, from_sys_argv=argv is None, traceback=traceback, help_all=help_all)

"""Entry point of the ``torchhys`` console script (and ``python -m torchhys``).

``torchhys fit|validate|test|predict`` are a LightningCLI (:mod:`torchhys.cli.train`), which
needs the ``train`` extra (Lightning, jsonargparse, torchmetrics, matplotlib): without it
they say which extra to install, in one line on stderr, and exit with status 2, instead of
failing with a traceback on an import. ``torchhys export`` (:mod:`torchhys.cli.export`)
reads a checkpoint as a spec plus weights and needs none of them. Both are answered by
:func:`torchhys.cli.commands.main`, which a fleet's device runs too.

``torchhys fleet`` (:mod:`torchhys.cli.fleet`) runs a fit per device, and ``torchhys
--version`` and ``torchhys configs`` (:mod:`torchhys.cli.info`) read nothing.

The options of the command itself are taken out before a subcommand reads the rest:
``--import MODULE`` and ``--import-path DIR`` (:mod:`torchhys.cli.plugins`), ``--threads N``
(:mod:`torchhys.cli.threads`), ``--quiet`` (:mod:`torchhys.cli.quiet`), ``--verbose``
(:mod:`torchhys.cli.verbose`), ``--traceback`` (:mod:`torchhys.cli.errors`), ``--help-all``
(:mod:`torchhys.cli.help`).
"""

from __future__ import annotations

import sys

from torchhys.cli import commands
from torchhys.cli.errors import split_traceback_flag

__all__ = ["main"]


def main(argv: list[str] | None = None) -> None:
    """Run the ``torchhys`` command (:func:`torchhys.cli.commands.main` documents its
    errors, flags and exit statuses; ``fleet`` is :func:`torchhys.cli.fleet.main`).

    Args:
        argv: command-line arguments without the program name (``sys.argv[1:]`` if None).
    """
    args, traceback = split_traceback_flag(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "fleet":  # each device a fit, given the command's options as they are
        commands.training_commands()
        from torchhys.cli.fleet import main as fleet_main

        raise SystemExit(fleet_main(args[1:], traceback=traceback))
    commands.main(argv)


if __name__ == "__main__":
    main()

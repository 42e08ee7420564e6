"""The commands that only inform: ``torchhys --version`` and ``torchhys configs``.

Neither needs the ``train`` extra nor reads a config: ``--version`` prints
``torchhys X.Y.Z`` (:data:`torchhys._version.__version__`), ``configs`` lists the shipped
configs, one line each, and how to use one by name (:mod:`torchhys.cli.configs`).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from torchhys._version import __version__
from torchhys.cli.configs import describe_all

__all__ = ["INFO_COMMANDS", "info_main"]

INFO_COMMANDS = ("--version", "configs")
"""The first arguments that :func:`info_main` answers."""


def info_main(argv: Sequence[str]) -> int:
    """Run ``torchhys --version`` or ``torchhys configs`` (``argv`` without the program
    name); the exit status (2 and one line on stderr for an argument they do not take)."""
    command, rest = argv[0], list(argv[1:])
    if command == "configs" and rest in (["-h"], ["--help"]):
        print("usage: torchhys configs\n\nThe configs shipped with torchhys, one line each; "
              "use one by name: torchhys fit --config NAME")
        return 0
    if rest:
        print(f"torchhys {command}: error: takes no arguments, got {' '.join(rest)}",
              file=sys.stderr)
        return 2
    if command == "--version":
        print(f"torchhys {__version__}")
        return 0
    lines = describe_all()
    print("\n".join(lines) if lines else "no shipped configs found")
    print("\nuse one by name: torchhys fit --config NAME (a file NAME in the current folder "
          "comes first)")
    return 0

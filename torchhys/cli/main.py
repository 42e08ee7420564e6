"""Entry point of the ``torchhys`` console script (and ``python -m torchhys``).

The command (``torchhys fit|validate|test|predict|export``) runs on the training side,
:mod:`torchhys.cli.train`, which needs the ``train`` extra (Lightning, jsonargparse,
torchmetrics, matplotlib). Without it the command says which extra to install, in one line
on stderr, and exits with status 2, instead of failing with a traceback on an import.
"""

from __future__ import annotations

import importlib.util
import sys

TRAIN_PACKAGES = ("lightning", "jsonargparse", "torchmetrics", "matplotlib")
"""Top-level modules of the ``train`` extra (``pip install "torchhys[train]"``)."""

INSTALL_TRAIN = 'pip install "torchhys[train]"'


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


def _refuse(missing: list[str]) -> None:
    print(f"torchhys: error: the torchhys command needs the training extra: {INSTALL_TRAIN} "
          f"(missing: {', '.join(missing)})", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> None:
    """Run the ``torchhys`` command, or say which extra it needs.

    Args:
        argv: command-line arguments without the program name (``sys.argv[1:]`` if None),
            passed on to :func:`torchhys.cli.train.main` unchanged.

    Raises:
        SystemExit: 2 when a package of the ``train`` extra is missing (after printing
            ``torchhys: error: the torchhys command needs the training extra: ...`` on
            stderr); otherwise as :func:`torchhys.cli.train.main`.
    """
    missing = missing_train_packages()
    if missing:
        _refuse(missing)
    try:
        from torchhys.cli.train import main as cli_main
    except ModuleNotFoundError as exc:
        # a package the extra pulls in (a dependency of Lightning, say) is missing
        top = (exc.name or "").split(".")[0]
        if not top or top == "torchhys":
            raise
        _refuse([top])
    cli_main(argv)

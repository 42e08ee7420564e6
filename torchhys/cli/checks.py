"""Checks of the ``torchhys`` command line for plain mistakes, each a one-line error.

- :func:`check_config_files`: a ``--config`` that is a data file (``--config data.csv``) or
  some other file whose first line is not YAML's ``key: value`` (read before the command's
  parser, whose error would print the whole file);
- :func:`check_optimizer_switch`: a ``--model.optimizer`` on the command line with the
  config's ``model.optimizer_kwargs`` of another optimizer (the obvious way to switch
  optimizer: ``--model.optimizer adam`` on a config that tunes L-BFGS).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from torchhys.optim.named import (
    OPTIMIZERS,
    RESET_OPTIMIZER_KWARGS,
    optimizer_keywords,
    unknown_optimizer_kwargs,
)

__all__ = ["check_config_files", "check_optimizer_switch"]

_CONFIG_FLAGS = ("--config", "-c")
_DATA_SUFFIXES = frozenset({".csv", ".tsv", ".txt", ".dat", ".npz", ".npy", ".xlsx", ".xls",
                            ".parquet", ".mat", ".h5", ".hdf5"})
_SNIFF_BYTES = 4096
_NOT_A_CONFIG = ("is not a YAML config (a config is a YAML mapping of sections: model:, data:, "
                 "trainer:)")


def _values(argv: Sequence[str], flags: Sequence[str]) -> Iterator[str]:
    """The values of ``FLAG VALUE`` / ``FLAG=VALUE`` in ``argv`` for each of ``flags``."""
    for i, a in enumerate(argv):
        if a in flags and i + 1 < len(argv):
            yield argv[i + 1]
        else:
            for flag in flags:
                if a.startswith(flag + "="):
                    yield a.split("=", 1)[1]


def _first_line(file: Path) -> str | None:
    """The first line of the file that is not blank, a comment or a YAML directive or
    document marker; None where the file cannot be read, is empty or is no text."""
    try:
        with file.open("rb") as fh:
            head = fh.read(_SNIFF_BYTES)
    except OSError:
        return None  # the parser's own error names the file
    if b"\0" in head:
        return ""
    text = head.decode("utf-8", errors="replace")
    for line in text.splitlines():
        s = line.strip()
        if s and not s.startswith(("#", "%", "---")):
            return s
    return None


def check_config_files(argv: Sequence[str]) -> None:
    """Raise ``ValueError`` for a ``--config FILE`` that is not a config: a data file (by
    its suffix: ``.csv``, ``.npz`` ...), binary, or text whose first line is not a mapping's
    (``key: value``, ``{``, ``? key``, a tag or an anchor). The message names the file;
    nothing of its content but its first line (shortened). Other files, and files that
    cannot be read, are left to the parser."""
    for value in _values(argv, _CONFIG_FLAGS):
        if value.lstrip().startswith(("{", "[")):
            continue  # a config given inline
        file = Path(value)
        if not file.is_file():
            continue
        where = f"--config {value}"
        if file.suffix.lower() in _DATA_SUFFIXES:
            raise ValueError(f"{where} {_NOT_A_CONFIG}; a {file.suffix} data file goes to "
                             f"--data.path {value}")
        line = _first_line(file)
        if line is None or ":" in line or line.startswith(("{", "?", "!", "&", "*")):
            continue
        shown = "binary content" if line == "" else f"its first line is {line[:60]!r}"
        raise ValueError(f"{where} {_NOT_A_CONFIG}: {shown}; a data file goes to --data.path")


def check_optimizer_switch(config: Any, argv: Sequence[str]) -> None:
    """Raise ``ValueError`` where the command line sets ``--model.optimizer`` but not
    ``--model.optimizer_kwargs`` and the config's ``model.optimizer_kwargs`` (from its file)
    are not keyword arguments of the optimizer chosen: the message says so and how to
    reset them. Other mismatches are left to the module's own check.

    Args:
        config: the subcommand's parsed config (``model.optimizer``,
            ``model.optimizer_kwargs``).
        argv: the command line.
    """
    if not any(True for _ in _values(argv, ("--model.optimizer",))):
        return
    if any(True for _ in _values(argv, ("--model.optimizer_kwargs",))):
        return
    optimizer, kwargs = config.get("model.optimizer"), config.get("model.optimizer_kwargs")
    if optimizer not in OPTIMIZERS or not isinstance(kwargs, dict):
        return
    unknown = unknown_optimizer_kwargs(optimizer, kwargs)
    if unknown:
        raise ValueError(
            f"--model.optimizer {optimizer} keeps the config's model.optimizer_kwargs "
            f"{kwargs}, of another optimizer: {OPTIMIZERS[optimizer].__name__} takes no "
            f"{', '.join(unknown)} (it takes {', '.join(optimizer_keywords(optimizer))}); "
            f"reset them with {RESET_OPTIMIZER_KWARGS} (or give {optimizer}'s own)")

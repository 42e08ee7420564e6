"""The configs shipped with torchhys, addressable by name.

The files of the checkout's ``configs/`` are package data: ``torchhys/configs`` is a link to
that folder in a checkout, and the wheel holds its files there (pyproject.toml). So
``torchhys fit --config measured`` (or ``measured.yaml``) reads the shipped
``configs/measured.yaml`` where no file of that name exists in the current folder; a path
that exists is read as it is, as before, and one that does not is a one-line error naming
the shipped configs (:func:`resolve_config_names`). ``torchhys configs``
lists them, one line each: the first sentence of the comment that opens the file
(:func:`describe`).

``torchhys fit`` without any ``--config`` says what it needs, in one line
(:func:`require_config`), instead of training the data module's default simulation with no
end set.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

__all__ = ["CONFIG_FLAGS", "describe", "describe_all", "require_config",
           "resolve_config_names", "shipped_configs"]

CONFIG_FLAGS = ("--config", "-c")
"""The options that name a config file (LightningCLI's)."""

_WIDTH = 100
"""The longest line of :func:`describe_all`."""


def _folder() -> Path:
    """The shipped configs' folder: ``torchhys/configs`` (the wheel's files, the checkout's
    link), else the checkout's ``configs/`` (a checkout whose link was not made)."""
    inside = Path(__file__).resolve().parents[1] / "configs"
    if inside.is_dir():
        return inside
    return Path(__file__).resolve().parents[2] / "configs"


def shipped_configs() -> dict[str, Path]:
    """The shipped configs by name (the file's stem), sorted by name."""
    folder = _folder()
    files = sorted(folder.glob("*.yaml")) if folder.is_dir() else []
    return {f.stem: f for f in files}


def describe(path: Path) -> str:
    """The headline of the comment that opens the config ``path``: its first sentence (its
    lines joined, up to the first ``". "`` before a capital, a command example or the end of
    the comment), up to its first ``": "``."""
    words: list[str] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        text = line[1:].strip()
        if not text or line.startswith("#  ") or text.startswith("torchhys "):
            break  # a blank comment line or an indented command example ends the sentence
        words.append(text)
    sentence = re.split(r"(?<!Ref)(?<!e\.g)(?<!i\.e)\.\s+(?=[A-Z])", " ".join(words), maxsplit=1)[0]
    return sentence.split(": ", 1)[0].rstrip(".:;,")


def describe_all(width: int = _WIDTH) -> list[str]:
    """One line per shipped config, ``name  description``, each at most ``width``
    characters (a longer description is cut at a word, with ``...``)."""
    configs = shipped_configs()
    pad = max(map(len, configs), default=0) + 2
    lines = []
    for name, path in configs.items():
        line = f"{name:<{pad}}{describe(path)}"
        if len(line) > width:
            line = line[:width - 3].rsplit(" ", 1)[0] + "..."
        lines.append(line)
    return lines


def _shipped(value: str) -> str:
    """``value``, or the shipped config of that name where no such file exists.

    Raises:
        ValueError: neither a file nor a shipped config's name (one line, naming them).
    """
    if Path(value).exists() or value.lstrip().startswith(("{", "[")) or "\n" in value:
        return value  # a file, or a config given inline (YAML or JSON)
    configs = shipped_configs()
    name = value[:-5] if value.endswith(".yaml") else value
    if "/" not in name and "\\" not in name and name in configs:
        return str(configs[name])
    raise ValueError(f"--config {value}: no such file, nor the name of a shipped config "
                     f"({', '.join(configs) or 'none found'}; torchhys configs describes them)")


def resolve_config_names(argv: Sequence[str]) -> list[str]:
    """``argv`` with each ``--config NAME`` (``-c NAME``, ``--config=NAME``) that is no file
    but the name of a shipped config (:func:`shipped_configs`, with or without ``.yaml``)
    replaced by that config's path; paths that exist, configs given inline, and every other
    argument, are left as they are.

    Raises:
        ValueError: a ``--config`` that is neither a file nor a shipped config's name.
    """
    out = list(argv)
    for i, arg in enumerate(out):
        if arg in CONFIG_FLAGS and i + 1 < len(out):
            out[i + 1] = _shipped(out[i + 1])
        else:
            for flag in CONFIG_FLAGS:
                if arg.startswith(flag + "="):
                    out[i] = f"{flag}={_shipped(arg.split('=', 1)[1])}"
    return out


def require_config(argv: Sequence[str]) -> None:
    """Raise a one-line :class:`ValueError` for ``fit`` without any ``--config`` (unless
    help or ``--print_config`` is asked for): the data module's default, the paper's
    simulation, with no ``max_epochs``, would train without end."""
    args = list(argv)
    sub = next((a for a in args if a in ("fit", "validate", "test", "predict")), None)
    if sub != "fit" or any(a in ("-h", "--help") or a.startswith("--print_config")
                                for a in args):
        return
    if any(a in CONFIG_FLAGS or a.startswith(tuple(f + "=" for f in CONFIG_FLAGS))
           for a in args):
        return
    names = ", ".join(shipped_configs()) or "none found"
    raise ValueError("fit needs a config: --config FILE, or a shipped config by name, e.g. "
                     "--config measured for your own recording (--data.path FILE) or --config "
                     f"paper_simulation_eiho for the paper's simulation (shipped: {names}; "
                     "torchhys configs describes them)")

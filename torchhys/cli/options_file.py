"""The ``fit`` style for an argparse command (``torchhys export``): options spelled with
underscores as well as hyphens (``--ckpt_path``, ``--input_margin``), ``--config FILE`` (a
YAML mapping of the options) and ``--print_config`` (the options as YAML, then exit).

:func:`parse` runs the parser on a command line in that style: the config's values are the
defaults that the command line's own options override, and the options the parser marks
``required`` are checked after the config was read (argparse's message, naming them).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["parse"]


def _long_flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings if s.startswith("--")}


def _normalize(argv: Sequence[str], flags: dict[str, argparse.Action],
               aliases: dict[str, str]) -> list[str]:
    """``--x_y`` (or ``--x_y=v``) as ``--x-y`` where that is a flag; ``aliases``' names as
    their flags."""
    out = []
    for arg in argv:
        if arg.startswith("--") and arg != "--":
            name, eq, value = arg.partition("=")
            name = aliases.get(name, name)
            hyphen = "--" + name[2:].replace("_", "-")
            if name not in flags and hyphen in flags:
                name = hyphen
            arg = name + eq + value
        out.append(arg)
    return out


def _config_values(path: str, flags: dict[str, argparse.Action],
                   aliases: dict[str, str]) -> dict[str, Any]:
    """The YAML mapping of ``path`` as the actions' destinations and values."""
    try:
        import yaml
    except ImportError:
        raise ValueError('--config needs PyYAML: pip install "torchhys[train]"') from None
    file = Path(path)
    if not file.is_file():
        raise ValueError(f"--config {path}: no such file")
    try:
        loaded = yaml.safe_load(file.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ValueError(f"--config {path}: not YAML{where}") from None
    if loaded is None:
        return {}
    if not isinstance(loaded, dict):
        raise ValueError(f"--config {path}: expected a mapping of options, got "
                         f"{type(loaded).__name__}")
    values = {}
    for key, value in loaded.items():
        flag = aliases.get(f"--{key}", "--" + str(key).replace("_", "-"))
        action = flags.get(flag) or flags.get(f"--{key}")
        if action is None or action.dest in ("config", "print_config", "help"):
            raise ValueError(f"--config {path}: {key!r} is not an option of this command")
        if value is not None and action.type is not None and not isinstance(value, list):
            value = action.type(str(value))
        elif isinstance(value, list) and action.type is not None:
            value = [action.type(str(v)) for v in value]
        if action.choices is not None and value is not None and value not in action.choices:
            raise ValueError(f"--config {path}: {key}: {value!r} is not one of "
                             f"{', '.join(map(str, action.choices))}")
        values[action.dest] = value
    return values


def _dump(args: argparse.Namespace, parser: argparse.ArgumentParser) -> str:
    import yaml

    out = {}
    for action in parser._actions:
        if action.dest in ("help", "config", "print_config") or not action.option_strings:
            continue
        value = getattr(args, action.dest, None)
        out[action.dest] = str(value) if isinstance(value, Path) else value
    return yaml.safe_dump(out, sort_keys=False)


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
          aliases: dict[str, str] | None = None) -> argparse.Namespace:
    """Parse ``argv`` (default ``sys.argv[1:]``) in the ``fit`` style (the module
    docstring); ``aliases``: more names of flags (``{"--ckpt_path": "--ckpt"}``). A bad
    config is the parser's error (exit 2, one line)."""
    aliases = dict(aliases or {})
    required = [a for a in parser._actions if a.required]
    for action in required:
        action.required = False
    parser.add_argument("--config", metavar="FILE",
                        help="a YAML file of this command's options (underscores or hyphens)")
    parser.add_argument("--print_config", "--print-config", action="store_true",
                        help="print the options (with --config's) as YAML and exit")
    flags = _long_flags(parser)
    argv = _normalize(list(sys.argv[1:] if argv is None else argv), flags, aliases)
    first = parser.parse_args(argv)
    if first.config is not None:
        try:
            parser.set_defaults(**_config_values(first.config, flags, aliases))
        except (ValueError, TypeError) as err:
            parser.error(str(err))
        first = parser.parse_args(argv)
    if first.print_config:
        print(_dump(first, parser), end="")
        raise SystemExit(0)
    missing = [a.option_strings[0] for a in required if getattr(first, a.dest) is None]
    if missing:
        parser.error(f"the following arguments are required: {', '.join(missing)}")
    return first

"""The YAML of configs (``--config`` files and option values), read with a bound on alias
expansion: a file whose aliases expand to more than :data:`MAX_NODES` nodes (a "billion
laughs" file: a few lines that expand to 9**9 strings) is refused before anything is
built from it, in one line.

:func:`install` makes it the loader of jsonargparse's ``yaml`` mode (the loader of
``torchhys fit --config`` and of :func:`torchhys.cli.train.read_config`); the values
are those of jsonargparse's own loader, which reads the text after the check.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["MAX_NODES", "ConfigSizeError", "check_config_aliases", "expanded_nodes",
           "install"]

MAX_NODES = 1_000_000
"""The most nodes (mappings, sequences, scalars) a config may expand to, aliases expanded."""


_CHECKED_BYTES = 1 << 20
"""The largest ``--config`` file checked before the parser (an alias bomb is a few hundred
bytes; a larger file, e.g. a data file given as a config, is left to the parser's checks
and to the loader's)."""


class ConfigSizeError(ValueError):
    """A config whose aliases expand past :data:`MAX_NODES`, or refer to themselves."""


def expanded_nodes(text: str) -> int:
    """The nodes of the YAML document ``text`` with every alias expanded (0 when it is not
    one YAML document: the loader reports that).

    Raises:
        ConfigSizeError: more than :data:`MAX_NODES`, or an alias inside its own anchor.
    """
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        root = yaml.compose(text, Loader=loader)
    except yaml.YAMLError:
        return 0
    if root is None:
        return 0
    sizes: dict[int, int] = {}
    open_: set[int] = set()
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:  # post-order, each node once: an alias is the node it names
        node, done = stack.pop()
        key = id(node)
        if key in sizes:
            continue
        children = (node.value if isinstance(node, yaml.SequenceNode)
                    else [n for kv in node.value for n in kv]
                    if isinstance(node, yaml.MappingNode) else [])
        if done:
            open_.discard(key)
            sizes[key] = 1 + sum(sizes[id(c)] for c in children)
            if sizes[key] > MAX_NODES:
                raise ConfigSizeError(
                    f"the YAML expands to more than {MAX_NODES} values (its aliases, "
                    f"*name, repeat anchored parts): a config is a few sections of options; "
                    "write it out without nested aliases")
            continue
        if key in open_:
            raise ConfigSizeError("the YAML holds an alias inside the part it names (a "
                                  "structure that contains itself); write it out without it")
        open_.add(key)
        stack.append((node, True))
        for child in children:
            if id(child) in open_ and id(child) not in sizes:
                raise ConfigSizeError(
                    "the YAML holds an alias inside the part it names (a structure that "
                    "contains itself); write it out without it")
            stack.append((child, False))
    return sizes[id(root)]


def check_config_aliases(argv: Sequence[str]) -> None:
    """Check the ``--config FILE`` (``-c``) files of a command line with
    :func:`expanded_nodes`, before the parser reads them.

    Raises:
        ConfigSizeError: the message names the file (``--config FILE: ...``).
    """
    flags = ("--config", "-c")
    for i, arg in enumerate(argv):
        value = argv[i + 1] if arg in flags and i + 1 < len(argv) else next(
            (arg.split("=", 1)[1] for f in flags if arg.startswith(f + "=")), None)
        if value is None or not Path(value).is_file():
            continue
        try:
            if Path(value).stat().st_size > _CHECKED_BYTES:
                continue  # no config (the parser's checks say so); the loader checks it
            expanded_nodes(Path(value).read_text(errors="replace"))
        except ConfigSizeError as err:
            raise ConfigSizeError(f"--config {value}: {err}") from None
        except OSError:
            continue  # the parser's own error names the file


def install() -> None:
    """Make the bounded loader jsonargparse's ``yaml`` loader (once; idempotent)."""
    from jsonargparse import get_loader, set_loader
    from jsonargparse._loaders_dumpers import get_loader_exceptions

    original = get_loader("yaml")
    if getattr(original, "_bounded", False):
        return

    def bounded_yaml_load(stream: str) -> Any:
        if isinstance(stream, str) and "*" in stream:  # no alias without a '*'
            expanded_nodes(stream)
        return original(stream)

    bounded_yaml_load._bounded = True  # type: ignore[attr-defined]
    set_loader("yaml", bounded_yaml_load, get_loader_exceptions("yaml"))

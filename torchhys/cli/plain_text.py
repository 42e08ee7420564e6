"""Help texts without reStructuredText markup.

The help of ``torchhys fit --help`` and ``torchhys export --help`` comes from docstrings
(ours, Lightning's, jsonargparse's), written in reStructuredText for the API pages. On a
terminal the markup is noise: :func:`plain` turns it into the text a reader sees on the
rendered page. It needs nothing beyond the standard library (``torchhys export`` runs
without the ``train`` extra).

What is written, and what is shown::

    ``max_epochs = -1``                  max_epochs = -1
    :class:`~lightning.pytorch.Trainer`  Trainer
    :func:`torch.no_grad`                torch.no_grad
    :ref:`the guide <guide>`             the guide
    `N` (the default role)               N
    `the docs <https://x.y>`_            the docs (https://x.y)
    *emphasis*, **strong**               emphasis, strong
    .. warning::                         Warning:
    a paragraph ending in ::             the same, ending in :
"""

from __future__ import annotations

import re

__all__ = ["MARKUP", "plain"]

MARKUP = re.compile(r"``|:[a-z]+(?::[a-z]+)?:`|\.\. [a-z-]+::")
"""What no plain help text holds: a literal's double backquotes, a role (``:class:`...``),
a directive (``.. note::``)."""

_TOKEN = re.compile(
    r"``(?P<literal>.+?)``"  # a literal: its text as it is (no emphasis inside)
    r"|:[a-z]+(?::[a-z]+)?:`(?P<role>[^`]+)`"  # :class:`~a.B`, :py:meth:`x`
    r"|`(?P<link>[^`<]+?)\s*<(?P<url>[^>`]+)>`__?"  # `text <url>`_
    r"|`(?P<ref>[^`]+)`__?"  # `name`_
    r"|`(?P<default>[^`]+)`"  # `N`: the default role
    r"|(?<![\w*\\])\*\*(?P<strong>\S(?:[^*\n]*?\S)?)\*\*(?![\w*])"
    r"|(?<![\w*\\])\*(?P<emphasis>\S(?:[^*\n]*?\S)?)\*(?![\w*])"
    r"|\.\. (?P<directive>[a-z-]+)::",
    re.S)
_LITERAL_BLOCK = re.compile(r"(?<=\S)::(?=\s|$)")


def _role(target: str) -> str:
    """What a role shows: ``title <target>`` its title, ``~a.b.c`` its last name, else the
    target as written (without a leading ``!``)."""
    titled = re.fullmatch(r"(.+?)\s*<[^>]+>", target, re.S)
    if titled:
        return titled.group(1)
    target = target.lstrip("!")
    if target.startswith("~"):
        return target[1:].rsplit(".", 1)[-1]
    return target


def _replace(m: re.Match[str]) -> str:
    kind = m.lastgroup
    if kind == "role":
        return _role(m["role"])
    if kind == "url":
        return f"{m['link']} ({m['url']})"
    if kind == "directive":
        return m["directive"].replace("-", " ").capitalize() + ":"
    return m[kind or 0]


def plain(text: str) -> str:
    """``text`` with its reStructuredText markup turned into what a rendered page shows
    (the table of the module docstring); text without markup comes back as it is.

    Args:
        text: a help text or docstring (may span lines).

    Returns:
        The text without literals' backquotes, roles, link syntax, emphasis stars and
        directives' dots.
    """
    if "`" not in text and "*" not in text and ".." not in text and "::" not in text:
        return text
    return _LITERAL_BLOCK.sub(":", _TOKEN.sub(_replace, text))

"""The help formatters of ``torchhys fit|validate|test|predict`` (:mod:`torchhys.cli.help`
says what each help shows): jsonargparse's, without reStructuredText markup, and a short one.

They are given to every parser the command builds (:func:`parser_kwargs`:
``formatter_class``): the formatter decides what a help shows, so a usage error prints the
short usage line too.
"""

from __future__ import annotations

import textwrap
from argparse import SUPPRESS, Action, HelpFormatter, _SubParsersAction
from collections.abc import Iterable
from typing import Any

from jsonargparse import DefaultHelpFormatter
from lightning.pytorch.cli import LightningArgumentParser

from torchhys.cli.help import SECTIONS, SHORT_OPTIONS, TEXTS, epilog, first_sentence
from torchhys.cli.plain_text import plain

__all__ = ["PlainArgumentParser", "PlainHelpFormatter", "ShortHelpFormatter", "help_formatter",
           "parser_kwargs"]


class PlainHelpFormatter(DefaultHelpFormatter):
    """jsonargparse's help formatter, its texts without reStructuredText markup; a text
    of several lines at the top level (the epilog) keeps its lines."""

    def _expand_help(self, action: Action) -> str:
        return plain(super()._expand_help(action))

    def start_section(self, heading: str | None) -> None:
        super().start_section(plain(heading) if heading else heading)

    def _format_text(self, text: str) -> str:
        text = plain(text)
        if "\n" in text and self._current_indent == 0:  # the epilog: its lines as they are
            return "\n".join(line if len(line) <= self._width else "\n".join(
                textwrap.wrap(line, self._width, subsequent_indent="    "))
                for line in text.splitlines()) + "\n\n"
        return super()._format_text(text)


class ShortHelpFormatter(PlainHelpFormatter):
    """:class:`PlainHelpFormatter` that, for the parser of a subcommand of
    :data:`~torchhys.cli.help.SHORT_OPTIONS` (the last word of its ``prog``), shows a
    one-line usage and only those options, in the sections of
    :data:`~torchhys.cli.help.SECTIONS` (each with its :data:`~torchhys.cli.help.TEXTS`
    entry or its text's first sentence, and its default). Another parser's help
    (``torchhys --help``) is :class:`PlainHelpFormatter`'s.

    One class for all parsers: jsonargparse gives a subcommand's parser the formatter of the
    parser above it. argparse calls ``add_usage``, ``add_text`` (the description), then for
    each group ``start_section``, ``add_text``, ``add_arguments``, ``end_section``, then
    ``add_text`` (the epilog): the groups' options are gathered and shown before the
    epilog, the groups themselves are not."""

    def __init__(self, prog: str, *args: Any, **kwargs: Any) -> None:
        super().__init__(prog, *args, **kwargs)
        words = prog.split()
        self._options = SHORT_OPTIONS.get(words[-1]) if words else None
        self._group = False  # inside a group of the parser
        self._found: dict[str, Action] = {}  # the options to show, by dest

    def add_usage(self, usage: str | None, actions: Iterable[Action], *args: Any,
                  **kwargs: Any) -> None:
        if self._options is not None:
            usage, actions = usage or _USAGE, []
        super().add_usage(usage, actions, *args, **kwargs)

    def start_section(self, heading: str | None) -> None:
        if self._options is None:
            super().start_section(heading)
        self._group = True

    def end_section(self) -> None:
        if self._options is None:
            super().end_section()
        self._group = False

    def add_text(self, text: str | None) -> None:
        if self._options is None:
            super().add_text(text)
        elif not self._group:  # the description, or the epilog after the options
            self._add_sections()
            super().add_text(text)

    def add_arguments(self, actions: Iterable[Action]) -> None:
        if self._options is None:
            super().add_arguments(actions)
            return
        self._found.update((a.dest, a) for a in actions
                           if a.dest in self._options and a.help != SUPPRESS)

    def _add_sections(self) -> None:
        for heading, dests in SECTIONS:
            shown = [self._found.pop(d) for d in dests if d in self._found]
            if shown:
                super().start_section(heading)
                super().add_arguments(shown)
                super().end_section()

    def _get_help_string(self, action: Action) -> str:
        if self._options is None:  # the parser of torchhys: a subcommand in one sentence
            if isinstance(action, _SubParsersAction._ChoicesPseudoAction):
                return first_sentence(plain(action.help or ""))
            return super()._get_help_string(action)
        text = TEXTS.get(action.dest) or first_sentence(plain(action.help or ""))
        text = text.rstrip(" .;,:")
        if action.default not in (None, SUPPRESS, False) and "%(default)" not in text \
                and action.option_strings and action.dest not in ("help", "config"):
            text += " (default: %(default)s)"
        return text


_USAGE = "%(prog)s [-h] [-c CONFIG] [--SECTION.OPTION VALUE ...]"


class PlainArgumentParser(LightningArgumentParser):
    """LightningCLI's parser with :class:`PlainHelpFormatter` as its default formatter: the
    help of a class (``--trainer.callbacks.help EarlyStopping``), which jsonargparse prints
    from a new parser of the same type, is plain text too."""

    def __init__(self, *args: Any, formatter_class: type[HelpFormatter] = PlainHelpFormatter,
                 **kwargs: Any) -> None:
        super().__init__(*args, formatter_class=formatter_class, **kwargs)


def help_formatter(*, full: bool) -> type[DefaultHelpFormatter]:
    """The formatter class of the command's parsers: :class:`PlainHelpFormatter` with
    ``full`` (``--help-all``), else :class:`ShortHelpFormatter`."""
    return PlainHelpFormatter if full else ShortHelpFormatter


def parser_kwargs(description: str, subcommands: Iterable[str], *,
                  full: bool) -> dict[str, Any]:
    """LightningCLI's ``parser_kwargs``: the description of ``torchhys --help``, the
    formatter (:func:`help_formatter`) and each parser's epilog
    (:func:`~torchhys.cli.help.epilog`)."""
    kwargs: dict[str, Any] = {"description": description,
                              "formatter_class": help_formatter(full=full),
                              "epilog": epilog(None, full=full)}
    for sub in subcommands:
        kwargs[sub] = {"epilog": epilog(sub, full=full)}
    return kwargs

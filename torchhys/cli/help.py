"""The help of ``torchhys fit|validate|test|predict``: short by default, every option with
``--help-all``, both without reStructuredText markup.

LightningCLI's parser lists every argument of the Trainer, the model, the data and the
callbacks (some 1400 lines). ``--help`` shows the options a first run needs
(:data:`SECTIONS`: the config, the data file and its columns, the network, model
selection, the epochs, the run folder, the logger, the checkpoint), each with the first
sentence of its text (or :data:`TEXTS`) and its default, the options of the command
itself, and a line naming ``--help-all``; ``--help-all`` is jsonargparse's full help. The
help texts come from docstrings (:class:`~torchhys.training.InverseHysteresisModule`,
:class:`~torchhys.training.HysteresisDataModule`, Lightning's ``Trainer``):
:func:`~torchhys.cli.plain_text.plain` takes their markup out in both.

This module says what each shows and needs only the standard library (the command reads
``--help-all`` before it imports Lightning); the formatters that show it are in
:mod:`torchhys.cli.help_format`.
"""

from __future__ import annotations

import re
import textwrap
from collections.abc import Sequence

__all__ = ["COMMAND_OPTIONS", "HELP_ALL_FLAG", "SECTIONS", "SHORT_OPTIONS", "TEXTS", "epilog",
           "first_sentence", "split_help_all_flag"]

HELP_ALL_FLAG = "--help-all"
"""The flag that shows every option (the command takes it out and asks for ``--help``)."""

SECTIONS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("options", ("help", "config", "print_config")),
    ("data (the recording and its columns)", (
        "data.path", "data.input_column", "data.target_column", "data.time_column",
        "data.run_column", "data.condition_columns", "data.split")),
    ("model (the network and its training)", (
        "model.operator", "model.hidden", "model.optimizer", "model.lr")),
    ("model selection (fit: candidates scored on validation data, the best one fitted)", (
        "model.select", "model.select_cv", "model.select_rule", "model.select_jobs",
        "model.select_budget_s")),
    ("trainer (Lightning's Trainer: any of its arguments as --trainer.NAME)", (
        "trainer.max_epochs", "trainer.accelerator", "trainer.devices",
        "trainer.default_root_dir", "trainer.logger")),
    ("checkpoint and outputs", ("ckpt_path", "baselines.max_degree", "predictions.filename")),
)
"""What ``--help`` shows (each option by its ``dest``), section by section; a subcommand
shows those its parser has (``fit`` alone the model selection's, ``test`` the baselines',
``predict`` the predictions file)."""

SHORT_OPTIONS: dict[str, tuple[str, ...]] = {
    sub: tuple(d for _, dests in SECTIONS for d in dests
               if (sub == "fit" or not d.startswith("model.select"))
               and (sub == "test" or not d.startswith("baselines."))
               and (sub == "predict" or not d.startswith("predictions.")))
    for sub in ("fit", "validate", "test", "predict")}
"""The options ``--help`` shows, per subcommand."""

TEXTS = {
    "help": "show this help (the most used options) and exit; --help-all: every option",
    "data.condition_columns": "columns of measured operating conditions (a coil voltage, a "
                              "supply pressure, a temperature), inputs of the network beside "
                              "the response",
    "trainer.max_epochs": "training epochs (with neither max_epochs nor max_steps: 1000)",
    "trainer.accelerator": "cpu, gpu, mps or auto",
    "trainer.devices": "devices to use: a number, a list of indices, -1 (all) or auto",
    "trainer.default_root_dir": "the run's folder: logs and checkpoints go under "
                                "<default_root_dir>/logs/version_<N>",
    "trainer.logger": "csv (the default: CSV files in the run's folder), tensorboard, "
                      "false (none), or a Logger's class_path",
    "ckpt_path": "a checkpoint: fit resumes it, validate, test and predict evaluate its "
                 "weights; 'last': the newest last.ckpt of the earlier runs",
}
"""The text ``--help`` shows for an option where its docstring's first sentence does not
say what torchhys does with it (the Trainer's, written for any Lightning program)."""

COMMAND_OPTIONS = (
    ("--import MODULE", "import a module first (an operator it registers can be named in "
                        "model.operator; repeatable)"),
    ("--import-path DIR", "a folder to search for the modules of --import (repeatable)"),
    ("--threads N", "torch's threads (default 1; also TORCHHYS_THREADS)"),
    ("--quiet", "no progress lines (also TORCHHYS_QUIET=1)"),
    ("--verbose", "Lightning's information lines and tips, and warnings with their source "
                  "line (also TORCHHYS_VERBOSE=1)"),
    ("--traceback", "the traceback of an error in the files, options or data (also "
                    "TORCHHYS_TRACEBACK=1)"),
)
"""The options of the ``torchhys`` command itself (taken out before the parser reads the
rest: :mod:`torchhys.cli.commands`), as the help lists them."""

_SENTENCE = re.compile(r"(?<!e\.g\.)(?<!i\.e\.)(?<=[^.\s]\.)\s+(?=\S)")
_LONG = 160
"""A first sentence longer than this (characters) ends at its first ';'."""


def epilog(subcommand: str | None, *, full: bool) -> str:
    """The end of a help: the options of the command itself, and the other help."""
    width = max(len(flag) for flag, _ in COMMAND_OPTIONS) + 2
    lines = ["options of the torchhys command (anywhere on the line):"]
    for flag, text in COMMAND_OPTIONS:
        lines += textwrap.wrap(text, 78, initial_indent=f"  {flag:<{width}}",
                               subsequent_indent=" " * (width + 2))
    prog = f"torchhys {subcommand}" if subcommand else "torchhys fit"
    lines.append(f"{prog} --help: the most used options only." if full else
                 f"{prog} {HELP_ALL_FLAG}: every option (the Trainer's, the callbacks', "
                 "the model's and the data's).")
    return "\n".join(lines)


def first_sentence(text: str) -> str:
    """The first sentence of ``text`` (up to its first '.' followed by a space; a long one
    up to its first ';')."""
    text = _SENTENCE.split(" ".join(text.split()), maxsplit=1)[0]
    if len(text) > _LONG:  # at its first ';' outside brackets
        depth = 0
        for i, c in enumerate(text):
            depth += (c in "([{") - (c in ")]}")
            if c == ";" and depth == 0:
                return text[:i]
    return text




def split_help_all_flag(argv: Sequence[str]) -> tuple[list[str], bool]:
    """``argv`` with ``--help-all`` turned into ``--help``, and whether it was there."""
    args = ["--help" if a == HELP_ALL_FLAG else a for a in argv]
    return args, HELP_ALL_FLAG in argv

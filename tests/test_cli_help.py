"""``torchhys fit --help`` is short (the most used options, the command's own, a line naming
``--help-all``), ``--help-all`` is every option, and neither (nor ``torchhys export
--help``) holds reStructuredText markup; :func:`torchhys.cli.plain_text.plain` against
texts written out by hand."""

from __future__ import annotations

import re
import sys

import pytest

from torchhys.cli.help import COMMAND_OPTIONS, SHORT_OPTIONS, first_sentence, split_help_all_flag
from torchhys.cli.main import main
from torchhys.cli.plain_text import MARKUP, plain

ROLE_OR_LITERAL = re.compile(r"``|:(class|func|mod|meth|data|attr|paramref|ref):`|\.\. \w+::")
"""The markup no help may hold (written out here, independently of MARKUP)."""


def _help(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, *args: str) -> str:
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    with pytest.raises(SystemExit) as exit_:
        main(list(args))
    assert exit_.value.code == 0
    out, err = capsys.readouterr()
    assert err == ""
    return out


@pytest.mark.parametrize(("text", "expected"), [
    ('Default: ``"auto"``.', 'Default: "auto".'),
    (":class:`~lightning.pytorch.trainer.trainer.Trainer`", "Trainer"),
    ("a :class:`datetime.timedelta` or", "a datetime.timedelta or"),
    (":paramref:`~lightning.pytorch.trainer.trainer.Trainer.callbacks`", "callbacks"),
    (":func:`torch.no_grad` during", "torch.no_grad during"),
    (":mod:`torchhys.cli.help`", "torchhys.cli.help"),
    (":data:`~torchhys.selection.jobs.AUTO_JOBS`", "AUTO_JOBS"),
    (":ref:`the guide <guide>`", "the guide"),
    ("every `N` epochs", "every N epochs"),
    ("see `the docs <https://a.b/c>`_ now", "see the docs (https://a.b/c) now"),
    ("an *emphasis* and **strong** word", "an emphasis and strong word"),
    ("``*_recordings`` (without it)", "*_recordings (without it)"),
    ("f(*args, **kwargs) and 2 * 3 * 4", "f(*args, **kwargs) and 2 * 3 * 4"),
    ("name. .. warning:: In a distributed run", "name. Warning: In a distributed run"),
    ("For example::", "For example:"),
    ("no markup here: a.b, c::d", "no markup here: a.b, c::d"),
])
def test_plain_shows_what_a_rendered_page_shows(text: str, expected: str) -> None:
    assert plain(text) == expected
    assert not MARKUP.search(plain(text))


def test_first_sentence_and_the_flag() -> None:
    assert first_sentence("Stop training here. Disabled by default.") == "Stop training here."
    assert first_sentence("values, e.g. 3 or 4. More.") == "values, e.g. 3 or 4."
    long = "a" * 170 + " (b; c); d"
    assert first_sentence(long) == "a" * 170 + " (b; c)"  # at the first ';' outside brackets
    assert split_help_all_flag(["fit", "--help-all", "-c", "x"]) == (
        ["fit", "--help", "-c", "x"], True)
    assert split_help_all_flag(["fit", "--help"]) == (["fit", "--help"], False)


@pytest.mark.parametrize("sub", ["fit", "validate", "test", "predict"])
def test_short_help_is_short_plain_and_names_help_all(monkeypatch, capsys, sub: str) -> None:
    out = _help(monkeypatch, capsys, sub, "--help")
    lines = out.splitlines()
    assert len(lines) < 150, len(lines)
    assert lines[0].startswith(f"usage: torchhys [options] {sub} ") and len(lines[0]) < 100
    assert f"torchhys {sub} --help-all: every option" in out
    for option in ("--config", "--print_config", "--data.path", "--data.input_column",
                   "--data.target_column", "--trainer.max_epochs",
                   "--trainer.default_root_dir", "--trainer.logger", "--ckpt_path"):
        assert re.search(rf"^  (-\w [A-Z]+, )?{re.escape(option)}\b", out, re.M), option
    assert ("--model.select " in out) is (sub == "fit")
    for flag, _ in COMMAND_OPTIONS:  # the command's own options
        assert f"  {flag}" in out
    assert not ROLE_OR_LITERAL.search(out), ROLE_OR_LITERAL.search(out)
    shown = set(re.findall(r"^  (?:-\w(?: [A-Z]+)?, )?--([\w.-]+)", out, re.M))
    assert shown - {"help", "import", "import-path", "threads", "quiet", "verbose",
                    "traceback"} == set(SHORT_OPTIONS[sub]) - {"help"}


def test_help_all_lists_every_option_without_markup(monkeypatch, capsys) -> None:
    short = _help(monkeypatch, capsys, "fit", "--help")
    full = _help(monkeypatch, capsys, "fit", "--help-all")
    assert len(full.splitlines()) > 5 * len(short.splitlines())
    for option in ("--trainer.gradient_clip_val", "--checkpoint.monitor", "--data.warmup"):
        assert option not in short and option in full
    assert "torchhys fit --help: the most used options only" in full
    assert not ROLE_OR_LITERAL.search(full), ROLE_OR_LITERAL.search(full)


def test_the_commands_help_and_a_usage_error_are_short(monkeypatch, capsys) -> None:
    out = _help(monkeypatch, capsys, "--help")
    assert "Available subcommands" in out and not ROLE_OR_LITERAL.search(out)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "--config", "compensator", "--no_such_option", "1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "no_such_option" in err and len(err.splitlines()) < 10, err


def test_export_help_is_plain(monkeypatch, capsys) -> None:
    out = _help(monkeypatch, capsys, "export", "--help")
    assert out.startswith("usage: torchhys export")
    assert "torchhys export: a trained checkpoint to a deployable compensator" in out
    assert re.search(r"--format \{[^}]*\}\s+the file's kind", out)
    assert not ROLE_OR_LITERAL.search(out), ROLE_OR_LITERAL.search(out)
    assert _help(monkeypatch, capsys, "export", "--help-all") == out


def test_fleet_help_is_plain(monkeypatch, capsys) -> None:
    out = _help(monkeypatch, capsys, "fleet", "--help")
    assert out.startswith("torchhys fleet: a fleet of devices identified in one command")
    assert "--device-timeout" in out and "--data.device_column" in out
    assert not ROLE_OR_LITERAL.search(out), ROLE_OR_LITERAL.search(out)
    assert _help(monkeypatch, capsys, "fleet", "--help-all") == out


def test_a_class_help_is_plain(monkeypatch, capsys) -> None:
    out = _help(monkeypatch, capsys, "fit", "--quiet", "--config", "compensator",
                "--trainer.callbacks.help", "EarlyStopping")
    assert "--trainer.callbacks.patience" in out
    assert not ROLE_OR_LITERAL.search(out), ROLE_OR_LITERAL.search(out)

"""The torch threads of a ``torchhys`` command: one by default, ``--threads`` or
``TORCHHYS_THREADS`` to change, said on stderr."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from torchhys.cli.threads import THREADS_ENV, choose_threads, split_threads_flag


@pytest.fixture(autouse=True)
def _restore_threads(monkeypatch):
    monkeypatch.delenv(THREADS_ENV, raising=False)
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_split_threads_flag() -> None:
    assert split_threads_flag(["fit", "--threads", "2", "--x"]) == (["fit", "--x"], 2)
    assert split_threads_flag(["fit", "--threads=3"]) == (["fit"], 3)
    assert split_threads_flag(["fit"]) == (["fit"], None)
    for bad in (["--threads"], ["--threads", "0"], ["--threads=two"]):
        with pytest.raises(ValueError, match="--threads"):
            split_threads_flag(bad)


def test_choice_flag_then_environment_then_one(monkeypatch, capsys) -> None:
    assert choose_threads(None, "torchhys fit") == 1 and torch.get_num_threads() == 1
    assert "torchhys fit: torch threads 1 (default" in capsys.readouterr().err
    monkeypatch.setenv(THREADS_ENV, "2")
    assert choose_threads(None, "torchhys fit") == 2 and torch.get_num_threads() == 2
    assert f"threads 2 ({THREADS_ENV}" in capsys.readouterr().err
    assert choose_threads(1, "torchhys fit", say=False) == 1 and torch.get_num_threads() == 1
    assert capsys.readouterr().err == ""
    monkeypatch.setenv(THREADS_ENV, "-1")
    with pytest.raises(ValueError, match=THREADS_ENV):
        choose_threads(None, "torchhys fit")


def test_the_command_says_its_threads_and_rejects_a_bad_count(tmp_path) -> None:
    env = {k: v for k, v in os.environ.items() if k != THREADS_ENV}
    run = subprocess.run([sys.executable, "-m", "torchhys", "export", "--threads",
                          "2", "--ckpt", str(tmp_path / "none.ckpt"), "--format",
                          "torchscript", "--out", str(tmp_path / "c.pt")],
                         capture_output=True, text=True, timeout=300, env=env)
    lines = run.stderr.strip().splitlines()
    assert lines[0].startswith("torchhys export: torch threads 2 (--threads")
    assert run.returncode == 2 and "none.ckpt" in lines[-1]
    bad = subprocess.run([sys.executable, "-m", "torchhys", "fit", "--threads",
                          "zero"], capture_output=True, text=True, timeout=300, env=env)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1].startswith("torchhys fit: error: --threads")

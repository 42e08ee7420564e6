"""``torchhys --version``, ``torchhys configs`` and the shipped configs by name
(``torchhys fit --config measured``), and ``fit`` without a config: one line."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import yaml

import torchhys
from torchhys.cli.configs import (
    describe,
    describe_all,
    require_config,
    resolve_config_names,
    shipped_configs,
)
from torchhys.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted((ROOT / "configs").glob("*.yaml"))


def _run(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """``torchhys ARGS`` as a user runs it (user errors in one line); status, out, err."""
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    with pytest.raises(SystemExit) as info:
        main(list(args))
    out = capsys.readouterr()
    return info.value.code, out.out, out.err


def test_version_prints_the_packages_version(monkeypatch, capsys) -> None:
    from torchhys._version import __version__

    assert _run(monkeypatch, capsys, "--version") == (0, f"torchhys {__version__}\n", "")
    assert __version__ == torchhys.__version__ and __version__.count(".") == 2
    code, _, err = _run(monkeypatch, capsys, "--version", "x")
    assert code == 2 and err == "torchhys --version: error: takes no arguments, got x\n"


def test_the_shipped_configs_are_the_checkouts_files() -> None:
    shipped = shipped_configs()
    assert list(shipped) == [f.stem for f in FILES] and len(FILES) >= 9
    for file in FILES:
        assert shipped[file.stem].read_bytes() == file.read_bytes()
    # the package's own folder (the checkout's link to configs/), not the checkout's root
    assert Path(torchhys.__file__).parent / "configs" in shipped["measured"].parents


def test_configs_lists_each_config_in_one_line(monkeypatch, capsys) -> None:
    code, out, err = _run(monkeypatch, capsys, "configs")
    assert code == 0 and err == ""
    lines = out.splitlines()
    rows = lines[:len(FILES)]
    assert [r.split()[0] for r in rows] == [f.stem for f in FILES]
    assert all(len(r) <= 100 for r in rows)
    assert lines[len(FILES)] == "" and "--config NAME" in lines[-1]
    assert rows == describe_all()
    for row, file in zip(rows, FILES, strict=True):
        text = " ".join(ln[1:].strip() for ln in file.read_text().splitlines()[:3])
        headline = row.split(None, 1)[1].removesuffix("...")
        assert headline and text.startswith(headline), (row, text)  # the opening comment's
    assert describe(ROOT / "configs" / "compensator.yaml") == (
        "The recommended deployable compensator")
    assert describe(ROOT / "configs" / "paper_simulation_zhaotan.yaml") == (
        "The paper's Section 5.2 with the baseline of Ref. [8]")


def test_a_name_becomes_the_shipped_file_and_a_path_stays(monkeypatch, tmp_path) -> None:
    monkeypatch.chdir(tmp_path)
    measured = str(shipped_configs()["measured"])
    assert resolve_config_names(["fit", "--config", "measured", "-c", "compensator.yaml"]) == [
        "fit", "--config", measured, "-c", str(shipped_configs()["compensator"])]
    assert resolve_config_names(["fit", "--config=measured"]) == ["fit", f"--config={measured}"]
    (tmp_path / "measured").write_text("trainer: {}\n")  # a file of that name comes first
    (tmp_path / "mine.yaml").write_text("trainer: {}\n")
    kept = ["fit", "--config", "measured", "-c", "mine.yaml", "--config", "{trainer: {}}",
            "--data.path", "compensator"]
    assert resolve_config_names(kept) == kept
    with pytest.raises(ValueError, match=r"^--config nosuch.yaml: no such file, nor the name "
                       r"of a shipped config \(compensator, conditions, .*measured.*\)$"):
        resolve_config_names(["fit", "--config", "nosuch.yaml"])
    with pytest.raises(ValueError, match="no such file"):
        resolve_config_names(["fit", "--config", "sub/measured"])  # a path, not a name


def test_fit_reads_a_shipped_config_by_name(monkeypatch, capsys, tmp_path) -> None:
    """From a folder without configs/: the same parsed config as the checkout's file."""
    def printed(config: str) -> dict:
        code, out, _ = _run(monkeypatch, capsys, "fit", "--config", config, "--print_config")
        assert code == 0
        return yaml.safe_load(out)

    by_path = printed(str(ROOT / "configs" / "measured.yaml"))
    monkeypatch.chdir(tmp_path)
    assert printed("measured") == by_path
    assert by_path["model"]["select_cv"] == 4  # the measured config's, not a default


def test_fit_without_a_config_says_what_it_needs(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(monkeypatch, capsys, "fit", "--trainer.max_epochs", "1")
    assert code == 2 and out == ""
    last = err.splitlines()[-1]
    assert last.startswith("torchhys fit: error: fit needs a config: --config FILE, or a "
                           "shipped config by name, e.g. --config measured")
    assert "paper_simulation_eiho" in last and "torchhys configs" in last
    assert os.listdir(tmp_path) == []  # nothing trained, nothing written


def test_only_fit_without_any_config_is_refused() -> None:
    require_config(["fit", "-c", "x.yaml"])
    require_config(["fit", "--config=x.yaml"])
    require_config(["fit", "--help"])
    require_config(["fit", "--print_config"])
    require_config(["test", "--ckpt_path", "last"])  # the checkpoint's own hyperparameters
    with pytest.raises(ValueError, match="^fit needs a config"):
        require_config(["fit", "--data.path", "log.csv"])


def test_version_and_configs_need_no_training_extra(tmp_path: Path) -> None:
    """With Lightning, jsonargparse, torchmetrics and matplotlib unimportable (as
    tests/test_packaging_extras.py simulates it), from a folder without configs/."""
    import subprocess

    from test_packaging_extras import BLOCKED, SITECUSTOMIZE

    (tmp_path / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = dict(os.environ, PYTHONPATH=str(tmp_path), TORCHHYS_TEST_BLOCK=",".join(BLOCKED))
    outs = []
    for args in (["--version"], ["configs"]):
        proc = subprocess.run([sys.executable, "-m", "torchhys", *args], capture_output=True,
                              text=True, env=env, cwd=tmp_path, timeout=300)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr
        outs.append(proc.stdout)
    assert outs[0] == f"torchhys {torchhys.__version__}\n"
    assert outs[1].splitlines()[:len(FILES)] == describe_all()

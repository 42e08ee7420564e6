"""``torchhys fit --trainer.logger csv|tensorboard``: the short names of Lightning's loggers,
writing where the default logger does, and one line naming the package TensorBoard needs
where it is not installed (simulated as tests/test_packaging_extras.py does)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from _training_helpers import cli, small_config
from jsonargparse import Namespace
from test_packaging_extras import SITECUSTOMIZE

import torchhys.cli.loggers as loggers
from torchhys.cli.loggers import LOGGERS, ROOT_DIR, expand_logger_names, prepare_loggers

CSV, TB = LOGGERS["csv"], LOGGERS["tensorboard"]


def test_the_short_names_are_the_loggers_classes() -> None:
    import importlib

    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    def load(path: str) -> type:
        module, _, name = path.rpartition(".")
        return getattr(importlib.import_module(module), name)

    assert load(CSV) is CSVLogger
    assert load(TB) is TensorBoardLogger


def test_a_short_name_becomes_its_class_path(monkeypatch) -> None:
    monkeypatch.setattr(loggers, "_found", lambda name: True)
    assert expand_logger_names(["fit", "--trainer.logger", "tensorboard", "-c", "x.yaml"]) == [
        "fit", f"--trainer.logger={TB}", f"--trainer.logger.save_dir={ROOT_DIR}",
        "-c", "x.yaml"]
    assert expand_logger_names(["fit", "--trainer.logger=CSV"]) == [
        "fit", f"--trainer.logger={CSV}", f"--trainer.logger.save_dir={ROOT_DIR}"]
    assert expand_logger_names([f"--trainer.logger={CSV}"])[-1].endswith(ROOT_DIR)
    other = ["fit", "--trainer.logger", "false", "--model.hidden", "csv",
             "--trainer.logger.name", "csv"]
    assert expand_logger_names(other) == other  # not a short name; not the logger's option


def test_the_short_name_resolves_in_the_parsed_config(monkeypatch, capsys, tmp_path) -> None:
    """``fit --print_config``: the class path, save_dir in the default logger's place until
    the config is read; a ``--trainer.logger.name`` after it is kept."""
    monkeypatch.setattr(loggers, "_found", lambda name: True)
    with pytest.raises(SystemExit) as info:
        cli(monkeypatch, "fit", "--config", str(small_config(tmp_path)),
            "--trainer.logger", "tensorboard", "--trainer.logger.name", "mine",
            "--print_config")
    assert info.value.code == 0
    logger = yaml.safe_load(capsys.readouterr().out)["trainer"]["logger"]
    assert logger["class_path"] == TB
    assert (logger["init_args"]["save_dir"], logger["init_args"]["name"]) == (ROOT_DIR, "mine")


def test_a_missing_tensorboard_is_one_line_naming_it(monkeypatch) -> None:
    monkeypatch.setattr(loggers, "_found", lambda name: False)
    with pytest.raises(ValueError, match=r"^trainer.logger lightning.pytorch.loggers."
                       r"TensorBoardLogger needs the tensorboard package, which is not "
                       r"installed: pip install tensorboard \(or choose --trainer.logger "
                       r"csv\)$"):
        expand_logger_names(["fit", "--trainer.logger", "tensorboard"])
    assert expand_logger_names(["fit", "--trainer.logger", "csv"])[1] == f"--trainer.logger={CSV}"


def test_a_logger_without_save_dir_writes_where_the_default_does(monkeypatch) -> None:
    monkeypatch.setattr(loggers, "_found", lambda name: True)
    logger = Namespace(class_path=TB,
                       init_args=Namespace(save_dir=ROOT_DIR, name="lightning_logs"))
    mine = Namespace(class_path=CSV, init_args=Namespace(save_dir="elsewhere", name="x"))
    prepare_loggers([logger, mine], "runs/a")
    assert (logger.init_args.save_dir, logger.init_args.name) == ("runs/a", "logs")
    assert (mine.init_args.save_dir, mine.init_args.name) == ("elsewhere", "x")


def test_fit_with_the_csv_logger_by_its_short_name(monkeypatch, tmp_path: Path) -> None:
    config, root = small_config(tmp_path), tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(config), f"--trainer.default_root_dir={root}",
        "--trainer.logger", "csv")
    rows = (root / "logs/version_0/metrics.csv").read_text().splitlines()
    assert rows[0].split(",").count("train_loss") == 1 and len(rows) > 3
    assert (root / "logs/version_0/checkpoints/last.ckpt").is_file()


@pytest.mark.parametrize("flag", [["--trainer.logger", "tensorboard"],
                                  [f"--trainer.logger={TB}"]])
def test_without_tensorboard_the_command_says_what_to_install(tmp_path: Path, flag) -> None:
    """By its short name or its class path: one line on stderr, status 2, no run folder."""
    (tmp_path / "sitecustomize.py").write_text(SITECUSTOMIZE)
    config, root = small_config(tmp_path), tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(tmp_path),
               TORCHHYS_TEST_BLOCK="tensorboard,tensorboardX")
    proc = subprocess.run([sys.executable, "-m", "torchhys", "fit", "--config", str(config),
                           f"--trainer.default_root_dir={root}", *flag],
                          capture_output=True, text=True, env=env, cwd=Path(sys.prefix),
                          timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines()[-1] == (
        f"torchhys fit: error: trainer.logger {TB} needs the tensorboard package, which is "
        "not installed: pip install tensorboard (or choose --trainer.logger csv)")
    assert "Traceback" not in proc.stderr
    assert not root.exists()

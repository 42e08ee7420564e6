"""Faults of checkpoints and signals: a checkpoint named by a URL is refused in one line and
nothing from it runs; every loader of checkpoints reads local files with
``weights_only=True``; SIGTERM ends a fit with a non-zero status after ``last.ckpt``;
``--ckpt_path last`` resumes the newest earlier run; the processes of ``model.select_jobs``
die with the command (SIGTERM, SIGKILL) and Ctrl-C during model selection is one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from torchhys.training.checkpoint_io import AtomicCheckpointIO
from torchhys.training.cli import main
from torchhys.training.errors import CheckpointError, read_checkpoint
from torchhys.training.export_cmd import main as export_main

ROOT = Path(__file__).resolve().parents[1]

TINY = """\
seed_everything: 0
trainer:
  accelerator: cpu
  devices: 1
  precision: 64-true
  max_epochs: 1
  check_val_every_n_epoch: 1000
  enable_progress_bar: false
  enable_model_summary: false
model:
  operator: null
  hidden: 2
  optimizer: cg
data:
  simulation: paper
  t_end: 6.3
  split: [0.6, 0.2, 0.2]
"""


class _Payload:
    """An object whose unpickling creates the folder ``marker``: loaded with
    ``weights_only=False``, the file runs code."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):  # noqa: ANN204 (pickle's protocol)
        return os.mkdir, (self.marker,)


@pytest.fixture
def evil(tmp_path: Path) -> tuple[Path, Path]:
    """A checkpoint-shaped file holding a payload, and the marker the payload would make."""
    marker = tmp_path / "payload-ran"
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "x": _Payload(marker)}, path)
    return path, marker


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def _one_line(capsys, prog: str, *names: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith(f"{prog}: error: "), err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    for name in names:
        assert name in lines[-1], lines[-1]
    return lines[-1]


# --- 1. checkpoints from URLs ---------------------------------------------------------------
@pytest.mark.parametrize("sub", ["fit", "test", "validate", "predict"])
def test_ckpt_path_url_is_refused_in_one_line(monkeypatch, capsys, tmp_path, tiny,
                                              sub) -> None:
    """Nothing listens on port 1: a download attempt would fail with a traceback."""
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    url = "http://127.0.0.1:1/evil.ckpt"
    with pytest.raises(SystemExit) as exc:
        main([sub, "--config", str(tiny), "--trainer.default_root_dir=run",
              f"--ckpt_path={url}"])
    assert exc.value.code == 2
    line = _one_line(capsys, f"torchhys {sub}", url, "URL", "local file")
    assert "download" in line
    assert not (tmp_path / "run").exists()  # refused before anything is written


def test_file_url_is_refused_and_runs_nothing(monkeypatch, capsys, tmp_path, tiny,
                                              evil) -> None:
    path, marker = evil
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    url = f"file://{path}"
    with pytest.raises(SystemExit) as exc:
        main(["test", "--config", str(tiny), "--trainer.default_root_dir=run",
              f"--ckpt_path={url}"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys test", url, "URL")
    assert not marker.exists()


def test_registry_ckpt_path_is_refused(monkeypatch, capsys, tmp_path, tiny) -> None:
    """Lightning's ``registry:`` values download a model: refused as a URL is."""
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["test", "--config", str(tiny), "--ckpt_path=registry:some/model"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys test", "registry:some/model", "local file")


@pytest.mark.parametrize("url", ["http://127.0.0.1:1/evil.ckpt", "https://h/x.ckpt",
                                 "s3://bucket/x.ckpt"])
def test_export_ckpt_url_is_refused(capsys, tmp_path, url) -> None:
    rc = export_main(["--ckpt", url, "--format", "torchscript", "--out",
                      str(tmp_path / "m.pt")])
    assert rc == 2
    _one_line(capsys, "torchhys export", "URL", "local file")
    assert not list(tmp_path.iterdir())


def test_read_checkpoint_refuses_urls_and_runs_nothing(evil) -> None:
    path, marker = evil
    for url in (f"file://{path}", Path(f"file://{path}"), "http://127.0.0.1:1/evil.ckpt"):
        with pytest.raises(CheckpointError, match="URL"):
            read_checkpoint(url, "--ckpt")
    with pytest.raises(CheckpointError, match="holds objects other than tensors"):
        read_checkpoint(path, "--ckpt")  # the local file: refused, not run
    assert not marker.exists()


def test_checkpoint_io_loads_local_files_with_weights_only(evil) -> None:
    """The trainer plugin of ``torchhys`` (Lightning's second read of ``--ckpt_path``, and
    ``best``/``hpc``): a URL is refused and ``weights_only=False`` does not run the file."""
    path, marker = evil
    io = AtomicCheckpointIO()
    with pytest.raises(CheckpointError, match="URL"):
        io.load_checkpoint("http://127.0.0.1:1/evil.ckpt")
    with pytest.raises(CheckpointError, match="URL"):
        io.load_checkpoint(f"file://{path}", weights_only=False)
    with pytest.raises(Exception, match="(?i)weights.only"):
        io.load_checkpoint(path, weights_only=False)
    assert not marker.exists()
    good = path.parent / "good.ckpt"
    torch.save({"state_dict": {"w": torch.ones(2)}, "epoch": 3}, good)
    assert io.load_checkpoint(good)["epoch"] == 3


# --- 6. --ckpt_path last ---------------------------------------------------------------------
def test_ckpt_path_last_without_an_earlier_run_is_one_line(monkeypatch, capsys, tmp_path,
                                                          tiny) -> None:
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(tiny), "--trainer.default_root_dir=run",
              "--ckpt_path=last"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys fit", "--ckpt_path last", "no earlier run's last.ckpt",
              "version_*")
    assert not (tmp_path / "run").exists()


def test_ckpt_path_last_resumes_the_newest_earlier_run(monkeypatch, tmp_path, tiny) -> None:
    monkeypatch.setenv("TORCHHYS_TRACEBACK", "1")
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    fit = ["fit", "--config", str(tiny), "--trainer.default_root_dir=run"]
    main(fit)  # version_0: epoch 0
    main([*fit, "--trainer.max_epochs=2", "--ckpt_path=last"])  # version_1: epoch 1
    main([*fit, "--trainer.max_epochs=3", "--ckpt_path=last"])  # version_2: epoch 2
    logs = tmp_path / "run" / "logs"
    for v in (1, 2):
        first = (logs / f"version_{v}" / "metrics.csv").read_text().splitlines()[1]
        assert first.split(",")[0] == str(v), (v, first)  # the epoch after the resumed one
        saved = torch.load(logs / f"version_{v}" / "checkpoints" / "last.ckpt",
                           weights_only=True)
        assert saved["epoch"] == v

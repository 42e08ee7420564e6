"""``torchhys`` as users run it: errors in their files, options, data and checkpoints are one
line on stderr (``torchhys fit: error: ...``, exit status 2, no traceback; ``--traceback``
or ``TORCHHYS_TRACEBACK=1`` shows it), bugs keep their traceback, a bad ``--ckpt_path``
writes nothing, and concurrent model selections keep their tables apart."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _training_helpers import DROP, small_config

from torchhys.checkpoints import CheckpointError, read_checkpoint
from torchhys.cli.export import main as export_main
from torchhys.cli.main import main
from torchhys.training import HysteresisDataModule

ROOT = Path(__file__).resolve().parents[1]

@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    return small_config(tmp_path, "tiny.yaml", trainer={"max_epochs": 1},
                        model={"operator_kwargs": DROP, "hidden": 2, "optimizer_kwargs": DROP})


def run(cwd: Path, *args: str, env: dict[str, str] | None = None
        ) -> subprocess.CompletedProcess:
    """``torchhys ARGS`` in a fresh process in ``cwd`` (one thread, no traceback setting)."""
    base = {k: v for k, v in os.environ.items() if k != "TORCHHYS_TRACEBACK"}
    return subprocess.run(
        [sys.executable, "-m", "torchhys", *args], cwd=cwd,
        env={**base, "OMP_NUM_THREADS": "1", **(env or {})}, capture_output=True, text=True,
        timeout=300, check=False)


def assert_one_line_error(proc: subprocess.CompletedProcess, prog: str, *names: str) -> str:
    """Exit status 2, the last line of stderr ``<prog>: error: ...`` naming ``names``, no
    traceback; that line."""
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert lines and lines[-1].startswith(f"{prog}: error: "), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    for name in names:
        assert name in lines[-1], lines[-1]
    return lines[-1]


def fit(tiny: Path, *extra: str) -> tuple[str, ...]:
    return ("fit", "--config", str(tiny), "--trainer.default_root_dir=run", *extra)


# --- data and options -------------------------------------------------------------------
def test_missing_data_file(tiny, tmp_path) -> None:
    proc = run(tmp_path, *fit(tiny, "--data.path", "absent.csv"))
    assert_one_line_error(proc, "torchhys fit", "absent.csv")


def test_bad_cell(tiny, tmp_path) -> None:
    rows = [f"{i},{0.5 * i}" for i in range(100)]
    rows[7] = "7,oops"
    (tmp_path / "log.csv").write_text("command,response\n" + "\n".join(rows) + "\n")
    proc = run(tmp_path, *fit(tiny, "--data.path", "log.csv"))
    line = assert_one_line_error(proc, "torchhys fit", "log.csv", "response", "oops")
    assert "line 9" in line  # the header is line 1


def test_negative_warmup(tiny, tmp_path) -> None:
    proc = run(tmp_path, *fit(tiny, "--data.warmup", "-1"))
    assert_one_line_error(proc, "torchhys fit", "warmup", "-1")


def test_bad_split(tiny, tmp_path) -> None:
    proc = run(tmp_path, *fit(tiny, "--data.split", "[0.5, 0.6, 0.1]"))
    assert_one_line_error(proc, "torchhys fit", "split", "[0.5, 0.6, 0.1]")


def test_empty_model_select(tiny, tmp_path) -> None:
    proc = run(tmp_path, *fit(tiny, "--model.select", "[]"))
    assert_one_line_error(proc, "torchhys fit", "model.select is empty")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("how", ["flag", "environment"])
def test_traceback_on_request(tiny, tmp_path, how: str) -> None:
    args = fit(tiny, "--data.warmup", "-1")
    if how == "flag":
        proc = run(tmp_path, *args, "--traceback")
    else:
        proc = run(tmp_path, *args, env={"TORCHHYS_TRACEBACK": "1"})
    assert proc.returncode == 1
    assert "Traceback (most recent call last)" in proc.stderr
    assert "ValueError: warmup must be an int >= 0, got -1" in proc.stderr


# --- checkpoints ------------------------------------------------------------------------
def lightning_like(path: Path) -> Path:
    """A small checkpoint of Lightning's form (any torch.save'd dict is a zip archive)."""
    torch.save({"state_dict": {"net.w": torch.zeros(64, 64)}, "hyper_parameters": {},
                "epoch": 0}, path)
    return path


def corrupt(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / f"{kind}.ckpt"
    if kind == "truncated":
        whole = lightning_like(tmp_path / "whole.ckpt").read_bytes()
        path.write_bytes(whole[: len(whole) // 2])
    elif kind == "csv":
        path.write_text("command,response\n" + "".join(f"{i},{i}\n" for i in range(20)))
    else:
        path.write_text("a checkpoint would be here\n")
    return path


KINDS = {"truncated": "damaged or truncated", "csv": "not a PyTorch file",
         "text": "not a PyTorch file"}


@pytest.mark.parametrize("kind", list(KINDS))
def test_export_corrupt_checkpoint(tmp_path, kind: str) -> None:
    ckpt = corrupt(tmp_path, kind)
    proc = run(tmp_path, "export", "--ckpt", ckpt.name, "--format", "torchscript",
               "--out", "comp.pt")
    line = assert_one_line_error(proc, "torchhys export", f"--ckpt {ckpt.name}", KINDS[kind],
                                 "torchhys fit", "state dict")
    assert len(line) < 400
    assert not (tmp_path / "comp.pt").exists()


@pytest.mark.parametrize("kind", list(KINDS))
def test_test_corrupt_checkpoint(tiny, tmp_path, kind: str) -> None:
    ckpt = corrupt(tmp_path, kind)
    proc = run(tmp_path, "test", "--config", str(tiny), "--trainer.default_root_dir=run",
               "--ckpt_path", ckpt.name)
    assert_one_line_error(proc, "torchhys test", f"--ckpt_path {ckpt.name}", KINDS[kind],
                          "torchhys fit")
    assert not (tmp_path / "run").exists()


def test_resume_from_a_missing_checkpoint_writes_nothing(tiny, tmp_path) -> None:
    (tmp_path / "run").mkdir()
    proc = run(tmp_path, *fit(tiny, "--ckpt_path", "run/last.ckpt"))
    assert_one_line_error(proc, "torchhys fit", "--ckpt_path run/last.ckpt", "does not exist")
    assert not list((tmp_path / "run").iterdir())  # no logs/version_0/config.yaml


def test_read_checkpoint_kinds(tmp_path) -> None:
    """The checks of the one checkpoint reader (no process: quick)."""
    ckpt = read_checkpoint(lightning_like(tmp_path / "ok.ckpt"), "--ckpt_path")
    assert set(ckpt) == {"state_dict", "hyper_parameters", "epoch"}
    torch.save({"w": torch.ones(2)}, tmp_path / "plain.pt")
    assert read_checkpoint(tmp_path / "plain.pt", lightning=False)["w"].tolist() == [1.0, 1.0]
    with pytest.raises(CheckpointError, match=r"plain\.pt has no 'state_dict' \(keys: 'w'\)"):
        read_checkpoint(tmp_path / "plain.pt", "--ckpt_path")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(CheckpointError, match=r"list\.pt holds a list, not a dict"):
        read_checkpoint(tmp_path / "list.pt")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"empty\.ckpt is empty"):
        read_checkpoint(tmp_path / "empty.ckpt")
    with pytest.raises(CheckpointError, match=r"is not a file"):
        read_checkpoint(tmp_path)


# --- bugs keep their traceback ----------------------------------------------------------
@pytest.mark.parametrize("error", [IndexError, RuntimeError, KeyError, TypeError])
def test_a_bug_propagates(monkeypatch, tiny, tmp_path, error: type) -> None:
    """An unexpected exception inside training (here from the data module's setup, inside
    Trainer.fit) is not reported as a user error: it propagates with its traceback; a
    TypeError too, once the config is read."""
    def broken(self, stage=None) -> None:
        raise error("a bug")

    monkeypatch.setattr(HysteresisDataModule, "setup", broken)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    with pytest.raises(error, match="a bug"):
        main(["fit", "--config", str(tiny), f"--trainer.default_root_dir={tmp_path / 'run'}"])


def test_a_user_error_inside_training_keeps_its_message(monkeypatch, capsys, tiny,
                                                         tmp_path) -> None:
    """Lightning re-raises an error of Trainer.fit after its teardown: the line is the
    original message (in-process: SystemExit 2)."""
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "--config", str(tiny), f"--trainer.default_root_dir={tmp_path / 'run'}",
              f"--data.path={tmp_path / 'absent.csv'}"])
    assert exit_.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert re.fullmatch(r"torchhys fit: error: .*absent\.csv: no such file.*", last), last


def test_export_bug_propagates(monkeypatch, tmp_path) -> None:
    def broken(*args, **kwargs) -> None:
        raise RuntimeError("a bug in the exporter")

    monkeypatch.setattr("torchhys.cli.export.build_net", broken)
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    with pytest.raises(RuntimeError, match="a bug in the exporter"):
        export_main(["--ckpt", str(lightning_like(tmp_path / "m.ckpt")), "--format",
                     "torchscript", "--out", str(tmp_path / "m.pt")])


# --- model selection: each run its own folder -------------------------------------------
def test_concurrent_selections_keep_their_tables(tiny, tmp_path) -> None:
    """Two ``fit`` runs with ``model.select`` started at once into the same
    default_root_dir: each table in its own version folder, each printed path real, and
    each run's final fit logged beside its table."""
    base = {k: v for k, v in os.environ.items() if k != "TORCHHYS_TRACEBACK"}
    args = [sys.executable, "-m", "torchhys", *fit(
        tiny, "--model.select", "[{hidden: 1}, {hidden: 2}]")]
    procs = [subprocess.Popen(args, cwd=tmp_path, env={**base, "OMP_NUM_THREADS": "1"},
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    tables = []
    for proc, (out, err) in zip(procs, outs, strict=True):
        assert proc.returncode == 0, err[-3000:]
        (printed,) = re.findall(r"table written to (\S+)", out)
        table = tmp_path / printed
        assert table.is_file() and table.name == "selection.csv"
        assert table.parent.parent == tmp_path / "run/logs"
        assert (table.parent / "checkpoints/last.ckpt").is_file()
        assert (table.parent / "config.yaml").is_file()
        assert len(list((table.parent / "selection").glob("candidate_*"))) == 2
        tables.append(table)
    assert tables[0] != tables[1]
    assert {t.parent.name for t in tables} == {"version_0", "version_1"}
    assert sorted(p.name for p in (tmp_path / "run/logs").iterdir()) == ["version_0",
                                                                         "version_1"]

"""model.select_jobs (candidates in parallel processes) and model.select_budget_s (no
candidate starts once the budget is spent)."""

from __future__ import annotations

import csv
import os
import re
import signal
import time
from pathlib import Path

import pytest
import torch
from _training_helpers import DROP, LINE, cli, small_config

from torchhys.selection.jobs import run_candidates

CONFIG = {"trainer": {"max_epochs": 10, "check_val_every_n_epoch": DROP},
          "model": {**LINE, "init": "default", "lr": 1.0,
                    "select": [{"operator": None},
                               {"operator": [{"fit": "pi_nonneg", "n_widths": 6}]},
                               {"operator": [{"fit": "stop_pi", "n_widths": 8, "segments": 2}]}],
                    "select_cv": 2},
          "data": {"dt": 0.05, "t_end": 25.2}}
"""The sections of :func:`small_config`: the line and two operators, by 2-fold
cross-validation."""


def _table(monkeypatch, tmp_path: Path, name: str, *options: str) -> list[dict]:
    cfg = small_config(tmp_path, "c.yaml", **CONFIG)
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path / name}",
        *options)
    (table,) = (tmp_path / name).glob("logs/version_*/selection.csv")
    with table.open() as fh:
        return list(csv.DictReader(fh))


def test_jobs_give_the_table_of_one_process(monkeypatch, tmp_path) -> None:
    one = _table(monkeypatch, tmp_path, "one")
    two = _table(monkeypatch, tmp_path, "two", "--model.select_jobs=2")
    assert [r["candidate"] for r in two] == ["0", "1", "2"]
    for a, b in zip(one, two, strict=True):
        assert (a["val_mse"], a["selected"], a["error"]) == (b["val_mse"], b["selected"],
                                                             b["error"])


def test_budget_skips_the_candidates_not_started(monkeypatch, tmp_path, capsys) -> None:
    rows = _table(monkeypatch, tmp_path, "budget", "--model.select_budget_s=1e-9")
    assert rows[0]["val_mse"] != "nan" and rows[0]["selected"] == "1"
    for r in rows[1:]:
        assert r["val_mse"] == "nan"
        assert r["error"].startswith("skipped: model.select_budget_s=1e-09 spent")
    assert "skipped: model.select_budget_s" in capsys.readouterr().out


@pytest.mark.parametrize("option, match", [
    ("--model.select_jobs=0", "model.select_jobs must be a whole number >= 1"),
    ("--model.select_budget_s=-1", "model.select_budget_s must be a finite number of seconds"),
])
def test_bad_values(monkeypatch, tmp_path, option, match) -> None:
    cfg = small_config(tmp_path, "c.yaml", **CONFIG)
    with pytest.raises(ValueError, match=match):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}",
            option)
    assert not (tmp_path / "logs").exists()


def _slow(i: int) -> int:
    time.sleep(0.3)
    return i


def _slower(i: int) -> int:
    time.sleep(1.2)
    return i


def test_candidates_run_at_the_same_time_and_report_in_order() -> None:
    seen: list[int] = []
    began = time.perf_counter()
    out = run_candidates(4, _slow, lambda i: -i, report=seen.append, jobs=4)
    assert out == seen == [0, 1, 2, 3]
    assert time.perf_counter() - began < 1.0  # four 0.3 s jobs at once, not 1.2 s
    # a budget spent after the first two started: the third is skipped, in its place (the
    # budget leaves a forked worker time to start on a loaded machine)
    assert run_candidates(3, _slower, lambda i: -i, jobs=2, budget_s=0.6) == [0, 1, -2]


def test_auto_jobs_take_the_usable_cores(monkeypatch, tmp_path, capsys) -> None:
    """select_jobs: auto is the usable cores, at most AUTO_JOBS (one where processes cannot
    be forked), at most one per candidate; the command says what it chose; the table is that
    of one process, and each candidate's seconds are its own."""
    from torchhys.selection import jobs

    monkeypatch.setattr(jobs, "usable_cores", lambda: 16)
    assert jobs.check_jobs("auto") == jobs.AUTO_JOBS
    monkeypatch.setattr(jobs, "usable_cores", lambda: 2)
    assert jobs.check_jobs("auto") == 2
    monkeypatch.setattr(jobs, "_can_fork", lambda: False)
    assert jobs.check_jobs("auto") == 1
    monkeypatch.undo()
    one = _table(monkeypatch, tmp_path, "one")
    capsys.readouterr()
    monkeypatch.setattr("torchhys.cli.train.check_jobs", lambda value: 8)
    auto = _table(monkeypatch, tmp_path, "auto", "--model.select_jobs=auto")
    out, err = capsys.readouterr()
    assert "candidates in 3 processes at a time, torch threads 1 each (model.select_jobs=auto" \
        in err
    seconds = [float(m) for m in re.findall(r"^candidate \d \(\d of 3\): val_mse .*?, "
                                            r"([\d.]+) s: ", out, re.M)]
    assert len(seconds) == 3 and all(s > 0 for s in seconds)
    for a, b in zip(one, auto, strict=True):
        assert (a["val_mse"], a["selected"], a["error"]) == (b["val_mse"], b["selected"],
                                                             b["error"])


def _pid(i: int) -> tuple[int, int]:
    time.sleep(0.05)
    return i, os.getpid()


def test_neighbours_sharing_a_fit_run_in_one_process() -> None:
    """Consecutive candidates with the same key run one after another in one process (where
    they share their fit); the scores still come back in order."""
    from torchhys.selection.jobs import _groups
    from torchhys.selection.run import shared_key

    stops = {"fit": "stop_pi", "n_widths": 40}
    gpi = {"fit": "gpi", "direction": "inverse"}
    keys = [shared_key(c) for c in (
        {"operator": None}, {"operator": [gpi]}, {"operator": [{**gpi, "epochs": 200}]},
        {"operator": [stops]}, {"operator": [stops, {"fit": "drift"}]}, {"hidden": 4},
        {"operator": [{"fit": "gpi", "direction": "direct"}]})]
    assert keys[0] is None and keys[5] is None and keys[1] == keys[2] and keys[3] == keys[4]
    assert keys[1] != keys[6]
    assert _groups(7, keys) == [[0], [1, 2], [3, 4], [5], [6]]
    out = run_candidates(7, _pid, lambda i: (i, -1), jobs=3, together=keys)
    assert [i for i, _ in out] == list(range(7))
    pids = [p for _, p in out]
    assert pids[1] == pids[2] and pids[3] == pids[4] and os.getpid() not in pids
    # a budget spent inside a group skips its later members, in their places
    out = run_candidates(3, _pid, lambda i: (i, -1), jobs=2, budget_s=0.01,
                         together=["a", "a", "a"])
    assert [p for _, p in out][1:] == [-1, -1]


def _killed(i: int) -> int:
    if i == 1:
        os.kill(os.getpid(), signal.SIGKILL)  # as the kernel ends a process out of memory
    return i


def test_a_killed_process_is_a_one_line_error_not_a_hang() -> None:
    from torchhys.selection.jobs import SelectionJobError

    with pytest.raises(SelectionJobError, match=r"the process scoring candidate 1 ended "
                       r"without a result \(killed: out of memory\?\).*select_jobs=1"):
        run_candidates(3, _killed, lambda i: -i, jobs=2)


def test_auto_jobs_are_one_process_where_the_trainer_may_use_cuda(monkeypatch) -> None:
    """CUDA does not survive a fork: select_jobs auto is one process when the trainer's
    accelerator is not the CPU on a machine with CUDA."""
    from torchhys.cli.train import _on_gpu

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert _on_gpu({"accelerator": "gpu"}) and _on_gpu({"accelerator": "auto"})
    assert _on_gpu({}) and not _on_gpu({"accelerator": "cpu"})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert not _on_gpu({"accelerator": "gpu"})

"""Every wait of the command is bounded: a model selection candidate that does not finish
within ``TORCHHYS_TIMEOUT_S`` is a one-line error naming it, and its process is stopped
(nothing hangs); an FMU's compiler that does not finish is an error naming it."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _training_helpers import small_config

from torchhys.selection import jobs
from torchhys.selection.jobs import (
    DEFAULT_TIMEOUT_S,
    TIMEOUT_ENV,
    SelectionJobError,
    SelectionTimeoutError,
    run_candidates,
    wait_timeout,
)

ROOT = Path(__file__).resolve().parents[1]


def test_the_limit_is_read_from_the_environment(monkeypatch) -> None:
    monkeypatch.delenv(TIMEOUT_ENV, raising=False)
    assert wait_timeout() == DEFAULT_TIMEOUT_S
    for text, value in (("12.5", 12.5), ("none", None), (" NONE ", None), ("3600", 3600.0)):
        monkeypatch.setenv(TIMEOUT_ENV, text)
        assert wait_timeout() == value
    for text in ("abc", "0", "-1", "inf", "nan"):
        monkeypatch.setenv(TIMEOUT_ENV, text)
        with pytest.raises(ValueError, match=rf"^{TIMEOUT_ENV} must be a finite number of "
                                             rf"seconds > 0 .*got '{text}'$"):
            wait_timeout()


def _stuck(i: int) -> int:
    if i == 1:
        time.sleep(120)  # as a deadlocked process: far beyond the limit
    return i


def _pool_processes(before: set) -> list:
    return [p for p in multiprocessing.active_children() if p not in before and p.is_alive()]


def test_a_candidate_past_the_limit_is_a_one_line_error_and_stopped() -> None:
    before = set(multiprocessing.active_children())
    with pytest.raises(SelectionTimeoutError) as err:
        run_candidates(3, _stuck, lambda i: -i, jobs=2, timeout_s=0.5,
                       describe=lambda i: f'{{"hidden": {4 * i}}}')
    text = str(err.value)
    assert "\n" not in text and isinstance(err.value, SelectionJobError | ValueError)
    assert text.startswith('model selection: candidate 1 ({"hidden": 4}) did not finish '
                           'within 0.5 s in its process (model.select_jobs), which was '
                           f'stopped; allow more with {TIMEOUT_ENV}=SECONDS'), text
    assert _pool_processes(before) == []  # killed, not waited for


def test_a_group_sharing_a_process_has_its_candidates_limit_each() -> None:
    with pytest.raises(SelectionTimeoutError, match=r"^model selection: candidates 0-1 "
                       r"did not finish within 1 s \(0\.5 s each, in one process\)"):
        run_candidates(3, _stuck, lambda i: -i, jobs=2, timeout_s=0.5,
                       together=["a", "a", None])


def test_within_the_limit_the_scores_come_back_and_the_processes_end(monkeypatch) -> None:
    monkeypatch.setattr(jobs, "_EXIT_S", 5.0)
    before = set(multiprocessing.active_children())
    assert run_candidates(4, lambda i: i * i, lambda i: -i,
                          jobs=2, timeout_s=60) == [0, 1, 4, 9]
    assert _pool_processes(before) == []


def test_the_command_names_the_candidate_in_one_line(tmp_path: Path) -> None:
    """``torchhys fit`` with model selection in two processes and a limit no fit can meet:
    one line on stderr naming the candidate, status 2, no traceback."""
    cfg = small_config(tmp_path, "c.yaml", trainer={"max_epochs": 1}, data={"t_end": 3.0},
                       model={"select": [{}, {"hidden": 3}], "select_jobs": 2})
    base = {k: v for k, v in os.environ.items() if not k.startswith("TORCHHYS_")}
    proc = subprocess.run(
        [sys.executable, "-m", "torchhys", "fit", "--config", str(cfg), "--quiet",
         f"--trainer.default_root_dir={tmp_path / 'run'}"], cwd=ROOT,
        env={**base, "OMP_NUM_THREADS": "1", TIMEOUT_ENV: "0.001"}, capture_output=True,
        text=True, timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr[-3000:]
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert errors[0].startswith("torchhys fit: error: model selection: candidate 0 ({}) did "
                                "not finish within 0.001 s"), errors


def test_a_compiler_past_its_limit_is_named(monkeypatch) -> None:
    """An FMU's binary: a compiler that does not finish is an error naming it and the
    limit, not subprocess's traceback."""
    from torchhys.deploy import export_fmu

    def hang(cmd, **kwargs):
        raise subprocess.TimeoutExpired(cmd, kwargs["timeout"])

    monkeypatch.setattr(export_fmu.shutil, "which", lambda name: f"/usr/bin/{name}")
    monkeypatch.setattr(export_fmu.subprocess, "run", hang)
    with pytest.raises(RuntimeError, match=r"^the FMU's sources did not compile within "
                       r"600 s \(/usr/bin/cc\): the compiler was stopped$"):
        export_fmu._compile({"a.c": b"int x;"}, "comp", ".so")

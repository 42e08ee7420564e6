"""``torchhys fit`` under DDP on two CPU processes with the default config for recorded data
(``configs/measured.yaml``, ``model.select_jobs: auto``): it finishes (no fork from inside a
rank: the selection runs its candidates one after another, said in one line) and chooses as
one process does (~2.5 min: slow)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torchhys.cli.selection import distributed

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("trainer", "expected"), [
    ({"devices": 1, "strategy": "auto"}, False), ({"devices": "auto"}, False),
    ({"devices": 2}, True), ({"devices": 1, "strategy": "ddp"}, True),
    ({"devices": 1, "num_nodes": 2}, True), ({"devices": "auto", "strategy": "ddp"}, True),
])
def test_distributed_names_the_trainers_that_start_ranks(trainer: dict, expected: bool) -> None:
    assert distributed(trainer) is expected


def _fit(root: Path, *extra: str) -> tuple[subprocess.CompletedProcess, list[dict]]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("TORCHHYS_")}
    proc = subprocess.run(
        [sys.executable, "-m", "torchhys", "fit", "--config", "configs/measured.yaml",
         f"--trainer.default_root_dir={root}", "--trainer.enable_progress_bar=false", *extra],
        capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(next(root.glob("**/selection.csv"))) as fh:
        return proc, list(csv.DictReader(fh))


@pytest.mark.slow
def test_ddp_on_two_cpu_processes_finishes_with_one_process_choice(tmp_path: Path) -> None:
    proc, ddp = _fit(tmp_path / "ddp", "--trainer.strategy=ddp", "--trainer.devices=2",
                     "--trainer.accelerator=cpu")
    assert "model.select_jobs falls back to 1 under a distributed" in proc.stderr
    _, one = _fit(tmp_path / "one", "--model.select_jobs=1")
    chosen = [r["candidate"] for r in ddp if r["selected"] == "1"]
    assert len(chosen) == 1 and chosen == [r["candidate"] for r in one if r["selected"] == "1"]
    # a Lightning run per candidate under DDP, select's own fits in one process: the same
    # scores up to the solvers' rounding
    np.testing.assert_allclose([float(r["val_mse"]) for r in ddp],
                               [float(r["val_mse"]) for r in one], rtol=1e-5, equal_nan=True)

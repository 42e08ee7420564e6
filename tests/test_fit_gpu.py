"""``trainer.accelerator: gpu``: the default config for recorded data makes the same choice
on CUDA as on the CPU (float64: the chosen candidate's validation MSE within 1e-9
relative), and its fitted model gives the CPU fit's commands. Skipped without a GPU."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch

pytest.importorskip("lightning")
from _training_helpers import cli  # noqa: E402

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA device (trainer.accelerator: gpu needs one)")

ROOT = Path(__file__).resolve().parents[1]


def _fit(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, accelerator: str) -> list[dict]:
    root = tmp_path / accelerator
    cli(monkeypatch, "fit", "--config", "configs/measured.yaml",
        f"--trainer.accelerator={accelerator}", f"--trainer.default_root_dir={root}",
        "--trainer.enable_progress_bar=false")
    (table,) = root.glob("logs/version_*/selection.csv")
    with table.open() as fh:
        return list(csv.DictReader(fh))


def test_gpu_fit_makes_the_cpu_choice(monkeypatch, tmp_path) -> None:
    cpu = _fit(monkeypatch, tmp_path, "cpu")
    gpu = _fit(monkeypatch, tmp_path, "gpu")
    chosen = [r["candidate"] for r in cpu if r["selected"] == "1"]
    assert chosen == [r["candidate"] for r in gpu if r["selected"] == "1"]
    for a, b in zip(cpu, gpu, strict=True):
        va, vb = float(a["val_mse"]), float(b["val_mse"])
        assert (math.isnan(va) and math.isnan(vb)) or math.isclose(va, vb, rel_tol=1e-9), (
            a["candidate"], va, vb)
    ckpts = {acc: next((tmp_path / acc).glob("logs/version_*/checkpoints/last.ckpt"))
             for acc in ("cpu", "gpu")}
    from torchhys.training.module import InverseHysteresisModule

    x = torch.linspace(-1.0, 1.0, 500, dtype=torch.float64)[None]
    outs = []
    for acc in ("cpu", "gpu"):
        module = InverseHysteresisModule.load_from_checkpoint(ckpts[acc], map_location="cpu")
        with torch.no_grad():
            outs.append(module.double()(x))
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-9, atol=1e-12)

"""``torchhys fit`` with a user's module in the config (``model.net: {class_path:
torchhys.compose.Composed, init_args: {module: {class_path: ..., init_args: ...}}}``, its
package found through ``--import-path``/``--import``) trains it, saves its spec in the
checkpoint, and ``torchhys export --import`` rebuilds it: the TorchScript file's and the C
file's commands equal the module's output (float64, 1e-12)."""

from __future__ import annotations

import csv
import importlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import CC, NO_CC, compile_harness, run_c
from _training_helpers import DROP, small_config

from torchhys.checkpoints import read_checkpoint
from torchhys.compose import Composed
from torchhys.compose.spec import build_composed
from torchhys.training import HysteresisDataModule

USER_MODULE = '''
"""A user's model: plays of the input, a GRU on [x, plays] and a linear readout."""
import torch
from torch import nn

import torchhys


class BacklashGRU(nn.Module):
    def __init__(self, hidden: int = 8, widths: list[float] = [0.1, 0.4]) -> None:
        super().__init__()
        self.bl = torchhys.Backlash(torch.tensor(widths))
        self.gru = nn.GRU(1 + len(widths), hidden, batch_first=True)
        self.lin = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.cat([x.unsqueeze(-1), self.bl(x)[0]], -1)
        h, _ = self.gru(f)
        return self.lin(h).squeeze(-1)
'''

NAME = "user_composed_models"

MODEL = {"net": {"class_path": "torchhys.compose.Composed",
                 "init_args": {"module": {"class_path": f"{NAME}.BacklashGRU",
                                          "init_args": {"hidden": 6}}}},
         "operator": DROP, "operator_kwargs": DROP, "hidden": DROP,
         "optimizer": "adam", "lr": 0.05, "optimizer_kwargs": DROP}

RAW = ["--direction", "none", "--input-margin", "none"]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONSAFEPATH": "1"}
    for key in ("TORCHHYS_IMPORT", "TORCHHYS_IMPORT_PATH", "PYTHONPATH"):
        env.pop(key, None)
    return subprocess.run([sys.executable, "-m", "torchhys", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600, env=env)


@pytest.mark.slow
def test_fit_a_composed_module_from_the_config_and_export_it(tmp_path: Path,
                                                            monkeypatch) -> None:
    (tmp_path / f"{NAME}.py").write_text(USER_MODULE)
    small_config(tmp_path, "c.yaml", trainer={"max_epochs": 15}, model=MODEL)
    imports = ["--import-path", ".", "--import", NAME]
    fit = _run(["fit", *imports, "--config", "c.yaml", "--trainer.default_root_dir=run"],
               tmp_path)
    assert fit.returncode == 0, fit.stderr[-3000:]
    logs = tmp_path / "run/logs/version_0"
    with (logs / "metrics.csv").open() as fh:
        losses = [float(r["train_loss"]) for r in csv.DictReader(fh) if r.get("train_loss")]
    assert losses[-1] < 0.5 * losses[0], losses
    ckpt = logs / "checkpoints/last.ckpt"
    saved = read_checkpoint(ckpt)
    assert saved["hyper_parameters"]["net"]["init_args"]["module"] == {
        "class_path": f"{NAME}.BacklashGRU", "init_args": {"hidden": 6, "widths": [0.1, 0.4]}}
    # without the user's module the export names the --import to give
    bare = _run(["export", "--ckpt", str(ckpt), "--format", "torchscript", "--out", "x.pt"],
                tmp_path)
    assert bare.returncode == 2 and f"give --import {NAME}" in bare.stderr
    ts = _run(["export", *imports, "--ckpt", str(ckpt), "--format", "torchscript",
               "--out", "comp.pt", *RAW], tmp_path)
    assert ts.returncode == 0, ts.stderr[-3000:]
    # the reference: the trained module, rebuilt here from the checkpoint's spec and weights
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.import_module(NAME)
    state = {k[4:]: v for k, v in saved["state_dict"].items() if k.startswith("net.")}
    model = build_composed(saved["hyper_parameters"]["net"], state)
    assert isinstance(model, Composed) and model.in_min.dtype == torch.float64
    dm = HysteresisDataModule(simulation="paper", t_end=6.3, split=[0.6, 0.2, 0.2])
    dm.setup("fit")
    x = dm.train_tensors()[0].double()[0]
    assert float(model.in_min) == float(x.min()) and float(model.in_max) == float(x.max())
    with torch.no_grad():
        expected = model(x[None])[0].clamp(float(model.out_min), float(model.out_max))
    scripted = torch.jit.load(str(tmp_path / "comp.pt"))
    with torch.no_grad():
        torch.testing.assert_close(scripted(x), expected, rtol=0, atol=1e-12)
    if CC is None:
        pytest.skip(NO_CC)
    (tmp_path / "c").mkdir()
    c = _run(["export", *imports, "--ckpt", str(ckpt), "--format", "c", "--out", "c", *RAW],
             tmp_path)
    assert c.returncode == 0, c.stderr[-3000:]
    got = run_c(compile_harness(tmp_path / "c"), x.numpy())
    np.testing.assert_allclose(got["u"], expected.numpy(), rtol=0, atol=1e-12)

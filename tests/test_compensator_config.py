"""``configs/compensator.yaml``, the recommended compensator: its structure, a short fit on a
simulated record, TorchScript export, and the ``torchhys`` command on the shipped example."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch
import yaml
from _helpers import RAW
from _training_helpers import trainer
from torch import nn

from torchhys import EIHO, Backlash
from torchhys.cli.export import main as export_main
from torchhys.cli.main import main
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "compensator.yaml"


@pytest.fixture(scope="module")
def config() -> dict:
    with CONFIG.open() as fh:
        return yaml.safe_load(fh)


def test_config_is_the_documented_network(config: dict) -> None:
    module = InverseHysteresisModule(**config["model"])
    net = module.net
    eiho, plays = net.operators
    assert isinstance(eiho, EIHO) and eiho.causal
    assert (eiho.rule, eiho.output) == ("recent", "branch")
    assert isinstance(plays, Backlash) and plays.n_operators == 16
    assert net.hidden.out_features == 64 and isinstance(net.activation, nn.Sigmoid)
    assert module.optimizer_name == "lbfgs"
    assert config["data"]["path"] == "examples/data/bouc_wen.csv"
    assert (ROOT / config["data"]["path"]).is_file()


def test_fit_and_export(config: dict, tmp_path: Path) -> None:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    dm = HysteresisDataModule(simulation="paper", t_end=2 * math.pi, split=[0.7, 0.15, 0.15])
    module = InverseHysteresisModule(**config["model"])
    tr = trainer(max_epochs=2)
    tr.fit(module, dm)
    assert math.isfinite(float(tr.callback_metrics["train_loss"]))
    # the play widths were fitted on the training split: 0.4 span(x) k / 16, k = 1..16
    x_train, _ = dm.train_tensors()
    span = float(x_train.max() - x_train.min())
    widths = module.net.operators[1].get_widths().detach()
    expected = 0.4 * span * torch.arange(1, 17, dtype=widths.dtype) / 16
    torch.testing.assert_close(widths, expected)

    net = module.net.eval()
    limits = (-1e3, 1e3)  # wide: compare the network itself, not the saturation
    scripted = to_torchscript(net, tmp_path / "compensator.pt", limits=limits, **RAW)
    loaded = load_torchscript(tmp_path / "compensator.pt")
    x = dm.x.to(net.hidden.weight.dtype)
    with torch.no_grad():
        eager, _ = net(x)
    torch.testing.assert_close(scripted(x), eager, rtol=0, atol=1e-6)
    torch.testing.assert_close(loaded(x), eager, rtol=0, atol=1e-6)


def test_cli_runs_out_of_the_box(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.chdir(ROOT)  # the config names the example file relative to the repository
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    torch.set_num_threads(1)
    root = tmp_path / "compensator"
    main(["fit", "--config", "configs/compensator.yaml", f"--trainer.default_root_dir={root}",
          "--trainer.max_epochs=1", "--trainer.enable_progress_bar=false"])
    ckpt = root / "logs/version_0/checkpoints/last.ckpt"
    assert ckpt.is_file()
    out = tmp_path / "compensator.pt"
    assert export_main(["--ckpt", str(ckpt), "--format", "torchscript", "--out", str(out)]) == 0
    comp = load_torchscript(out)
    y = comp(torch.linspace(-2.0, 2.0, 50, dtype=torch.float64))
    assert y.shape == (50,) and bool(torch.isfinite(y).all())

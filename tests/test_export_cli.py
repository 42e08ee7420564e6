"""``torchhys export`` (torchhys/cli/export.py): checkpoints to compensator files."""

from __future__ import annotations

import json

import pytest
import torch

from torchhys import InverseHysteresisNet
from torchhys.cli.export import main
from torchhys.deploy.export import load_torchscript
from torchhys.deploy.streaming import StreamingCompensator

OPERATOR_KWARGS = {"a": 1.3, "rule": "dominant", "threshold": 0.1}


def trained() -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", 8, operator_kwargs=OPERATOR_KWARGS)
    x = 3 * torch.sin(torch.linspace(0, 20, 400))
    net.fit_normalization(x, 0.5 * x)
    return net


def lightning_ckpt(net: InverseHysteresisNet) -> dict:
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    state["normalization_fitted"] = torch.tensor(True)
    hp = {"operator": "eiho", "hidden": 8, "activation": "sigmoid",
          "operator_kwargs": OPERATOR_KWARGS, "optimizer": "cg"}
    return {"state_dict": state, "hyper_parameters": hp, "epoch": 3}


def test_lightning_checkpoint_to_torchscript(tmp_path, capsys) -> None:
    net = trained()
    torch.save(lightning_ckpt(net), tmp_path / "m.ckpt")
    out = tmp_path / "m.pt"
    rc = main(["--ckpt", str(tmp_path / "m.ckpt"), "--format", "torchscript", "--out", str(out),
               "--limits", "-2", "2"])
    assert rc == 0 and "wrote" in capsys.readouterr().out
    y = 2 * torch.sin(torch.linspace(0, 30, 500))
    expected = StreamingCompensator(net, limits=(-2.0, 2.0))(y)
    torch.testing.assert_close(load_torchscript(out)(y), expected, rtol=0, atol=1e-6)


def test_lightning_checkpoint_to_onnx(tmp_path, capsys) -> None:
    pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx

    net = trained().double()
    torch.save(lightning_ckpt(net), tmp_path / "m.ckpt")
    out = tmp_path / "m.onnx"
    rc = main(["--ckpt", str(tmp_path / "m.ckpt"), "--format", "onnx", "--out", str(out),
               "--limits", "-2", "2"])
    assert rc == 0 and "wrote" in capsys.readouterr().out
    y = 2 * torch.sin(torch.linspace(0, 30, 300, dtype=torch.float64))
    expected = StreamingCompensator(net, limits=(-2.0, 2.0))(y)
    stepper = load_onnx(out)
    got = torch.stack([torch.as_tensor(stepper.step(v.reshape(1)))[0] for v in y])
    torch.testing.assert_close(got.double(), expected, rtol=0, atol=1e-12)


def test_plain_state_dict_with_architecture(tmp_path) -> None:
    net = trained()
    torch.save(net.state_dict(), tmp_path / "sd.pt")
    out = tmp_path / "m.pt"
    rc = main(["--ckpt", str(tmp_path / "sd.pt"), "--format", "torchscript", "--out", str(out),
               "--hidden", "8", "--operator", "eiho",
               "--operator-kwargs", json.dumps(OPERATOR_KWARGS)])
    assert rc == 0
    m = load_torchscript(out)
    low, high = float(m.low), float(m.high)  # default: the training output range
    assert low < -1.5 * 0.99 and high > 1.5 * 0.99


@pytest.mark.parametrize("extra, message", [
    ([], "--hidden"),
    (["--hidden", "8", "--limits", "1", "-1"], "limits"),
    (["--hidden", "5"], "size mismatch"),
])
def test_errors_are_reported(tmp_path, capsys, extra: list[str], message: str) -> None:
    torch.save(trained().state_dict(), tmp_path / "sd.pt")
    rc = main(["--ckpt", str(tmp_path / "sd.pt"), "--format", "torchscript",
               "--out", str(tmp_path / "m.pt"), "--operator-kwargs",
               json.dumps(OPERATOR_KWARGS), *extra])
    assert rc == 2
    assert message in capsys.readouterr().err


def test_missing_file_and_bad_format(tmp_path, capsys) -> None:
    assert main(["--ckpt", str(tmp_path / "none.ckpt"), "--format", "torchscript",
                 "--out", str(tmp_path / "m.pt")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--ckpt", "x", "--format", "tflite", "--out", "y"])

"""A Composed survives its checkpoint: rebuilt from its spec by
:func:`torchhys.compose.spec.build_composed` (the user's class from a module imported
already, an ``nn.Module``), and restored by ``InverseHysteresisModule.load_from_checkpoint``
with the net passed again; refusals are one line naming what to give."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from _training_helpers import trainer
from test_compose_training import BacklashGRU, inverse_data

from torchhys.compose import compose
from torchhys.compose.spec import build_composed, is_composed_spec
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

SPEC = {"class_path": "torchhys.compose.Composed",
        "init_args": {"module": {"class_path": "test_compose_training.BacklashGRU",
                                 "init_args": {"hidden": 5}}, "x": None, "y": None}}


def _trained() -> torch.nn.Module:
    torch.manual_seed(0)
    x, y = inverse_data(60)
    model = compose(BacklashGRU(5).double(), x=x, y=y)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model


def test_build_composed_restores_the_weights_and_ranges() -> None:
    model = _trained()
    rebuilt = build_composed(SPEC, model.state_dict())
    x, _ = inverse_data(60)
    with torch.no_grad():
        assert torch.equal(rebuilt(x), model(x))
    for k in ("in_min", "in_max", "out_min", "out_max", "trend"):
        assert torch.equal(getattr(rebuilt, k), getattr(model, k))
    assert is_composed_spec(SPEC) and not is_composed_spec({"class_path": "x.Y"})


@pytest.mark.parametrize("path, message", [
    ("no_such_pkg.Model", r"net.module is no_such_pkg.Model: give --import no_such_pkg "),
    ("os.system", r"net.module is os.system: expected an nn.Module class of the imported "
                  r"module os, found builtin_function_or_method$"),
    ("Model", r"net.module: class_path must be 'module.Class', got 'Model'$"),
])
def test_a_spec_names_what_it_cannot_build(path: str, message: str) -> None:
    spec = {**SPEC, "init_args": {"module": {"class_path": path}}}
    with pytest.raises(ValueError, match=rf"^{message}"):
        build_composed(spec, {})


def test_a_spec_of_other_weights_or_arguments_is_refused() -> None:
    state = _trained().state_dict()
    wrong = {**SPEC, "init_args": {"module": {"class_path": "test_compose_training.BacklashGRU",
                                              "init_args": {"hidden": 7}}}}
    with pytest.raises(ValueError, match=r"^net: the weights do not fit the module "
                                         r"test_compose_training.BacklashGRU: "):
        build_composed(wrong, state)
    bad = {**SPEC, "init_args": {"module": {"class_path": "test_compose_training.BacklashGRU",
                                            "init_args": {"units": 7}}}}
    with pytest.raises(ValueError, match=r"^net.module \(test_compose_training.BacklashGRU\) "
                                         r"cannot be built from its init_args \['units'\]"):
        build_composed(bad, state)
    with pytest.raises(ValueError, match=r"^net: expected the spec of "
                                         r"torchhys.compose.Composed, got 'torch.nn.GRU'$"):
        build_composed({"class_path": "torch.nn.GRU"}, state)


def test_load_from_checkpoint_restores_a_composed_net(tmp_path: Path) -> None:
    torch.manual_seed(0)
    dm = HysteresisDataModule(simulation="paper", t_end=3.0, split=[0.6, 0.2, 0.2])
    module = InverseHysteresisModule(net=compose(BacklashGRU(4).double()), optimizer="adam")
    fit = trainer(max_epochs=2)
    fit.fit(module, datamodule=dm)
    fit.save_checkpoint(tmp_path / "m.ckpt")
    restored = InverseHysteresisModule.load_from_checkpoint(
        tmp_path / "m.ckpt", net=compose(BacklashGRU(4).double()))
    for (k, a), (k2, b) in zip(module.state_dict().items(), restored.state_dict().items(),
                               strict=True):
        assert k == k2 and torch.equal(a, b), k
    assert bool(restored.normalization_fitted)
    # without a spec (built in Python) torchhys export says how to export it instead
    from torchhys.cli.export import build_net

    saved = torch.load(tmp_path / "m.ckpt", weights_only=True)
    assert saved["hyper_parameters"]["net"] is None
    with pytest.raises(ValueError, match=r"^the checkpoint's model \(a sequence model\) was "
                                         r"passed in built, .* export it from Python"):
        build_net(saved)


def test_export_refuses_a_composed_model_whose_output_is_not_finite(tmp_path: Path,
                                                                     capsys) -> None:
    """Finite float64 weights near 1e308 (a fit stopped as it diverged): the composed model's
    output across its recorded input range is infinite; ``torchhys export`` refuses it in
    one line, as it refuses such a network, and writes nothing."""
    from torchhys.cli.export import main

    model = _trained()
    x, _ = inverse_data(60)
    with torch.no_grad():  # the readout's terms all of one sign: its sum overflows
        f = torch.cat([x.unsqueeze(-1), model.module.bl(x)[0]], -1)
        h = model.module.gru(f)[0]
        model.module.lin.weight.copy_(1e308 * h.mean((0, 1)).sign()[None])
        model.module.lin.bias.fill_(1.7e308)
        assert not model(x).isfinite().all()
    ckpt = {"state_dict": {f"net.{k}": v for k, v in model.state_dict().items()},
            "hyper_parameters": {"net": SPEC}}
    torch.save(ckpt, tmp_path / "big.ckpt")
    out = tmp_path / "m.pt"
    assert main(["--ckpt", str(tmp_path / "big.ckpt"), "--format", "torchscript", "--out",
                 str(out), "--import", "test_compose_training"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert re.search(r"^torchhys export: error: --ckpt .*big\.ckpt: the model's output is not "
                     r"finite at \d+ of 128 inputs across its training input range \(weights "
                     r"up to 1.7e\+308", err), err
    assert not out.exists()

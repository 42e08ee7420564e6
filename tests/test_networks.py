"""InverseHysteresisNet: shapes, normalization in physical units, batches, expanded inputs."""

from __future__ import annotations

import pytest
import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet
from torchhys.identification.fitting import fit_full_batch


def data() -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.linspace(0, 12, 300, dtype=torch.float64)
    x = 100.0 * torch.sin(t) + 50.0  # physical units far from 0 / 1
    return x, 1e-3 * x + 1e-4 * torch.cos(t)


@pytest.mark.parametrize("operator", ["eiho", "zhao_tan", None])
def test_shapes(operator: str | None) -> None:
    net = InverseHysteresisNet(operator, hidden=5).double()
    x, y = data()
    net.fit_normalization(x, y)
    out, state = net(x)
    assert out.shape == x.shape and len(state) == (0 if operator is None else 1)
    out2, _ = net(torch.stack([x, x.flip(0)]))
    assert out2.shape == (2, x.shape[0])
    torch.testing.assert_close(out2[0], out)  # batch consistency


def test_normalization_buffers_hold_physical_scales() -> None:
    net = InverseHysteresisNet("eiho", hidden=5).double()
    x, y = data()
    net.fit_normalization(x, y)
    assert abs(float(net.in_mean[0]) - float(x.mean())) < 1e-9
    assert abs(float(net.out_std) - float(y.std())) < 1e-12
    buffers = dict(net.named_buffers())
    assert {"in_mean", "in_std", "out_mean", "out_std"} <= set(buffers)


def test_fits_in_physical_units() -> None:
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", hidden=8).double()
    x, y = data()
    result = fit_full_batch(net, x, y, adam_epochs=100, lbfgs_epochs=50)
    assert result.mse < 1e-2 * float(y.var())


def test_expanded_input_space_with_plays() -> None:
    ops = [EIHO(a=0.5), EIHO(a=2.0, rule="dominant"), Backlash(torch.tensor([1.0, 5.0]))]
    net = InverseHysteresisNet(ops, hidden=6, activation="gelu").double()
    assert net.hidden.in_features == 1 + 1 + 1 + 2
    x, y = data()
    net.fit_normalization(x, y)
    feats, states = net.features(x)
    assert feats.shape == (1, x.shape[0], 5) and len(states) == 3


def test_learnable_operator_trains_jointly() -> None:
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", hidden=6, operator_kwargs={"a": "learnable"}).double()
    before = float(net.operators[0].coef.log_a.detach())
    x, y = data()
    fit_full_batch(net, x, y, adam_epochs=30, lbfgs_epochs=0)
    assert float(net.operators[0].coef.log_a.detach()) != before

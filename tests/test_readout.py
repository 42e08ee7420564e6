"""Model selection's affine readout solved by least squares (torchhys.training.readout)
scores a candidate as the Trainer's L-BFGS training of it does."""

from __future__ import annotations

import math

import pytest
import torch
from _training_helpers import trainer

from torchhys.training import HysteresisDataModule, InverseHysteresisModule
from torchhys.training.folds import BlockFold
from torchhys.training.readout import direct_validation, solvable

DATA = {"dt": 0.05, "t_end": 25.2, "split": [0.7, 0.15, 0.15], "warmup": 20}
LBFGS = {"hidden": 1, "activation": "identity", "init": "default", "optimizer": "lbfgs",
         "lr": 1.0, "optimizer_kwargs": {"max_iter": 20, "tolerance_grad": 1e-12,
                                         "tolerance_change": 1e-15}}


def module(operator) -> InverseHysteresisModule:
    torch.manual_seed(0)
    return InverseHysteresisModule(operator=operator, **LBFGS)


@pytest.mark.parametrize("operator", [
    None,
    [{"fit": "stop_pi", "n_widths": 8, "segments": 2}],
    [{"fit": "stop_pi", "n_widths": 8, "segments": 2}, {"fit": "drift"}],
])
@pytest.mark.parametrize("fold", [0, 2])
def test_direct_readout_scores_as_the_trained_one(operator, fold) -> None:
    dm = HysteresisDataModule(**DATA)
    run = trainer(max_epochs=10, limit_val_batches=1.0)
    direct = module(operator)
    assert solvable(direct, BlockFold(dm, 4, fold), run)
    mse, errors = direct_validation(direct, BlockFold(dm, 4, fold), run)
    trained, data = module(operator), BlockFold(dm, 4, fold)
    run.fit(trained, datamodule=data)
    (result,) = run.validate(trained, datamodule=data, verbose=False)
    assert errors.numel() == data.n_val and math.isclose(float(errors.mean()), mse)
    # L-BFGS reaches the least-squares solution of the readout, whose MSE is the least
    assert mse == pytest.approx(result["val_mse"], rel=1e-6)
    x, y, _, held = data._val
    with torch.no_grad():
        both = (direct(x) - trained(x))[held]
    assert float(both.abs().max()) < 1e-5 * float(y[held].std())


def test_not_solvable_where_the_readout_is_not_affine() -> None:
    dm = HysteresisDataModule(**DATA)
    fold, run = BlockFold(dm, 4, 0), trainer(max_epochs=10)
    assert not solvable(InverseHysteresisModule(operator=None, **{**LBFGS,
                                                                  "activation": "sigmoid"}),
                        fold, run)
    assert not solvable(InverseHysteresisModule(operator=None, **{**LBFGS, "optimizer": "adam",
                                                                  "lr": 1e-2,
                                                                  "optimizer_kwargs": {}}),
                        fold, run)
    learnable = [{"fit": "pi_ls", "n_widths": 4, "learnable": True}]  # trainable operators
    assert not solvable(InverseHysteresisModule(operator=learnable, **LBFGS), fold, run)


def test_least_squares_output_is_numpys_ridge_fit_and_keeps_the_hidden_layer() -> None:
    """The output layer over the hidden activations: numpy's least squares of the ridge's
    stacked system ``[A; sqrt(ridge) I] w = [t; 0]`` in float64, on every row of a batch."""
    import numpy as np

    from torchhys import Backlash, InverseHysteresisNet
    from torchhys.init import least_squares_output

    torch.manual_seed(0)
    t = torch.linspace(0, 12, 300, dtype=torch.float64)
    x = torch.stack([torch.sin(t) * (1 + 0.1 * t), 0.8 * torch.sin(1.3 * t)])
    y = x + 0.2 * torch.cos(t)
    net = InverseHysteresisNet([Backlash([0.2, 0.5])], hidden=6, activation="tanh").double()
    net.fit_normalization(x, y)
    hidden = net.hidden.weight.detach().clone()
    ridge = 1e-3
    least_squares_output(net, x, y, ridge=ridge)
    f, _ = net.features(x)
    z = ((f - net.in_mean) / net.in_std).reshape(-1, f.shape[-1]).detach().numpy()
    h = np.tanh(z @ hidden.numpy().T + net.hidden.bias.detach().numpy())
    a = np.hstack([h, np.ones((h.shape[0], 1))])
    target = ((y - net.out_mean) / net.out_std).reshape(-1).detach().numpy()
    stacked = np.vstack([a, math.sqrt(ridge) * np.eye(a.shape[1])])
    want = np.linalg.lstsq(stacked, np.concatenate([target, np.zeros(a.shape[1])]),
                           rcond=None)[0]
    got = torch.cat([net.output.weight[0], net.output.bias]).detach().numpy()
    assert np.allclose(got, want, rtol=1e-9, atol=1e-11)
    assert torch.equal(net.hidden.weight, hidden)
    with pytest.raises(ValueError, match=r"y must have the shape of x \(2, 300\)"):
        least_squares_output(net, x, y[:1])
    with pytest.raises(ValueError, match="ridge must be a finite number >= 0, got -1"):
        least_squares_output(net, x, y, ridge=-1)

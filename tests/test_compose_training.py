"""A user's module, composed, trains through ``fit_full_batch`` as a
:class:`~torchhys.protocols.SequenceModel`: its ranges are recorded from the training data
(over the mask), its output is fitted end to end, and the trained model streams through the
StreamingCompensator with commands equal to the module's output (float64, 1e-12)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

import torchhys
from torchhys.compose import compose
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.identification.fitting import fit_full_batch
from torchhys.plants import bouc_wen
from torchhys.protocols import SequenceModel, check_sequence_model


class BacklashGRU(nn.Module):
    """A user's model: two plays, a GRU on [x, plays] and a linear readout."""

    def __init__(self, hidden: int = 8) -> None:
        super().__init__()
        self.bl = torchhys.Backlash(torch.tensor([0.1, 0.4]))
        self.gru = nn.GRU(3, hidden, batch_first=True)
        self.lin = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.cat([x.unsqueeze(-1), self.bl(x)[0]], -1)
        h, _ = self.gru(f)
        return self.lin(h).squeeze(-1)


def inverse_data(T: int = 300) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverse problem of a simulated Bouc-Wen plant: x = the plant's output, y = its
    input (a decaying two-tone command), (2, T) float64."""
    t = torch.linspace(0.0, 12.0, T, dtype=torch.float64)
    u = torch.stack([torch.sin(t) * torch.exp(-0.1 * t),
                     0.7 * torch.sin(1.7 * t) + 0.2 * torch.sin(0.5 * t)])
    return bouc_wen(u, t), u


def _mse(model: nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    with torch.no_grad():
        return float((model(x) - y).square().mean())


def _ranges(model: nn.Module) -> list[float]:
    return [float(getattr(model, k)) for k in ("in_min", "in_max", "out_min", "out_max")]


def test_a_composed_module_is_a_sequence_model() -> None:
    model = compose(BacklashGRU().double())
    assert isinstance(model, SequenceModel)
    assert check_sequence_model(model) is model
    with pytest.raises(TypeError, match=r"^model must be .*SequenceModel.* it has no "
                                         r"record_ranges$"):
        check_sequence_model(BacklashGRU())


@pytest.mark.parametrize("adam, lbfgs", [(60, 0), (0, 40)])
def test_fit_full_batch_trains_and_streams_a_composed_module(adam: int, lbfgs: int) -> None:
    torch.manual_seed(0)
    x, y = inverse_data()
    model = compose(BacklashGRU().double())
    assert all(math.isnan(v) for v in _ranges(model))  # composed without data: none yet
    before = _mse(model, x, y)
    result = fit_full_batch(model, x, y, adam_epochs=adam, lbfgs_epochs=lbfgs, lr=5e-2)
    after = _mse(model, x, y)
    assert result.mse == pytest.approx(after, rel=1e-12)
    assert after < 0.02 * before, (before, after)  # measured: 0.27 -> 1e-3 (both)
    # the ranges are the training data's
    assert _ranges(model) == [float(x.min()), float(x.max()), float(y.min()), float(y.max())]
    xc, yc = x.flatten() - x.mean(), y.flatten() - y.mean()
    assert float(model.trend) == pytest.approx(float(xc @ yc / (xc.norm() * yc.norm())),
                                               abs=1e-12)
    model.check()  # the trained weights still stream node by node
    comp = StreamingCompensator(model, direction="none")  # limits and clamp from the ranges
    assert (float(comp.low), float(comp.high)) == (float(y.min()), float(y.max()))
    with torch.no_grad():
        expected = model(x).clamp(float(comp.low), float(comp.high))
        steps = torch.stack([comp.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(steps, expected, rtol=0, atol=1e-12)


def test_the_ranges_and_the_loss_take_the_mask_and_warmup() -> None:
    torch.manual_seed(1)
    x, y = inverse_data(120)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[1, 60:] = False  # a held-out block: neither in the ranges nor in the loss
    model = compose(BacklashGRU(4).double())
    result = fit_full_batch(model, x, y, adam_epochs=3, lbfgs_epochs=0, mask=mask, warmup=5)
    fitted = mask.clone()
    fitted[:, :5] = False
    assert _ranges(model) == [float(x[fitted].min()), float(x[fitted].max()),
                              float(y[fitted].min()), float(y[fitted].max())]
    with torch.no_grad():
        reference = float((model(x) - y)[fitted].square().mean())
    assert result.mse == pytest.approx(reference, rel=1e-12)


def test_a_plain_module_is_refused_with_what_to_do() -> None:
    x, y = inverse_data(50)
    with pytest.raises(TypeError, match=r"^model must be an InverseHysteresisNet, a "
                                        r"torchhys.HysteresisOperator or a .*SequenceModel "
                                        r"\(a user's module through torchhys.compose.compose\), "
                                        r"got BacklashGRU$"):
        fit_full_batch(BacklashGRU().double(), x, y, adam_epochs=1, lbfgs_epochs=0)


def test_a_sequence_model_of_the_wrong_output_shape_is_named() -> None:
    class Wide(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.lin = nn.Linear(1, 2)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return self.lin(x.unsqueeze(-1))

    class Ranged(Wide):
        def record_ranges(self, x, y, *, mask=None) -> None:
            pass

    x, y = inverse_data(50)
    with pytest.raises(ValueError, match=r"^model Ranged must map x \(batch, time\) to y "
                                         r"\(batch, time\): its output for x \(2, 50\) is "
                                         r"\(2, 50, 2\)$"):
        fit_full_batch(Ranged().double(), x, y, adam_epochs=1, lbfgs_epochs=0)

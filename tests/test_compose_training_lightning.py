"""A user's module, composed, trains through the Lightning module
(``InverseHysteresisModule(net=composed)``): its ranges are recorded from the datamodule's
training part in ``setup``, the loss falls (Adam and L-BFGS), and the trained model streams
with commands equal to its output."""

from __future__ import annotations

import pytest
import torch
from _training_helpers import trainer
from lightning.pytorch.callbacks import Callback
from test_compose_training import BacklashGRU

from torchhys.compose import Composed, compose
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.training import HysteresisDataModule, InverseHysteresisModule


class Losses(Callback):
    """The logged train_loss of every epoch."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def on_train_epoch_end(self, trainer, module) -> None:  # noqa: ANN001 (Lightning's)
        self.values.append(float(trainer.callback_metrics["train_loss"]))


@pytest.mark.parametrize("optimizer, lr, epochs", [("adam", 0.05, 12), ("lbfgs", 1.0, 3)])
def test_the_lightning_module_trains_a_composed_module(optimizer: str, lr: float,
                                                       epochs: int) -> None:
    torch.manual_seed(0)
    dm = HysteresisDataModule(simulation="paper", t_end=6.3, split=[0.6, 0.2, 0.2])
    net = compose(BacklashGRU(6).double())
    module = InverseHysteresisModule(net=net, optimizer=optimizer, lr=lr)
    assert module.net is net and module.hparams["net"] is None  # built in Python: no spec
    losses = Losses()
    trainer(max_epochs=epochs, callbacks=[losses]).fit(module, datamodule=dm)
    assert losses.values[-1] < 0.5 * losses.values[0], losses.values
    dm.setup("fit")
    x, y = (t.double() for t in dm.train_tensors())
    assert [float(getattr(net, k)) for k in ("in_min", "in_max", "out_min", "out_max")] == [
        float(x.min()), float(x.max()), float(y.min()), float(y.max())]
    comp = StreamingCompensator(net, direction="none")
    with torch.no_grad():
        expected = module(x).clamp(float(comp.low), float(comp.high))
        steps = torch.stack([comp.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(steps, expected, rtol=0, atol=1e-12)
    assert isinstance(module.net, Composed)

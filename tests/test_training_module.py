"""InverseHysteresisModule: each optimizer, true-loss logging, closure-optimizer guards."""

from __future__ import annotations

import math
import warnings

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from _training_helpers import trainer

from torchhys import InverseHysteresisNet
from torchhys.functional import NonCausalWarning
from torchhys.init import initialize
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

torch.set_num_threads(1)


def small_data(**kwargs) -> HysteresisDataModule:
    """The paper's plant over 2 pi (628 samples): quick full-batch steps."""
    return HysteresisDataModule(t_end=2 * math.pi, **kwargs)


def full_batch_loss(module: InverseHysteresisModule, dm: HysteresisDataModule) -> float:
    x, y = dm.train_tensors()
    with torch.no_grad():
        return float(F.mse_loss(module(x.to(module.dtype), target=y.to(module.dtype)),
                                y.to(module.dtype)))


class LossRecorder(L.Callback):
    """Logged train_loss against the true full-batch loss, after every epoch."""

    def __init__(self, dm: HysteresisDataModule) -> None:
        self.dm, self.logged, self.true = dm, [], []

    def on_train_epoch_end(self, trainer: L.Trainer, module: InverseHysteresisModule) -> None:
        self.logged.append(float(trainer.callback_metrics["train_loss"]))
        self.true.append(full_batch_loss(module, self.dm))


@pytest.mark.parametrize("optimizer", ["adam", "cg", "lbfgs"])
def test_each_optimizer_lowers_the_loss(optimizer: str) -> None:
    torch.manual_seed(0)
    dm = small_data()
    module = InverseHysteresisModule(operator="zhao_tan", hidden=16, optimizer=optimizer,
                                     operator_kwargs={"scale": 1.8}, lr=3e-2,
                                     optimizer_kwargs={"max_iter": 5} if optimizer == "lbfgs"
                                     else None)
    rec = LossRecorder(dm)
    trainer(max_epochs=6, callbacks=[rec]).fit(module, dm)
    assert module.automatic_optimization == (optimizer == "adam")
    assert rec.true[-1] < 0.5 * rec.true[0]
    if optimizer != "adam":
        assert all(b <= a for a, b in zip(rec.true, rec.true[1:], strict=False))


@pytest.mark.parametrize("optimizer", ["cg", "lbfgs"])
def test_closure_optimizer_logs_the_true_loss_after_the_step(optimizer: str) -> None:
    torch.manual_seed(0)
    dm = small_data()
    module = InverseHysteresisModule(operator=None, hidden=8, optimizer=optimizer)
    rec = LossRecorder(dm)
    trainer(max_epochs=5, callbacks=[rec]).fit(module, dm)
    assert rec.logged == pytest.approx(rec.true, rel=1e-12, abs=0)


def test_learnable_a_is_trained_jointly() -> None:
    torch.manual_seed(0)
    dm = small_data()
    module = InverseHysteresisModule(operator="eiho", hidden=8, optimizer="cg",
                                     operator_kwargs={"a": "learnable", "a_init": 0.3})
    before = module.net.operators[0].coef.log_a.detach().clone()
    trainer(max_epochs=3).fit(module, dm)
    assert not torch.equal(before, module.net.operators[0].coef.log_a.detach())


def test_per_segment_eiho_gets_the_target_and_caches_features() -> None:
    torch.manual_seed(0)
    dm = small_data()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        module = InverseHysteresisModule(operator="eiho_segment", hidden=16, optimizer="cg")
    calls = []
    original = module.net.features

    def counting(*args, **kwargs):
        calls.append(kwargs.get("target") is not None)
        return original(*args, **kwargs)

    module.net.features = counting
    t = trainer(max_epochs=4, limit_val_batches=1.0, check_val_every_n_epoch=2)
    t.fit(module, dm)
    # normalization fit, then one evaluation per stage: training and validation data match,
    # but are cached separately; every call got the target
    assert calls and all(calls)
    assert len(calls) <= 3
    result = t.test(module, dm, verbose=False)
    # torchmetrics keeps its sums in float32
    assert result[0]["test_mse"] == pytest.approx(full_batch_loss(module, dm), rel=1e-6)


@pytest.mark.parametrize(
    "option, value, match",
    [("gradient_clip_val", 1.0, "gradient_clip_val"),
     ("accumulate_grad_batches", 2, "accumulate_grad_batches"),
     ("precision", "16-mixed", "precision"),
     ("precision", "bf16-mixed", "precision")],
)
@pytest.mark.parametrize("optimizer", ["cg", "lbfgs"])
def test_closure_optimizer_rejects_trainer_options(option, value, match, optimizer) -> None:
    module = InverseHysteresisModule(operator=None, hidden=4, optimizer=optimizer)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = trainer(max_epochs=1, **{option: value})
    with pytest.raises(ValueError, match=match) as err:
        t.fit(module, small_data())
    assert optimizer in str(err.value)


class GradNorm(L.Callback):
    """Norm of the gradient the optimizer stepped with (after clipping), per batch."""

    def __init__(self) -> None:
        self.norms: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        grads = [p.grad.norm() for p in module.parameters() if p.grad is not None]
        self.norms.append(float(torch.stack(grads).norm()))


def test_adam_accepts_clipping_and_accumulation() -> None:
    torch.manual_seed(0)
    module = InverseHysteresisModule(operator=None, hidden=4, optimizer="adam")
    before = [p.detach().clone() for p in module.parameters()]
    rec = GradNorm()
    t = trainer(max_epochs=2, gradient_clip_val=1e-3, accumulate_grad_batches=2,
                callbacks=[rec])
    t.fit(module, small_data())
    # one batch per epoch: the epoch's end closes the accumulation, so Adam steps each epoch
    assert t.global_step == 2
    assert all(not torch.equal(a, b.detach()) for a, b in zip(before, module.parameters(),
                                                                strict=True))
    # the raw gradient norm is ~2.7 here: clipping scaled it to the clip value
    assert rec.norms == pytest.approx([1e-3, 1e-3], rel=1e-5)


def test_closure_optimizer_may_evaluate_with_any_trainer() -> None:
    module = InverseHysteresisModule(operator=None, hidden=4, optimizer="cg")
    dm = small_data()
    out = trainer(gradient_clip_val=1.0, limit_val_batches=1.0).validate(module, dm, verbose=False)
    assert math.isfinite(out[0]["val_mse"])


def test_ready_network_is_used_as_is() -> None:
    net = InverseHysteresisNet(None, 6)
    module = InverseHysteresisModule(net, optimizer="adam")
    assert module.net is net
    assert "net" not in module.hparams


def test_bad_options() -> None:
    with pytest.raises(ValueError, match="optimizer must be one of"):
        InverseHysteresisModule(optimizer="sgd")
    with pytest.raises(ValueError, match="init must be one of"):
        InverseHysteresisModule(init="xavier")
    with pytest.raises(ValueError, match="nn.Linear"):
        initialize(torch.nn.Identity(), "nguyen_widrow")


def test_nguyen_widrow_spreads_the_units() -> None:
    torch.manual_seed(0)
    net = InverseHysteresisNet(None, 50)
    initialize(net, "nguyen_widrow")
    norms = net.hidden.weight.norm(dim=1)
    torch.testing.assert_close(norms, torch.full_like(norms, 0.7 * 50.0))
    assert float(net.hidden.bias.abs().max()) <= 0.7 * 50.0
    assert float(net.output.bias) == 0.0

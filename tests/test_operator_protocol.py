"""The operator protocol: a new operator defined here alone trains, streams and exports.

``DeadZone`` is the worked example of docs/adding-an-operator.md: a dead zone with a
learnable width, ``f(x) = x - clamp(x, -w, w)``, written in this module only (no library
file knows it) and registered by one line.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from _helpers import RAW
from torch import Tensor, nn

import torchhys.registry as registry
from torchhys import InverseHysteresisNet
from torchhys._checks import as_batched_sequence
from torchhys.deploy.export import load_aoti, load_torchscript, to_aoti, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.operator import HysteresisOperator, check_operator
from torchhys.registry import OPERATORS, make_operator, register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import example_of


def dead_zone(x: Tensor, width: Tensor) -> Tensor:
    """``x - clamp(x, -w, w)``: the maths, defined once (scriptable)."""
    return x - torch.minimum(torch.maximum(x, -width), width)


class DeadZoneStep(OperatorStep):
    def __init__(self, width: Tensor) -> None:
        super().__init__()
        self.register_buffer("width", width)
        self.n_outputs = 1
        self.state_spec = []  # memoryless

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        return dead_zone(x, self.width), state


class DeadZone(HysteresisOperator):
    n_outputs = 1

    def __init__(self, width: float = 0.5) -> None:
        super().__init__()
        self.raw = nn.Parameter(torch.tensor(math.log(math.expm1(width))))

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        as_batched_sequence(x, "x")  # bad input: TypeError or ValueError naming x
        return dead_zone(x, F.softplus(self.raw).to(x.dtype)), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return DeadZoneStep(F.softplus(self.raw).detach().to(dtype))


register_operator("dead_zone", DeadZone)


class Sticky(HysteresisOperator):
    """A stateful toy: the last input outside a band of +/- w around the held value."""

    n_outputs = 2

    def __init__(self, w: float = 0.3) -> None:
        super().__init__()
        self.w = w

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb = x if x.dim() == 2 else x[None]
        held = xb[:, :1] if state is None else state
        out = []
        for xt in xb.unbind(1):
            held = torch.where((xt[:, None] - held).abs() > self.w, xt[:, None], held)
            out.append(torch.cat([held, xt[:, None] - held], 1))
        f = torch.stack(out, 1)
        return (f if x.dim() == 2 else f[0]), held

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return StickyStep(self.w)


class StickyStep(OperatorStep):
    def __init__(self, w: float) -> None:
        super().__init__()
        self.w = w
        self.n_outputs = 2
        self.state_spec = [StateBlock("held", 1, from_sample=1.0)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        held = torch.where((x - state[0]).abs() > self.w, x, state[0])
        return torch.cat([held, x - held], 1), [held]


def data(T: int = 300, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    t = torch.linspace(0, 12, T, dtype=dtype)
    x = 2 * torch.sin(t) + 0.5 * torch.sin(3.3 * t)
    return x[None], torch.tanh(x)[None] + 0.3 * x[None]


def trained_net(dtype: torch.dtype = torch.float64) -> InverseHysteresisNet:
    torch.manual_seed(0)
    x, y = data(dtype=dtype)
    net = InverseHysteresisNet([DeadZone(0.4), Sticky(0.3)], hidden=8).to(dtype)
    net.fit_normalization(x, y)
    return net


def test_registered_by_one_line_and_built_by_name() -> None:
    assert OPERATORS["dead_zone"] is DeadZone
    op = make_operator("dead_zone", width=0.2)
    assert isinstance(op, DeadZone)
    assert float(F.softplus(op.raw.detach())) == pytest.approx(0.2)
    net = InverseHysteresisNet("dead_zone", operator_kwargs={"width": 0.7}, hidden=3)
    assert float(F.softplus(net.operators[0].raw.detach())) == pytest.approx(0.7)
    with pytest.raises(ValueError, match="operator 'dead_zone'.*unexpected keyword"):
        make_operator("dead_zone", widht=0.2)
    with pytest.raises(ValueError, match="registered already"):
        register_operator("dead_zone", Sticky)
    register_operator("dead_zone", DeadZone)  # the same class again: a no-op
    assert OPERATORS["dead_zone"] is DeadZone


def test_a_redefinition_of_the_same_class_replaces_it(monkeypatch) -> None:
    # a notebook cell that defines and registers an operator, run twice: two class objects
    # of the same module and qualified name; the example stays with its class
    monkeypatch.setitem(OPERATORS, "dead_zone", DeadZone)
    monkeypatch.setattr(registry, "EXAMPLES", {})
    assert isinstance(example_of("dead_zone").build(), DeadZone)  # DeadZone()
    register_operator("dead_zone", DeadZone, example=lambda: DeadZone(0.2))
    register_operator("dead_zone", DeadZone)  # again without one: the example is kept
    width = F.softplus(example_of("dead_zone").build().raw.detach())
    assert float(width) == pytest.approx(0.2)
    again = type("DeadZone", (DeadZone,), {"__module__": DeadZone.__module__,
                                           "__qualname__": DeadZone.__qualname__})
    register_operator("dead_zone", again)
    assert OPERATORS["dead_zone"] is again
    assert type(example_of("dead_zone").build()) is again
    other = type("DeadZone", (DeadZone,), {"__module__": "elsewhere"})
    with pytest.raises(ValueError, match="registered already"):
        register_operator("dead_zone", other)


def test_a_module_outside_the_protocol_is_a_type_error_naming_what_is_missing() -> None:
    with pytest.raises(TypeError, match="HysteresisOperator.*got Linear.*streaming_step"):
        InverseHysteresisNet([nn.Linear(1, 1)])
    with pytest.raises(TypeError, match="Can't instantiate abstract class"):
        type("Half", (HysteresisOperator,), {"forward": lambda self, x, s=None: (x, s)})()

    class BadCount(DeadZone):
        n_outputs = 0

    with pytest.raises(TypeError, match="n_outputs must be an int >= 1, got 0"):
        check_operator(BadCount())


@pytest.mark.parametrize("op", [DeadZone(0.4), Sticky(0.3)])
def test_step_equals_sequence(op: HysteresisOperator) -> None:
    x, _ = data()
    x = torch.cat([x, -0.5 * x.flip(1)])
    with torch.no_grad():
        f, _ = op(x)
    got = op.streaming_step(torch.float64).run(x)
    torch.testing.assert_close(got, f.reshape(got.shape), rtol=0, atol=0)


def test_trains_in_a_network_through_the_lightning_module(tmp_path) -> None:
    from _training_helpers import trainer

    from torchhys.identification.specs import build_operators
    from torchhys.training import HysteresisDataModule, InverseHysteresisModule

    modules, fitters = build_operators([{"name": "dead_zone", "width": 0.4}])
    assert isinstance(modules[0], DeadZone) and fitters == {}
    x, y = data()
    path = tmp_path / "record.csv"
    rows = "\n".join(f"{a!r},{b!r}" for a, b in zip(x[0].tolist(), y[0].tolist(), strict=True))
    path.write_text("response,command\n" + rows + "\n")
    dm = HysteresisDataModule(path=str(path), split=[1.0, 0.0, 0.0])
    torch.manual_seed(0)
    module = InverseHysteresisModule(operator=[{"name": "dead_zone", "width": 0.4}],
                                     hidden=8, optimizer="adam", lr=0.05)
    raw0 = module.net.operators[0].raw.detach().clone()
    fit = trainer(max_epochs=40)
    fit.fit(module, datamodule=dm)
    with torch.no_grad():
        out, _ = module.net(x.to(module.net.output.weight.dtype))
    mse = float(((out - y) ** 2).mean())
    assert mse < 0.1 * float(y.var())  # it learned the map through the operator
    assert not torch.equal(module.net.operators[0].raw.detach(), raw0)  # and the width


def test_streams_and_exports_to_torchscript(tmp_path) -> None:
    net = trained_net()
    x, _ = data()
    with torch.no_grad():
        ref, _ = net(x)
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)
    to_torchscript(net, tmp_path / "toy.pt", limits=(-1e3, 1e3), **RAW)
    ts = load_torchscript(tmp_path / "toy.pt")
    torch.testing.assert_close(ts(x), ref, rtol=0, atol=1e-12)
    assert ts.torchhys_metadata["counter"] == "1:0"


def test_exports_to_aoti_and_runs(tmp_path) -> None:
    """The default suite's one AOTInductor compile (a small float64 step, ~1 min)."""
    net = trained_net()
    x, _ = data(T=120)
    with torch.no_grad():
        ref, _ = net(x)
    path = to_aoti(net, tmp_path / "toy.pt2", limits=(-1e3, 1e3), **RAW)
    stepper = load_aoti(path)
    got = torch.stack([stepper.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)
    stepper.step(torch.tensor([float("nan")], dtype=torch.float64))
    assert int(stepper.nonfinite_count()) == 1


def test_a_module_that_cannot_be_copied_still_loads() -> None:
    """AtomicLoad tries a deep copy first; a non-leaf tensor attribute (which deepcopy
    refuses) makes it load directly instead of failing."""
    from torchhys import PrandtlIshlinskii

    src = PrandtlIshlinskii(torch.tensor([0.2, 0.5]), torch.tensor([0.3, 0.1]))
    dst = PrandtlIshlinskii(torch.tensor([0.1, 0.4]), torch.tensor([0.0, 0.0]))
    dst.cache = torch.ones(2, requires_grad=True) * 2.0
    dst.load_state_dict(src.state_dict())
    for a, b in zip(dst.state_dict().values(), src.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    import threading

    del dst.cache
    dst.lock = threading.Lock()  # deepcopy raises TypeError (cannot pickle)
    dst.load_state_dict(PrandtlIshlinskii(torch.tensor([0.3, 0.6]),
                                          torch.tensor([0.2, 0.2])).state_dict())
    assert torch.equal(dst.weights, torch.tensor([0.2, 0.2]))


def test_the_predictor_is_forward_by_default_and_fit_full_batch_uses_an_override() -> None:
    """``predictor(x)`` of the base class is the output of ``forward``; ``fit_full_batch``
    calls the operator's own (counted here)."""
    from torchhys import PrandtlIshlinskii
    from torchhys.identification.fitting import fit_full_batch

    calls = []

    class Counted(PrandtlIshlinskii):
        def predictor(self, x):
            calls.append(x.shape)
            return super().predictor(x)

    x = torch.sin(torch.linspace(0, 6, 50))[None]
    op = Counted(torch.tensor([0.2, 0.5]), torch.tensor([0.3, 0.1]), learnable=True)
    torch.testing.assert_close(op.predictor(x)(), op(x)[0], rtol=0, atol=0)
    calls.clear()
    result = fit_full_batch(op, x, 2 * x, adam_epochs=3, lbfgs_epochs=0)
    assert result.mse >= 0 and calls == [x.shape]


class _PlayByStep(HysteresisOperator):
    """A play operator given by its step only: the base class's sequence path runs it."""

    def __init__(self, width: float) -> None:
        super().__init__()
        self.width = width

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return _PlayOnlyStep(self.width)


class _PlayOnlyStep(OperatorStep):
    def __init__(self, width: float) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("play", 1, from_sample=1.0)]
        self.width = width

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        z = torch.minimum(torch.maximum(state[0], x - self.width), x + self.width)
        return z, [z]


def test_an_operator_with_only_a_step_gets_a_sequence_forward() -> None:
    """The default forward runs the step: equal to the library's play started at the first
    sample, chunked calls equal one call, (time,) in gives (time,) out, gradients reach x."""
    from torchhys.functional.backlash import backlash

    torch.manual_seed(0)
    x = torch.randn(3, 40, dtype=torch.float64).cumsum(1) * 0.3
    op = _PlayByStep(0.25)
    y, state = op(x)
    # backlash takes the dead band's full width: 2 x the play's half-width
    ref = backlash(x, torch.tensor([0.5], dtype=torch.float64), state=x[:, :1])[..., 0]
    torch.testing.assert_close(y, ref, rtol=0, atol=0)
    y1, s1 = op(x[:, :17])
    y2, _ = op(x[:, 17:], s1)
    torch.testing.assert_close(torch.cat([y1, y2], 1), y, rtol=0, atol=0)
    torch.testing.assert_close(op(x[0])[0], y[0], rtol=0, atol=0)
    xg = x[:1, :12].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda v: op(v)[0], (xg,))
    with pytest.raises(ValueError, match="^x must"):
        op(torch.zeros(2, 3, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match="^state must be the list of 1 tensor"):
        op(x, torch.zeros(3, 1, dtype=torch.float64))

"""Cascade: operators in series. Forward equals the composition, chunked calls equal one call,
the step (eager, TorchScript, torch.export) equals the sequence path with the second
operator's anchored blocks started from its own first input, a network streams through the
StreamingCompensator and exports equal to eager, calibration, the registry, bad input."""

from __future__ import annotations

import warnings

import pytest
import torch
from _helpers import RAW, run_split

from torchhys import EIHO, Backlash, Cascade, InverseHysteresisNet, PrandtlIshlinskii, SegmentEIHO
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.dynamics import StateSpace, TransferFunction
from torchhys.registry import make_operator


def _tf() -> TransferFunction:
    # DC gain 0.9/0.3 = 3, so the filter's first output differs from its first input
    return TransferFunction.from_coefficients([0.5, 0.3, 0.1], [1.0, -1.2, 0.5])


def _eiho() -> EIHO:
    return EIHO(a=1.0, rule="recent", output="branch", threshold=0.0).double()


def _cascades() -> dict[str, Cascade]:
    torch.manual_seed(0)
    plays = torch.tensor([0.1, 0.4, 0.9], dtype=torch.float64)
    return {
        "tf-eiho": Cascade(_tf(), _eiho()),
        "tf-plays": Cascade(_tf(), Backlash(plays)),
        "tf-pi": Cascade(_tf(), PrandtlIshlinskii(plays, [0.2, 0.3, 0.5], linear_weight=0.4)),
        "pi-tf": Cascade(PrandtlIshlinskii(plays, linear_weight=0.4), _tf()),
        "tf-ss": Cascade(_tf(), StateSpace(3, 2).double()),
        "three": Cascade([_tf(), Backlash(plays[:1]), _eiho()]),
        "nested left": Cascade(Cascade(_tf(), Backlash(plays[:1])), _eiho()),
        "nested right": Cascade(_tf(), Cascade(Backlash(plays[:1]), _eiho())),
        "eiho-eiho": Cascade(_eiho(), _eiho()),
    }


def _signal(batch: int = 2, time: int = 300, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = 0.2 * torch.randn(batch, time, generator=g, dtype=torch.float64).cumsum(1)
    return x + torch.linspace(0.7, -0.4, batch, dtype=torch.float64)[:, None]  # nonzero start


def _script(module: torch.nn.Module) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():  # torch.jit.script is deprecated in torch 2.13
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated",
                                category=DeprecationWarning)
        return torch.jit.script(module)


def test_forward_is_the_composition():
    tf, eiho, plays = _tf(), _eiho(), Backlash(torch.tensor([0.2, 0.5], dtype=torch.float64))
    x = _signal()
    with torch.no_grad():
        v, _ = tf(x)
        torch.testing.assert_close(Cascade(tf, eiho)(x)[0], eiho(v)[0], rtol=0, atol=0)
        torch.testing.assert_close(Cascade(tf, plays)(x)[0], plays(v)[0], rtol=0, atol=0)
        three = Cascade(tf, plays.__class__(torch.tensor([0.3], dtype=torch.float64)), eiho)
        w = three.stages[1](v)[0].squeeze(-1)
        torch.testing.assert_close(three(x)[0], eiho(w)[0], rtol=0, atol=0)
        y1, _ = Cascade(tf, eiho)(x[0])  # unbatched
    assert Cascade(tf, plays).n_outputs == 2 and y1.shape == x[0].shape
    torch.testing.assert_close(y1, eiho(v[0])[0], rtol=0, atol=0)


@pytest.mark.parametrize("name", list(_cascades()))
@pytest.mark.parametrize("splits", [[1] * 30, [7, 100, 193], [299, 1]])
def test_chunked_calls_equal_one_call(name, splits):
    op = _cascades()[name]
    x = _signal(time=sum(splits), seed=1)
    with torch.no_grad():
        whole, _ = op(x)
        chunked, _ = run_split(op, x, splits)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(_cascades()))
def test_step_eager_and_scripted_equal_sequence(name):
    op = _cascades()[name]
    x = _signal(seed=2)
    with torch.no_grad():
        f, _ = op(x)
    f = f.reshape(2, 300, -1)
    step = op.streaming_step(torch.float64)
    assert step.n_outputs == op.n_outputs
    for s in (step, _script(step)):
        state = step.initial_state(x[:, :1])
        outs = []
        for xt in x.unbind(1):
            out, state = s(xt.unsqueeze(1), state)
            outs.append(out)
        torch.testing.assert_close(torch.stack(outs, 1), f, rtol=0, atol=1e-12)
    torch.testing.assert_close(step.run(x), f, rtol=0, atol=1e-12)


def test_exported_step_equals_sequence():
    op = _cascades()["tf-eiho"].float()
    x = _signal(time=60, seed=3).float()
    step = op.streaming_step(torch.float32)
    state = step.initial_state(x[:, :1])
    exported = torch.export.export(step, (x[:, :1], state)).module()
    outs = []
    for xt in x.unbind(1):
        out, state = exported(xt.unsqueeze(1), state)
        outs.append(out)
    with torch.no_grad():
        f, _ = op(x)
    torch.testing.assert_close(torch.stack(outs, 1).squeeze(-1), f, rtol=0, atol=1e-5)


def test_second_operator_anchors_at_its_own_first_input():
    """The EIHO's turning point must start at the filter's first output, not at x0."""
    step = _cascades()["tf-eiho"].streaming_step(torch.float64)
    parts = _tf().streaming_step(torch.float64), _eiho().streaming_step(torch.float64)
    assert step.state_spec == parts[0].state_spec + parts[1].state_spec  # no extra block
    x = _signal(seed=4)
    # the naive series of the two steps, state started from x0 for both, differs
    tf_step, eiho_step = _tf().streaming_step(torch.float64), _eiho().streaming_step(
        torch.float64)
    s1, s2 = tf_step.initial_state(x[:, :1]), eiho_step.initial_state(x[:, :1])
    naive = []
    for xt in x.unbind(1):
        v, s1 = tf_step(xt.unsqueeze(1), s1)
        f, s2 = eiho_step(v, s2)
        naive.append(f)
    with torch.no_grad():
        f, _ = _cascades()["tf-eiho"](x)
    assert float((torch.stack(naive, 1).squeeze(-1) - f).abs().max()) > 1e-3
    torch.testing.assert_close(step.run(x).squeeze(-1), f, rtol=0, atol=1e-12)


def _network() -> InverseHysteresisNet:
    ops = _cascades()
    torch.manual_seed(1)
    net = InverseHysteresisNet([_tf(), ops["tf-eiho"], ops["tf-plays"], ops["nested right"]],
                               hidden=12).double()
    x = _signal(seed=5)
    net.fit_normalization(x, 0.5 * x + 0.1 * x.square())
    return net


def test_network_streams_through_the_compensator_equal_to_eager():
    net = _network()
    x = _signal(seed=6)
    with torch.no_grad():
        y, _ = net(x)
        comp = StreamingCompensator(net, limits=(-100.0, 100.0), **RAW)
        u = comp(x)
        comp.reset()
        stepped = torch.stack([comp.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(u, y, rtol=0, atol=1e-10)
    torch.testing.assert_close(stepped, y, rtol=0, atol=1e-10)
    # the cascades start their parts themselves: no block besides the operators' own
    names = [row[2] for row in comp.layout()]
    assert not any("cascade" in n for n in names)
    assert sum(getattr(s, "custom", False) for s in comp.slots) >= 2


def test_torchscript_export_equals_eager(tmp_path):
    net = _network()
    x = _signal(seed=7)
    with torch.no_grad():
        y, _ = net(x)
    scripted = to_torchscript(net, tmp_path / "cascade.pt", limits=(-100.0, 100.0), **RAW)
    loaded = load_torchscript(tmp_path / "cascade.pt")
    torch.testing.assert_close(scripted(x), y, rtol=0, atol=1e-10)
    torch.testing.assert_close(loaded(x), y, rtol=0, atol=1e-10)
    loaded.reset()
    torch.testing.assert_close(torch.stack([loaded.step(xt) for xt in x.unbind(1)], 1), y,
                               rtol=0, atol=1e-10)


def test_calibrate_sees_the_filtered_input():
    x = _signal(seed=8) + 0.01 * torch.randn(2, 300, dtype=torch.float64)
    tf = _tf()
    alone = EIHO(a=1.0, rule="recent", output="branch", threshold="auto").double()
    inside = EIHO(a=1.0, rule="recent", output="branch", threshold="auto").double()
    with torch.no_grad():
        alone.calibrate(tf(x)[0])
    Cascade(tf, inside).calibrate(x)
    assert float(inside.threshold) == float(alone.threshold) > 0


def test_gradients_reach_every_operator():
    op = Cascade(_tf(), PrandtlIshlinskii(torch.tensor([0.2, 0.5], dtype=torch.float64),
                                          learnable=True))
    x = _signal(seed=9)
    op(x)[0].square().mean().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0)
               for p in op.parameters() if p.requires_grad and p.numel() > 0)


def test_registry_builds_a_cascade_from_specs():
    op = make_operator("cascade", first={"name": "transfer_function", "order": 2},
                       second={"name": "eiho", "a": 1.0, "output": "branch"})
    assert isinstance(op, Cascade) and isinstance(op.stages[0], TransferFunction)
    assert isinstance(op.stages[1], EIHO)
    x = _signal(seed=10).float()
    assert op(x)[0].shape == x.shape


def test_bad_input():
    tf = _tf()
    with pytest.raises(ValueError, match="at least two operators"):
        Cascade([tf])
    with pytest.raises(ValueError, match="Cascade\\(first, second"):
        Cascade(tf)
    with pytest.raises(ValueError, match="must have one output"):
        Cascade(Backlash([0.1, 0.2]), tf)
    with pytest.warns(UserWarning), pytest.raises(ValueError, match="not causal"):
        Cascade(tf, SegmentEIHO())
    with pytest.raises(TypeError, match="HysteresisOperator"):
        Cascade(tf, torch.nn.Linear(1, 1))
    with pytest.raises(ValueError, match="name"):
        Cascade(tf, {"a": 1.0})
    with pytest.raises(ValueError, match="list of 2 states"):
        Cascade(tf, _eiho())(_signal(), state=[None])

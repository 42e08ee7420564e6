"""Streaming compensator: saturation, NaN/inf hold and counter, bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from _helpers import RAW

from torchhys import (
    EIHO,
    Backlash,
    InverseHysteresisNet,
    PrandtlIshlinskii,
    SegmentEIHO,
    ZhaoTanOperator,
)
from torchhys.deploy.ranges import default_limits
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.functional import NonCausalWarning


def make_net(dtype: torch.dtype = torch.float64) -> tuple[InverseHysteresisNet, torch.Tensor]:
    torch.manual_seed(0)
    t = torch.linspace(0, 12, 300, dtype=dtype)
    x = 3 * torch.sin(t) + torch.sin(3.1 * t)
    net = InverseHysteresisNet(
        [EIHO(a=1.0, rule="dominant", threshold=0.1), Backlash([0.5, 1.5])], hidden=6
    ).to(dtype)
    net.fit_normalization(x, 2 * x + 1)
    return net, x


def test_saturation_to_limits() -> None:
    net, x = make_net()
    free = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)(x)
    lo, hi = float(free.quantile(0.2)), float(free.quantile(0.8))
    comp = StreamingCompensator(net, limits=(lo, hi), **RAW)
    u = comp(x)
    assert float(u.min()) >= lo and float(u.max()) <= hi
    torch.testing.assert_close(u, free.clamp(lo, hi), rtol=0, atol=0)
    assert float(comp.low) == lo and float(comp.high) == hi


def test_default_limits_from_training_range() -> None:
    net, x = make_net()
    y = 2 * x + 1
    low, high = default_limits(net)
    # the training targets' range, recorded by fit_normalization
    assert low == pytest.approx(float(y.min())) and high == pytest.approx(float(y.max()))
    comp = StreamingCompensator(net)
    assert float(comp.low) == pytest.approx(low) and float(comp.high) == pytest.approx(high)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_input_holds_command_and_counts(bad: float) -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    clean = comp(x)
    comp.reset()
    out = []
    for t, xt in enumerate(x.unbind(-1)):
        if t in (50, 51, 120):  # bad samples inserted before these clean samples
            out.append(comp.step(torch.tensor([bad], dtype=x.dtype)))
            assert torch.isfinite(out[-1]).all()
            assert torch.equal(out[-1], out[-2])  # the last valid command is held
        out.append(comp.step(xt[None]))
    assert int(comp.nonfinite_count()) == 3
    assert all(torch.isfinite(s).all() for s in comp.state if s.is_floating_point())
    valid = torch.cat([o for i, o in enumerate(out) if i not in (50, 52, 122)])
    # the state was left as it was: the clean samples give the clean commands
    torch.testing.assert_close(valid, clean, rtol=0, atol=0)
    comp.reset()
    assert int(comp.nonfinite_count()) == 0


def test_nonfinite_first_samples_hold_initial_command() -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), initial_command=0.25, **RAW)
    xs = torch.cat([torch.tensor([float("nan"), float("inf")], dtype=x.dtype), x])
    u = comp(xs)
    assert u[:2].tolist() == [0.25, 0.25]
    torch.testing.assert_close(u[2:], comp(x), rtol=0, atol=0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), True, "0"])
def test_bad_initial_command(bad: object) -> None:
    net, _ = make_net()
    with pytest.raises(ValueError, match=f"initial_command must be a finite real number, got "
                       f"{bad!r}"):
        StreamingCompensator(net, limits=(-1.0, 1.0), initial_command=bad, **RAW)
    for good in (torch.tensor(0.25), np.float32(0.25), np.int64(0)):  # numbers of any kind
        comp = StreamingCompensator(net, limits=(-1.0, 1.0), initial_command=good, **RAW)
        assert float(comp.u0) == float(good)


def test_batch_rows_are_independent_under_nan() -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    xb = torch.stack([x, x.flip(0)])
    xb_bad = xb.clone()
    xb_bad[0, 30] = float("nan")
    u, ref = comp(xb_bad), comp(xb)
    torch.testing.assert_close(u[1], ref[1], rtol=0, atol=0)
    assert u[0, 30] == u[0, 29]
    comp.reset()
    for xt in xb_bad.unbind(-1):
        comp.step(xt)
    assert comp.nonfinite_count().tolist() == [1, 0]


def test_overflowing_input_never_reaches_the_plant() -> None:
    net, x = make_net(torch.float32)
    with torch.no_grad():  # two units off (sigmoid 0) unless x is huge; together they overflow
        net.hidden.weight[:2] = 0.0
        net.hidden.weight[:2, 0] = 1.0
        net.hidden.bias[:2] = -1e3
        net.output.weight[0, :2] = 2e38 / float(net.out_std)
    clean = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    for xt in x[:20].unbind(-1):
        clean.step(xt[None])
        comp.step(xt[None])
    # a large finite sample with a finite command is a sample: the command stays in limits
    big = torch.tensor([1e2])
    u = comp.step(big)
    assert torch.isfinite(u).all() and -1e3 <= float(u) <= 1e3
    clean.step(big)
    # a finite sample whose command overflows (inf - inf in the hidden layer): held, counted
    u_held = comp.step(torch.tensor([1e36]))
    assert torch.equal(u_held, u) and int(comp.nonfinite_count()) == 1
    # ... and the state was left as it was: later clean samples go on as if it never came
    a = torch.cat([comp.step(xt[None]) for xt in x[20:].unbind(-1)])
    b = torch.cat([clean.step(xt[None]) for xt in x[20:].unbind(-1)])
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert torch.isfinite(a).all() and int(comp.nonfinite_count()) == 1
    assert int(clean.nonfinite_count()) == 0


def test_non_causal_eiho_is_rejected() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        net = InverseHysteresisNet(SegmentEIHO(), hidden=4)
    with pytest.raises(ValueError, match="cannot be deployed"):
        StreamingCompensator(net, limits=(-1, 1), **RAW)


def test_uncalibrated_auto_threshold_is_rejected() -> None:
    net = InverseHysteresisNet(ZhaoTanOperator(threshold="auto"), hidden=4)
    with pytest.raises(ValueError, match="calibrate"):
        StreamingCompensator(net, limits=(-1, 1), **RAW)


@pytest.mark.parametrize("limits", [(1.0, 1.0), (2.0, -2.0), (0.0, float("nan")), (1.0,), "ab"])
def test_bad_limits(limits: object) -> None:
    net, _ = make_net()
    with pytest.raises(ValueError, match="limits"):
        StreamingCompensator(net, limits=limits, **RAW)


def test_missing_limits_are_explained() -> None:
    inv = PrandtlIshlinskii([0.5, 1.0], linear_weight=1.0).inverse()
    with pytest.raises(ValueError, match="limits=.low, high."):
        StreamingCompensator(inv)
    with pytest.raises(ValueError, match="limits"):
        StreamingCompensator(InverseHysteresisNet("eiho", hidden=3))


def test_unsupported_models_and_operators() -> None:
    with pytest.raises(TypeError, match="InverseHysteresisNet"):
        StreamingCompensator(torch.nn.Linear(1, 1), limits=(-1, 1))

    class Custom(torch.nn.Module):
        def forward(self, x, state=None):
            return x, None

    with pytest.raises(TypeError, match="Custom"):
        StreamingCompensator(InverseHysteresisNet(Custom(), hidden=3), limits=(-1, 1))


def test_wrong_shapes() -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-10, 10), **RAW)
    with pytest.raises(ValueError, match=r"\(batch,\)"):
        comp.step(torch.zeros(2, 3, dtype=x.dtype))
    with pytest.raises(ValueError, match=r"\(time,\) or \(batch, time\)"):
        comp(torch.zeros(2, 3, 4, dtype=x.dtype))
    comp.step(torch.zeros(2, dtype=x.dtype))
    with pytest.raises(ValueError, match="reset"):
        comp.step(torch.zeros(3, dtype=x.dtype))
    comp.reset()
    assert comp.step(torch.zeros(3, dtype=x.dtype)).shape == (3,)


@pytest.mark.parametrize("activation", ["sigmoid", "tanh", "relu", "gelu"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_deployed_network_every_activation_equals_eager_and_holds(
        activation: str, bad: float) -> None:
    """The deployed configuration (threshold-0 re-based recent EIHO + plays) with every
    activation: equal to eager, and a non-finite sample holds the command (an infinite
    sample may give a finite command through a saturating activation: it is held all the
    same)."""
    torch.manual_seed(1)
    t = torch.linspace(0, 12, 300, dtype=torch.float64)
    x = 3 * torch.sin(t) + torch.sin(3.1 * t)
    net = InverseHysteresisNet([EIHO(a=0.7, rule="recent", output="branch"),
                                Backlash([0.0, 0.5, 1.5])], hidden=6,
                               activation=activation).double()
    net.fit_normalization(x, 2 * x + 1)
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    with torch.no_grad():
        ref, _ = net(x)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)
    comp.reset()
    out = []
    for k, xt in enumerate(x.unbind(-1)):
        if k in (0, 40, 41):
            held = comp.step(torch.tensor([bad], dtype=x.dtype))
            assert torch.isfinite(held).all()
            assert k == 0 or torch.equal(held, out[-1])
        out.append(comp.step(xt[None]))
    assert int(comp.nonfinite_count()) == 3
    torch.testing.assert_close(torch.cat(out), ref, rtol=0, atol=1e-12)


def test_layout_with_two_float64_operators_and_two_rebased_eihos() -> None:
    """Several steps of each kind share the packed tensors: each finds its own blocks."""
    t = torch.linspace(0, 12, 400, dtype=torch.float64)
    x = torch.stack([3 * torch.sin(t) + torch.sin(3.1 * t), 2 * torch.cos(1.3 * t)])
    ops = [EIHO(a=0.8, rule="recent", threshold=0.2), EIHO(a=0.6, rule="recent", output="branch"),
           ZhaoTanOperator(rule="recent", threshold=0.1, scale=2.0), Backlash([0.5, 1.5]),
           EIHO(a=(1.1, 0.4), rule="recent", output="branch"),
           EIHO(a=1.0, rule="dominant", threshold=0.1, max_depth=5)]
    torch.manual_seed(0)
    net = InverseHysteresisNet(ops, hidden=8).double()
    net.fit_normalization(x, torch.tanh(x))
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), **RAW)
    kinds = [t.dtype for t in comp.initial_state(2)]
    assert kinds == [torch.float64, torch.long, torch.bool, torch.float64]
    f64 = [row for row in comp.layout() if row[1] == "float64"]
    assert [(r[3], r[4]) for r in f64] == [(0, 1), (1, 1)]  # the two level recent-rule steps
    with torch.no_grad():
        ref, _ = net(x)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)


def test_rows_whose_first_finite_sample_comes_at_different_steps() -> None:
    """Each row starts (anchors its operators) at its own first finite sample."""
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), initial_command=0.25, **RAW)
    lead = [0, 3, 17]
    rows = torch.stack([torch.cat([torch.full((k,), float("nan"), dtype=x.dtype), x[: 200 - k]])
                        for k in lead])
    got = comp(rows)
    comp.reset()
    steps = torch.stack([comp.step(xt) for xt in rows.unbind(-1)], -1)
    torch.testing.assert_close(steps, got, rtol=0, atol=0)
    assert comp.nonfinite_count().tolist() == lead
    for b, k in enumerate(lead):
        assert torch.all(got[b, :k] == 0.25)  # the initial command until the row starts
        with torch.no_grad():
            ref, _ = net(x[: 200 - k])
        torch.testing.assert_close(got[b, k:], ref.clamp(-1e3, 1e3), rtol=0, atol=1e-12)

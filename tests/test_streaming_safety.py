"""Streaming compensator: saturation, NaN/inf hold and counter, bad input."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet, PrandtlIshlinskii, ZhaoTanOperator
from torchhys.functional import NonCausalWarning
from torchhys.streaming import StreamingCompensator, default_limits


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
    free = StreamingCompensator(net, limits=(-1e6, 1e6))(x)
    lo, hi = float(free.quantile(0.2)), float(free.quantile(0.8))
    comp = StreamingCompensator(net, limits=(lo, hi))
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


def test_default_limits_of_a_state_dict_without_the_range() -> None:
    net, x = make_net()
    state = {k: v for k, v in net.state_dict().items() if k not in ("out_min", "out_max")}
    old = InverseHysteresisNet(list(net.operators), hidden=net.hidden.out_features).double()
    old.load_state_dict(state)
    assert torch.isnan(old.out_min) and torch.isnan(old.out_max)
    mean, std = float(net.out_mean), float(net.out_std)
    assert default_limits(old) == pytest.approx((mean - 3 * std, mean + 3 * std))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_input_holds_command_and_counts(bad: float) -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3))
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
    comp = StreamingCompensator(net, limits=(-1e3, 1e3), initial_command=0.25)
    xs = torch.cat([torch.tensor([float("nan"), float("inf")], dtype=x.dtype), x])
    u = comp(xs)
    assert u[:2].tolist() == [0.25, 0.25]
    torch.testing.assert_close(u[2:], comp(x), rtol=0, atol=0)


def test_batch_rows_are_independent_under_nan() -> None:
    net, x = make_net()
    comp = StreamingCompensator(net, limits=(-1e3, 1e3))
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
    comp = StreamingCompensator(net, limits=(-1e3, 1e3))
    for xt in x[:20].unbind(-1):
        comp.step(xt[None])
    u = comp.step(torch.tensor([3e38]))
    assert torch.isfinite(u).all()


def test_non_causal_eiho_is_rejected() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        net = InverseHysteresisNet(EIHO(a="segment"), hidden=4)
    with pytest.raises(ValueError, match="cannot be deployed"):
        StreamingCompensator(net, limits=(-1, 1))


def test_uncalibrated_auto_threshold_is_rejected() -> None:
    net = InverseHysteresisNet(ZhaoTanOperator(threshold="auto"), hidden=4)
    with pytest.raises(ValueError, match="calibrate"):
        StreamingCompensator(net, limits=(-1, 1))


@pytest.mark.parametrize("limits", [(1.0, 1.0), (2.0, -2.0), (0.0, float("nan")), (1.0,), "ab"])
def test_bad_limits(limits: object) -> None:
    net, _ = make_net()
    with pytest.raises(ValueError, match="limits"):
        StreamingCompensator(net, limits=limits)


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
    comp = StreamingCompensator(net, limits=(-10, 10))
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
    comp = StreamingCompensator(net, limits=(-1e3, 1e3))
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

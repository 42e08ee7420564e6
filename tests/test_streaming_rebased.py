"""Streaming and export of the re-based branch operators (``output="branch"``)."""

from __future__ import annotations

import pytest
import torch
from _helpers import RAW, inputs, net_of, per_op_features, steps_of

from torchhys import EIHO, Backlash, ZhaoTanOperator
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.operators.branch_steps import RebasedStep


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("threshold", [0.0, 0.5])
@pytest.mark.parametrize("a", [1.5, (1.5, 0.5), "anchored"])
def test_branch_eiho_network_step_equals_sequence(rule: str, threshold: float, a: object):
    x = inputs()
    opts = {"a_init": 0.7, "anchor_scale": 2.0} if a == "anchored" else {}
    op = EIHO(a=a, rule=rule, threshold=threshold, max_depth=6, output="branch", **opts)
    net = net_of([op, Backlash([0.0, 0.5, 2.0])], torch.float64, x)
    with torch.no_grad():
        ref, _ = net(x)
        level = net_of([EIHO(a=a, rule=rule, threshold=threshold, max_depth=6, **opts),
                        Backlash([0.0, 0.5, 2.0])], torch.float64, x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(steps_of(comp, x), ref, rtol=0, atol=1e-12)
    # the option reaches the step: the level network streams differently
    assert not torch.allclose(StreamingCompensator(level, limits=(-1e6, 1e6), **RAW)(x), ref)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("threshold", [0.0, 0.75])
def test_branch_operator_features_bit_for_bit_float32(rule: str, threshold: float) -> None:
    x = inputs().float()
    ops = [EIHO(a=(1.2, 0.8), rule=rule, threshold=threshold, max_depth=4, output="branch"),
           ZhaoTanOperator(rule=rule, threshold=threshold, scale=2.5, output="branch"),
           Backlash(torch.tensor([0.0, 0.3, 1.0]))]
    net = net_of(ops, torch.float32, x)
    with torch.no_grad():
        feats, _ = net.features(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(per_op_features(comp, x), feats[..., 1:], rtol=0, atol=0)


@pytest.mark.parametrize("a", [0.5, (0.5, 1.25)])
def test_deployed_branch_eiho_step_float32(a: object) -> None:
    """The deployed configuration (threshold 0, fixed coefficients: the step keeps the last
    sample, x_a and v = x - x_a, f = a_d signed_sqrt(v)) with plays after it: float32
    features bit for bit, steps == forward bit for bit."""
    x = inputs().float()
    ops = [EIHO(a=a, rule="recent", output="branch"), Backlash(torch.tensor([0.0, 0.3, 1.0]))]
    net = net_of(ops, torch.float32, x)
    with torch.no_grad():
        feats, _ = net.features(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    assert isinstance(comp.slots[0].step, RebasedStep)
    torch.testing.assert_close(per_op_features(comp, x), feats[..., 1:], rtol=0, atol=0)
    torch.testing.assert_close(steps_of(comp, x), comp(x), rtol=0, atol=0)


def test_branch_network_torchscript_equals_eager(tmp_path) -> None:
    x = inputs(300)
    ops = [EIHO(a=0.9, rule="recent", threshold=0.25, output="branch"),
           ZhaoTanOperator(rule="dominant", scale=2.0, output="branch"),
           Backlash([0.0, 1.0])]
    net = net_of(ops, torch.float64, x)
    with torch.no_grad():
        ref, _ = net(x)
    to_torchscript(net, tmp_path / "comp.pt", limits=(-1e6, 1e6), **RAW)
    ts = load_torchscript(tmp_path / "comp.pt")
    torch.testing.assert_close(ts(x), ref, rtol=0, atol=1e-12)

"""Streaming compensator: the per-sample step equals the eager sequence implementation."""

from __future__ import annotations

import math

import pytest
import torch
from _helpers import RAW, inputs, net_of, per_op_features, steps_of

from torchhys import (
    EIHO,
    Backlash,
    PrandtlIshlinskii,
    ZhaoTanOperator,
    signals,
)
from torchhys.deploy.streaming import StreamingCompensator

RULES = ["recent", "dominant"]
THRESHOLDS = [0.0, 0.5, 1.0]
A_MODES = [1.5, (1.5, 0.5), "learnable"]


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("threshold", THRESHOLDS)
@pytest.mark.parametrize("a", A_MODES)
def test_eiho_network_step_equals_sequence(rule: str, threshold: float, a: object) -> None:
    x = inputs()
    init = {"a_init": 0.7} if a == "learnable" else {}
    op = EIHO(a=a, rule=rule, threshold=threshold, max_depth=6, **init)
    net = net_of([op], torch.float64, x)
    with torch.no_grad():
        ref, _ = net(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(steps_of(comp, x), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("threshold", [0.0, 0.75])
def test_operator_features_step_equal_sequence_float32(rule: str, threshold: float) -> None:
    """Each operator's output, step by step, equals its sequence forward (float32)."""
    x = inputs().float()
    ops = [EIHO(a=(1.2, 0.8), rule=rule, threshold=threshold, max_depth=4),
           ZhaoTanOperator(rule=rule, threshold=threshold, scale=2.5),
           Backlash(torch.tensor([0.0, 0.3, 1.0, 2.5]))]
    net = net_of(ops, torch.float32, x)
    with torch.no_grad():
        feats, _ = net.features(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    got = per_op_features(comp, x)
    # bit-exact: the step repeats the sequence arithmetic operation by operation
    torch.testing.assert_close(got, feats[..., 1:], rtol=0, atol=0)


def test_dominant_stack_overflow_matches() -> None:
    """Deeply nested loops overflow a small stack: the oldest entries are forgotten alike."""
    t = torch.linspace(0.0, 1.0, 3000, dtype=torch.float64)
    x = signals.nested_reversals(t, amplitude=5.0, n_reversals=40, ratio=0.9)[None]
    net = net_of([EIHO(a=1.0, rule="dominant", max_depth=3)], torch.float64, x)
    with torch.no_grad():
        ref, _ = net(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)


def test_float32_network_to_1e6() -> None:
    x = inputs(1000).float()
    ops = [EIHO(a=1.0, rule="dominant", threshold=0.25), Backlash(torch.linspace(0.1, 2.0, 8))]
    net = net_of(ops, torch.float32, x)
    with torch.no_grad():
        ref, _ = net(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(steps_of(comp, x), comp(x), rtol=0, atol=0)


def test_pi_inverse_compensator() -> None:
    pi = PrandtlIshlinskii(torch.linspace(0.2, 2.0, 6).double(), linear_weight=0.5)
    inv = pi.inverse()
    y = 3 * torch.sin(torch.linspace(0, 12, 500, dtype=torch.float64))[None]
    ref, _ = inv(y)
    comp = StreamingCompensator(inv, limits=(-100, 100), **RAW)
    torch.testing.assert_close(comp(y), ref, rtol=0, atol=1e-12)
    # and it inverts the plant
    h, _ = pi(comp(y))
    torch.testing.assert_close(h, y, rtol=0, atol=1e-9)


def test_batch_consistency_and_shapes() -> None:
    x = inputs(200)
    net = net_of([EIHO(a=1.0, rule="dominant", threshold=0.5)], torch.float64, x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    whole = comp(x)
    assert whole.shape == x.shape
    for b in range(x.shape[0]):
        row = comp(x[b])
        assert row.shape == x[b].shape
        torch.testing.assert_close(row, whole[b], rtol=0, atol=1e-12)  # matmul blocking
    assert comp(x[:, :0]).shape == (x.shape[0], 0)


def test_forward_leaves_stored_state_alone() -> None:
    x = inputs(50)
    net = net_of([EIHO(a=1.0, rule="recent")], torch.float64, x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    first = [comp.step(xt) for xt in x[:, :10].unbind(-1)]
    comp(x)
    rest = [comp.step(xt) for xt in x[:, 10:].unbind(-1)]
    torch.testing.assert_close(torch.stack(first + rest, -1), comp(x), rtol=0, atol=0)
    assert math.isfinite(float(comp(x).sum()))


def anchored_eiho(rule: str, threshold: float, dtype: torch.dtype) -> EIHO:
    op = EIHO(a="anchored", rule=rule, threshold=threshold, max_depth=5, a_init=0.8,
              anchor_center=0.5, anchor_scale=2.0)
    with torch.no_grad():
        op.coef.log_a.copy_(torch.tensor([-0.2, 0.3]))
        op.coef.slope.copy_(torch.tensor([0.4, -0.7]))
    return op.to(dtype)


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("threshold", [0.0, 0.5])
def test_anchored_eiho_step_equals_sequence(rule: str, threshold: float) -> None:
    """a='anchored': float64 network to 1e-12, float32 operator output bit for bit."""
    x = inputs()
    net = net_of([anchored_eiho(rule, threshold, torch.float64), Backlash([0.5])],
                 torch.float64, x)
    with torch.no_grad():
        ref, _ = net(x)
    comp = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(comp(x), ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(steps_of(comp, x), ref, rtol=0, atol=1e-12)
    x32 = x.float()
    net32 = net_of([anchored_eiho(rule, threshold, torch.float32)], torch.float32, x32)
    with torch.no_grad():
        feats, _ = net32.features(x32)
    comp32 = StreamingCompensator(net32, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(per_op_features(comp32, x32), feats[..., 1:], rtol=0, atol=0)

"""Autograd of the branch operators: gradcheck where smooth, finite gradients at kinks."""

from __future__ import annotations

import math

import pytest
import torch
from _helpers import smooth_input

from torchhys import EIHO
from torchhys.functional import eiho, zhao_tan


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_gradcheck_eiho(rule: str) -> None:
    x = smooth_input().requires_grad_()
    a = torch.tensor([1.2, 0.8], dtype=torch.float64, requires_grad=True)
    x0 = x.detach()[0] - 0.1  # fixed anchor below the first sample

    def fn(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        # keep the anchor fixed at the start value so the first sample is not at x_e
        return eiho(torch.cat([x0.reshape(1), x]), a, rule=rule)[0][1:]

    assert torch.autograd.gradcheck(fn, (x, a), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_gradcheck_zhao_tan(rule: str) -> None:
    x = smooth_input().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: zhao_tan(x, rule=rule)[0], (x,), eps=1e-7)


def test_gradcheck_per_segment_coefficients() -> None:
    x = smooth_input()
    a = torch.tensor([[1.0, 0.5, 2.0, 1.5]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: eiho(x, a, per_segment=True)[0], (a,))


@pytest.mark.parametrize("output", ["level", "branch"])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("threshold", [0.0, 0.5])
def test_gradients_finite_at_kinks(rule: str, threshold: float, output: str) -> None:
    # starts at x_e, flat stretches, a turning point exactly on a sample, repeated samples
    x = torch.tensor(
        [0.0, 0.0, 1.0, 2.0, 2.0, 2.0, 1.0, 1.0, 0.0, 0.0, 3.0, 2.5, 2.5, 3.0, 4.0, 4.0],
        dtype=torch.float64, requires_grad=True,
    )
    a = torch.tensor([1.0, 2.0], dtype=torch.float64, requires_grad=True)
    f, _ = eiho(x, a, rule=rule, threshold=threshold, output=output)
    gx, ga = torch.autograd.grad(f.sum(), (x, a))
    assert torch.isfinite(gx).all() and torch.isfinite(ga).all()
    fz, _ = zhao_tan(x, rule=rule, threshold=threshold, output=output)
    assert torch.isfinite(torch.autograd.grad(fz.sum(), x)[0]).all()


def test_slope_at_anchor_is_bounded() -> None:
    x = torch.tensor([1.0, 1.0, 1.0 + 1e-12], dtype=torch.float64, requires_grad=True)
    f, _ = eiho(x, 1.0, eps=1e-8)
    g = torch.autograd.grad(f[-1], x)[0]
    assert torch.isfinite(g).all() and g.abs().max() <= 1 / math.sqrt(1e-8) + 1e-6


def test_learnable_a_receives_gradient() -> None:
    op = EIHO(a="learnable", per_direction=True).double()
    f, _ = op(smooth_input())
    f.sum().backward()
    assert op.coef.log_a.grad is not None and torch.isfinite(op.coef.log_a.grad).all()
    assert op.coef.log_a.grad.abs().min() > 0

"""EIHO whose coefficient is a learned positive function of the branch's start point."""

from __future__ import annotations

import math

import pytest
import torch
from _branch_reference import ref_branch
from _helpers import batch, random_walk, run_chunked, smooth_input

from torchhys import EIHO, InverseHysteresisNet
from torchhys.functional import eiho
from torchhys.identification.fitting import fit_full_batch

A = (1.3, 0.7)
K = (0.4, -0.25)


def a_anchor(d: int, x_e: float) -> float:
    return A[0] * math.exp(K[0] * x_e) if d >= 0 else A[1] * math.exp(K[1] * x_e)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("threshold", [0.0, 1.0])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_matches_loop(seed: int, threshold: float, rule: str) -> None:
    x = random_walk(seed, quantize=seed % 2 == 0) / 4
    a, k = torch.tensor(A, dtype=torch.float64), torch.tensor(K, dtype=torch.float64)
    f, _ = eiho(x, a, rule=rule, threshold=threshold, max_depth=6, anchor_slope=k)
    ref = ref_branch(x.tolist(), threshold=threshold, rule=rule, depth=6, a_anchor=a_anchor)
    torch.testing.assert_close(f, torch.tensor(ref, dtype=torch.float64), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_zero_slope_is_a_constant_coefficient(rule: str) -> None:
    x = batch()
    op = EIHO(a="anchored", rule=rule, a_init=1.7, anchor_center=3.0, anchor_scale=2.0).double()
    a = op.coefficient().detach()
    assert abs(float(a[0]) - 1.7) < 1e-6
    torch.testing.assert_close(op(x)[0], eiho(x, a, rule=rule)[0], rtol=1e-12, atol=1e-12)


def test_module_normalizes_the_anchor() -> None:
    op = EIHO(a="anchored", anchor_center=1.0, anchor_scale=4.0).double()
    with torch.no_grad():
        op.coef.log_a.copy_(torch.log(torch.tensor(A, dtype=torch.float64)))
        op.coef.slope.copy_(torch.tensor(K, dtype=torch.float64) * 4.0)
    x = random_walk(3, quantize=False) / 4
    f, _ = op(x)
    ref = ref_branch(x.tolist(), a_anchor=lambda d, xe: a_anchor(d, xe - 1.0))
    torch.testing.assert_close(f, torch.tensor(ref, dtype=torch.float64), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("threshold", [0.0, 0.75])
@pytest.mark.parametrize("sizes", [[1], [7, 1, 30]])
def test_chunked_equals_whole(rule: str, threshold: float, sizes: list[int]) -> None:
    op = EIHO(a="anchored", rule=rule, threshold=threshold, max_depth=6, anchor_scale=3.0)
    op = op.double()
    with torch.no_grad():
        op.coef.slope.copy_(torch.tensor(K))
    x = batch()
    whole, _ = op(x)
    torch.testing.assert_close(run_chunked(op, x, sizes), whole, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_gradcheck(rule: str) -> None:
    x = smooth_input().requires_grad_()
    a = torch.tensor(A, dtype=torch.float64, requires_grad=True)
    k = torch.tensor(K, dtype=torch.float64, requires_grad=True)
    x0 = x.detach()[0] - 0.1

    def fn(x: torch.Tensor, a: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        return eiho(torch.cat([x0.reshape(1), x]), a, rule=rule, anchor_slope=k)[0][1:]

    assert torch.autograd.gradcheck(fn, (x, a, k), eps=1e-7, atol=1e-6)


def test_causal_and_finite_gradients_at_kinks() -> None:
    x = torch.tensor(
        [0.0, 0.0, 1.0, 2.0, 2.0, 2.0, 1.0, 1.0, 0.0, 0.0, 3.0, 2.5, 2.5, 3.0, 4.0, 4.0],
        dtype=torch.float64, requires_grad=True,
    )
    op = EIHO(a="anchored", rule="dominant", threshold=0.5).double()
    f, _ = op(x)
    changed = x.detach().clone()
    changed[10:] -= 5.0
    torch.testing.assert_close(op(changed)[0][:10], f[:10].detach())
    f.sum().backward()
    for g in (x.grad, op.coef.log_a.grad, op.coef.slope.grad):
        assert g is not None and bool(torch.isfinite(g).all())
    assert float(op.coef.slope.grad.abs().sum()) > 0


def test_slope_trains_with_the_network() -> None:
    torch.manual_seed(0)
    t = torch.linspace(0, 12, 200, dtype=torch.float64)
    x = 2 * torch.sin(t) + torch.sin(3.1 * t)
    net = InverseHysteresisNet(EIHO(a="anchored", rule="dominant"), hidden=6).double()
    fit_full_batch(net, x, torch.tanh(x), adam_epochs=20, lbfgs_epochs=0)
    assert float(net.operators[0].coef.slope.detach().abs().sum()) > 0


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="anchor_scale"):
        EIHO(a="anchored", anchor_scale=0.0)
    x = batch()
    with pytest.raises(ValueError, match="anchor_slope must be a scalar"):
        eiho(x, 1.0, anchor_slope=torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="finite"):
        eiho(x, 1.0, anchor_slope=float("nan"))
    with pytest.raises(ValueError, match="per_segment"):
        eiho(x, torch.ones(3, 2, dtype=torch.float64), per_segment=True, anchor_slope=0.1)
    with pytest.raises(TypeError, match="anchor_slope"):
        eiho(x, 1.0, anchor_slope="0.1")

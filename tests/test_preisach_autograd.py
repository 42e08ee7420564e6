"""Preisach autograd: gradcheck (smooth relays in x, the density, offset, linear), the custom
backward against autograd of the materialised relays, ties, the projected density."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _preisach_helpers import model, signal

from torchhys.functional.preisach import preisach, preisach_grid, relay_states
from torchhys.operators.preisach import Preisach

F64 = torch.float64


def _off_threshold(B: int, T: int, n: int, seed: int) -> torch.Tensor:
    """Samples a tenth of a cell or more away from every level (the levels are the cell
    centers), so that finite differences stay on a branch."""
    g = torch.Generator().manual_seed(seed)
    edge = torch.randint(0, n + 1, (B, T), generator=g).to(F64)
    shift = 0.4 * (2 * torch.rand(B, T, generator=g, dtype=F64) - 1)
    return -1.0 + 2.0 * (edge + shift) / n


@pytest.mark.parametrize("smooth", [None, 0.3])
def test_gradcheck(smooth):
    alpha, beta = preisach_grid(-1.0, 1.0, 5, dtype=F64)
    x = _off_threshold(2, 40, 5, seed=8).requires_grad_()
    w = torch.rand(alpha.numel(), dtype=F64, requires_grad=True)
    off = torch.tensor(0.2, dtype=F64, requires_grad=True)
    lin = torch.tensor(0.7, dtype=F64, requires_grad=True)

    def f(x, w, off, lin):
        return preisach(x, w, alpha, beta, offset=off, linear=lin, smooth=smooth)

    assert torch.autograd.gradcheck(f, (x, w, off, lin))
    if smooth is not None:
        assert torch.autograd.gradcheck(
            lambda x: relay_states(x, alpha, beta, smooth=smooth), (x,))


@pytest.mark.parametrize("smooth", [None, 0.2])
def test_custom_backward_equals_autograd_of_the_materialised_relays(smooth):
    alpha, beta = preisach_grid(-1.0, 1.0, 7, dtype=F64)
    x = signal(2, 120, 7, seed=9).requires_grad_()
    w = torch.rand(alpha.numel(), dtype=F64, requires_grad=True)
    probe = torch.randn(2, 120, dtype=F64)
    g1 = torch.autograd.grad((preisach(x, w, alpha, beta, smooth=smooth) * probe).sum(),
                             (x, w), allow_unused=True, materialize_grads=True)
    g2 = torch.autograd.grad((relay_states(x, alpha, beta, smooth=smooth) @ w * probe).sum(),
                             (x, w), allow_unused=True, materialize_grads=True)
    for a, b in zip(g1, g2, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_smooth_tends_to_hard_relays():
    alpha, beta = preisach_grid(-1.0, 1.0, 6, dtype=F64)
    x = _off_threshold(2, 200, 6, seed=10)
    hard = relay_states(x, alpha, beta)
    for tau, tol in ((1e-2, 1e-2), (1e-4, 1e-12)):
        torch.testing.assert_close(relay_states(x, alpha, beta, smooth=tau), hard,
                                   rtol=0, atol=tol)


def test_module_gradients_and_projection():
    m = model()
    x = signal(2, 80, 9, seed=11)
    with torch.no_grad():
        m.weights[:3] = -0.5  # as after a gradient step below zero
    y, _ = m(x)
    ref = Preisach(-1.0, 1.0, 9).double()
    ref.load_state_dict({**m.state_dict(), "weights": m.weights.detach().clamp_min(0)})
    torch.testing.assert_close(y, ref(x)[0])
    y.sum().backward()
    assert m.weights.grad is not None and bool((m.weights.grad[:3] == 0).all())
    assert m.linear.grad is not None and m.offset.grad is not None
    m.project_()
    assert float(m.weights.detach().min()) == 0.0


@pytest.mark.parametrize(
    "alpha, beta, r0, x, hard, theta",
    [
        (0.0, 0.0, -1.0, 0.0, 1.0, 0.0),  # diagonal relay at its threshold: up wins
        (0.0, 0.0, 1.0, 0.0, 1.0, 0.0),
        (0.5, -0.5, -1.0, 0.5, 1.0, -0.5),  # reaches alpha: up, next threshold beta
        (0.5, -0.5, 1.0, -0.5, -1.0, 0.5),  # reaches beta: down, next threshold alpha
        (0.5, -0.5, 1.0, 0.2, 1.0, -0.5),  # in between: keeps r0
    ],
)
def test_ties_and_gradient_at_a_threshold(alpha, beta, r0, x, hard, theta):
    a, b = torch.tensor([alpha], dtype=F64), torch.tensor([beta], dtype=F64)
    r = torch.tensor([r0], dtype=F64)
    xs = torch.tensor([x], dtype=F64, requires_grad=True)
    assert relay_states(xs, a, b, state=r).item() == hard
    tau = 0.25
    y = preisach(xs, torch.ones(1, dtype=F64), a, b, state=r, smooth=tau)
    expected = np.tanh((x - theta) / tau)
    assert y.item() == pytest.approx(expected, abs=1e-15)
    (gx,) = torch.autograd.grad(y.sum(), xs)
    assert gx.item() == pytest.approx((1 - expected**2) / tau, abs=1e-12)

"""Gradients of the play operators: gradcheck and an independent autograd loop."""

from __future__ import annotations

import pytest
import torch

from torchhys.functional import backlash


def _loop(x: torch.Tensor, widths: torch.Tensor, y0: torch.Tensor) -> torch.Tensor:
    """Per-sample autograd loop (min/max form): the independent gradient reference."""
    r = 0.5 * widths
    s = y0
    out = []
    for x_t in x.unbind(1):
        s = torch.minimum(x_t.unsqueeze(-1) + r, torch.maximum(x_t.unsqueeze(-1) - r, s))
        out.append(s)
    return torch.stack(out, 1)


@pytest.mark.parametrize("T", [1, 9, 150])
def test_gradcheck_x_widths_y0(backend, T):
    torch.manual_seed(T)
    x = torch.randn(2, T, dtype=torch.float64).cumsum(1).requires_grad_()
    widths = (torch.rand(4, dtype=torch.float64) * 2 + 0.1).requires_grad_()
    y0 = torch.randn(2, 4, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: backlash(a, b, state=c), (x, widths, y0))


def test_gradcheck_unbatched_broadcast_state(backend):
    torch.manual_seed(3)
    x = torch.randn(80, dtype=torch.float64).cumsum(0).requires_grad_()
    widths = (torch.rand(3, dtype=torch.float64) + 0.2).requires_grad_()
    y0 = torch.randn(3, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, c: backlash(a, b, state=c), (x, widths, y0))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_match_autograd_loop(backend, dtype):
    torch.manual_seed(0)
    B, T, N = 3, 400, 5
    x0 = torch.randn(B, T, dtype=dtype).cumsum(1)
    w0 = torch.rand(N, dtype=dtype) * 3 + 0.05
    s0 = torch.randn(B, N, dtype=dtype)
    g = torch.randn(B, T, N, dtype=dtype)
    grads = []
    for fn in (lambda a, b, c: backlash(a, b, state=c), _loop):
        x, w, s = (t.clone().requires_grad_() for t in (x0, w0, s0))
        out = fn(x, w, s)
        grads.append(torch.autograd.grad((out * g).sum(), (x, w, s)))
    tol = {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {}
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, **tol)


def test_zero_width_passes_gradient_to_x(backend):
    x = torch.randn(1, 30, dtype=torch.float64).cumsum(1).requires_grad_()
    widths = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    y = backlash(x, widths)
    (gx, gw) = torch.autograd.grad(y.sum(), (x, widths))
    torch.testing.assert_close(gx, torch.ones_like(x))
    assert torch.isfinite(gw).all()


def test_flat_input_routes_gradient_to_last_clamp(backend):
    # rising ramp (clamped at the lower bound) then a flat stretch (inactive): the
    # outputs on the flat stretch equal x[last rise] - r, so its gradient collects there
    x = torch.tensor([[0.0, 1.0, 2.0, 2.0, 2.0, 2.0]], dtype=torch.float64, requires_grad=True)
    widths = torch.tensor([1.0], dtype=torch.float64, requires_grad=True)
    y = backlash(x, widths)
    torch.testing.assert_close(y[0, :, 0], torch.tensor([0.0, 0.5, 1.5, 1.5, 1.5, 1.5]).double())
    gx, gw = torch.autograd.grad(y.sum(), (x, widths))
    torch.testing.assert_close(gx, torch.tensor([[0.0, 1.0, 4.0, 0.0, 0.0, 0.0]]).double())
    torch.testing.assert_close(gw, torch.tensor([-2.5]).double())

"""Gradients of the linear dynamics: gradcheck (float64), double backward, fused kernel adjoint
against the differentiable backward, module parameters."""

from __future__ import annotations

import pytest
import torch
from _dynamics_helpers import BACKENDS, signal, stable_denominator, use_backend
from torch.autograd import gradcheck, gradgradcheck
from torch.func import functional_call

from torchhys.dynamics import StateSpace, TransferFunction
from torchhys.functional.linear_filter import lfilter, linear_recurrence, state_space


def _filter_inputs(nb: int, na: int, T: int, seed: int = 0, a0: float = 1.0):
    g = torch.Generator().manual_seed(seed)
    n = max(na, nb) - 1
    x = torch.randn(2, T, generator=g, dtype=torch.float64)
    b = torch.randn(nb, generator=g, dtype=torch.float64)
    poles = [0.8 * complex(torch.rand(1, generator=g).item(), 0.5) for _ in range((na - 1) // 2)]
    poles += [0.7] * ((na - 1) % 2)
    a = a0 * torch.tensor(stable_denominator(poles), dtype=torch.float64)
    zi = torch.randn(2, n, generator=g, dtype=torch.float64)
    return [t.requires_grad_() for t in (x, b, a, zi)]


def _lfilter(x, b, a, zi):
    return lfilter(x, b, a, state=zi)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("nb,na,T", [(3, 3, 25), (2, 4, 20), (5, 2, 15), (3, 3, 1), (4, 4, 2)])
def test_lfilter_gradcheck(backend, nb, na, T):
    inputs = _filter_inputs(nb, na, T, seed=nb * 10 + na, a0=1.5)  # a[0] != 1: normalized
    with use_backend(backend):
        assert gradcheck(_lfilter, inputs)


@pytest.mark.parametrize("backend", BACKENDS)
def test_lfilter_gradgradcheck(backend):
    inputs = _filter_inputs(3, 3, 12, seed=3)
    with use_backend(backend):
        assert gradgradcheck(_lfilter, inputs)


@pytest.mark.parametrize("backend", BACKENDS)
def test_fused_adjoint_equals_differentiable_backward(backend):
    """Two computations of the same gradient: the fused C adjoint (no graph) and the backward
    written with tensor operations (taken when create_graph=True)."""
    x, b, a, zi = _filter_inputs(4, 5, 3000, seed=4)
    probe = signal((2, 3000), seed=5)
    with use_backend(backend):
        y, zf = lfilter(x, b, a, state=zi)
        loss = (y * probe).sum() + zf.square().sum()
        fused = torch.autograd.grad(loss, (x, b, a, zi), retain_graph=True)
        graph = torch.autograd.grad(loss, (x, b, a, zi), create_graph=True)
    for f, g in zip(fused, graph, strict=True):
        torch.testing.assert_close(f, g.detach(), rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("backend", BACKENDS)
def test_linear_recurrence_and_state_space_gradcheck(backend):
    g = torch.Generator().manual_seed(6)
    A = (0.4 * torch.randn(3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    w = torch.randn(2, 15, 3, generator=g, dtype=torch.float64, requires_grad=True)
    s0 = torch.randn(2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    B, C, D = (torch.randn(*s, generator=g, dtype=torch.float64).requires_grad_()
               for s in [(3,), (2, 3), (2,)])
    u = torch.randn(2, 15, generator=g, dtype=torch.float64, requires_grad=True)
    with use_backend(backend):
        assert gradcheck(lambda A, w, s0: linear_recurrence(A, w, state=s0), (A, w, s0))
        assert gradgradcheck(lambda A, w, s0: linear_recurrence(A, w, state=s0), (A, w, s0))
        assert gradcheck(lambda u, A, B, C, D, s0: state_space(u, A, B, C, D, state=s0),
                         (u, A, B, C, D, s0))


@pytest.mark.parametrize("order,feedthrough", [(1, True), (2, False), (3, True), (4, True)])
def test_transfer_function_parameter_gradcheck(order, feedthrough):
    torch.manual_seed(order)
    block = TransferFunction(order, feedthrough=feedthrough).double()
    names = [n for n, _ in block.named_parameters()]
    params = [p.detach().clone().requires_grad_() for p in block.parameters()]
    x = signal((2, 30), seed=7).requires_grad_()
    state = torch.randn(2, order, dtype=torch.float64, requires_grad=True)

    def f(x, state, *ps):
        return functional_call(block, dict(zip(names, ps, strict=True)), (x, state))

    assert gradcheck(f, (x, state, *params))


def test_state_space_parameter_gradcheck():
    torch.manual_seed(8)
    block = StateSpace(3, 2).double()
    with torch.no_grad():
        block.W.mul_(4.0)  # ||W|| > 1: the norm clamp is active
    assert torch.linalg.matrix_norm(block.W, ord=2) > 1
    names = [n for n, _ in block.named_parameters()]
    params = [p.detach().clone().requires_grad_() for p in block.parameters()]
    x = signal((2, 25), seed=9).requires_grad_()

    def f(x, *ps):
        return functional_call(block, dict(zip(names, ps, strict=True)), (x,))

    assert gradcheck(f, (x, *params))


def test_transfer_function_learns_a_filter():
    torch.manual_seed(0)
    target = TransferFunction.from_coefficients([0.1, 0.2], [1.0, -1.2, 0.5])
    x = signal((4, 400), seed=10)
    with torch.no_grad():
        y_target, _ = target(x)
    block = TransferFunction(2).double()
    opt = torch.optim.LBFGS(block.parameters(), lr=1.0, max_iter=200,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = (block(x)[0] - y_target).square().mean()
        loss.backward()
        return loss

    first = closure().item()
    opt.step(closure)
    assert closure().item() < 1e-8 * first
    torch.testing.assert_close(block.denominator(), target.denominator(), rtol=0, atol=1e-4)

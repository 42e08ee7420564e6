"""Derivatives through the autograd functions: ``torch.func`` equal to autograd, ``vmap``
equal to a loop, and second derivatives (``gradgradcheck`` in float64, and the play
operator's Hessian against the analytic one).

Each check runs with the compiled kernels and with the pure-torch paths (the ``kernel`` and
``filter_kernel`` fixtures' modes)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
from _helpers import smooth_input
from torch import Tensor

from torchhys.functional import (
    backlash,
    eiho,
    lfilter,
    prandtl_ishlinskii,
    preisach,
    preisach_grid,
    stop_pi,
)
from torchhys.functional._filter_kernel import filter_kernel_enabled
from torchhys.functional._kernel import kernel_enabled
from torchhys.functional.generalized_pi import monotone_mse
from torchhys.functional.linear_filter import linear_recurrence, state_space

F64 = torch.float64


@pytest.fixture(params=["kernel", "torch"])
def kernels(request: pytest.FixtureRequest):  # noqa: ANN201
    """Both paths: the compiled kernels (where built; else this equals the torch mode) and
    the pure-torch scans."""
    on = request.param == "kernel"
    with kernel_enabled(on), filter_kernel_enabled(on):
        yield request.param


def _walk(B: int = 2, T: int = 30, seed: int = 0) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, T, generator=g, dtype=F64).cumsum(1) * 0.5)


def _params(seed: int = 1) -> dict[str, Tensor]:
    g = torch.Generator().manual_seed(seed)
    alpha, beta = preisach_grid(-1.5, 1.5, 4, dtype=F64)
    return {
        "widths": torch.rand(4, generator=g, dtype=F64) + 0.1,
        "weights": torch.rand(4, generator=g, dtype=F64) + 0.2,
        "state": torch.randn(2, 4, generator=g, dtype=F64) * 0.2,
        "stop_w": torch.rand(4, 2, generator=g, dtype=F64) + 0.1,
        "alpha": alpha, "beta": beta,
        "density": torch.rand(alpha.shape[0], generator=g, dtype=F64),
        "b": torch.tensor([0.5, 0.3, -0.2], dtype=F64),
        "a": torch.tensor([1.0, -0.6, 0.2], dtype=F64),
        "A": torch.tensor([[0.5, 0.2], [-0.1, 0.4]], dtype=F64),
    }


P = _params()

# name -> (function of the differentiated tensors, those tensors)
OPERATORS: dict[str, tuple[Callable[..., Tensor], tuple[Tensor, ...]]] = {
    "play": (lambda x, w, s: backlash(x, w, state=s), (_walk(), P["widths"], P["state"])),
    "pi": (lambda x, w, v: prandtl_ishlinskii(x, w, v, linear_weight=0.5),
           (_walk(), P["widths"], P["weights"])),
    "stop_pi": (lambda x, w: stop_pi(x, P["widths"], w, linear_weight=0.3)[0],
                (_walk(), P["stop_w"])),
    "preisach_smooth": (lambda x, w: preisach(x, w, P["alpha"], P["beta"], smooth=0.3,
                                              linear=0.5), (_walk(), P["density"])),
    "preisach_hard": (lambda x, w: preisach(x, w, P["alpha"], P["beta"], linear=0.5),
                      (_walk(), P["density"])),
    "lfilter": (lambda x, b, a: lfilter(x, b, a)[0], (_walk(T=12), P["b"], P["a"])),
    "linear_recurrence": (lambda A, w: linear_recurrence(A, w),
                          (P["A"], _walk(T=24).reshape(2, 12, 2))),
    "state_space": (lambda u, A: state_space(u, A, torch.ones(2, dtype=F64),
                                             torch.ones(1, 2, dtype=F64),
                                             torch.zeros(1, dtype=F64))[0],
                    (_walk(T=12), P["A"])),
}


def _leaves(tensors: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    return tuple(t.detach().clone().requires_grad_() for t in tensors)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_func_grad_equals_autograd(name: str, kernels: str) -> None:
    fn, tensors = OPERATORS[name]
    args = _leaves(tensors)
    loss = lambda *a: fn(*a).square().sum()  # noqa: E731
    expected = torch.autograd.grad(loss(*args), args)
    got = torch.func.grad(loss, argnums=tuple(range(len(args))))(*args)
    for e, g in zip(expected, got, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)
    # vjp and jacrev against the same gradient
    out, vjp = torch.func.vjp(lambda *a: fn(*a), *args)
    for e, g in zip(expected, vjp(2 * out), strict=True):
        torch.testing.assert_close(g, e, rtol=1e-12, atol=1e-12)
    jac = torch.func.jacrev(lambda a1: loss(args[0], a1, *args[2:]))(args[1])
    torch.testing.assert_close(jac, expected[1], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_vmap_over_inputs_and_parameters_equals_a_loop(name: str, kernels: str) -> None:
    fn, tensors = OPERATORS[name]
    first, second, *rest = tensors
    g = torch.Generator().manual_seed(5)
    firsts = torch.stack([first, first + 0.1 * torch.randn(first.shape, generator=g, dtype=F64)])
    seconds = torch.stack([second, second * 1.1])
    got = torch.func.vmap(lambda f: fn(f, second, *rest))(firsts)
    torch.testing.assert_close(got, torch.stack([fn(f, second, *rest) for f in firsts]),
                               rtol=1e-12, atol=1e-12)
    got = torch.func.vmap(lambda s: fn(first, s, *rest))(seconds)
    torch.testing.assert_close(got, torch.stack([fn(first, s, *rest) for s in seconds]),
                               rtol=1e-12, atol=1e-12)
    # gradients per batch entry: vmap of grad against a loop of autograd
    loss = lambda f: fn(f, second, *rest).square().sum()  # noqa: E731
    got = torch.func.vmap(torch.func.grad(loss))(firsts)
    want = torch.stack([torch.autograd.grad(loss(f), f)[0]
                        for f in firsts.clone().requires_grad_()])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_gradgradcheck(name: str, kernels: str) -> None:
    fn, tensors = OPERATORS[name]
    args = _leaves(tuple(t[..., :10] if t.dim() == 2 and t.shape[-1] > 10 else t
                         for t in tensors))
    assert torch.autograd.gradgradcheck(fn, args)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_gradgradcheck_eiho(rule: str) -> None:
    x = smooth_input(20).requires_grad_()
    a = torch.tensor([1.2, 0.8], dtype=F64, requires_grad=True)
    x0 = x.detach()[0] - 0.1  # a fixed anchor below the first sample (off the square root's kink)

    def fn(x: Tensor, a: Tensor) -> Tensor:
        return eiho(torch.cat([x0.reshape(1), x]), a, rule=rule)[0][1:]

    assert torch.autograd.gradgradcheck(fn, (x, a), eps=1e-7, atol=1e-6)


def test_gradgradcheck_generalized_pi_loss() -> None:
    g = torch.Generator().manual_seed(2)
    design, y = torch.randn(20, 3, generator=g, dtype=F64), torch.randn(20, generator=g, dtype=F64)
    params = _leaves((torch.randn(3, generator=g, dtype=F64), torch.tensor(1.2, dtype=F64),
                      torch.rand(4, generator=g, dtype=F64), torch.randn(4, generator=g, dtype=F64),
                      torch.rand(4, generator=g, dtype=F64) + 0.5, torch.tensor(0.1, dtype=F64)))
    loss = lambda *p: monotone_mse(design, y, *p)  # noqa: E731
    assert torch.autograd.gradgradcheck(loss, params)
    # torch.func against autograd, and vmap over stacked parameter sets
    expected = torch.autograd.grad(loss(*params), params)
    got = torch.func.grad(loss, argnums=tuple(range(6)))(*params)
    for e, h in zip(expected, got, strict=True):
        torch.testing.assert_close(h, e, rtol=1e-12, atol=1e-12)
    ws = torch.randn(3, 3, generator=g, dtype=F64)
    torch.testing.assert_close(torch.func.vmap(lambda w: loss(w, *params[1:]))(ws),
                               torch.stack([loss(w, *params[1:]) for w in ws]))


def test_play_hessian_is_the_analytic_one(kernels: str) -> None:
    """L = sum(y^2): its Hessian in x is 2 J^T J (the play operator's own second derivative
    is zero), J the Jacobian; torch.func.hessian (forward over reverse) and the double
    backward (reverse over reverse) give it."""
    x = _walk(B=1, T=16)[0]
    w = P["widths"]
    J = torch.autograd.functional.jacobian(lambda x: backlash(x, w), x).reshape(-1, x.numel())
    loss = lambda x: backlash(x, w).square().sum()  # noqa: E731
    torch.testing.assert_close(torch.func.hessian(loss)(x), 2 * J.T @ J, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(torch.func.jacrev(torch.func.jacrev(loss))(x), 2 * J.T @ J,
                               rtol=1e-12, atol=1e-12)
    # the Jacobian is 0/1 (each output follows one input sample or the state)
    assert set(J.unique().tolist()) <= {0.0, 1.0}

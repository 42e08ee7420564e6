"""The torch-integration checks of :func:`torchhys.testing.check_conformance`: an operator
under ``torch.compile``, ``torch.export``, ``torch.func`` (``vmap``, ``grad``), meta and
fake tensors, and double backward (loaded when the checks run)."""

import copy
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor
from torch.utils._pytree import tree_flatten

from torchhys._conformance import PASSED, Case, assert_close, signal
from torchhys.operator import HysteresisOperator

TORCH_ATOL = 1e-12
"""Float64 tolerance of a traced or transformed path against eager, relative to the output's
scale (at least 1): compiled kernels fuse and round differently."""
T = 24
"""Samples of the signals of the torch checks (a trace that unrolls time costs with T)."""


def _x(case: Case, n: int = T) -> Tensor:
    return signal(n, case.dtype)


def _atol(case: Case) -> float:
    return max(TORCH_ATOL, case.atol) if case.dtype == torch.float64 else case.atol


def _cotangent(out: Tensor) -> Tensor:
    g = torch.Generator().manual_seed(5)
    return torch.randn(out.shape, generator=g, dtype=torch.float64).to(out.dtype)


def _params(op: HysteresisOperator) -> dict[str, Tensor]:
    return {k: p for k, p in op.named_parameters() if p.requires_grad}


def _grads(op: HysteresisOperator, call: Callable[[Tensor], Any], x: Tensor
           ) -> tuple[Tensor, list[Tensor], list[Tensor | None]]:
    """``call(x)``'s output (and state leaves), and the gradients of ``sum(out * g)`` in
    ``x`` and in the operator's parameters."""
    x = x.detach().clone().requires_grad_()
    out, state = call(x)
    params = list(_params(op).values())
    grads = torch.autograd.grad((out * _cotangent(out)).sum(), [x, *params],
                                allow_unused=True, materialize_grads=True)  # unused: zero
    return out.detach(), [s.detach() for s in tree_flatten(state)[0] if isinstance(s, Tensor)], \
        list(grads)


def _assert_grads(got: list, ref: list, atol: float, what: str, names: list[str]) -> None:
    for name, a, b in zip(names, got, ref, strict=True):
        if (a is None) != (b is None):
            raise AssertionError(f"{what}: the gradient in {name} is {a} against {b}")
        if a is not None and (a.numel() or a.shape != b.shape):
            assert_close(a, b, atol, f"{what}: the gradient in {name}")


def _states(got: list[Tensor], ref: list[Tensor], atol: float, what: str) -> None:
    if len(got) != len(ref):
        raise AssertionError(f"{what}: {len(got)} state tensors, expected {len(ref)}")
    for i, (a, b) in enumerate(zip(got, ref, strict=True)):
        assert_close(a, b, atol if a.is_floating_point() else 0.0, f"{what}, state leaf {i}")


def _compile(case: Case) -> str | None:
    """``torch.compile(op, fullgraph=True)``: output, state and gradients equal eager's."""
    op, x = case.build(), _x(case)
    torch._dynamo.reset()
    compiled = torch.compile(op, fullgraph=True)
    ref = _grads(op, op, x)
    got = _grads(op, compiled, x)
    names = ["x", *_params(op)]
    assert_close(got[0], ref[0], _atol(case), "torch.compile(fullgraph=True) against eager")
    _states(got[1], ref[1], _atol(case), "torch.compile(fullgraph=True)'s state against eager")
    _assert_grads(got[2], ref[2], _atol(case), "torch.compile(fullgraph=True)", names)
    torch._dynamo.reset()
    return PASSED


def _export(case: Case) -> str | None:
    """``torch.export.export`` with a dynamic time dimension: the program's output and state
    equal eager's, at the traced length and at another."""
    op, x = case.build(), _x(case)
    time = torch.export.Dim("time", min=2, max=1 << 20)
    with torch.no_grad():
        program = torch.export.export(op, (x,), dynamic_shapes={"x": {1: time}})
        module = program.module()
        for n in (T, T + 13, 5):
            v = _x(case, n)
            out, state = op(v)
            got, got_state = module(v)
            assert_close(got, out, _atol(case), f"the exported program at T={n} against eager")
            _states([s for s in tree_flatten(got_state)[0] if isinstance(s, Tensor)],
                    [s for s in tree_flatten(state)[0] if isinstance(s, Tensor)], _atol(case),
                    f"the exported program's state at T={n}")
    return PASSED


def _tensors(state: Any) -> list[Tensor]:
    return [s for s in tree_flatten(state)[0] if isinstance(s, Tensor)]


def _vmap(case: Case) -> str | None:
    """``torch.func.vmap`` over a batch of inputs (3 x (batch, time)): each equals its own
    call."""
    op, x = case.build(), _x(case)
    xs = torch.stack([x, 0.7 * x.flip(-1), -0.5 * x])
    with torch.no_grad():
        got, got_state = torch.func.vmap(lambda v: _pair(op(v)))(xs)
        for i in range(len(xs)):
            out, state = op(xs[i])
            assert_close(got[i], out, _atol(case), f"vmap over inputs, input {i}, against eager")
            _states([s[i] for s in got_state], _tensors(state), _atol(case),
                    f"vmap over inputs, input {i}'s state")
    return PASSED


def _pair(result: tuple[Tensor, Any]) -> tuple[Tensor, list[Tensor]]:
    return result[0], _tensors(result[1])


def _copies(op: HysteresisOperator, n: int) -> list[HysteresisOperator]:
    """``n`` copies of ``op``, the k-th with its floating parameters and buffers scaled by
    ``1 + 0.05 k`` where the operator's checks accept it (else as they were)."""
    out = [op]
    for k in range(1, n):
        other = copy.deepcopy(op)
        state = {key: v.detach().clone() for key, v in op.state_dict().items()}
        for key, value in state.items():
            if not value.is_floating_point():
                continue
            trial = {**state, key: value * (1 + 0.05 * k)}
            try:
                copy.deepcopy(op).load_state_dict(trial)
            except (RuntimeError, ValueError):
                continue
            state = trial
        other.load_state_dict(state)
        out.append(other)
    return out


def _vmap_params(case: Case) -> str | None:
    """``torch.func.vmap`` over stacked parameters and buffers
    (``torch.func.stack_module_state`` + ``functional_call``): each equals its module's call."""
    ops, x = _copies(case.build(), 3), _x(case)
    params, buffers = torch.func.stack_module_state(ops)
    base = copy.deepcopy(ops[0])

    def call(p: dict, b: dict) -> tuple[Tensor, list[Tensor]]:
        return _pair(torch.func.functional_call(base, (p, b), (x,)))
    with torch.no_grad():
        got, got_state = torch.func.vmap(call)(params, buffers)
        for i, op in enumerate(ops):
            out, state = op(x)
            assert_close(got[i], out, _atol(case),
                         f"vmap over stacked parameters, model {i}, against its own call")
            _states([s[i] for s in got_state], _tensors(state), _atol(case),
                    f"vmap over stacked parameters, model {i}'s state")
    return PASSED


def _shapes(result: tuple[Tensor, Any]) -> list[tuple[tuple[int, ...], torch.dtype]]:
    return [(tuple(t.shape), t.dtype) for t in [result[0], *_tensors(result[1])]]


def _meta(case: Case) -> str | None:
    """The operator on the meta device (``op.to("meta")``): the output's and state's shapes
    and dtypes are eager's."""
    op, x = case.build(), _x(case)
    with torch.no_grad():
        ref = _shapes(op(x))
        got = _shapes(copy.deepcopy(op).to("meta")(x.to("meta")))
    if got != ref:
        raise AssertionError(f"on meta tensors: shapes and dtypes {got}, eager {ref}")
    return PASSED


def _fake(case: Case) -> str | None:
    """The operator under ``FakeTensorMode``, its parameters and buffers fake
    (``functional_call``): the output's and state's shapes and dtypes are eager's."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    op, x = case.build(), _x(case)
    with torch.no_grad():
        ref = _shapes(op(x))
        mode = FakeTensorMode()
        entries = {**dict(op.named_parameters()), **dict(op.named_buffers())}
        fake = {k: mode.from_tensor(v) for k, v in entries.items()}
        fx = mode.from_tensor(x)
        with mode:
            got = _shapes(torch.func.functional_call(op, fake, (fx,)))
    if got != ref:
        raise AssertionError(f"under FakeTensorMode: shapes and dtypes {got}, eager {ref}")
    return PASSED


def _func_grad(case: Case) -> str | None:
    """``torch.func.grad`` of ``sum(forward(x) * g)`` in the input and in the parameters
    equals ``torch.autograd.grad``."""
    op, x = case.build(), _x(case)
    _, _, ref = _grads(op, op, x)
    g = _cotangent(op(x)[0])
    params = {k: p.detach() for k, p in _params(op).items()}

    def loss(v: Tensor, p: dict) -> Tensor:
        return (torch.func.functional_call(op, p, (v,))[0] * g).sum()
    gx, gp = torch.func.grad(loss, argnums=(0, 1))(x, params)
    _assert_grads([gx, *gp.values()], ref, _atol(case), "torch.func.grad against autograd",
                  ["x", *params])
    return PASSED


def _gradgradcheck(case: Case) -> str | None:
    """``torch.autograd.gradgradcheck`` of ``forward`` in the input (float64), or the
    example's documented refusal: double backward raises an error matching it."""
    if case.example.no_gradcheck is not None:
        return case.example.no_gradcheck
    if case.dtype != torch.float64:
        return "gradgradcheck runs in float64"
    op, t = case.build(), torch.arange(12, dtype=torch.float64)
    x = torch.stack([0.8 * torch.sin(0.61 * t + 0.3) + 0.05 * t ** 0.5,
                     0.7 * torch.cos(0.83 * t + 0.1) - 0.013 * t]).requires_grad_()
    refusal = getattr(case.example, "no_gradgradcheck", None)
    if refusal is not None:
        import re
        try:
            y = op(x)[0]
            v = _cotangent(y).requires_grad_()  # as gradgradcheck's: once_differentiable
            (g,) = torch.autograd.grad((y * v).sum(), x, create_graph=True)  # raises then
            g.sum().backward()  # every node runs: a refusal in one raises
        except RuntimeError as e:
            if not re.search(refusal, str(e)):
                raise AssertionError(f"double backward raises {str(e)!r}, not the documented "
                                     f"refusal {refusal!r}") from e
            return f"double backward is refused as documented: {e}"
        raise AssertionError(f"double backward does not raise the documented refusal "
                             f"{refusal!r}")
    torch.autograd.gradgradcheck(lambda v: op(v)[0], (x,), raise_exception=True)
    return PASSED


RUNS: dict[str, tuple[Callable[[Case], str | None], bool]] = {
    "compile": (_compile, False),
    "export": (_export, False),
    "vmap": (_vmap, True),
    "vmap_params": (_vmap_params, True),
    "meta": (_meta, False),
    "fake": (_fake, False),
    "func_grad": (_func_grad, True),
    "gradgradcheck": (_gradgradcheck, True),
}
"""The torch-integration checks by name, and whether each runs with the compiled kernels
and with the scans."""

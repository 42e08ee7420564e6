"""The compiled kernels as torch custom ops (``torch.ops.torchhys.*``): ``opcheck`` (schema,
fake implementation, autograd registration, AOT dispatch), results against plain loops,
fake and meta shapes, the kernel-or-scan choice made when the op runs, Dynamo tracing
through the ops without graph breaks, and the adjoint ops' refusal to be differentiated."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor
from torch._subclasses.fake_tensor import FakeTensorMode

from torchhys.functional import _filter_kernel as fk
from torchhys.functional import _kernel as pk
from torchhys.functional import backlash, lfilter, play_step
from torchhys.functional._compile import dispatched
from torchhys.functional.linear_filter import df2t_step, linear_recurrence

F64 = torch.float64


@pytest.fixture(params=["kernel", "torch"])
def mode(request: pytest.FixtureRequest):  # noqa: ANN201
    """The op running the compiled kernels (where built) and running the torch scans."""
    on = request.param == "kernel"
    with pk.kernel_enabled(on), fk.filter_kernel_enabled(on):
        yield request.param


def _rand(*shape: int, seed: int = 0, grad: bool = False) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=F64).requires_grad_(grad)


def _play_args(T: int = 70, grad: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    # T = 70 > 64: the scan cuts time into chunks (with padding)
    x = (_rand(2, T, seed=1).cumsum(1) * 0.5).requires_grad_(grad)
    return x, (_rand(3, seed=2).abs() + 0.1).requires_grad_(grad), _rand(2, 3, seed=3, grad=grad)


def _filter_args(grad: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    b = _rand(2, 3, seed=4, grad=grad)
    a = (0.3 * _rand(2, 2, seed=5)).requires_grad_(grad)
    return _rand(4, 20, seed=6, grad=grad), b, a, _rand(4, 2, seed=7, grad=grad)


def _linrec_args(grad: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    A = (0.3 * _rand(2, 2, seed=8)).requires_grad_(grad)
    return A, _rand(3, 15, 2, seed=9, grad=grad), _rand(3, 2, seed=10, grad=grad)


def test_opcheck_play_ops(mode: str) -> None:
    args = _play_args()
    torch.library.opcheck(pk.play_op, args)
    y = pk.play_op(*args).detach()
    g = _rand(*y.shape, seed=11, grad=True)
    torch.library.opcheck(pk.play_adjoint_op, (g, *(a.detach() for a in args), y))


def test_opcheck_filter_ops(mode: str) -> None:
    args = _filter_args()
    torch.library.opcheck(fk.df2t_op, args)
    y, zf = fk.df2t_op(*args)
    plain = tuple(a.detach() for a in args)
    torch.library.opcheck(fk.df2t_adjoint_op, (_rand(*y.shape, seed=12), _rand(*zf.shape, seed=13),
                                               plain[0], plain[1], plain[2], y.detach()))
    args = _linrec_args()
    torch.library.opcheck(fk.linrec_op, args)
    s = fk.linrec_op(*args).detach()
    plain = tuple(a.detach() for a in args)
    torch.library.opcheck(fk.linrec_adjoint_op, (_rand(*s.shape, seed=14), plain[0], plain[2], s))


def test_opcheck_preisach_inverse() -> None:
    from torchhys import Preisach
    from torchhys.functional._preisach_kernel import _load, inverse_op
    from torchhys.functional.preisach_inverse import (
        _inverse_windows,
        preisach_inverse_constants,
    )

    if _load() is None:
        pytest.skip("the Preisach-inverse kernel is not built here")
    m = Preisach(-2.0, 3.0, 5, scale=0.5).double()
    with torch.no_grad():
        m.weights.copy_(torch.rand(m.n_relays, generator=torch.Generator().manual_seed(0),
                                   dtype=F64))
        m.linear.fill_(0.7)
    linear = m.linear.detach().reshape(())
    tables = preisach_inverse_constants(m.alpha, m.beta, m.weights.detach(), linear,
                                        m.offset.detach().reshape(()), m.center, m.scale)
    y = (_rand(2, 40, seed=15).cumsum(1) * 0.3).clamp(-1.5, 2.5)
    r0 = torch.ones(2, m.n_relays, dtype=F64)
    args = (y, r0, m.alpha, m.beta, *tables, float(linear), float(m.center), m.scale)
    torch.library.opcheck(inverse_op, args)
    x, r = inverse_op(*args)
    ref, r_ref = _inverse_windows(y, r0, m.alpha, m.beta, tables, linear, m.center, m.scale)
    torch.testing.assert_close(x, ref, rtol=1e-12, atol=1e-12)
    assert torch.equal(r, r_ref)
    with pytest.raises(RuntimeError, match="preisach_inverse has no gradient"):
        yg = y.clone().requires_grad_()
        inverse_op(yg, *args[1:])[0].sum().backward()


def test_play_op_equals_the_step_loop_and_its_gradients_autograd_of_the_loop(mode: str) -> None:
    x, r, y0 = _play_args()
    y = pk.play_op(x, r, y0)
    s, steps = y0, []
    for t in range(x.shape[1]):
        s = play_step(x[:, t:t + 1], r, s)
        steps.append(s)
    ref = torch.stack(steps, dim=1)
    torch.testing.assert_close(y, ref, rtol=0, atol=0)
    g = _rand(*y.shape, seed=16)
    got = torch.autograd.grad(y, (x, r, y0), g)
    want = torch.autograd.grad(ref, (x, r, y0), g)
    for u, v in zip(got, want, strict=True):
        torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-12)


def test_df2t_and_linrec_ops_equal_the_step_loops(mode: str) -> None:
    x, b, a, zi = (t.detach() for t in _filter_args())
    y, zf = fk.df2t_op(x, b, a, zi)
    rows = torch.arange(x.shape[0]) % b.shape[0]
    z, outs = zi, []
    for t in range(x.shape[1]):
        yt, z = df2t_step(x[:, t:t + 1], z, b[rows], a[rows])
        outs.append(yt)
    torch.testing.assert_close(y, torch.cat(outs, 1), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(zf, z, rtol=1e-13, atol=1e-13)
    A, w, s0 = (t.detach() for t in _linrec_args())
    s, states = s0, []
    for t in range(w.shape[1]):
        s = s @ A.mT + w[:, t]
        states.append(s)
    torch.testing.assert_close(fk.linrec_op(A, w, s0), torch.stack(states, 1), rtol=1e-13,
                               atol=1e-13)


def test_the_op_chooses_kernel_or_scan_when_it_runs() -> None:
    """The choice is made inside the op, at run time: one compiled graph follows
    kernel_enabled, with the same results."""
    if pk.kernel_unavailable_reason() is not None:
        pytest.skip(pk.kernel_unavailable_reason())
    x, r, y0 = _play_args(grad=False)
    calls = []
    real = pk.play_forward_kernel

    def counting(*args: Tensor) -> Tensor:
        calls.append(1)
        return real(*args)

    f = torch.compile(lambda x: pk.play_op(x, r, y0), fullgraph=True, backend="eager")
    pk.play_forward_kernel = counting  # type: ignore[assignment]
    try:
        with pk.kernel_enabled(True):
            on = f(x)
        with pk.kernel_enabled(False):
            off = f(x)
    finally:
        pk.play_forward_kernel = real  # type: ignore[assignment]
    assert len(calls) == 1
    torch.testing.assert_close(on, off, rtol=0, atol=0)


def test_fake_and_meta_shapes() -> None:
    with FakeTensorMode():
        x, r, y0 = torch.randn(2, 50, dtype=F64), torch.rand(3, dtype=F64), torch.zeros(2, 3,
                                                                                     dtype=F64)
        assert dispatched(x)
        assert pk.play_op(x, r, y0).shape == (2, 50, 3)
        gx, gr, gy0 = pk.play_adjoint_op(torch.randn(2, 50, 3, dtype=F64), x, r, y0,
                                         torch.randn(2, 50, 3, dtype=F64))
        assert (gx.shape, gr.shape, gy0.shape) == ((2, 50), (3,), (2, 3))
        y, zf = fk.df2t_op(torch.randn(4, 9), torch.randn(2, 3), torch.randn(2, 2),
                           torch.zeros(4, 2))
        assert (y.shape, zf.shape) == ((4, 9), (4, 2))
        assert fk.linrec_op(torch.eye(2), torch.randn(3, 7, 2), torch.zeros(3, 2)).shape == (
            3, 7, 2)
    meta = torch.randn(2, 50, device="meta")
    assert dispatched(meta) and not dispatched(torch.randn(3))
    assert backlash(meta, torch.rand(3, device="meta")).shape == (2, 50, 3)
    assert lfilter(meta, torch.ones(2, device="meta"), torch.tensor([1.0, -0.5],
                                                                     device="meta"))[0].shape == (
        2, 50)


@pytest.mark.parametrize("name", ["backlash", "lfilter", "linear_recurrence"])
def test_dynamo_traces_through_the_ops_without_graph_breaks(name: str, mode: str) -> None:
    x = (_rand(2, 70, seed=17).cumsum(1) * 0.3).requires_grad_()
    w = (_rand(3, seed=18).abs() + 0.1).requires_grad_()
    A = (0.3 * _rand(3, 3, seed=19)).requires_grad_()
    fns = {
        "backlash": (lambda x, w: backlash(x, w), torch.ops.torchhys.play),
        "lfilter": (lambda x, w: lfilter(x, w, torch.tensor([1.0, -0.4], dtype=F64))[0],
                    torch.ops.torchhys.df2t),
        "linear_recurrence": (lambda x, w: linear_recurrence(A, x.unsqueeze(-1).expand(
            -1, -1, 3) * w), torch.ops.torchhys.linrec),
    }
    fn, op = fns[name]
    torch._dynamo.reset()
    explained = torch._dynamo.explain(fn)(x, w)
    assert explained.graph_break_count == 0, explained.break_reasons
    targets = {node.target for graph in explained.graphs for module in graph.modules()
               if isinstance(module, torch.fx.GraphModule) for node in module.graph.nodes}
    assert any(getattr(t, "overloadpacket", t) is op or t is op for t in targets), targets
    compiled = torch.compile(fn, fullgraph=True, backend="aot_eager")
    out, ref = compiled(x, w), fn(x, w)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    g = torch.randn_like(ref)
    for u, v in zip(torch.autograd.grad(out, (x, w), g), torch.autograd.grad(ref, (x, w), g),
                    strict=True):
        torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-12)


def test_the_filter_adjoint_ops_refuse_a_derivative_of_their_own() -> None:
    x, b, a, zi = (t.detach() for t in _filter_args())
    y, zf = fk.df2t_op(x, b, a, zi)
    gy = torch.randn_like(y).requires_grad_()
    gx = fk.df2t_adjoint_op(gy, torch.zeros_like(zf), x, b, a, y)[0]
    with pytest.raises(RuntimeError, match="df2t_adjoint is a first-order gradient"):
        gx.sum().backward()
    # differentiating the forward op twice goes through the tensor-operation adjoint instead
    args = _filter_args()
    assert torch.autograd.gradgradcheck(lambda *a: fk.df2t_op(*a)[0], args)
    assert torch.autograd.gradgradcheck(fk.linrec_op, _linrec_args())
    assert torch.autograd.gradgradcheck(pk.play_op, _play_args(T=12))

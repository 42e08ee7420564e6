"""Preisach model: plain-loop reference, hysteresis properties, chunking, streaming step
(eager and TorchScript), autograd."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import torchhys.functional.preisach as fp
from torchhys.functional.preisach import (
    demagnetized_state,
    preisach,
    preisach_grid,
    relay_states,
)
from torchhys.operator import OPERATORS, make_operator
from torchhys.preisach import Preisach

F64 = torch.float64


def relay_reference(x: np.ndarray, alpha: np.ndarray, beta: np.ndarray,
                    r0: np.ndarray) -> np.ndarray:
    """Plain float64 loop: x (B, T), alpha, beta (K,), r0 (B, K) -> relays (B, T, K)."""
    B, T = x.shape
    K = alpha.shape[0]
    out = np.empty((B, T, K))
    for b in range(B):
        r = [float(v) for v in r0[b]]
        for t in range(T):
            for k in range(K):
                if x[b, t] >= alpha[k]:
                    r[k] = 1.0
                elif x[b, t] <= beta[k]:
                    r[k] = -1.0
            out[b, t] = r
    return out


def demag_reference(n: int) -> np.ndarray:
    """+1 strictly below the anti-diagonal i + j = n - 1 of the grid, -1 on and above it."""
    i, j = np.tril_indices(n)
    return np.where(i + j < n - 1, 1.0, -1.0)


def signal(B: int, T: int, n: int, seed: int = 0) -> torch.Tensor:
    """A random walk over [-1.3, 1.3] with samples exactly on the grid levels, repeats and
    a flat stretch (ties and saturation)."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.randn(B, T, generator=g, dtype=F64) * 0.35).cumsum(1)
    x = 1.3 * torch.sin(x)
    levels = -1.0 + 2.0 * (torch.arange(n, dtype=F64) + 0.5) / n
    on = torch.rand(B, T, generator=g) < 0.3
    x = torch.where(on, levels[torch.randint(n, (B, T), generator=g)], x)
    x[:, T // 3: T // 3 + 5] = x[:, T // 3: T // 3 + 1]
    return x


def ramps(points: list[float], step: float = 0.01) -> torch.Tensor:
    """Piecewise-linear input through the given extrema, (1, T)."""
    parts = [torch.tensor([points[0]], dtype=F64)]
    for a, b in zip(points[:-1], points[1:], strict=True):
        m = max(1, int(round(abs(b - a) / step)))
        parts.append(torch.linspace(a, b, m + 1, dtype=F64)[1:])
    return torch.cat(parts)[None]


def model(n: int = 9, seed: int = 0, **options) -> Preisach:
    m = Preisach(-1.0, 1.0, n, **options).double()
    with torch.no_grad():
        m.weights.copy_(torch.rand(m.n_relays, generator=torch.Generator().manual_seed(seed),
                                   dtype=F64))
        m.linear.fill_(0.3)
        m.offset.fill_(-0.2)
    return m


@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_grid_and_demagnetized_state(n):
    alpha, beta = preisach_grid(-3.7, 11.1, n, dtype=F64)
    assert alpha.shape == beta.shape == (n * (n + 1) // 2,)
    assert bool((alpha >= beta).all())
    i, j = np.tril_indices(n)
    levels = -3.7 + 14.8 * (np.arange(n) + 0.5) / n
    np.testing.assert_allclose(alpha.numpy(), levels[i], rtol=0, atol=1e-12)
    np.testing.assert_allclose(beta.numpy(), levels[j], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(demagnetized_state(alpha, beta).numpy(), demag_reference(n))
    m = Preisach(-3.7, 11.1, n)
    np.testing.assert_array_equal(m.initial_relays.numpy(), demag_reference(n))


@pytest.mark.parametrize("B, T, n", [(1, 1, 1), (3, 257, 7), (2, 60, 4), (1, 300, 12)])
@pytest.mark.parametrize("given_r0", [False, True])
def test_relays_match_reference(B, T, n, given_r0):
    x = signal(B, T, n)
    alpha, beta = preisach_grid(-1.0, 1.0, n, dtype=F64)
    K = alpha.numel()
    r0 = (torch.randint(0, 2, (B, K), generator=torch.Generator().manual_seed(1)) * 2 - 1
          ).to(F64) if given_r0 else None
    ref_r0 = r0.numpy() if given_r0 else np.tile(demag_reference(n), (B, 1))
    ref = relay_reference(x.numpy(), alpha.numpy(), beta.numpy(), ref_r0)
    out = relay_states(x, alpha, beta, r0=r0)
    assert out.shape == (B, T, K) and out.dtype == F64
    np.testing.assert_array_equal(out.numpy(), ref)
    w = torch.rand(K, dtype=F64)
    y = preisach(x, w, alpha, beta, offset=0.4, linear=-1.5, r0=r0)
    np.testing.assert_allclose(y.numpy(), 0.4 - 1.5 * x.numpy() + ref @ w.numpy(),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(relay_states(x[0], alpha, beta, r0=None if r0 is None
                                               else r0[0]).numpy(), ref[0])


@pytest.mark.parametrize("chunk", [1, 7, 50, 1000])
def test_time_chunks_carry_the_crossings(monkeypatch, chunk):
    x = signal(2, 211, 6, seed=3)
    alpha, beta = preisach_grid(-1.0, 1.0, 6, dtype=F64)
    w = torch.rand(alpha.numel(), dtype=F64, requires_grad=True)
    whole = relay_states(x, alpha, beta)
    y = preisach(x, w, alpha, beta, smooth=0.1)
    (gw,) = torch.autograd.grad(y.square().sum(), w)
    monkeypatch.setattr(fp, "_CHUNK", chunk)
    torch.testing.assert_close(relay_states(x, alpha, beta), whole, rtol=0, atol=0)
    y2 = preisach(x, w, alpha, beta, smooth=0.1)
    torch.testing.assert_close(y2, y, rtol=0, atol=1e-13)
    torch.testing.assert_close(torch.autograd.grad(y2.square().sum(), w)[0], gw)


def test_wiping_out():
    """A larger maximum erases the memory of the smaller extrema before it."""
    m = model(initial="negative")
    ya, sa = m(ramps([-1.2, 0.5, -0.2, 0.35, -0.1, 0.8]))
    yb, sb = m(ramps([-1.2, 0.8]))
    torch.testing.assert_close(sa, sb, rtol=0, atol=0)
    tail = ramps([0.8, -0.5, 0.3, -0.1])
    torch.testing.assert_close(m(tail, sa)[0], m(tail, sb)[0], rtol=0, atol=0)
    assert not torch.equal(m(ramps([-1.2, 0.5, -0.2, 0.35]))[1], m(ramps([-1.2, 0.35]))[1])


def test_congruency_of_minor_loops():
    """Minor loops between the same two inputs after different histories: same shape,
    shifted vertically."""
    m = model(n=12, seed=2, initial="negative")
    u1, u2 = -0.25, 0.35
    loop = ramps([u2, u1, u2, u1, u2, u1, u2])[:, 1:]
    ya, sa = m(ramps([-1.2, 0.9, -0.6]))
    yb, sb = m(ramps([-1.2, 0.5, -0.95]))
    with torch.no_grad():
        diff = (m(loop, sa)[0] - m(loop, sb)[0])[0, loop.shape[1] // 3:]
    assert abs(float(diff.mean())) > 1e-3  # the histories differ
    assert float(diff.std()) < 1e-12


def test_return_point_memory():
    """Closing a minor loop returns to the output at its start and forgets the loop."""
    m = model(seed=4)
    head = ramps([-1.2, 0.6, -0.4, 0.5])
    y0, s0 = m(head)
    y1, s1 = m(ramps([0.5, 0.1, 0.5])[:, 1:], s0)
    torch.testing.assert_close(y1[:, -1], y0[:, -1], rtol=0, atol=1e-14)
    torch.testing.assert_close(s1, s0, rtol=0, atol=0)
    tail = ramps([0.5, -0.3, 0.2])[:, 1:]
    torch.testing.assert_close(m(tail, s1)[0], m(tail, s0)[0], rtol=0, atol=0)


@pytest.mark.parametrize("smooth", [None, 0.05])
@pytest.mark.parametrize("splits", [[1] * 30, [5, 100, 152], [256, 1], [100, 157]])
def test_chunked_calls_equal_one_call(smooth, splits):
    m = model(smooth=smooth)
    x = signal(3, sum(splits), 9, seed=5)
    whole, final = m(x)
    parts, state = [], None
    for chunk in x.split(splits, dim=1):
        y, state = m(chunk, state)
        parts.append(y)
    torch.testing.assert_close(torch.cat(parts, 1), whole, rtol=0, atol=1e-14)
    torch.testing.assert_close(state, final, rtol=0, atol=0)


def _run(step, x: torch.Tensor, init) -> tuple[torch.Tensor, list[torch.Tensor]]:
    state = init.initial_state(x[:, :1])
    outs = []
    for xt in x.unbind(1):
        f, state = step(xt.unsqueeze(1), state)
        outs.append(f)
    return torch.stack(outs, 1), state


@pytest.mark.parametrize("smooth", [None, 0.05])
@pytest.mark.parametrize("initial", ["demagnetized", "positive", "negative"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_step_eager_and_scripted_equal_sequence(smooth, initial, dtype):
    m = model(smooth=smooth, initial=initial)
    x = signal(2, 150, 9, seed=6).to(dtype)
    y, final = m.to(dtype)(x)
    step = m.streaming_step(dtype)
    assert step.n_outputs == 1 and step.state_spec[0].size == m.n_relays
    with warnings.catch_warnings():  # torch.jit.script is deprecated in torch 2.13
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated",
                                category=DeprecationWarning)
        scripted = torch.jit.script(step)
    for s in (step, scripted):
        f, state = _run(s, x, step)
        assert f.shape == (2, 150, 1) and f.dtype == dtype
        tol = 1e-13 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(f[..., 0], y.detach(), rtol=0, atol=tol)
        torch.testing.assert_close(state[0], final, rtol=0, atol=0)
    torch.testing.assert_close(step.run(x)[..., 0], y.detach(), rtol=0, atol=tol)


def test_registered_and_one_dimensional():
    assert OPERATORS["preisach"] is Preisach
    m = make_operator("preisach", lo=-1.0, hi=1.0, n=5)
    x = signal(1, 40, 5, seed=7).float()
    y, s = m(x[0])
    assert y.shape == (40,) and s.shape == (15,)
    torch.testing.assert_close(y, m(x)[0][0])


def _off_threshold(B: int, T: int, n: int, seed: int) -> torch.Tensor:
    """Samples a tenth of a cell or more away from every level (the levels are the cell
    centres), so that finite differences stay on a branch."""
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
    assert relay_states(xs, a, b, r0=r).item() == hard
    tau = 0.25
    y = preisach(xs, torch.ones(1, dtype=F64), a, b, r0=r, smooth=tau)
    expected = np.tanh((x - theta) / tau)
    assert y.item() == pytest.approx(expected, abs=1e-15)
    (gx,) = torch.autograd.grad(y.sum(), xs)
    assert gx.item() == pytest.approx((1 - expected**2) / tau, abs=1e-12)

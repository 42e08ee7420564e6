"""Preisach model: plain-loop reference, hysteresis properties, chunking, streaming step
(eager and TorchScript), autograd."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch
from _preisach_helpers import model, signal

from torchhys.functional.preisach import (
    demagnetized_state,
    preisach,
    preisach_grid,
    relay_states,
)
from torchhys.operators.preisach import Preisach

F64 = torch.float64

# the module (the package re-exports a function of the same name)
fp = importlib.import_module("torchhys.functional.preisach")


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


def ramps(points: list[float], step: float = 0.01) -> torch.Tensor:
    """Piecewise-linear input through the given extrema, (1, T)."""
    parts = [torch.tensor([points[0]], dtype=F64)]
    for a, b in zip(points[:-1], points[1:], strict=True):
        m = max(1, int(round(abs(b - a) / step)))
        parts.append(torch.linspace(a, b, m + 1, dtype=F64)[1:])
    return torch.cat(parts)[None]


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
    out = relay_states(x, alpha, beta, state=r0)
    assert out.shape == (B, T, K) and out.dtype == F64
    np.testing.assert_array_equal(out.numpy(), ref)
    w = torch.rand(K, dtype=F64)
    y = preisach(x, w, alpha, beta, offset=0.4, linear=-1.5, state=r0)
    np.testing.assert_allclose(y.numpy(), 0.4 - 1.5 * x.numpy() + ref @ w.numpy(),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(relay_states(x[0], alpha, beta, state=None if r0 is None
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


@pytest.mark.parametrize("initial", ["positive", "negative", "given", "demagnetized"])
def test_module_initial_relays_and_fixed_terms(initial: str) -> None:
    """``Preisach(initial=...)`` starts from the stated relays (against the plain loop), and
    ``linear=False`` / ``offset=False`` hold those terms at 0 outside the parameters."""
    n = 6
    alpha, beta = preisach_grid(-1.0, 1.0, n, dtype=F64)
    K = alpha.numel()
    g = torch.Generator().manual_seed(7)
    given = torch.where(torch.rand(K, generator=g, dtype=F64) < 0.5, -1.0, 1.0).to(F64)
    r0 = {"positive": np.ones(K), "negative": -np.ones(K), "given": given.numpy(),
          "demagnetized": demag_reference(n)}[initial]
    m = Preisach(-1.0, 1.0, n, linear=False, offset=False,
                 initial=given if initial == "given" else initial).to(F64)
    w = torch.rand(K, generator=g, dtype=F64)
    with torch.no_grad():
        m.weights.copy_(w)
    names = {name for name, _ in m.named_parameters()}
    assert names == {"weights"}
    x = (0.15 * torch.randn(1, 120, generator=g, dtype=F64)).cumsum(1).clamp(-1.2, 1.2)
    relays = relay_reference(x.numpy(), alpha.numpy(), beta.numpy(), r0[None])
    expected = torch.from_numpy(relays @ w.numpy())
    torch.testing.assert_close(m(x)[0], expected, rtol=0, atol=1e-12)
    with torch.no_grad():  # a held term is a buffer: it still reads from the state dict
        m.offset.fill_(0.25)
    torch.testing.assert_close(m(x)[0], expected + 0.25, rtol=0, atol=1e-12)

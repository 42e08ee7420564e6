"""The pure-torch fallback of :mod:`torchhys.functional.linear_filter`: a chunked scan.

``s[t] = A s[t-1] + w[t]`` over T samples: the time axis is cut into C chunks of
``K ~ sqrt(T / 2)`` samples; one pass over the K positions (vectorised over all chunks) runs
each chunk from a zero entering state, one pass over the C chunks carries the state entering
each chunk with ``A^K``, and one batched product adds ``A^(k+1) s_in`` to position k. About
``2 sqrt(2 T)`` tensor operations, no autograd graph (the callers' backward is their own),
equal to the sample-by-sample recursion to float rounding. Used where the compiled kernel
cannot run (no C compiler, a non-CPU device, a dtype other than float32/float64).

The adjoints (:func:`df2t_adjoint_torch`, :func:`linrec_adjoint_torch`) are the backward
passes in tensor operations, with the recursion a function argument: the autograd function
(differentiable again) or the kernel-or-scan implementation (no graph).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor


def recurrence_scan(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    """s[t] = A s[t-1] + w[t], s[-1] = s0: A (n, n), w (R, T, n), s0 (R, n) -> (R, T, n)."""
    R, T, n = w.shape
    K = T if T <= 16 else max(4, round(math.sqrt(T / 2.0)))
    C = -(-T // K)
    if C * K > T:
        w = torch.cat([w, w.new_zeros(R, C * K - T, n)], dim=1)
    wc = w.reshape(R, C, K, n)
    AT = A.mT
    local = torch.empty_like(wc)  # each chunk from a zero entering state
    s = w.new_zeros(R, C, n)
    for k in range(K):
        s = s @ AT + wc[:, :, k]
        local[:, :, k] = s
    powers = torch.empty(K, n, n, dtype=w.dtype, device=w.device)  # A^(k+1)
    p = A
    for k in range(K):
        powers[k] = p
        p = p @ A
    carry = torch.empty(R, C, n, dtype=w.dtype, device=w.device)
    s = s0
    for c in range(C):
        carry[:, c] = s
        s = s @ powers[K - 1].mT + local[:, c, K - 1]
    out = local + torch.einsum("rcj,kij->rcki", carry, powers)
    return out.reshape(R, C * K, n)[:, :T]


def df2t_scan(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    """DF2T through the scan: the delays follow z <- Ac z + (b[1:] - a b[0]) x."""
    n = a.shape[0]
    Ac = torch.diag(x.new_ones(n - 1), 1)
    Ac[:, 0] -= a
    z = recurrence_scan(Ac, x.unsqueeze(-1) * (b[1:] - a * b[0]), zi)
    z0 = torch.cat([zi[:, :1], z[:, :-1, 0]], dim=1)
    return b[0] * x + z0, z[:, -1]


def _df2t_scan_filters(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`df2t_scan` for F filters (b (F, n+1), a (F, n), row r uses filter r % F): one
    scan per filter over all its rows."""
    F = b.shape[0]
    if F == 1:
        return df2t_scan(x, b[0], a[0], zi)
    R, T = x.shape
    xs, zs = x.reshape(R // F, F, T), zi.reshape(R // F, F, -1)
    parts = [df2t_scan(xs[:, f], b[f], a[f], zs[:, f]) for f in range(F)]
    y = torch.stack([p[0] for p in parts], dim=1).reshape(R, T)
    return y, torch.stack([p[1] for p in parts], dim=1).reshape(R, -1)


def df2t_adjoint_torch(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor,
                       df2t: Callable[..., tuple[Tensor, Tensor]]
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gradients (gx, gb, ga, gzi) of ``<gy, y> + <gzf, zf>`` for the DF2T filters of
    x (R, T), b (F, n+1), a (F, n) = a[:, 1:] (row r uses filter r % F), with
    ``df2t(x, b, a, zi) -> (y, zf)`` running the all-pole adjoint recursion."""
    R, T = x.shape
    F, n = a.shape
    rows = a.repeat(R // F, 1)  # each row's a: (R, n)
    # lam[T + i] = gzf[i]: the tail input that makes the backward recursion produce it
    tail = gzf
    for k in range(1, n):
        tail = tail + rows[:, k - 1:k] * torch.cat([gzf[:, k:], gzf.new_zeros(R, k)], 1)
    u = torch.cat([gy, tail], dim=1).flip(1)
    e0 = torch.cat([b.new_ones(F, 1), b.new_zeros(F, n)], dim=1)
    lam = df2t(u, e0, a, u.new_zeros(R, n))[0].flip(1)  # (R, T + n)
    win = torch.stack([lam[:, k: k + T] for k in range(n + 1)], 1)  # lam[t + k]: (R, n+1, T)
    win = win.reshape(R // F, F, n + 1, T)  # rows as (batch, filter)
    xs, ys = x.reshape(R // F, F, T), y.reshape(R // F, F, T)
    gx = torch.einsum("fk,bfkt->bft", b, win).reshape(R, T)
    gb = torch.einsum("bfkt,bft->fk", win, xs)
    ga = -torch.einsum("bfkt,bft->fk", win[:, :, 1:], ys)
    return gx, gb, ga, lam[:, :n]


def linrec_adjoint_torch(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor,
                         linrec: Callable[..., Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients (gA, gw, gs0) of ``<gs, s>`` for s[t] = A s[t-1] + w[t], with
    ``linrec(A, w, s0) -> s`` running the adjoint recursion."""
    # lam[t] = gs[t] + A^T lam[t+1]: the same recurrence, backwards in time, with A^T
    lam = linrec(A.mT, gs.flip(1), torch.zeros_like(s0)).flip(1)
    prev = torch.cat([s0.unsqueeze(1), s[:, :-1]], dim=1)
    gA = torch.einsum("rti,rtj->ij", lam, prev)
    return gA, lam, lam[:, 0] @ A

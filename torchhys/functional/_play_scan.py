"""The pure-torch play-operator scan: a blocked clamp composition and its exact adjoint.

The algorithm is described in :mod:`torchhys.functional.backlash`; the compiled kernel of
:mod:`torchhys.functional._kernel` computes the same results where it can run.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _chunking(T: int) -> tuple[int, int]:
    """Chunk length K and number of chunks C with C * K >= T.

    K is near sqrt(T / 2), which balances the two passes over K positions against the
    pass over C chunks; a divisor of T within 30% of it is preferred (no padding).
    """
    if T <= 64:
        return T, 1
    target = max(8, int(math.sqrt(T / 2.0)))
    for delta in range(0, int(0.3 * target) + 1):
        for K in (target + delta, target - delta):
            if K >= 8 and T % K == 0:
                return K, T // K
    return target, -(-T // target)


def _padded_chunks(x: Tensor, K: int, C: int) -> Tensor:
    """(B, T) -> (B, C, K), padding the tail with the last sample."""
    pad = C * K - x.shape[1]
    if pad:
        x = torch.cat([x, x[:, -1:].expand(-1, pad)], dim=1)
    return x.reshape(x.shape[0], C, K)


def _scan_forward(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """Play outputs for x (B, T), r (N,), y0 (B, N); returns a buffer (B, C*K, N)."""
    B, T = x.shape
    N = r.shape[0]
    K, C = _chunking(T)
    xc = _padded_chunks(x, K, C).unsqueeze(-1)  # (B, C, K, 1)
    if C > 1:
        # pass 1: each chunk's composed clamp map, clamp(., lo, hi)
        lo = xc[:, :, 0] - r
        hi = xc[:, :, 0] + r
        for k in range(1, K):
            a = xc[:, :, k] - r
            b = xc[:, :, k] + r
            lo = torch.minimum(torch.maximum(lo, a), b)
            hi = torch.minimum(torch.maximum(hi, a), b)
        # carries: the state entering each chunk
        carry = torch.empty(B, C, N, dtype=x.dtype, device=x.device)
        s = y0
        for c in range(C):
            carry[:, c] = s
            s = torch.minimum(torch.maximum(s, lo[:, c]), hi[:, c])
        del lo, hi
    else:
        carry = y0.unsqueeze(1)
    # pass 2: the outputs
    y = torch.empty(B, C, K, N, dtype=x.dtype, device=x.device)
    s = carry
    for k in range(K):
        s = torch.minimum(torch.maximum(s, xc[:, :, k] - r), xc[:, :, k] + r)
        y[:, :, k] = s
    return y.view(B, C * K, N)


def _clamp_signs(xc: Tensor, r: Tensor, y0: Tensor, yc: Tensor) -> Tensor:
    """Which bound was active at each sample: +1 (x + r), -1 (x - r), 0 (none), as int8.

    xc (B, C, K, 1), yc (B, C, K, N) -> (K, B, C, N): position-major, so that the scans
    read contiguous slices. Computed a block of chunks at a time so that the
    temporaries stay a fraction of the output's size.
    """
    B, C, K, N = yc.shape
    sign = torch.empty(K, B, C, N, dtype=torch.int8, device=yc.device)
    first_prev = torch.cat([y0.unsqueeze(1), yc[:, :-1, K - 1]], dim=1)  # (B, C, N)
    step = max(1, C // 8)
    for c0 in range(0, C, step):
        c1 = min(C, c0 + step)
        prev = torch.cat([first_prev[:, c0:c1, None], yc[:, c0:c1, :-1]], dim=2)
        xb = xc[:, c0:c1]
        high = (prev > xb + r).to(torch.int8)
        sign[:, :, c0:c1] = high.sub_((prev < xb - r).to(torch.int8)).permute(2, 0, 1, 3)
    return sign


def _scan_backward(
    g: Tensor, x: Tensor, r: Tensor, y0: Tensor, ybuf: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of sum(g * y) with respect to x (B, T), r (N,) and y0 (B, N), given the
    outputs ybuf: (B, T, N), or the (B, C*K, N) buffer of :func:`_scan_forward`."""
    B, T = x.shape
    N = r.shape[0]
    K, C = _chunking(T)
    xc = _padded_chunks(x, K, C).unsqueeze(-1)  # (B, C, K, 1)
    pad = C * K - T
    if pad:
        g = torch.cat([g, g.new_zeros(B, pad, N)], dim=1)
    if ybuf.shape[1] < C * K:  # the padded samples repeat the last input: the output holds
        ybuf = torch.cat([ybuf, ybuf[:, -1:].expand(-1, C * K - T, -1)], dim=1)
    gc = g.reshape(B, C, K, N)
    sign = _clamp_signs(xc, r, y0, ybuf.reshape(B, C, K, N))  # (K, B, C, N) int8

    if C > 1:
        # pass 1: local adjoint at each chunk start (no inflow) and its inflow gain
        lam = gc[:, :, K - 1].clone()
        gain = torch.ones_like(lam)
        for k in range(K - 2, -1, -1):
            passing = sign[k + 1] == 0
            lam = gc[:, :, k] + lam * passing
            gain = gain * passing
        passing0 = sign[0] == 0
        # carries: inflow into the last sample of each chunk, from the next chunk
        inflow = torch.zeros(B, C, N, dtype=g.dtype, device=g.device)
        mu = torch.zeros(B, N, dtype=g.dtype, device=g.device)
        for c in range(C - 1, -1, -1):
            inflow[:, c] = mu
            mu = (lam[:, c] + gain[:, c] * mu) * passing0[:, c]
        del lam, gain
    else:
        inflow = torch.zeros(B, 1, N, dtype=g.dtype, device=g.device)
    # pass 2: the adjoint, reduced on the fly
    grad_x = torch.empty(B, C, K, dtype=g.dtype, device=g.device)
    acc_r = torch.zeros(B, C, N, dtype=g.dtype, device=g.device)
    lam = inflow
    passing_next = None
    for k in range(K - 1, -1, -1):
        lam = gc[:, :, k] + (inflow if passing_next is None else lam * passing_next)
        sk = sign[k].to(g.dtype)
        contrib = lam * sk  # +lam where clamped at x + r, -lam at x - r
        acc_r += contrib
        grad_x[:, :, k] = (contrib * sk).sum(-1)
        passing_next = sign[k] == 0
    grad_r = acc_r.sum((0, 1))
    grad_y0 = lam[:, 0] * passing_next[:, 0]
    return grad_x.view(B, C * K)[:, :T], grad_r, grad_y0


def play_tangent(x: Tensor, r: Tensor, y0: Tensor, y: Tensor, dx: Tensor, dr: Tensor,
                 dy0: Tensor) -> Tensor:
    """The play operator's derivative in the direction (dx (B, T), dr (N,), dy0 (B, N)) at
    x, r, y0 with outputs y (B, T, N): (B, T, N), in differentiable tensor operations.

    Each output is ``x[s] -+ r`` at the last sample s <= t where a bound was active, or
    y0 where none was (the tie rule of :func:`_scan_backward`: a tie follows the inactive
    branch), so its derivative is ``dx[s] -+ dr``, or dy0. Linear in the direction, with
    coefficients that are piecewise constant in x, r and y0.
    """
    T = x.shape[1]
    prev = torch.cat([y0.unsqueeze(1), y[:, :-1]], dim=1)
    xe = x.unsqueeze(-1)
    sign = (prev > xe + r).to(dx.dtype) - (prev < xe - r).to(dx.dtype)  # +1: at x + r
    t = torch.arange(T, device=x.device).view(1, T, 1)
    last = torch.where(sign != 0, t, -1).cummax(1).values  # last active sample, or -1
    source = dx.unsqueeze(-1) + sign * dr
    return torch.where(last >= 0, source.gather(1, last.clamp_min(0)), dy0.unsqueeze(1))

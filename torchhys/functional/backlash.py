"""Play (backlash) operators: a blocked clamp-composition scan with an exact adjoint.

The discrete play operator of half-width r is the recurrence

    y[t] = min(x[t] + r, max(x[t] - r, y[t-1])),    y[-1] = y0,

that is, ``y[t] = clamp(y[t-1], x[t] - r, x[t] + r)``. Composed clamp maps are clamp
maps, so the sequence is computed as a two-level scan: the time axis is cut into C
chunks of K samples; one pass over the K positions (vectorized over all chunks)
composes each chunk's clamps, a pass over the C chunks carries the state, and a
second pass over the K positions writes the outputs. That costs about 2 sqrt(2 T)
vectorized steps instead of T, and no memory beyond the output.

The backward pass uses the structure of the play operator: each output equals
``x[s] - r`` or ``x[s] + r`` for the last sample s at which the clamp was active,
or ``y0`` when it never was. The adjoint ``lam[t] = g[t] + pass[t+1] * lam[t+1]``
(pass: the clamp was inactive) is a masked reverse sum, computed with the same
two-level scan, and is reduced on the fly into the gradients of x, r and y0.

At a tie (``y[t-1]`` exactly on a bound) the operator is not differentiable; the
gradient then follows the inactive branch (``y[t] = y[t-1]``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_tensor,
    check_widths,
    sequence_batch,
)
from torchhys.functional._kernel import (
    kernel_available,
    play_backward_kernel,
    play_forward_kernel,
)

__all__ = ["backlash", "check_play_state", "play_step"]


def play_step(x_t: Tensor, r: Tensor, y_prev: Tensor) -> Tensor:
    """One step of the play operator, ``min(max(y_prev, x_t - r), x_t + r)``.

    Written with ``minimum``/``maximum`` (not ``clamp``) so that autograd and
    TorchScript return gradients to the bounds.

    Args:
        x_t: input sample, shape (B, 1) or broadcastable to ``y_prev``.
        r: half-widths, shape (N,).
        y_prev: previous outputs, shape (B, N).

    Returns:
        The new outputs, shape (B, N).
    """
    return torch.minimum(torch.maximum(y_prev, x_t - r), x_t + r)


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
    """Gradients of sum(g * y) with respect to x (B, T), r (N,) and y0 (B, N)."""
    B, T = x.shape
    N = r.shape[0]
    K, C = _chunking(T)
    xc = _padded_chunks(x, K, C).unsqueeze(-1)  # (B, C, K, 1)
    pad = C * K - T
    if pad:
        g = torch.cat([g, g.new_zeros(B, pad, N)], dim=1)
    gc = g.reshape(B, C, K, N)
    sign = _clamp_signs(xc, r, y0, ybuf.view(B, C, K, N))  # (K, B, C, N) int8

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


class _PlayScan(torch.autograd.Function):
    """Autograd function: x (B, T), r (N,), y0 (B, N) -> y (B, T, N)."""

    @staticmethod
    def forward(ctx, x: Tensor, r: Tensor, y0: Tensor) -> Tensor:  # type: ignore[override]
        ctx.kernel = kernel_available(x, r, y0)
        if ctx.kernel:
            y = play_forward_kernel(x, r, y0)
            ctx.save_for_backward(x, r, y0, y)
            return y
        ybuf = _scan_forward(x, r, y0)
        ctx.save_for_backward(x, r, y0, ybuf)
        return ybuf[:, : x.shape[1]]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_y: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, r, y0, ybuf = ctx.saved_tensors
        if ctx.kernel:
            grad_x, grad_r, grad_y0 = play_backward_kernel(grad_y, x, r, y0, ybuf)
        else:
            grad_x, grad_r, grad_y0 = _scan_backward(grad_y, x, r, y0, ybuf)
        return (
            grad_x if ctx.needs_input_grad[0] else None,
            grad_r if ctx.needs_input_grad[1] else None,
            grad_y0 if ctx.needs_input_grad[2] else None,
        )


def _validate_state(y0: Tensor, B: int, n: int, name: str) -> None:
    check_tensor(y0, name)
    check_floating(y0, name)
    if y0.shape not in (torch.Size([n]), torch.Size([B, n])):
        raise ValueError(
            f"{name} must have shape ({n},) or ({B}, {n}) for {n} operators and batch {B}, "
            f"got shape {tuple(y0.shape)}"
        )
    check_finite(y0, name)


def _check_state(y0: Tensor | None, x: Tensor, n: int, name: str = "state") -> Tensor:
    """Return the initial state as (B, N) in x's dtype and device."""
    B = x.shape[0]
    if y0 is None:
        return x.new_zeros(B, n)
    _validate_state(y0, B, n, name)
    return y0.to(dtype=x.dtype, device=x.device).expand(B, n)


def check_play_state(state: Tensor | None, x: Tensor, n: int, name: str) -> None:
    """Raise unless ``state`` is None or the outputs of ``n`` play operators before the first
    sample of ``x`` (time,) or (batch, time): a finite floating tensor of shape (n,) or
    (batch, n). The messages name the argument ``name`` (``state`` of a module's
    ``forward`` and of the functional models).

    Raises:
        TypeError, ValueError: a bad ``state``. ``x`` is only read for its batch size
        (checked where it is used: an ``x`` that is not a (time,) or (batch, time) tensor
        leaves the state to that check).
    """
    B = sequence_batch(x)
    if state is not None and B is not None:
        _validate_state(state, B, n, name)


def backlash(x: Tensor, widths: Tensor, *, state: Tensor | None = None) -> Tensor:
    """Outputs of N play (backlash) operators driven by the same input.

    Each operator i has the full dead-band width ``d_i`` (half-width ``d_i / 2``,
    Eq. (20) of the EIHO paper) and follows, in discrete time,

        y_i[t] = min(x[t] + d_i / 2, max(x[t] - d_i / 2, y_i[t-1])),   y_i[-1] = state_i.

    A width of zero gives ``y_i = x``. Supports autograd with respect to ``x``,
    ``widths`` and ``state`` (first order), batches, float32 and float64. Cost: about
    ``2 sqrt(2 T)`` vectorized steps; memory: the output.

    Args:
        x: input, shape (time,) or (batch, time), floating point.
        widths: dead-band widths d_i >= 0, shape (N,).
        state: outputs before the first sample, shape (N,) or (batch, N); zeros if None.

    Returns:
        Operator outputs, shape ``x.shape + (N,)``, i.e. (time, N) or (batch, time, N).

    Raises:
        TypeError: a non-tensor or a non-floating tensor.
        ValueError: wrong dimensions, NaN or inf, negative widths, mismatched ``state``.

    References:
        M. Brokate and J. Sprekels, Hysteresis and Phase Transitions, Springer 1996
        (the play operator); Eqs. (20)-(21) of the EIHO paper (backlash hysteresis).
    """
    xb, squeezed = as_batched_sequence(x, "x")
    check_widths(widths, "widths")
    y0 = _check_state(state, xb, widths.shape[0])
    r = 0.5 * widths.to(dtype=xb.dtype, device=xb.device)
    y = _PlayScan.apply(xb, r, y0)
    return y.squeeze(0) if squeezed else y

"""Differentiable linear recursions: ``lfilter`` (DF2T), a state-space recurrence and their steps.

Conventions (those of ``scipy.signal.lfilter``): ``b`` and ``a`` are the coefficients of
``B(z) = b[0] + b[1] z^-1 + ...`` and ``A(z) = a[0] + a[1] z^-1 + ...``; both are divided by
``a[0]``; with ``n = max(len(a), len(b)) - 1`` the direct form II transposed (DF2T) keeps
``n`` delays ``z`` and advances, per sample (:func:`df2t_step`)::

    y[t]   = b[0] x[t] + z[0]
    z[i]  <- b[i+1] x[t] + z[i+1] - a[i+1] y[t]          (z[n] = 0)

Sequence path. The recursion runs in a compiled C loop (:mod:`._filter_kernel`) with the
operations of :func:`df2t_step` in the same order, so the sequence path and the per-sample
step agree bit for bit. Without the kernel (no compiler, a non-CPU device, another dtype) it
runs as a chunked scan of the state-space form ``s[t] = A s[t-1] + w[t]``: chunks of
``K ~ sqrt(T / 2)`` samples are filtered from a zero state (one vectorised pass over the K
positions), the state entering each chunk is carried with ``A^K`` (one pass over the chunks),
and ``A^(k+1) s_in`` is added in one batched product: about ``2 sqrt(2 T)`` tensor operations,
equal to the recursion to float rounding.

Backward. The adjoint ``lam[t] = g_y[t] - sum_k a[k] lam[t+k]``, with ``lam[T+i] = g_zf[i]``,
is the same all-pole recursion run backwards in time, and then, with ``lam`` read at
``t + k``::

    dx[t] = sum_k b[k] lam[t+k]    db[k] = sum_t lam[t+k] x[t]    da[k] = -sum_t lam[t+k] y[t]
    dzi[i] = lam[i]

On the CPU one fused C pass computes all of it (sums over time in float64). When a graph is
being built (``create_graph=True``, double backward) or without the kernel, the backward is
written with differentiable tensor operations instead (the recursion through this same
function, the lag sums as batched products); both give the same gradients to rounding.

Why this path: the recursion is latency-bound (each output needs the previous one) and does
about ``3n`` flops a sample, so a scalar C loop runs it at a few nanoseconds a sample; the
chunked scan adds ``n^2`` work a sample (the ``A^(k+1) s_in`` products) and ~``2 sqrt(2 T)``
tensor operations, the per-sample Python loop a dispatch and an autograd node per sample.
``benchmarks/linear_filter.py`` times the three (docs/benchmarks.md). The FIR part is not
split off as a ``conv1d``: that costs more than the whole DF2T loop.

References:
    A. V. Oppenheim and R. W. Schafer, Discrete-Time Signal Processing, 3rd ed., Pearson
    2010, Sec. 6.5 (transposed forms); ``scipy.signal.lfilter`` (the DF2T convention and
    ``zi``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchhys._checks import check_finite, check_floating, check_tensor, concrete
from torchhys.functional._compile import call_function, signature_once
from torchhys.functional._filter_kernel import df2t, df2t_adjoint, linrec, linrec_adjoint
from torchhys.functional._linear_scan import df2t_adjoint_torch, linrec_adjoint_torch

__all__ = ["df2t_step", "lfilter", "linear_recurrence", "state_space", "state_space_step"]


def df2t_step(x: Tensor, z: Tensor, b: Tensor, a: Tensor) -> tuple[Tensor, Tensor]:
    """One DF2T step (the maths of :func:`lfilter`; scriptable).

    Args:
        x: input sample, (batch, 1).
        z: delays, (batch, n) with n >= 1.
        b: numerator, (n + 1,); a: denominator without its leading 1, ``a[1:]``, (n,).

    Several filters step at once with leading dimensions that broadcast: x (..., 1),
    z (..., n), b (..., n + 1), a (..., n).

    Returns:
        ``(y, z)``: the output (batch, 1) and the new delays (batch, n).
    """
    y = b[..., :1] * x + z[..., :1]
    shifted = torch.cat([z[..., 1:], torch.zeros_like(z[..., :1])], dim=-1)
    return y, b[..., 1:] * x + shifted - a * y


def state_space_step(u: Tensor, s: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor
                     ) -> tuple[Tensor, Tensor]:
    """One state-space step ``y = C s + D u``, ``s <- A s + B u`` (scriptable).

    Args:
        u: input sample, (batch, 1) with one input, (batch, m) with m inputs.
        s: state, (batch, n).
        A: (n, n). B: (n,) with one input, (n, m) with m. C: (p, n). D: (p,) or (p, m).

    Returns:
        ``(y, s)``: the output (batch, p) and the new state (batch, n).
    """
    if B.dim() == 1:
        return s @ C.mT + u * D, s @ A.mT + u * B
    return s @ C.mT + u @ D.mT, s @ A.mT + u @ B.mT


# --- autograd functions ------------------------------------------------------------------------


@signature_once
class _DF2T(torch.autograd.Function):
    """x (R, T), b (F, n+1), a (F, n) = a[:, 1:], zi (R, n) -> y (R, T), zf (R, n).

    Row r uses filter ``r % F`` (R a multiple of F). Works with ``torch.func`` (``grad``,
    ``vjp``, ``jacrev``, ``vmap``: the forward and the fused backward are the
    ``torchhys::df2t`` ops, which have ``vmap`` rules). Differentiable twice and more: when a
    graph of the gradient is asked for, the backward is written in tensor operations over this
    function itself."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: Tensor, b: Tensor, a: Tensor, zi: Tensor  # type: ignore[override]
                ) -> tuple[Tensor, Tensor]:
        return df2t(x, b, a, zi)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        x, b, a, _ = inputs
        ctx.save_for_backward(x, b, a, output[0])

    @staticmethod
    def backward(ctx, gy: Tensor, gzf: Tensor  # type: ignore[override]
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        x, b, a, y = ctx.saved_tensors
        if torch.is_grad_enabled():  # a graph of the gradient is asked for
            return df2t_adjoint_torch(gy, gzf, x, b, a, y, _DF2T.apply)
        return df2t_adjoint(gy, gzf, x, b, a, y)  # the fused kernel where it runs, no graph


@signature_once
class _LinearRecurrence(torch.autograd.Function):
    """A (n, n), w (R, T, n), s0 (R, n) -> s (R, T, n), s[t] = A s[t-1] + w[t].

    ``torch.func`` and higher derivatives as :class:`_DF2T` (the ops ``torchhys::linrec``)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:  # type: ignore[override]
        return linrec(A, w, s0)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        A, _, s0 = inputs
        ctx.save_for_backward(A, s0, output)

    @staticmethod
    def backward(ctx, gs: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # type: ignore[override]
        A, s0, s = ctx.saved_tensors
        if torch.is_grad_enabled():
            return linrec_adjoint_torch(gs, A, s0, s, _LinearRecurrence.apply)
        return linrec_adjoint(gs, A, s0, s)


# --- public entry points -----------------------------------------------------------------------


def _check_sequence(x: Tensor, name: str, min_dim: int = 1) -> None:
    check_tensor(x, name)
    check_floating(x, name)
    if x.dim() < min_dim or x.shape[-min_dim] == 0:
        layout = "(..., time)" if min_dim == 1 else "(..., time, n)"
        raise ValueError(f"{name} must have shape {layout} with time >= 1, got shape "
                         f"{tuple(x.shape)}")
    if concrete(x) and not bool(torch.isfinite(x.detach().sum())):  # a NaN or inf
        check_finite(x, name)  # makes the sum non-finite: the full check names it (or passes
        # if the sum overflowed)


def _coefficients(v: Tensor, name: str, x: Tensor, shape: tuple[int, ...] | None = None
                  ) -> Tensor:
    """Check a coefficient tensor (1-D, or ``shape`` where given) and cast it to x's dtype."""
    check_tensor(v, name)
    check_floating(v, name)
    if (shape is None and (v.dim() != 1 or v.numel() == 0)) or (
            shape is not None and v.shape != shape):
        want = "(length,) with length >= 1" if shape is None else str(shape)
        raise ValueError(f"{name} must have shape {want}, got shape {tuple(v.shape)}")
    check_finite(v, name)
    return v.to(dtype=x.dtype, device=x.device)


def _initial(s0: Tensor | None, batch: torch.Size, n: int, x: Tensor, name: str) -> Tensor:
    """The initial state as (R, n): None (zeros), (n,) or ``batch + (n,)``."""
    if s0 is None:
        return x.new_zeros(batch.numel(), n)
    check_tensor(s0, name)
    check_floating(s0, name)
    if s0.shape not in (torch.Size([n]), batch + (n,)):
        raise ValueError(f"{name} must have shape ({n},) or {tuple(batch + (n,))}, got shape "
                         f"{tuple(s0.shape)}")
    check_finite(s0, name)
    return s0.to(dtype=x.dtype, device=x.device).expand(batch + (n,)).reshape(batch.numel(), n)


def _filters(v: Tensor, name: str, x: Tensor) -> Tensor:
    """Check one filter's coefficients (length,) or F filters' (F, length), F = x.shape[-2];
    return them as (1 or F, length) in x's dtype."""
    check_tensor(v, name)
    if v.dim() == 2 and x.dim() >= 2 and v.shape[0] == x.shape[-2] and v.shape[1] > 0:
        return _coefficients(v.reshape(-1), name, x).reshape(v.shape)
    if v.dim() == 2:
        filters = x.shape[-2] if x.dim() >= 2 else "x.shape[-2]"
        raise ValueError(f"{name} must have shape (length,) or (filters, length) with one "
                         f"filter a row of x (filters = {filters}), got shape {tuple(v.shape)}")
    return _coefficients(v, name, x).unsqueeze(0)


def lfilter(x: Tensor, b: Tensor, a: Tensor, *, state: Tensor | None = None
            ) -> tuple[Tensor, Tensor]:
    """Filter ``x`` along time with ``B(z) / A(z)`` in direct form II transposed.

    Same results as ``scipy.signal.lfilter(b, a, x, zi=state)`` (``b`` and ``a`` divided by
    ``a[0]``; ``state`` is the DF2T state of the normalized filter). Supports autograd with
    respect to ``x``, ``b``, ``a`` and ``state`` (double backward too), batches, float32 and
    float64, CPU (compiled kernel) and other devices (chunked scan). Stability is not checked.

    Several filters in one call: with ``b`` (F, nb) and/or ``a`` (F, na) (a 1-D one is shared)
    and ``x`` (..., F, time), row f of x is filtered with ``b[f]`` and ``a[f]`` (the rows of
    one filter run together on the kernel; the scan runs one filter at a time).

    Args:
        x: input, (..., time), finite, floating point.
        b: numerator, (nb,) or (F, nb). a: denominator, (na,) or (F, na), ``a[..., 0] != 0``.
        state: delays before the first sample, (n,) or (..., n) with ``n = max(na, nb) - 1``;
            zeros if None.

    Returns:
        ``(y, zf)``: y (..., time) and the delays after the last sample (..., n), which
        continue the filter: calls on consecutive chunks equal one call.

    Raises:
        TypeError: a non-tensor or a non-floating tensor.
        ValueError: wrong shapes, NaN or inf, ``a[0] == 0``.

    References:
        Oppenheim & Schafer, Discrete-Time Signal Processing, Sec. 6.5;
        ``scipy.signal.lfilter``.
    """
    _check_sequence(x, "x")
    b = _filters(b, "b", x)
    a = _filters(a, "a", x)
    if concrete(a) and bool((a[:, 0] == 0).any()):
        bad = a[(a[:, 0] == 0).nonzero()[0, 0]]
        raise ValueError(f"a[0] must be non-zero (it weights the current output y[t]), got "
                         f"a = {bad.tolist()}")
    F = max(a.shape[0], b.shape[0])
    n = max(a.shape[1], b.shape[1]) - 1
    b = torch.cat([b, b.new_zeros(b.shape[0], n + 1 - b.shape[1])], 1) / a[:, :1]
    a = torch.cat([a, a.new_zeros(a.shape[0], n + 1 - a.shape[1])], 1) / a[:, :1]
    b, a = b.expand(F, n + 1), a.expand(F, n + 1)
    batch = x.shape[:-1]
    z0 = _initial(state, batch, n, x, "state")
    if n == 0:
        gain = b[:, 0] if F == 1 else b[:, :1]
        return gain * x, x.new_zeros(batch + (0,))
    y, zf = call_function(_DF2T, x.reshape(-1, x.shape[-1]), b, a[:, 1:], z0)
    return y.reshape(x.shape), zf.reshape(batch + (n,))


def linear_recurrence(A: Tensor, w: Tensor, *, state: Tensor | None = None) -> Tensor:
    """States of ``s[t] = A s[t-1] + w[t]`` with ``s[-1] = state``.

    Supports autograd with respect to ``A``, ``w`` and ``state`` (double backward too). Stability
    is not checked.

    Args:
        A: (n, n). w: inputs, (..., time, n). state: (n,) or (..., n); zeros if None.

    Returns:
        The states s[0], ..., s[T-1], (..., time, n).

    Raises:
        TypeError, ValueError: as :func:`lfilter`.
    """
    _check_sequence(w, "w", min_dim=2)
    n = w.shape[-1]
    A = _coefficients(A, "A", w, (n, n))
    batch = w.shape[:-2]
    start = _initial(state, batch, n, w, "state")
    s = call_function(_LinearRecurrence, A, w.reshape(-1, w.shape[-2], n), start)
    return s.reshape(w.shape)


def state_space(u: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor, *,
                state: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Outputs of ``s[t+1] = A s[t] + B u[t]``, ``y[t] = C s[t] + D u[t]``.

    One input: u (..., time), B (n,), D (p,). m inputs: u (..., time, m), B (n, m), D (p, m).
    The recursion is :func:`linear_recurrence` on ``w[t] = B u[t]`` (no loop over samples in
    Python); the outputs are one batched product.

    Args:
        u: input, (..., time) or (..., time, m). A: (n, n). B: (n,) or (n, m). C: (p, n).
        D: (p,) or (p, m).
        state: state at the first sample, (n,) or (..., n); zeros if None.

    Returns:
        ``(y, s)``: y (..., time, p) and the state after the last sample (..., n).

    Raises:
        TypeError, ValueError: as :func:`lfilter`.

    References:
        ``scipy.signal.dlsim`` (the same convention).
    """
    for name, m in (("A", A), ("C", C)):
        if check_tensor(m, name).dim() != 2:
            raise ValueError(f"{name} must be a matrix, got shape {tuple(m.shape)}")
    multi = check_tensor(B, "B").dim() == 2
    _check_sequence(u, "u", min_dim=2 if multi else 1)
    n, p = A.shape[0], C.shape[0]
    m = B.shape[1] if multi else 1
    if multi and u.shape[-1] != m:
        raise ValueError(f"u must have shape (..., time, {m}) for B of shape {tuple(B.shape)} "
                         f"({m} inputs), got shape {tuple(u.shape)}")
    A = _coefficients(A, "A", u, (n, n))
    B = _coefficients(B, "B", u, (n, m) if multi else (n,))
    C = _coefficients(C, "C", u, (p, n))
    D = _coefficients(D, "D", u, (p, m) if multi else (p,))
    batch = u.shape[:-2] if multi else u.shape[:-1]
    T = u.shape[-2] if multi else u.shape[-1]
    start = _initial(state, batch, n, u, "state")
    ur = u.reshape(-1, T, m)
    s = call_function(_LinearRecurrence, A, ur @ B.mT if multi else ur * B, start)
    # the state entering each sample; sliced from T + 1 states, not cat with s[:, :-1], whose
    # size T - 1 makes torch.export with a dynamic time dimension guard on T != 2
    entering = torch.cat([start.unsqueeze(1), s], dim=1)[:, :T]
    y = entering @ C.mT + (ur @ D.mT if multi else ur * D)
    return y.reshape(batch + (T, p)), s[:, -1].reshape(batch + (n,))

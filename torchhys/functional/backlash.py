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

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_tensor,
    check_widths,
    sequence_batch,
)
from torchhys.functional._compile import call_function, signature_once
from torchhys.functional._kernel import play_adjoint, play_forward, play_op
from torchhys.functional._play_scan import play_tangent

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


@signature_once
class _PlayScan(torch.autograd.Function):
    """Autograd function: x (B, T), r (N,), y0 (B, N) -> y (B, T, N).

    Works with ``torch.func`` (``grad``, ``vjp``, ``jacrev``, ``jvp``, ``vmap``: the forward and
    the backward run the ``torchhys::play`` ops, which have ``vmap`` rules). Differentiable
    twice: the backward is :class:`_PlayAdjoint`, whose own backward is the play operator's
    directional derivative (:func:`~torchhys.functional._play_scan.play_tangent`). The second
    derivative with respect to x, r and y0 is zero (each output is ``x[s] -+ r`` or y0 on a
    set of samples that is piecewise constant in them), exact away from ties.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:  # type: ignore[override]
        return play_forward(x, r, y0)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        ctx.save_for_backward(*inputs, output)
        ctx.save_for_forward(*inputs, output)

    @staticmethod
    def jvp(ctx, dx: Tensor | None, dr: Tensor | None,  # type: ignore[override]  # noqa: ANN001
            dy0: Tensor | None) -> Tensor:
        x, r, y0, y = ctx.saved_tensors
        return play_tangent(x, r, y0, y, *_zeros_for_none((dx, dr, dy0), (x, r, y0)))

    @staticmethod
    def backward(ctx, grad_y: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, r, y0, y = ctx.saved_tensors
        if torch.is_grad_enabled():  # a graph of the gradient is asked for
            grad_x, grad_r, grad_y0 = call_function(_PlayAdjoint, grad_y, x, r, y0, y)
        else:
            grad_x, grad_r, grad_y0 = play_adjoint(grad_y, x, r, y0, y)
        return (
            grad_x if ctx.needs_input_grad[0] else None,
            grad_r if ctx.needs_input_grad[1] else None,
            grad_y0 if ctx.needs_input_grad[2] else None,
        )


@signature_once
class _PlayAdjoint(torch.autograd.Function):
    """The play operator's gradient as a function: g (B, T, N), x, r, y0, y -> (gx, gr, gy0).

    Linear in g; its derivative with respect to g is the directional derivative of the
    play operator (:func:`~torchhys.functional._play_scan.play_tangent`), and with respect
    to x, r, y0 and y it is zero (the active bounds are piecewise constant in them).
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(g: Tensor, x: Tensor, r: Tensor, y0: Tensor,  # type: ignore[override]
                y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return play_adjoint(g, x, r, y0, y)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        ctx.save_for_backward(*inputs)  # the same tensors for both (vmap's generated rule
        ctx.save_for_forward(*inputs)  # keeps one record of the saved tensors' batch dims)

    @staticmethod
    def jvp(ctx, dg: Tensor | None, *_: Tensor | None  # type: ignore[override]  # noqa: ANN001
            ) -> tuple[Tensor, Tensor, Tensor]:
        g, x, r, y0, y = ctx.saved_tensors
        return play_adjoint(*_zeros_for_none((dg,), (g,)), x, r, y0, y)

    @staticmethod
    def backward(ctx, ggx: Tensor, ggr: Tensor,  # type: ignore[override]
                 ggy0: Tensor) -> tuple[Tensor | None, ...]:
        _, x, r, y0, y = ctx.saved_tensors
        return play_tangent(x, r, y0, y, ggx, ggr, ggy0), None, None, None, None


def _play(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """:class:`_PlayScan`; while Dynamo or export traces, the ``torchhys::play`` op with its
    registered autograd instead (the same formulas; Dynamo traces no ``autograd.Function``
    with a custom ``jvp``)."""
    if torch.compiler.is_compiling():
        return play_op(x, r, y0)
    return call_function(_PlayScan, x, r, y0)


def _zeros_for_none(tangents: tuple[Tensor | None, ...], like: tuple[Tensor, ...]
                    ) -> tuple[Tensor, ...]:
    return tuple(torch.zeros_like(p) if t is None else t for t, p in zip(tangents, like,
                                                                        strict=True))


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
    ``widths`` and ``state`` (twice: the second derivative in them is zero, see
    :class:`_PlayScan`), ``torch.func`` transforms, batches, float32 and float64. Cost: about
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
    y = _play(xb, r, y0)
    return y.squeeze(0) if squeezed else y

"""Discretised Preisach model: relay hysterons on a triangular grid of thresholds.

A relay with thresholds ``alpha >= beta`` outputs +1 once the input reached alpha
(``x >= alpha``), -1 once it fell to beta (``x <= beta``), and keeps its value in between;
when one sample does both (``alpha == beta == x``) switching up wins. The model is

    y[t] = offset + linear * x[t] + sum_k w_k r_k[t],        w_k >= 0 (the density),

here over the relays of a triangular grid (:func:`preisach_grid`), numbered row by row::

    n = 3 levels l0 < l1 < l2 (cell centers of [lo, hi]); relay k at (alpha, beta):

                 beta = l0   l1   l2
      alpha = l0        0
              l1        1    2
              l2        3    4    5        K = n (n + 1) / 2 relays, diagonal included

Sequence path, with no loop over samples: a relay's output at t is decided by the threshold
the input crossed last. For each distinct alpha the last index u <= t with ``x >= alpha``
is a running maximum (``cummax``) of ``where(x >= alpha, t, -1)``; likewise d for beta. The
relay is +1 where ``u >= max(d, 0)``, -1 where ``d > u``, and keeps its initial value r0
where neither happened (``u = d = -1``). Time is cut into chunks of about 2**18
relay-samples that carry the last-crossing indices (int32), so the work memory does not grow
with the length; relays are laid out (K, batch, chunk), so that picking each relay's
thresholds copies whole rows. The per-sample step (:func:`relay_update`) and the sequence
path share :func:`relay_events` and :func:`relay_switch`, hence the tie rule.

Smooth relays (``smooth = tau > 0``), for gradients with respect to the input: the switching
is decided as above, and relay k outputs ``tanh((x - theta_k) / tau)`` with theta_k the
threshold that would switch it next (beta while it is up, alpha while it is down). Far from
that threshold this is the hard relay's +-1; near it the output bends towards 0, and its
slope ``(1 - r**2) / tau`` says how close the input is to flipping the relay. A diagonal
relay becomes ``tanh((x - alpha) / tau)``. As tau -> 0 the outputs tend to the hard relays at
every x off the thresholds. (Blending towards the threshold crossed *last* would not: a relay
up since x passed alpha must stay near +1 on the way back down to beta.) A switch is still a
jump, so the gradient is that of the branch the input is on.

Supports autograd: :func:`preisach` has a custom backward that recomputes the relays chunk by
chunk (memory O(batch * time) beyond the input) and returns gradients to the weights,
offset, linear and, with ``smooth``, to x. Hard relays have derivative 0 in x almost
everywhere; thresholds and r0 get no gradient. The per-sample functions are TorchScript- and
export-friendly.

References:
    I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991 (chapter 1).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_tensor,
    concrete,
    sequence_batch,
)
from torchhys.functional._compile import call_function, signature_once

__all__ = [
    "check_relay_state",
    "check_scale",
    "demagnetized_state",
    "graded_input",
    "graded_input_inverse",
    "preisach",
    "preisach_grid",
    "preisach_with_state",
    "relay_events",
    "relay_output",
    "relay_states",
    "relay_switch",
    "relay_update",
]

_CHUNK = 1 << 18  # relay-samples per chunk of the sequence path


def preisach_grid(
    lo: float, hi: float, n: int, *, scale: float | None = None,
    dtype: torch.dtype | None = None
) -> tuple[Tensor, Tensor]:
    """Thresholds of the triangular Preisach grid on ``[lo, hi]`` with n levels per axis.

    The levels are the centers of n equal cells, ``lo + (hi - lo) (i + 1/2) / n``; relay
    ``k = i (i + 1) / 2 + j`` (``0 <= j <= i < n``) has ``alpha = level[i]``,
    ``beta = level[j]`` (see the module docstring). An input at or beyond hi (lo) sets every
    relay to +1 (-1): the relays saturate.

    With ``scale = s``, a graded grid: the cells are equal in :func:`graded_input`
    ``c + s asinh((x - c) / s)``, c = (lo + hi) / 2, so the levels are dense within about s
    of the center and sparse beyond (a magnetic core's field: the loops of small amplitude
    need fine thresholds near 0, the tips of the large ones few).

    Returns:
        alpha, beta: (K,) each, K = n (n + 1) / 2, in ``dtype`` (default: torch's).

    Raises:
        ValueError: n < 1, lo or hi not finite, lo >= hi, scale not None or finite > 0.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    lo_f, hi_f = _real(lo, "lo"), _real(hi, "hi")
    if not lo_f < hi_f:
        raise ValueError(f"lo must be less than hi, got lo={lo_f} and hi={hi_f}")
    scale = check_scale(scale)
    c = 0.5 * (lo_f + hi_f)
    glo, ghi = (graded_input(torch.tensor([lo_f, hi_f], dtype=torch.float64), c, scale)
                .tolist())
    cells = glo + (ghi - glo) * (torch.arange(n, dtype=torch.float64) + 0.5) / n
    levels = graded_input_inverse(cells, c, scale)
    i, j = torch.tril_indices(n, n)
    dtype = torch.get_default_dtype() if dtype is None else dtype
    return levels[i].to(dtype), levels[j].to(dtype)


def check_scale(scale: object) -> float | None:
    """None, or a finite number > 0 as a float (the ``scale`` of a graded grid)."""
    return _positive_or_none(scale, "scale")


def graded_input(x: Tensor, center: float, scale: float | None) -> Tensor:
    """``center + scale * asinh((x - center) / scale)``: x near the center, growing like the
    logarithm of ``|x - center|`` beyond ``scale``; x itself when ``scale`` is None.

    A graded Preisach model (:func:`preisach_grid` with ``scale``) spaces its levels equally
    in this variable, and its linear term reads it: a reversible part that saturates (the
    flux density of a magnetic core against its field).
    """
    if scale is None:
        return x
    return center + scale * torch.asinh((x - center) / scale)


def graded_input_inverse(v: Tensor, center: float, scale: float | None) -> Tensor:
    """The inverse of :func:`graded_input`: ``center + scale * sinh((v - center) / scale)``."""
    if scale is None:
        return v
    return center + scale * torch.sinh((v - center) / scale)


def demagnetized_state(alpha: Tensor, beta: Tensor, center: float | None = None) -> Tensor:
    """The demagnetised relays: +1 strictly below the line ``alpha + beta = 2 center``, -1 on
    and above it (a margin of 64 machine epsilons, relative, absorbs rounding, so grid relays
    on the line are -1).

    Args:
        alpha, beta: (K,) thresholds.
        center: default ``(alpha.max() + beta.min()) / 2``, which is ``(lo + hi) / 2`` on a
            :func:`preisach_grid`.

    Returns:
        (K,) of +-1 in alpha's dtype.
    """
    total = alpha.max() + beta.min() if center is None else 2.0 * center
    tol = 64 * torch.finfo(alpha.dtype).eps * (alpha.abs().max() + beta.abs().max())
    one = torch.ones_like(alpha)
    return torch.where(alpha + beta < total - tol, one, -one)


def relay_events(x: Tensor, alpha: Tensor, beta: Tensor) -> tuple[Tensor, Tensor]:
    """Whether x reaches the switch-up (``x >= alpha``) and switch-down (``x <= beta``)
    thresholds, broadcast."""
    return x >= alpha, x <= beta


def relay_switch(up: Tensor, down: Tensor, r: Tensor) -> Tensor:
    """+1 where ``up``, else -1 where ``down``, else ``r`` (switching up wins a tie),
    broadcast, in r's dtype."""
    one = torch.ones_like(r)
    return torch.where(up, one, torch.where(down, -one, r))


def relay_update(x: Tensor, alpha: Tensor, beta: Tensor, r_prev: Tensor) -> Tensor:
    """One step of the relays: x (batch, 1), alpha, beta (K,), r_prev (batch, K) -> (batch, K)."""
    up, down = relay_events(x, alpha, beta)
    return relay_switch(up, down, r_prev)


def relay_output(x: Tensor, alpha: Tensor, beta: Tensor, r: Tensor, smooth: float | None) -> Tensor:
    """What relays in state r (+-1) output at input x: r itself, or with ``smooth = tau``
    the smooth relay ``tanh((x - theta) / tau)``, theta = beta where r > 0, else alpha."""
    if smooth is None:
        return r
    return torch.tanh((x - torch.where(r > 0, beta, alpha)) / smooth)


def relay_states(
    x: Tensor,
    alpha: Tensor,
    beta: Tensor,
    *,
    state: Tensor | None = None,
    smooth: float | None = None,
) -> Tensor:
    """Outputs of every relay at every sample (materialised: memory batch * time * K).

    Args:
        x: input, (time,) or (batch, time).
        alpha, beta: thresholds, (K,) each, ``alpha >= beta``.
        state: relays before the first sample, +-1, (K,) or (batch, K); default
            :func:`demagnetized_state`.
        smooth: temperature tau > 0 of smooth relays (module docstring), or None.

    Returns:
        (batch, time, K) or (time, K) in x's dtype; differentiable in x when smooth.
    """
    xb, alpha, beta, r0b, squeeze = _check_inputs(x, alpha, beta, state, smooth)
    a, b = alpha[:, None, None], beta[:, None, None]
    outs = [
        relay_output(xb[None, :, start:stop], a, b, r, smooth).permute(1, 2, 0)
        for start, stop, r in _relay_chunks(xb.detach(), alpha, beta, r0b)
    ]
    out = torch.cat(outs, dim=1)
    return out[0] if squeeze else out


def preisach(
    x: Tensor,
    weights: Tensor,
    alpha: Tensor,
    beta: Tensor,
    *,
    offset: float | Tensor = 0.0,
    linear: float | Tensor = 0.0,
    state: Tensor | None = None,
    smooth: float | None = None,
    center: float = 0.0,
    scale: float | None = None,
) -> Tensor:
    """Preisach model ``offset + linear * x + relays @ weights``, chunked (module docstring).

    Args:
        x: input, (time,) or (batch, time).
        weights: density w, (K,); non-negative for a Preisach model (not checked here).
        alpha, beta: thresholds, (K,) each, ``alpha >= beta`` (e.g. :func:`preisach_grid`).
        offset, linear: numbers or 0-dim tensors.
        state: relays before the first sample, +-1, (K,) or (batch, K); default
            :func:`demagnetized_state`.
        smooth: temperature of smooth relays, or None for hard relays.
        center, scale: a graded grid's (:func:`preisach_grid`): the linear term reads
            ``graded_input(x, center, scale)``; scale None: x.

    Returns:
        y, the shape of x. Supports autograd (weights, offset, linear; x through ``linear``
        and, when smooth, through the relays).
    """
    return preisach_with_state(
        x, weights, alpha, beta, offset=offset, linear=linear, state=state, smooth=smooth,
        center=center, scale=scale,
    )[0]


def preisach_with_state(
    x: Tensor,
    weights: Tensor,
    alpha: Tensor,
    beta: Tensor,
    *,
    offset: float | Tensor = 0.0,
    linear: float | Tensor = 0.0,
    state: Tensor | None = None,
    smooth: float | None = None,
    center: float = 0.0,
    scale: float | None = None,
) -> tuple[Tensor, Tensor]:
    """:func:`preisach`, also returning the relays at the last sample, (K,) or (batch, K),
    to pass as state to the call on the continuation of the sequence. With ``scale`` (a graded
    grid) the linear term reads ``graded_input(x, center, scale)``."""
    xb, alpha, beta, r0b, squeeze = _check_inputs(x, alpha, beta, state, smooth)
    check_tensor(weights, "weights")
    check_floating(weights, "weights")
    if weights.shape != alpha.shape:
        raise ValueError(f"weights must have shape {tuple(alpha.shape)} (one per relay), got "
                         f"shape {tuple(weights.shape)}")
    check_finite(weights, "weights")
    relays, last = call_function(_PreisachRelays, xb, weights.to(xb.dtype), alpha, beta, r0b,
                                 smooth)
    y = relays + linear * graded_input(xb, center, check_scale(scale)) + offset
    return (y[0], last[0]) if squeeze else (y, last)


@signature_once
class _PreisachRelays(torch.autograd.Function):
    """``relays @ weights`` for x (B, T), weights (K,), r0 (B, K) -> ((B, T), last (B, K)).

    Works with ``torch.func`` (``grad``, ``vjp``, ``jacrev``; ``vmap`` through
    ``generate_vmap_rule``: batched tensors take the one-chunk relays). Differentiable
    twice: the backward is written in tensor operations (the relay states are recomputed and
    held constant), so the second derivative is that of the relays' outputs on the branch the
    input is on: in the weights it is zero, in x (smooth relays) that of ``tanh``; hard relays
    have none in x (their derivative is zero almost everywhere)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x, weights, alpha, beta, r0, smooth):  # type: ignore[override]  # noqa: ANN001, ANN205
        a, b = alpha[:, None, None], beta[:, None, None]
        r = r0.t().unsqueeze(-1)
        parts = []
        for start, stop, r in _relay_chunks(x, alpha, beta, r0):
            out = relay_output(x[None, :, start:stop], a, b, r, smooth)
            parts.append((weights @ out.flatten(1)).view(x.shape[0], -1))
        y = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        return y, r[:, :, -1].t().contiguous()

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        x, weights, alpha, beta, r0, smooth = inputs
        ctx.mark_non_differentiable(output[1])
        ctx.save_for_backward(x, weights, alpha, beta, r0)
        ctx.smooth = smooth

    @staticmethod
    def backward(ctx, grad_y, grad_last):  # type: ignore[override]  # noqa: ANN001, ANN205
        x, weights, alpha, beta, r0 = ctx.saved_tensors
        smooth = ctx.smooth
        need_w = ctx.needs_input_grad[1]
        need_x = ctx.needs_input_grad[0] and smooth is not None
        if not (need_w or need_x):
            return None, None, None, None, None, None
        a, b = alpha[:, None, None], beta[:, None, None]
        gw, gx = None, []
        for start, stop, r in _relay_chunks(x.detach(), alpha, beta, r0):
            out = relay_output(x[None, :, start:stop], a, b, r, smooth).flatten(1)  # (K, B L)
            g = grad_y[:, start:stop]
            if need_w:
                part = out @ g.reshape(-1)
                gw = part if gw is None else gw + part
            if need_x:  # d/dx tanh((x - theta) / tau) = (1 - out**2) / tau
                slope = weights @ (1.0 - out * out) / smooth
                gx.append(g * slope.view_as(g))
        grad_x = None if not need_x else gx[0] if len(gx) == 1 else torch.cat(gx, dim=1)
        return grad_x, gw, None, None, None, None


def _relays_in_one_chunk(
    x: Tensor, alpha: Tensor, beta: Tensor, r0: Tensor
) -> Iterator[tuple[int, int, Tensor]]:
    """:func:`_relay_chunks` as one chunk over every relay's own levels (no ``unique``, whose
    output's shape depends on the values, and no loop over the samples): where the values
    cannot be read. The same states."""
    T = x.shape[1]
    t = torch.arange(T, dtype=torch.int32, device=x.device)
    up, down = relay_events(x, alpha[:, None, None], beta[:, None, None])  # (K, B, T)
    u = torch.where(up, t, -1).cummax(-1).values
    d = torch.where(down, t, -1).cummax(-1).values
    yield 0, T, relay_switch(u >= d.clamp_min(0), d > u, r0.t().unsqueeze(-1))


def _relay_chunks(
    x: Tensor, alpha: Tensor, beta: Tensor, r0: Tensor
) -> Iterator[tuple[int, int, Tensor]]:
    """Hard relay states chunk by chunk: x (B, T), alpha, beta (K,), r0 (B, K) -> yields
    ``(start, stop, r)``, r (K, B, stop - start) the states at samples start:stop in r0's
    dtype."""
    B, T = x.shape
    K = alpha.shape[0]
    if not concrete(x, alpha, beta, r0):  # traced, batched, meta or fake: the relays' own
        # levels (their number is the shape) and one chunk (no Python loop over the samples)
        yield from _relays_in_one_chunk(x, alpha, beta, r0)
        return
    ua, ia = torch.unique(alpha, return_inverse=True)
    ub, ib = torch.unique(beta, return_inverse=True)
    ua, ub = ua[:, None, None], ub[:, None, None]
    u = torch.full((ua.shape[0], B, 1), -1, dtype=torch.int32, device=x.device)
    d = torch.full((ub.shape[0], B, 1), -1, dtype=torch.int32, device=x.device)
    r0 = r0.t().unsqueeze(-1)  # (K, B, 1)
    length = max(1, _CHUNK // (max(B, 1) * max(K, ua.shape[0], ub.shape[0])))
    for start in range(0, T, length):
        stop = min(start + length, T)
        t = torch.arange(start, stop, dtype=torch.int32, device=x.device)
        up, down = relay_events(x[:, start:stop], ua, ub)  # (levels, B, L)
        u = torch.maximum(torch.where(up, t, -1).cummax(-1).values, u[..., -1:])
        d = torch.maximum(torch.where(down, t, -1).cummax(-1).values, d[..., -1:])
        uk, dk = u.index_select(0, ia), d.index_select(0, ib)  # (K, B, L)
        yield start, stop, relay_switch(uk >= dk.clamp_min(0), dk > uk, r0)


def _real(value: object, name: str) -> float:
    """A finite real number (a Python or NumPy number, or a one-element tensor)."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    if not math.isfinite(float(value)):
        raise ValueError(f"{name} must be finite, got {value}")
    return float(value)


def _positive_or_none(value: object, name: str) -> float | None:
    """None, or a finite real number > 0 as a float; else ``ValueError`` naming ``name``."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (
            0.0 < float(value) < math.inf):
        raise ValueError(f"{name} must be None or a finite number > 0, got {value!r}")
    return float(value)


def _check_smooth(smooth: object) -> float | None:
    """None, or a finite number > 0 as a float (a smooth relay's temperature)."""
    return _positive_or_none(smooth, "smooth")


def _check_inputs(
    x: Tensor, alpha: Tensor, beta: Tensor, r0: Tensor | None, smooth: float | None
) -> tuple[Tensor, Tensor, Tensor, Tensor, bool]:
    """Validate; return x as (B, T), alpha and beta in x's dtype, r0 as (B, K), squeeze."""
    xb, squeeze = as_batched_sequence(x, "x")
    for name, v in (("alpha", alpha), ("beta", beta)):
        check_tensor(v, name)
        check_floating(v, name)
        if v.dim() != 1 or v.numel() == 0:
            raise ValueError(f"{name} must have shape (K,) with K >= 1, got shape "
                             f"{tuple(v.shape)}")
        check_finite(v, name)
    if alpha.shape != beta.shape:
        raise ValueError(f"alpha and beta must have the same shape, got {tuple(alpha.shape)} "
                         f"and {tuple(beta.shape)}")
    if concrete(alpha, beta) and bool((alpha < beta).any()):
        k = int((alpha < beta).nonzero()[0])
        raise ValueError(f"alpha must be >= beta for every relay, got alpha[{k}]="
                         f"{alpha[k].item():.6g} < beta[{k}]={beta[k].item():.6g}")
    _check_smooth(smooth)
    alpha, beta = alpha.to(xb.dtype), beta.to(xb.dtype)
    K = alpha.shape[0]
    if r0 is None:
        r0 = demagnetized_state(alpha, beta)
    _check_relays(r0, xb.shape[0], K, "state")
    return xb, alpha, beta, r0.to(xb.dtype).expand(xb.shape[0], K), squeeze


def _check_relays(r0: Tensor, B: int, K: int, name: str) -> None:
    check_tensor(r0, name)
    if r0.shape not in ((K,), (B, K)):
        raise ValueError(f"{name} must have shape ({K},) or ({B}, {K}), got shape "
                         f"{tuple(r0.shape)}")
    if concrete(r0) and not bool(((r0 == 1) | (r0 == -1)).all()):
        raise ValueError(f"{name} must hold relay values +1 or -1 only")


def check_relay_state(state: Tensor | None, x: Tensor, K: int, name: str) -> None:
    """Raise unless ``state`` is None or the ``K`` relays before the first sample of ``x``
    (time,) or (batch, time): a tensor of +-1 of shape (K,) or (batch, K). The messages name
    the argument ``name`` (``state`` of :class:`~torchhys.Preisach`'s ``forward`` and of the
    functions here).

    Raises:
        TypeError, ValueError: a bad ``state``. ``x`` is only read for its batch size
        (checked where it is used: an ``x`` that is not a (time,) or (batch, time) tensor
        leaves the state to that check).
    """
    B = sequence_batch(x)
    if state is not None and B is not None:
        _check_relays(state, B, K, name)

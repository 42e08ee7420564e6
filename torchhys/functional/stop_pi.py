"""Stop operators and the stop-type Prandtl-Ishlinskii model with piecewise-linear
characteristics.

The stop operator of threshold r is the elastic-plastic element: its output follows the
input's increments and is held in ``[-r, r]`` (it "slips" at the bounds). It is the input
minus the play operator of half-width r (full width 2 r) started at the same state:

    s[t] = u[t] - p[t],    p[t] = clamp(p[t-1], u[t] - r, u[t] + r),

so it runs on the play machinery of :mod:`torchhys.functional.backlash`. The model

    y = offset + w0 u + sum_i sum_k W[i, k] clamp(s_i, kappa[i, k], kappa[i, k + 1]),
    u = x - center,    kappa[i, k] = r_i (2 k / K - 1),  k = 0..K,

passes every stop's output through a piecewise-linear characteristic of K equal segments
over ``[-r_i, r_i]`` (``W[i, k]`` the slope on segment k). With ``K = 1`` it is the classical
stop-type Prandtl-Ishlinskii model ``offset + w0 u + sum_i W[i, 0] s_i``; with ``W >= 0``
every characteristic rises (a spring that stiffens or softens), as in a friction element in
series with a nonlinear spring. A stop started at zero never slips while ``|u| <= r_i``: its
output is then u itself, and its characteristic a memoryless, piecewise-linear function of the
input. With the center at the midpoint of the input's range, the stops of thresholds of at
least half its span are such (the elastic part of the model).

The output is linear in ``(offset, w0, W)``: :func:`torchhys.fit_stop_pi` identifies
them by least squares (non-negative ``W`` optionally).

References:
    M. Brokate and J. Sprekels, Hysteresis and Phase Transitions, Springer, 1996, Ch. 2
    (stop and play operators, the Prandtl-Ishlinskii model of stop type);
    P. Krejci, Hysteresis, Convexity and Dissipation in Hyperbolic Equations, 1996.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_real,
    check_tensor,
    concrete,
)
from torchhys.functional.backlash import backlash, check_play_state, play_step

__all__ = ["check_invertible", "check_stop_parameters", "check_thresholds",
           "inverse_constants", "stop_characteristic", "stop_pi", "stop_pi_inverse",
           "stop_knots", "stop_pi_inverse_step", "stop_segments"]


def check_thresholds(thresholds: Tensor) -> None:
    """Thresholds: finite, positive, floating, (N,), N >= 1.

    Raises:
        TypeError, ValueError: naming ``thresholds``.
    """
    check_tensor(thresholds, "thresholds")
    check_floating(thresholds, "thresholds")
    if thresholds.dim() != 1 or thresholds.numel() == 0:
        raise ValueError("thresholds must have shape (N,) with N >= 1, got shape "
                         f"{tuple(thresholds.shape)}")
    check_finite(thresholds, "thresholds")
    if concrete(thresholds) and bool((thresholds <= 0).any()):
        raise ValueError("thresholds must be positive, got minimum "
                         f"{thresholds.min().item():.6g}")


def check_stop_parameters(thresholds: Tensor, weights: Tensor) -> None:
    """Thresholds as :func:`check_thresholds`; weights: finite, floating, (N, K).

    Raises:
        TypeError, ValueError: naming ``thresholds`` or ``weights``.
    """
    check_thresholds(thresholds)
    check_tensor(weights, "weights")
    check_floating(weights, "weights")
    n = thresholds.shape[0]
    if weights.dim() != 2 or weights.shape[0] != n or weights.shape[1] == 0:
        raise ValueError(f"weights must have shape ({n}, K), one row of K >= 1 segment slopes "
                         f"per threshold, got shape {tuple(weights.shape)}")
    check_finite(weights, "weights")


def _scalar(value: float | Tensor, name: str, like: Tensor) -> Tensor:
    """A finite real number or one-element real tensor (its gradient kept) as a 0-dim tensor
    in the dtype and on the device of ``like``; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(value, Tensor):
        if value.numel() != 1 or value.is_complex():
            raise ValueError(f"{name} must be a finite real number or a one-element real "
                             f"tensor, got a tensor of shape {tuple(value.shape)}")
        if concrete(value):
            check_real(value.detach(), name)
        return value.reshape(()).to(device=like.device, dtype=like.dtype)
    return torch.tensor(check_real(value, name), dtype=like.dtype, device=like.device)


def stop_knots(thresholds: Tensor, segments: int, like: Tensor) -> Tensor:
    """The knots ``kappa[i, k] = r_i (2 k / K - 1)``, k = 0..K, of ``segments`` = K equal
    segments over each stop's ``[-r_i, r_i]``: (N, K + 1) in ``like``'s dtype and device.
    Scriptable."""
    k = torch.arange(segments + 1, dtype=like.dtype, device=like.device) * (2.0 / segments) - 1.0
    return thresholds.to(like.dtype).unsqueeze(-1) * k


def stop_segments(s: Tensor, thresholds: Tensor, segments: int) -> Tensor:
    """The segment features ``clamp(s_i, kappa[i, k], kappa[i, k + 1])``: stop outputs s
    (..., N) -> (..., N, K), K = ``segments`` equal segments over ``[-r_i, r_i]``.

    Written with ``minimum``/``maximum`` so that autograd and TorchScript pass gradients to
    the bounds. Scriptable: the sequence path, the step and the fit call it.
    """
    knots = stop_knots(thresholds, segments, s)  # (N, K + 1)
    lo, hi = knots[:, :-1], knots[:, 1:]
    return torch.minimum(torch.maximum(s.unsqueeze(-1), lo), hi)


def stop_characteristic(s: Tensor, thresholds: Tensor, weights: Tensor) -> Tensor:
    """``sum_i sum_k W[i, k] clamp(s_i, kappa[i, k], kappa[i, k + 1])``: stop outputs s
    (..., N) -> (...).

    A product and a sum over the last two dimensions (not a matrix product, whose blocking
    changes with the number of rows): chunked and per-sample evaluations equal the whole.
    """
    w = weights.to(s.dtype)
    return (stop_segments(s, thresholds, int(w.shape[1])) * w).sum((-2, -1))


def _characteristic_in_place(s: Tensor, thresholds: Tensor, weights: Tensor) -> Tensor:
    """:func:`stop_characteristic` without gradients: one clamp into one buffer, the product
    in place (faster on long sequences, see docs/benchmarks.md; equal to the bit: the same
    segment values, products and sum)."""
    w = weights.to(s.dtype)
    knots = stop_knots(thresholds, int(w.shape[1]), s)  # (N, K + 1)
    return torch.clamp(s.unsqueeze(-1), knots[:, :-1], knots[:, 1:]).mul_(w).sum((-2, -1))


def stop_pi(
    x: Tensor,
    thresholds: Tensor,
    weights: Tensor,
    *,
    center: float | Tensor = 0.0,
    linear_weight: float | Tensor = 0.0,
    offset: float | Tensor = 0.0,
    state: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Stop-type Prandtl-Ishlinskii output with piecewise-linear characteristics.

    Args:
        x: input, (time,) or (batch, time).
        thresholds: stop thresholds r_i > 0, (N,).
        weights: segment slopes W, (N, K).
        center: the input value c at which the stops' plays start (u = x - c).
        linear_weight, offset: w0 and the offset.
        state: the plays of u before the first sample, (N,) or (batch, N); zeros if None
            (every stop starts at ``u[0]`` clipped to ``[-r_i, r_i]``).

    Returns:
        ``(y, p)``: y the shape of x; p the plays at the last sample, (N,) or (batch, N)
        (the state to pass on to the continuation of the sequence).

    Raises:
        TypeError, ValueError: bad x, thresholds, weights or state.
    """
    xb, squeezed = as_batched_sequence(x, "x")
    check_stop_parameters(thresholds, weights)
    u = xb - _scalar(center, "center", xb)
    w0, b = _scalar(linear_weight, "linear_weight", xb), _scalar(offset, "offset", xb)
    check_play_state(state, xb, thresholds.shape[0], "state")
    r = thresholds.to(device=xb.device, dtype=xb.dtype)
    p = backlash(u, 2.0 * r, state=state)  # (B, T, N)
    w = weights.to(xb.device)
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (p, r, w, w0, b))
    in_place = not needs_grad and concrete(p, w)  # batched (vmap) rows: out of place
    characteristic = _characteristic_in_place if in_place else stop_characteristic
    y = b + w0 * u + characteristic(u.unsqueeze(-1) - p, r, w)
    last = p[:, -1, :]
    return (y[0], last[0]) if squeezed else (y, last)


# --- the exact inverse --------------------------------------------------------------------
def check_invertible(weights: Tensor, linear_weight: Tensor) -> None:
    """Raise unless the output is strictly monotone in the current input whatever the state,
    as the inverse needs it: ``linear_weight`` finite and nonzero, every segment slope finite
    and of its sign or zero. (The output's slope in u is ``w0`` plus the slopes of the stops
    that do not slip; this sufficient condition is the one a non-negative fit with a bounded
    linear weight meets.) The ``ValueError`` names the argument and the fit that gives such a
    model (``fit_stop_pi(..., nonnegative=True, min_linear_weight=...)``).
    """
    hint = ("; fit_stop_pi(..., nonnegative=True, min_linear_weight=m) with m > 0 fits a "
            "model with an inverse")
    if not concrete(weights, linear_weight):
        return
    w0 = float(linear_weight)
    if not math.isfinite(w0):
        raise ValueError(f"linear_weight must be finite, got {w0}")
    if not bool(torch.isfinite(weights).all()):
        raise ValueError("weights must be finite, got a non-finite value")
    if w0 == 0.0:
        raise ValueError("linear_weight must be nonzero for an inverse (where every stop "
                         f"slips, the output's slope is linear_weight alone), got 0{hint}")
    wrong = float(weights.min()) if w0 > 0 else float(weights.max())
    if (wrong < 0) if w0 > 0 else (wrong > 0):
        sign = "non-negative" if w0 > 0 else "non-positive"
        raise ValueError(f"weights must be {sign} (the sign of linear_weight, {w0:.6g}) for "
                         f"an inverse, got a segment slope of {wrong:.6g}: the output is not "
                         f"monotone in the input{hint}")


def inverse_constants(
    thresholds: Tensor, weights: Tensor, linear_weight: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """What :func:`stop_pi_inverse_step` needs of the model, computed once: the sign that
    makes the output increase (``-1`` when ``linear_weight < 0``), the slopes and linear
    weight times it, the knots ``kappa`` (N, K + 1), the change of the output's slope at
    each breakpoint ``p_i + kappa[i, k]``, ``W[i, k] - W[i, k - 1]`` (``W[i, -1] =
    W[i, K] = 0``: beyond ``+-r_i`` the stop slips), flat (N (K + 1),), and the stops'
    part of the output below every breakpoint (every stop at ``-r_i``), 0-dim, detached
    (it only locates the segment). Scriptable."""
    sign = torch.where(linear_weight < 0, -torch.ones_like(linear_weight),
                       torch.ones_like(linear_weight))
    w = weights * sign
    n = w.shape[0]
    knots = stop_knots(thresholds, w.shape[1], w)
    zero = torch.zeros(n, 1, dtype=w.dtype, device=w.device)
    jumps = (torch.cat([w, zero], 1) - torch.cat([zero, w], 1)).reshape(-1)
    floor = (w * knots[:, :-1]).sum().detach()
    return sign, w, linear_weight * sign, knots, jumps, floor


def stop_pi_inverse_step(y: Tensor, p: Tensor, r: Tensor, sign: Tensor, w: Tensor, w0: Tensor,
                         knots: Tensor, jumps: Tensor, floor: Tensor, center: Tensor,
                         offset: Tensor) -> tuple[Tensor, Tensor]:
    """One sample of the exact inverse: the input x with ``F(x - center) = y``, F the
    model's output at this sample as a function of the current input, given the plays p.

    ``F(u) = offset + w0 u + sum_i psi_i(clamp(u - p_i, -r_i, r_i))`` is piecewise linear
    in u with breakpoints ``p_i + kappa[i, k]``. The breakpoints are sorted and F
    accumulated over them (below the lowest every stop is at ``-r_i``) only to find, by
    ``searchsorted``, the segment that holds y; on it F and its slope are evaluated directly
    at a point strictly inside (its midpoint; a unit beyond the breakpoints at either end,
    where the slope is ``w0``) and F is solved in closed form. Exact to rounding; the
    gradient is that of the solution on the chosen segment (the implicit-function one), kept
    when rounding puts the solution a hair outside the segment and it is clamped back: at a
    breakpoint (a held sample after the stops slipped) it is the derivative on one side of
    the kink, the side rounding picks. A
    decreasing F is handled through ``sign`` (:func:`inverse_constants`). Scriptable.

    Args:
        y: (B, 1); p: the plays before this sample, (B, N); r: thresholds (N,);
        sign, w, w0, knots, jumps, floor: :func:`inverse_constants`; center, offset: 0-dim.

    Returns:
        ``(x, p_new)``: x (B, 1), the new plays (B, N).
    """
    target = (y - offset) * sign  # (B, 1): solve w0 u + sum_i psi_i = target, increasing
    with torch.no_grad():  # locate the segment
        b = (p.unsqueeze(-1) + knots).reshape(p.shape[0], -1)  # (B, M) breakpoints in u
        bs, order = b.sort(-1)
        slopes = w0 + jumps[order].cumsum(-1)  # on [bs_j, bs_j+1]
        start = w0 * bs[:, :1] + floor  # F at bs_0: every stop at -r_i
        fb = torch.cat([start, start + (slopes[:, :-1] * (bs[:, 1:] - bs[:, :-1])).cumsum(-1)],
                       -1)
        j = torch.searchsorted(fb.contiguous(), target.detach().contiguous(), right=True) - 1
    m = bs.shape[1]
    below, above = j < 0, j >= m - 1  # beyond the breakpoints: the slope is w0
    i = j.clamp(0, m - 1)
    lower = bs.gather(-1, i)
    upper = bs.gather(-1, (i + 1).clamp_max(m - 1))
    # a point strictly inside the segment (no stop at a knot there: F is smooth at it), the
    # midpoint, or a unit beyond the breakpoints: F and its slope there, with their gradient
    q = torch.where(below, lower - 1.0, torch.where(above, lower + 1.0, 0.5 * (lower + upper)))
    f_q = w0 * q + stop_characteristic(
        torch.minimum(torch.maximum(q - p, -r), r).unsqueeze(1), r, w)
    s_q = (q - p).unsqueeze(-1)  # (B, N, 1)
    inside = (s_q > knots[:, :-1]) & (s_q < knots[:, 1:])  # (B, N, K)
    slope = w0 + (inside.to(w.dtype) * w).sum((-2, -1)).unsqueeze(-1)
    u = q + (target - f_q) / slope
    # rounding in the accumulated F can pick a neighbouring segment: the value is clamped
    # into the chosen one, the gradient kept
    inf = torch.full_like(lower, float("inf"))
    lo = torch.where(below, -inf, lower)
    hi = torch.where(above, inf, torch.where(below, lower, upper))
    u = u + (torch.minimum(torch.maximum(u.detach(), lo), hi) - u.detach())
    return u + center, play_step(u, r, p)


def stop_pi_inverse(
    y: Tensor,
    thresholds: Tensor,
    weights: Tensor,
    *,
    center: float | Tensor = 0.0,
    linear_weight: float | Tensor = 1.0,
    offset: float | Tensor = 0.0,
    state: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The exact inverse of :func:`stop_pi`: the input x whose output is y, sample by sample
    (:func:`stop_pi_inverse_step`; a loop over time: each sample's plays depend on the
    inputs solved before it).

    Args:
        y: the model's output, (time,) or (batch, time).
        thresholds, weights, center, linear_weight, offset: the model's, as in
            :func:`stop_pi`; the output must be strictly monotone in the input
            (:func:`check_invertible`).
        state: the model's plays before the first sample, (N,) or (batch, N); zeros if None.

    Returns:
        ``(x, p)``: x the shape of y; p the plays at the last sample (the model's state: the
        inverse and the model it inverts share it).

    Raises:
        TypeError, ValueError: bad arguments (each named), or a model without an inverse.
    """
    yb, squeezed = as_batched_sequence(y, "y")
    check_stop_parameters(thresholds, weights)
    c = _scalar(center, "center", yb)
    w0, b = _scalar(linear_weight, "linear_weight", yb), _scalar(offset, "offset", yb)
    check_invertible(weights.detach(), w0.detach())
    check_play_state(state, yb, thresholds.shape[0], "state")
    r = thresholds.to(device=yb.device, dtype=yb.dtype)
    sign, w, w0s, knots, jumps, floor = inverse_constants(
        r, weights.to(device=yb.device, dtype=yb.dtype), w0)
    p = (yb.new_zeros(yb.shape[0], r.shape[0]) if state is None
         else state.to(device=yb.device, dtype=yb.dtype).reshape(-1, r.shape[0])
         .expand(yb.shape[0], -1))
    xs = []
    for t in range(yb.shape[1]):
        x_t, p = stop_pi_inverse_step(yb[:, t:t + 1], p, r, sign, w, w0s, knots, jumps, floor,
                                      c, b)
        xs.append(x_t)
    x = torch.cat(xs, 1)
    return (x[0], p[0]) if squeezed else (x, p)

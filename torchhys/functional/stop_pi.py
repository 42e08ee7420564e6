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
input. With the centre at the midpoint of the input's range, the stops of thresholds of at
least half its span are such (the elastic part of the model).

The output is linear in ``(offset, w0, W)``: :func:`torchhys.fit_stop_pi` identifies
them by least squares (non-negative ``W`` optionally).

References:
    M. Brokate and J. Sprekels, Hysteresis and Phase Transitions, Springer, 1996, Ch. 2
    (stop and play operators, the Prandtl-Ishlinskii model of stop type);
    P. Krejci, Hysteresis, Convexity and Dissipation in Hyperbolic Equations, 1996.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_real,
    check_tensor,
)
from torchhys.functional.backlash import backlash, check_play_state

__all__ = ["check_invertible", "check_stop_parameters", "check_thresholds",
           "stop_characteristic", "stop_pi", "stop_pi_inverse", "stop_pi_inverse_step",
           "stop_segments"]


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
    if bool((thresholds <= 0).any()):
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
        check_real(value.detach(), name)
        return value.reshape(()).to(device=like.device, dtype=like.dtype)
    return torch.tensor(check_real(value, name), dtype=like.dtype, device=like.device)


def stop_segments(s: Tensor, thresholds: Tensor, segments: int) -> Tensor:
    """The segment features ``clamp(s_i, kappa[i, k], kappa[i, k + 1])``: stop outputs s
    (..., N) -> (..., N, K), K = ``segments`` equal segments over ``[-r_i, r_i]``.

    Written with ``minimum``/``maximum`` so that autograd and TorchScript pass gradients to
    the bounds. Scriptable: the sequence path, the step and the fit call it.
    """
    k = torch.arange(segments + 1, dtype=s.dtype, device=s.device) * (2.0 / segments) - 1.0
    knots = thresholds.to(s.dtype).unsqueeze(-1) * k  # (N, K + 1)
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


def stop_pi(
    x: Tensor,
    thresholds: Tensor,
    weights: Tensor,
    *,
    center: float | Tensor = 0.0,
    linear_weight: float | Tensor = 0.0,
    offset: float | Tensor = 0.0,
    p0: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Stop-type Prandtl-Ishlinskii output with piecewise-linear characteristics.

    Args:
        x: input, (time,) or (batch, time).
        thresholds: stop thresholds r_i > 0, (N,).
        weights: segment slopes W, (N, K).
        center: the input value c at which the stops' plays start (u = x - c).
        linear_weight, offset: w0 and the offset.
        p0: the plays of u before the first sample, (N,) or (batch, N); zeros if None
            (every stop starts at ``u[0]`` clipped to ``[-r_i, r_i]``).

    Returns:
        ``(y, p)``: y the shape of x; p the plays at the last sample, (N,) or (batch, N)
        (the state to pass on to the continuation of the sequence).

    Raises:
        TypeError, ValueError: bad x, thresholds, weights or p0.
    """
    xb, squeezed = as_batched_sequence(x, "x")
    check_stop_parameters(thresholds, weights)
    u = xb - _scalar(center, "center", xb)
    w0, b = _scalar(linear_weight, "linear_weight", xb), _scalar(offset, "offset", xb)
    check_play_state(p0, xb, thresholds.shape[0], "p0")
    r = thresholds.to(device=xb.device, dtype=xb.dtype)
    p = backlash(u, 2.0 * r, y0=p0)  # (B, T, N)
    y = b + w0 * u + stop_characteristic(u.unsqueeze(-1) - p, r, weights.to(xb.device))
    last = p[:, -1, :]
    return (y[0], last[0]) if squeezed else (y, last)


# --- the exact inverse --------------------------------------------------------------------
def check_invertible(weights: Tensor, linear_weight: Tensor) -> None:
    """A stop-type model whose output is strictly monotone in the current input, whatever
    its state: ``linear_weight`` nonzero and every segment slope of its sign or zero (the
    output's slope in u is ``w0`` plus the slopes of the stops that do not slip: never 0,
    never of the other sign). Otherwise ``ValueError`` naming the argument, with the fit
    that gives such a model (``fit_stop_pi(..., nonnegative=True, min_linear_weight=...)``).
    """
    hint = ("; fit_stop_pi(..., nonnegative=True, min_linear_weight=m) with m > 0 fits a "
            "model with an inverse")
    w0 = float(linear_weight)
    if not w0 != 0.0:
        raise ValueError("linear_weight must be nonzero for an inverse (where every stop "
                         f"slips, the output's slope is linear_weight alone), got 0{hint}")
    wrong = float(weights.min()) if w0 > 0 else float(weights.max())
    if (wrong < 0) if w0 > 0 else (wrong > 0):
        sign = "non-negative" if w0 > 0 else "non-positive"
        raise ValueError(f"weights must be {sign} (the sign of linear_weight, {w0:.6g}) for "
                         f"an inverse, got a segment slope of {wrong:.6g}: the output is not "
                         f"monotone in the input{hint}")


def stop_pi_inverse_step(y: Tensor, p: Tensor, r: Tensor, weights: Tensor, center: Tensor,
                         linear_weight: Tensor, offset: Tensor) -> tuple[Tensor, Tensor]:
    """One sample of the exact inverse: the input x with ``F(x - center) = y``, F the
    model's output at this sample as a function of the current input, given the plays p.

    ``F(u) = offset + w0 u + sum_i psi_i(clamp(u - p_i, -r_i, r_i))`` is piecewise linear
    in u with breakpoints ``p_i + kappa[i, k]``; at each, the slope changes by
    ``W[i, k] - W[i, k - 1]`` (``W[i, -1] = W[i, K] = 0``: beyond ``+-r_i`` the stop slips).
    The breakpoints are sorted, F accumulated over them (below the lowest every stop is at
    ``-r_i``), the segment holding y found by ``searchsorted``, and u solved on it in closed
    form: exact to rounding, and differentiable (the gradient of the solution on that
    segment, the implicit-function one). Needs a strictly monotone F
    (:func:`check_invertible`; a decreasing one is negated). Scriptable.

    Args:
        y: (B, 1); p: the plays before this sample, (B, N); r: thresholds (N,); weights:
        (N, K); center, linear_weight, offset: 0-dim.

    Returns:
        ``(x, p_new)``: x (B, 1), the new plays (B, N).
    """
    sign = torch.where(linear_weight < 0, -torch.ones_like(linear_weight),
                       torch.ones_like(linear_weight))
    w = weights * sign
    w0 = linear_weight * sign
    target = (y - offset) * sign  # (B, 1)
    n, k = w.shape[0], w.shape[1]
    steps = torch.arange(k + 1, dtype=y.dtype, device=y.device) * (2.0 / k) - 1.0
    knots = r.unsqueeze(-1) * steps  # (N, K + 1)
    zero = torch.zeros(n, 1, dtype=w.dtype, device=w.device)
    jumps = (torch.cat([w, zero], 1) - torch.cat([zero, w], 1)).reshape(-1)  # (M,)
    b = (p.unsqueeze(-1) + knots).reshape(p.shape[0], -1)  # (B, M) breakpoints in u
    bs, order = b.sort(-1)
    slopes = w0 + jumps[order].cumsum(-1)  # on [bs_j, bs_j+1]; after the last: w0
    start = w0 * bs[:, :1] + (w * knots[:, :-1]).sum()  # F at bs_0: every stop at -r_i
    gaps = bs[:, 1:] - bs[:, :-1]
    fb = torch.cat([start, start + (slopes[:, :-1] * gaps).cumsum(-1)], -1)  # (B, M)
    j = torch.searchsorted(fb.detach().contiguous(), target.detach().contiguous(),
                           right=True) - 1  # (B, 1): -1 below bs_0
    below = j < 0
    i = j.clamp_min(0)
    anchor, f_anchor = bs.gather(-1, i), fb.gather(-1, i)
    slope = torch.where(below, w0.expand_as(anchor), slopes.gather(-1, i))
    u = anchor + (target - f_anchor) / slope
    # rounding in the accumulated F can pick a neighbouring segment: stay inside this one
    inf = torch.full_like(anchor, float("inf"))
    lo = torch.where(below, -inf, anchor)
    hi = torch.where(i + 1 < bs.shape[1], bs.gather(-1, (i + 1).clamp_max(bs.shape[1] - 1)),
                     inf)
    hi = torch.where(below, anchor, hi)
    u = torch.minimum(torch.maximum(u, lo), hi)
    return u + center, torch.minimum(torch.maximum(p, u - r), u + r)


def stop_pi_inverse(
    y: Tensor,
    thresholds: Tensor,
    weights: Tensor,
    *,
    center: float | Tensor = 0.0,
    linear_weight: float | Tensor = 1.0,
    offset: float | Tensor = 0.0,
    p0: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The exact inverse of :func:`stop_pi`: the input x whose output is y, sample by sample
    (:func:`stop_pi_inverse_step`; a loop over time: each sample's plays depend on the
    inputs solved before it).

    Args:
        y: the model's output, (time,) or (batch, time).
        thresholds, weights, center, linear_weight, offset: the model's, as in
            :func:`stop_pi`; the output must be strictly monotone in the input
            (:func:`check_invertible`).
        p0: the model's plays before the first sample, (N,) or (batch, N); zeros if None.

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
    check_play_state(p0, yb, thresholds.shape[0], "p0")
    r = thresholds.to(device=yb.device, dtype=yb.dtype)
    w = weights.to(device=yb.device, dtype=yb.dtype)
    p = (yb.new_zeros(yb.shape[0], r.shape[0]) if p0 is None
         else p0.to(yb.dtype).reshape(-1, r.shape[0]).expand(yb.shape[0], -1))
    xs = []
    for t in range(yb.shape[1]):
        x_t, p = stop_pi_inverse_step(yb[:, t:t + 1], p, r, w, c, w0, b)
        xs.append(x_t)
    x = torch.cat(xs, 1) if xs else yb.clone()
    return (x[0], p[0]) if squeezed else (x, p)

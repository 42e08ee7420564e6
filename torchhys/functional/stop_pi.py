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

__all__ = ["check_stop_parameters", "check_thresholds", "stop_characteristic", "stop_pi",
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

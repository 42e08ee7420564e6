"""Prandtl-Ishlinskii models: weighted sums of play operators, and their exact inverse."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import (
    check_finite,
    check_floating,
    check_tensor,
    check_widths,
    concrete,
)
from torchhys.functional.backlash import backlash

__all__ = [
    "PIInverseParameters", "pi_output", "prandtl_ishlinskii",
    "prandtl_ishlinskii_inverse_parameters",
]


def _check_weights(weights: Tensor, n: int, name: str = "weights") -> Tensor:
    check_tensor(weights, name)
    check_floating(weights, name)
    if weights.shape != torch.Size([n]):
        raise ValueError(
            f"{name} must have shape ({n},), one weight per width, got shape {tuple(weights.shape)}"
        )
    return check_finite(weights, name)


def pi_output(x: Tensor, y: Tensor, weights: Tensor, linear_weight: Tensor) -> Tensor:
    """``w0 * x + sum_i w_i * y_i``: x (...), play outputs y (..., N) -> (...).

    A product and a sum over the last dimension (not a matrix product, whose blocking, and
    so its rounding, changes with the number of rows): each output depends on its own row
    only, so chunked and per-sample evaluations equal the whole. Scriptable: the sequence
    path and the streaming step call it.
    """
    return linear_weight * x + (y * weights).sum(-1)


def prandtl_ishlinskii(
    x: Tensor,
    widths: Tensor,
    weights: Tensor,
    *,
    linear_weight: float | Tensor = 0.0,
    state: Tensor | None = None,
) -> Tensor:
    """Prandtl-Ishlinskii output ``H[x] = w0 * x + sum_i w_i * play_{d_i}[x]``.

    Args:
        x: input, shape (time,) or (batch, time).
        widths: full dead-band widths d_i >= 0 of the play operators, shape (N,).
        weights: weights w_i, shape (N,).
        linear_weight: the weight w0 of the linear term (float or 0-dim tensor).
        state: play-operator outputs before the first sample, (N,) or (batch, N); zeros if None.

    Returns:
        H[x], the shape of ``x``.

    Raises:
        TypeError, ValueError: see :func:`torchhys.functional.backlash`; also for
        weights of the wrong shape or non-finite weights.
    """
    check_widths(widths, "widths")
    _check_weights(weights, widths.shape[0])
    y = backlash(x, widths, state=state)
    return pi_output(x, y, weights.to(y.dtype), torch.as_tensor(linear_weight, dtype=y.dtype))


class PIInverseParameters(NamedTuple):
    """Parameters of the inverse Prandtl-Ishlinskii model (sorted by width)."""

    widths: Tensor
    """Full dead-band widths of the inverse play operators, shape (M,)."""
    weights: Tensor
    """Their weights, shape (M,)."""
    linear_weight: Tensor
    """The inverse's linear weight, 0-dim."""
    order: Tensor
    """Indices of the forward operators with positive width, sorted by width, shape (M,)."""
    cumulative: Tensor
    """Slopes of the initial loading curve on each interval, shape (M + 1,)."""


def prandtl_ishlinskii_inverse_parameters(
    widths: Tensor, weights: Tensor, linear_weight: float | Tensor
) -> PIInverseParameters:
    """The classical inversion rule for a Prandtl-Ishlinskii model.

    With half-widths sorted, ``0 = r_0 < r_1 < ... < r_M`` (operators of width zero are
    identities and are folded into the linear weight w_0), and the slopes of the
    initial loading curve ``s_j = w_0 + sum_{i<=j} w_i``, the inverse is again a
    Prandtl-Ishlinskii model with

        r'_j = sum_{i<=j} w_i (r_j - r_i),   w'_0 = 1 / s_0,   w'_j = -w_j / (s_j s_{j-1}).

    It exists when the initial loading curve is strictly increasing (every s_j > 0).

    Args:
        widths: full dead-band widths d_i >= 0, shape (N,).
        weights: weights w_i, shape (N,).
        linear_weight: the linear weight w_0.

    Returns:
        :class:`PIInverseParameters`.

    Raises:
        ValueError: when the initial loading curve is not strictly increasing, so the
            model has no inverse (e.g. ``linear_weight = 0`` with all widths positive).

    References:
        P. Krejci and K. Kuhnen, "Inverse control of systems with hysteresis and creep",
        IEE Proc. Control Theory Appl. 148(3), 2001; M. Brokate and J. Sprekels,
        Hysteresis and Phase Transitions, 1996, Sec. 2.3.
    """
    check_widths(widths, "widths")
    _check_weights(weights, widths.shape[0])
    w0 = torch.as_tensor(linear_weight, dtype=widths.dtype, device=widths.device)
    zero = widths == 0
    w0 = w0 + weights[zero].sum()
    order = torch.nonzero(~zero).flatten()
    order = order[torch.argsort(widths[order], stable=True)]
    r = 0.5 * widths[order]
    w = weights[order]
    slopes = torch.cat([w0.reshape(1), w0 + torch.cumsum(w, 0)])
    if concrete(slopes) and bool((slopes <= 0).any()):
        j = int((slopes <= 0).nonzero()[0])
        raise ValueError(
            "the Prandtl-Ishlinskii model has no inverse: its initial loading curve must be "
            f"strictly increasing, but its slope on interval {j} is {slopes[j].item():.6g} "
            "(with all widths positive this needs linear_weight > 0)"
        )
    # r'_j = sum_{i<=j} w_i (r_j - r_i) + w0 r_j
    r_inv = w0 * r + torch.cumsum(w, 0) * r - torch.cumsum(w * r, 0)
    w_inv = -w / (slopes[1:] * slopes[:-1])
    return PIInverseParameters(2.0 * r_inv, w_inv, 1.0 / slopes[0], order, slopes)

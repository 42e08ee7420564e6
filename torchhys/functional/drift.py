"""A slow drift driven by the input's accumulated variation.

Some devices do not repeat their loop: a shape-memory-alloy actuator cycled under load
stretches a little more every cycle (transformation-induced plasticity, "ratcheting"), a
magnetic core or a seal settles over its first cycles. Such a drift grows with how much the
device has been driven, not with time, and slows down. This module models it as a
saturating function of the input's accumulated variation (its total variation since the
start of the record),

    v[t] = v[-1] + sum_{s <= t} |x[s] - x[s-1]|,    x[-1] the previous input,
    d[t] = offset + sum_k w_k (1 - exp(-v[t] / c_k)),

with saturation scales ``c_k > 0`` (in input units: a full cycle of amplitude A adds 2 A to
v). A variation floor ``v_0 >= 0`` (``min_variation``) holds the drift at its value there for
smaller v: ``d[t]`` uses ``max(v[t], v_0)``. A drift identified on samples whose variation is
at least ``v_0`` (a record whose first cycles were held out) is then not extrapolated
backwards, where large weights fitted on the flat tails of its exponentials would move it
far; from ``v_0`` on it is unchanged (0: no floor, v is never negative). With weights of one
sign the drift is monotone and decelerating, the form of the accumulated transformation
strain of shape-memory alloys. The drift has memory (v) but no loop: beside a hysteresis
model it shifts the whole loop as the device is used.

v is accumulated in float64 (the sum of many small steps); chunked calls with the returned
state equal one call exactly.

References:
    D. C. Lagoudas and P. B. Entchev, "Modeling of transformation-induced plasticity and its
    effect on the behavior of porous shape memory alloys. Part I", Mech. Mater. 36 (2004)
    865-892 (the saturating exponential of the accumulated transformation).
"""

from __future__ import annotations

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

__all__ = ["accumulated_variation", "check_drift_state", "check_scales", "drift",
           "drift_features", "drift_step", "weighted_sum"]


def check_scales(scales: Tensor) -> None:
    """Saturation scales: a floating (K,) tensor, K >= 1, finite and positive.

    Raises:
        TypeError, ValueError: naming ``scales``.
    """
    check_tensor(scales, "scales")
    check_floating(scales, "scales")
    if scales.dim() != 1 or scales.shape[0] == 0:
        raise ValueError(f"scales must have shape (K,) with K >= 1, got shape "
                         f"{tuple(scales.shape)}")
    if concrete(scales) and not bool((scales.isfinite() & (scales > 0)).all()):
        raise ValueError(f"scales must be finite and positive (saturation scales in input "
                         f"units), got {scales.tolist()}")


def check_drift_state(state: Tensor | None, x: Tensor, name: str = "state") -> None:
    """Raise unless ``state`` is None or ``(previous input, accumulated variation)`` before
    the first sample of x: a finite floating tensor of shape (2,) or (batch, 2) whose
    variation column is >= 0.

    Raises:
        TypeError, ValueError: naming ``name``.
    """
    B = sequence_batch(x)
    if state is None or B is None:
        return
    check_tensor(state, name)
    check_floating(state, name)
    if state.shape not in (torch.Size([2]), torch.Size([B, 2])):
        raise ValueError(f"{name} must have shape (2,) or ({B}, 2) (previous input, "
                         f"accumulated variation) for batch {B}, got shape "
                         f"{tuple(state.shape)}")
    check_finite(state, name)
    if concrete(state) and bool((state[..., 1] < 0).any()):
        raise ValueError(f"{name}: the accumulated variation (column 1) must be >= 0, got "
                         f"{state[..., 1].min().item():.6g}")


def accumulated_variation(x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The input's accumulated variation ``v[t] = v[-1] + sum_{s <= t} |x[s] - x[s-1]|``.

    Args:
        x: input, (time,) or (batch, time), floating, finite.
        state: ``(previous input, accumulated variation)`` before the first sample, (2,) or
            (batch, 2); None: a fresh start (the previous input is ``x[0]``, no variation).

    Returns:
        ``(v, state)``: v in float64, the shape of x; the state after the last sample,
        (batch, 2) float64 (or (2,) for a (time,) input).
    """
    xb, squeezed = as_batched_sequence(x, "x")
    check_drift_state(state, x)
    x64 = xb.to(torch.float64)
    if state is None:
        s = torch.stack([x64[:, 0], torch.zeros_like(x64[:, 0])], dim=1)
    else:
        s = state.to(dtype=torch.float64, device=x.device).expand(xb.shape[0], 2)
    steps = torch.diff(x64, dim=1, prepend=s[:, :1]).abs()
    # v[-1] first, so that chunked calls add in the order of one call (and of the step)
    v = torch.cumsum(torch.cat([s[:, 1:], steps], dim=1), dim=1)[:, 1:]
    new = torch.stack([x64[:, -1], v[:, -1]], dim=1)
    if squeezed:
        return v[0], new[0]
    return v, new


def drift_features(v: Tensor, scales: Tensor) -> Tensor:
    """``1 - exp(-v / c_k)`` for every scale: v float64 (...,), scales (K,) -> (..., K),
    float64."""
    return -torch.expm1(-v.unsqueeze(-1) / scales.to(torch.float64))


def weighted_sum(g: Tensor, weights: Tensor) -> Tensor:
    """``sum_k g[..., k] w_k``, added in the order of k (the sequence path and the step add
    alike: the same bits; scriptable)."""
    out = g[..., 0] * weights[0]
    for k in range(1, weights.shape[0]):
        out = out + g[..., k] * weights[k]
    return out


def drift(x: Tensor, scales: Tensor, weights: Tensor, offset: Tensor | float = 0.0,
          state: Tensor | None = None,
          min_variation: Tensor | float = 0.0) -> tuple[Tensor, Tensor]:
    """The drift ``offset + sum_k w_k (1 - exp(-max(v, v_0) / c_k))`` of the accumulated
    variation v.

    Args:
        x: input, (time,) or (batch, time).
        scales: saturation scales c_k > 0, (K,).
        weights: w_k, (K,).
        offset: a scalar.
        state: as :func:`accumulated_variation`.
        min_variation: the floor v_0 >= 0 (a scalar; 0: none).

    Returns:
        ``(d, state)``: d in x's dtype, the shape of x; the state after the last sample.
    """
    check_scales(scales)
    check_tensor(weights, "weights")
    if weights.shape != scales.shape:
        raise ValueError(f"weights must have the shape of scales {tuple(scales.shape)}, got "
                         f"{tuple(weights.shape)}")
    v, new = accumulated_variation(x, state)
    floor = torch.as_tensor(min_variation, dtype=torch.float64, device=v.device)
    g = drift_features(torch.maximum(v, floor), scales).to(x.dtype)
    return offset + weighted_sum(g, weights.to(x.dtype)), new


def drift_step(x: Tensor, previous: Tensor, variation: Tensor, scales: Tensor,
               weights: Tensor, offset: Tensor,
               min_variation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """One sample of :func:`drift` (scriptable): x (B, 1); previous input and accumulated
    variation (B, 1) float64; the floor, a 0-dim float64 tensor -> the drift (B, 1) in x's
    dtype, and the new previous input and variation."""
    x64 = x.to(torch.float64)
    v = variation + (x64 - previous).abs()
    g = drift_features(torch.maximum(v, min_variation.to(torch.float64)),
                       scales).to(x.dtype)  # (B, 1, K)
    return offset + weighted_sum(g, weights), x64, v

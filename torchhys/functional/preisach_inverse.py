"""The exact inverse of the hard-relay Preisach model
(:func:`torchhys.functional.preisach.preisach`): the input at which the model, from its
relays, outputs a target, sample by sample (:func:`preisach_inverse_step`), or over a
sequence in windows of samples that leave the relays as they are (:func:`preisach_inverse`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchhys._checks import check_tensor, concrete
from torchhys.functional._preisach_kernel import inverse_kernel, inverse_kernel_available
from torchhys.functional.preisach import (
    _check_inputs,
    check_scale,
    graded_input,
    graded_input_inverse,
    relay_update,
)

__all__ = [
    "check_preisach_invertible",
    "inverse_on_relays",
    "preisach_inverse",
    "preisach_inverse_constants",
    "preisach_inverse_step",
]


def check_preisach_invertible(weights: Tensor, linear: Tensor) -> None:
    """Raise unless a hard-relay Preisach model with this density and linear term rises
    strictly with its input at every state (finite weights >= 0 and a finite linear term
    > 0), so that it has an exact inverse.

    Raises:
        ValueError: naming ``weights`` or ``linear``.
    """
    if not concrete(weights, linear):
        return
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise ValueError("weights must be finite and non-negative (a Preisach density) for "
                         "an inverse")
    if linear.numel() != 1 or not (math.isfinite(float(linear)) and float(linear) > 0):
        raise ValueError(f"linear must be one finite number > 0 for an inverse (the output "
                         f"must rise with the input between the relays' thresholds), got "
                         f"{linear.tolist()!r:.60}")


def preisach_inverse_constants(
    alpha: Tensor, beta: Tensor, weights: Tensor, linear: Tensor, offset: Tensor,
    center: float, scale: float | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The tables of :func:`inverse_on_relays` for the model with thresholds alpha, beta
    (K,), density ``weights`` (K,), 0-dim ``linear`` and ``offset``, and its grading;
    differentiable in the weights, linear and offset. With the L distinct thresholds
    (levels, ascending) and their graded values g (:func:`graded_input`), each table is
    indexed by m, the number of levels below the solution (0..L):

    - ``offs0`` (L + 1,) and ``doffs`` (K, L + 1): the output less its linear term just
      above level m - 1 (below every level for m = 0) is ``offs0 + r @ doffs`` for relays r.
      Relay k adds ``(1 - r_k) w_k`` at its alpha and ``(1 + r_k) w_k`` at its beta to
      ``offset - sum(w)``; summed over the levels up to m - 1 that is
      ``w @ (A + B) + r @ (w (B - A))``, A and B counting whether each relay's alpha and
      beta lie at or below the level.
    - ``lin_g`` (L,): ``linear * g``, the linear term at each level.
    - ``cap`` (L + 1,): g at level m, where the output jumps (inf for m = L); ``level``
      (L + 1,): level m (the last level for m = L, never used); ``bounds`` (2, L + 1): the
      nearest floats inside the open segment between levels m - 1 and m (-inf and inf at
      the ends).
    """
    both = torch.cat([alpha, beta])
    # where the values cannot be read (traced, batched, meta, fake) the levels keep their
    # repeats (unique's size depends on the values): a repeated level's empty segment is
    # never the one searchsorted finds, so the solutions are the same
    levels = torch.unique(both) if concrete(both) else both.sort().values
    one = torch.eye(levels.shape[0], dtype=alpha.dtype, device=alpha.device)
    at_a = one[torch.searchsorted(levels, alpha)].cumsum(-1)  # (K, L): alpha <= level
    at_b = one[torch.searchsorted(levels, beta)].cumsum(-1)
    w = weights.to(alpha.dtype)
    base = (offset - w.sum()).reshape(1)
    offs0 = torch.cat([base, base + w @ (at_a + at_b)])
    doffs = torch.cat([torch.zeros_like(w)[:, None], w[:, None] * (at_b - at_a)], -1)
    glevels = graded_input(levels, center, scale)
    inf = torch.full_like(levels[:1], math.inf)
    cap = torch.cat([glevels, inf])
    level = torch.cat([levels, levels[-1:]])
    bounds = torch.stack([torch.cat([-inf, torch.nextafter(levels, inf)]),
                          torch.cat([torch.nextafter(levels, -inf), inf])])
    return offs0, doffs, linear * glevels, cap, level, bounds


def inverse_on_relays(
    y: Tensor, r: Tensor, offs0: Tensor, doffs: Tensor, lin_g: Tensor, cap: Tensor,
    level: Tensor, bounds: Tensor, linear: Tensor, center: float, scale: float | None,
) -> Tensor:
    """The input x at which the model outputs y while its relays stay r: the solve of
    :func:`preisach_inverse_step`, for any number of samples of y against one state.

    Given r, the output is a non-decreasing function of the input x: between neighbouring
    levels it is ``offset + linear * graded_input(x) + const``, and at a level it jumps by
    ``(1 - r_k) w_k`` for the relays with alpha there and ``(1 + r_k) w_k`` for those with
    beta there. The jumps are summed level by level (one matrix product with the tables of
    :func:`preisach_inverse_constants`), the segment whose range holds y is found by
    ``searchsorted``, and y is solved in closed form on it; a y inside a jump (which the
    model cannot output) gives that level itself, where the relays switch as the model
    switches them at an input equal to it (both its alpha and its beta relays). x is kept
    strictly inside its segment (against rounding in the graded map), so that the relays
    then switch as the solution says (:func:`relay_update`).

    Args:
        y: target, (batch, m). r: relays, (batch, K).
        offs0, doffs, lin_g, cap, level, bounds: :func:`preisach_inverse_constants`.
        linear: 0-dim (> 0: :func:`check_preisach_invertible`).
        center, scale: the grading (:func:`graded_input`).

    Returns:
        x, (batch, m). Differentiable in y and in what the tables are differentiable in, on
        the chosen segment (0 in y inside a jump).
    """
    offs = offs0 + r @ doffs  # (B, L + 1): the output less its linear term above level m - 1
    with torch.no_grad():  # m: the number of levels whose output just above lies below y
        m = torch.searchsorted((lin_g + offs[:, 1:]).detach(), y.detach().contiguous())
    g = (y - offs.gather(1, m)) / linear
    c = cap[m]
    x = graded_input_inverse(torch.minimum(g, c), center, scale)
    x = torch.maximum(torch.minimum(x, bounds[1][m]), bounds[0][m])
    return torch.where(g >= c, level[m], x)  # inside a jump: the level itself, exactly


def preisach_inverse_step(
    y: Tensor, r: Tensor, alpha: Tensor, beta: Tensor, offs0: Tensor, doffs: Tensor,
    lin_g: Tensor, cap: Tensor, level: Tensor, bounds: Tensor, linear: Tensor, center: float,
    scale: float | None,
) -> tuple[Tensor, Tensor]:
    """One sample of the inverse: the input x at which the model, from relays r, outputs y
    (:func:`inverse_on_relays`), and the relays after it (:func:`relay_update`).

    Args:
        y: target, (batch, 1). r: relays, (batch, K).
        alpha, beta: (K,); offs0, doffs, lin_g, cap, level, bounds:
            :func:`preisach_inverse_constants`.
        linear: 0-dim (linear > 0: :func:`check_preisach_invertible`).
        center, scale: the grading (:func:`graded_input`).

    Returns:
        ``(x, r)``: x (batch, 1), the relays after it (batch, K).
    """
    x = inverse_on_relays(y, r, offs0, doffs, lin_g, cap, level, bounds, linear, center,
                          scale)
    return x, relay_update(x, alpha, beta, r)


def _inverse_windows(
    y: Tensor, r: Tensor, alpha: Tensor, beta: Tensor, tables: tuple[Tensor, ...],
    linear: Tensor, center: float, scale: float | None, first: int = 8, largest: int = 4096,
) -> tuple[Tensor, Tensor]:
    """The sequence path of :func:`preisach_inverse`, for y (batch, time >= 1), from relays
    r (batch, K): what a loop of :func:`preisach_inverse_step` returns, in fewer steps.

    The relays change only at the samples where the solved input reaches a threshold. So a
    window of samples is solved at once against the relays at its start
    (:func:`inverse_on_relays`); its solutions hold up to and including the first sample
    whose solution switches a relay (:func:`relay_switch`'s rule: a relay down at
    ``x >= alpha``; one up at ``x <= beta``, or ``x < beta`` on the diagonal, where switching
    up wins a tie). The relays are switched with that sample's solution
    (:func:`relay_update`) and the next window starts after it. A window is ``first``
    samples long, twice as long after one without a switch, and twice the run up to the
    switch after one with (at most ``largest``): the cost follows the number of switches,
    not of samples. Where the relays switch at almost every sample (a fine grid under a
    noisy target) it costs about what the loop does.

    Returns:
        ``(x, r)``: x (batch, time), r the relays at the last sample.
    """
    if not concrete(y, r, alpha, beta):  # no window sizes from the values: the loop itself
        steps = []
        for k in range(y.shape[1]):
            x, r = preisach_inverse_step(y[:, k:k + 1], r, alpha, beta, *tables, linear,
                                         center, scale)
            steps.append(x)
        return torch.cat(steps, 1), r
    xs: list[Tensor] = []
    diagonal = alpha == beta

    def next_switches(r: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The thresholds that switch one of the relays r next, (B, 1) each: a relay down
        switches up at x >= alpha; one up switches down at x <= beta, a diagonal one
        (alpha == beta) at x < beta."""
        up = r > 0
        return (torch.where(up, math.inf, alpha).amin(-1, keepdim=True),
                torch.where(up & ~diagonal, beta, -math.inf).amax(-1, keepdim=True),
                torch.where(up & diagonal, beta, -math.inf).amax(-1, keepdim=True))

    next_up, next_down, next_below = next_switches(r)
    T = y.shape[1]
    s = 0
    width = first
    while s < T:
        x = inverse_on_relays(y[:, s:s + width], r, *tables, linear, center, scale)
        switch = ((x >= next_up) | (x <= next_down) | (x < next_below)).any(0)  # (m,)
        m = x.shape[1]
        # the first switch, or m where there is none (argmax returns the first maximum)
        j = int(torch.cat([switch, switch.new_ones(1)]).to(torch.int8).argmax())
        if j < m:
            r = relay_update(x[:, j:j + 1], alpha, beta, r)
            next_up, next_down, next_below = next_switches(r)
            x = x[:, :j + 1]
            width = min(max(2 * (j + 1), first), largest)
        else:
            width = min(2 * width, largest)
        xs.append(x)
        s += x.shape[1]
    return torch.cat(xs, 1), r


def preisach_inverse(
    y: Tensor,
    weights: Tensor,
    alpha: Tensor,
    beta: Tensor,
    *,
    offset: Tensor,
    linear: Tensor,
    state: Tensor | None = None,
    center: float = 0.0,
    scale: float | None = None,
) -> tuple[Tensor, Tensor]:
    """The exact inverse of the hard-relay Preisach model :func:`preisach`: the input x,
    sample by sample, at which the model outputs y (:func:`preisach_inverse_step`), in
    windows of samples that leave the relays as they are (:func:`_inverse_windows`); without
    gradients on the CPU, one compiled loop
    (:mod:`torchhys.functional._preisach_kernel`).

    Args:
        y: target, (time,) or (batch, time).
        weights, alpha, beta, offset, linear: the model (non-negative weights, linear > 0).
        state: relays before the first sample, (K,) or (batch, K); default
            :func:`demagnetized_state`.
        center, scale: its grading (:func:`preisach_grid`).

    Returns:
        ``(x, r)``: x the shape of y, r the relays at the last sample.

    Raises:
        ValueError: bad arguments; a model without an inverse
            (:func:`check_preisach_invertible`).
    """
    yb, alpha, beta, r, squeeze = _check_inputs(y, alpha, beta, state, None)
    check_tensor(weights, "weights")
    if weights.shape != alpha.shape:
        raise ValueError(f"weights must have shape {tuple(alpha.shape)} (one per relay), got "
                         f"shape {tuple(weights.shape)}")
    linear = torch.as_tensor(linear, dtype=yb.dtype, device=yb.device).reshape(())
    offset = torch.as_tensor(offset, dtype=yb.dtype, device=yb.device).reshape(())
    check_preisach_invertible(weights.detach(), linear.detach())
    scale = check_scale(scale)
    tables = preisach_inverse_constants(alpha, beta, weights.to(yb.dtype), linear, offset,
                                        float(center), scale)
    if inverse_kernel_available(yb, r, alpha, beta, weights, linear, offset):
        x, r = inverse_kernel(yb, r, alpha, beta, tables, linear, float(center), scale)
    else:
        x, r = _inverse_windows(yb, r, alpha, beta, tables, linear, float(center), scale)
    return (x[0], r[0]) if squeeze else (x, r)

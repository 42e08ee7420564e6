"""Causal turning-point detection with a reversal threshold.

A turning point is a local extremum of the input. On measured (noisy) data every sample
would be one, so a reversal only counts once the input has moved back by *more than*
``threshold`` from the running extremum (a zigzag / hysteresis-band detector). The
detector is the play operator of full width ``threshold``: its output moves up exactly
while the input sets a new running maximum and turns exactly when the input has fallen
more than ``threshold`` below it. The play output is a prefix composition of clamp maps,
computed here with a logarithmic number of vectorized steps (no loop over samples).

Timing: the turning point at sample ``s`` is only *known* at the later confirmation
sample ``c`` (with ``threshold=0``, ``c = s + 1``). The mask marks ``s`` itself.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence, concrete

__all__ = [
    "Branches", "Zigzag", "branches_between", "estimate_threshold", "reversal_ranges",
    "turning_points", "zigzag",
]

#: Factor applied to the robust noise estimate by ``threshold="auto"``.
AUTO_FACTOR = 10.0


class Zigzag(NamedTuple):
    """Per-sample output of the causal detector, all of shape (batch, time)."""

    move: Tensor
    """+1 / -1 where the running extremum advanced at this sample, else 0 (long)."""
    direction: Tensor
    """Direction of the committed branch after each sample: +1, -1 or 0 (not yet set)."""
    confirm: Tensor
    """True where a reversal is confirmed (the previous running extremum is a turning point)."""
    extremum: Tensor
    """Index of the sample holding the running extremum, -1 when it lies before the call."""
    play: Tensor
    """Detector (play operator) state after the last sample, shape (batch,)."""


def _prefix_clamp(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Prefix composition of clamp maps ``y -> clamp(y, lo_t, hi_t)`` along the last axis.

    ``clamp(clamp(y, a1, b1), a2, b2) = clamp(y, clamp(a1, a2, b2), clamp(b1, a2, b2))``;
    the result holds only copies of the inputs (min/max are exact). O(T log T) time, O(T)
    memory (used without autograd: the detector output is discrete). A symbolic ``T``
    (``torch.export`` with a dynamic time dimension) takes :func:`_prefix_clamp_symbolic`.
    """
    T = lo.shape[-1]
    if not isinstance(T, int):
        return _prefix_clamp_symbolic(lo, hi)
    k = 1
    while k < T:
        lo_cur, hi_cur = lo[..., k:], hi[..., k:]
        new_lo = torch.minimum(torch.maximum(lo[..., :-k], lo_cur), hi_cur)
        new_hi = torch.minimum(torch.maximum(hi[..., :-k], lo_cur), hi_cur)
        lo = torch.cat([lo[..., :k], new_lo], dim=-1)
        hi = torch.cat([hi[..., :k], new_hi], dim=-1)
        k *= 2
    return lo, hi


def _prefix_clamp_symbolic(lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_prefix_clamp` for a symbolic length ``T``, the same values: each doubling
    composes with the maps ``k`` samples earlier, shifted in behind the identity map
    ``clamp(y, -inf, inf)`` (no slice of size ``T - k``, on which export would guard), over
    the doublings of the largest length ``T`` may take (2 ** 62 if unbounded)."""
    T = lo.shape[-1]
    upper = T.node.shape_env.bound_sympy(T.node.expr).upper
    largest = int(upper) if upper.is_finite and upper < 1 << 62 else 1 << 62
    k = 1
    while k < largest:
        shift = torch.sym_min(k, T)
        lo_prev = torch.nn.functional.pad(lo, (shift, 0), value=-math.inf)[..., :T]
        hi_prev = torch.nn.functional.pad(hi, (shift, 0), value=math.inf)[..., :T]
        lo, hi = (torch.minimum(torch.maximum(lo_prev, lo), hi),
                  torch.minimum(torch.maximum(hi_prev, lo), hi))
        k *= 2
    return lo, hi


def zigzag(x: Tensor, threshold: Tensor, play0: Tensor, direction0: Tensor) -> Zigzag:
    """Run the causal detector on a chunk (internal building block of the operators).

    Args:
        x: (batch, time), values only (no gradient is taken).
        threshold: (batch, 1) reversal threshold, >= 0.
        play0: (batch,) detector state before the chunk.
        direction0: (batch,) long direction before the chunk.

    Returns:
        :class:`Zigzag`.
    """
    with torch.no_grad():
        x = x.detach()
        B, T = x.shape
        r = 0.5 * threshold.to(x.dtype)
        lo, hi = _prefix_clamp(x - r, x + r)
        p = torch.minimum(torch.maximum(play0.to(x.dtype)[:, None], lo), hi)
        prev = torch.cat([play0.to(x.dtype)[:, None], p], dim=1)[:, :T]  # no size T - 1
        move = torch.sign(p - prev).to(torch.long)
        idx = torch.arange(T, device=x.device).expand(B, T)
        last = torch.where(move != 0, idx, -1).cummax(dim=1).values
        moved = move.gather(1, last.clamp(min=0))
        direction = torch.where(last >= 0, moved, direction0[:, None])
        d_prev = torch.cat([direction0[:, None], direction], dim=1)[:, :T]
        confirm = (move != 0) & (d_prev != 0) & (move != d_prev)
    return Zigzag(move, direction, confirm, last, p[:, -1])


def estimate_threshold(x: Tensor, *, factor: float = AUTO_FACTOR) -> Tensor:
    """Reversal threshold from the data's noise: ``factor`` times a robust noise level.

    The noise standard deviation is estimated from the second difference
    ``e_t = x_{t+1} - 2 x_t + x_{t-1}``, which removes a smooth signal and has standard
    deviation ``sqrt(6) sigma`` for white noise: ``sigma = 1.4826 MAD(e) / sqrt(6)``. The
    threshold is ``factor * sigma`` (``factor=10`` by default: a run of white noise seldom
    swings back by more than about 7 sigma). Correlated noise is underestimated.

    Args:
        x: (time,) or (batch, time).
        factor: multiplier, > 0.

    Returns:
        Threshold per sequence, shape (batch,) (``()`` for a 1-D input).
    """
    xb, squeezed = as_batched_sequence(x, "x")
    if xb.shape[-1] < 3:
        raise ValueError(
            f"x must hold at least 3 samples to estimate a threshold, got shape {tuple(x.shape)}"
        )
    e = xb[:, 2:] - 2 * xb[:, 1:-1] + xb[:, :-2]
    mad = (e - e.median(dim=1, keepdim=True).values).abs().median(dim=1).values
    th = factor * 1.4826 * mad / math.sqrt(6.0)
    return th[0] if squeezed else th


class Branches(NamedTuple):
    """The complete branches of a sequence (:func:`reversal_ranges`), in time order."""

    start: Tensor
    """(n,) long: the sample where each branch starts (a turning point)."""
    end: Tensor
    """(n,) long: the sample where each branch ends (the next turning point)."""
    range: Tensor
    """(n,): the input's change along each branch, ``|x[end] - x[start]|``."""


def reversal_ranges(x: Tensor, *, threshold: float | str | Tensor = 0.0) -> Branches:
    """The complete branches of ``x``: from each turning point to the next
    (:func:`turning_points`), with the range ``|x[s_{i+1}] - x[s_i]|`` of each.

    A periodic loop of one amplitude gives ranges that all equal its peak-to-peak span;
    minor loops add smaller ones (the half-cycles of rainflow counting, without pairing).
    The branch from the first sample to the first turning point and the one after the last
    are not complete, and not counted.

    Args:
        x: input, shape (time,), floating point, finite.
        threshold: reversal threshold, as in :func:`turning_points` (``"auto"``: from the
            noise): a smaller swing back is not a reversal.

    Returns:
        :class:`Branches` of ``n`` branches (the number of turning points less one; none
        with fewer than two).

    Raises:
        TypeError, ValueError: as :func:`turning_points`; ``x`` not 1-D.
    """
    if isinstance(x, Tensor) and x.dim() != 1:
        raise ValueError(f"x must be a sequence of shape (time,), got {tuple(x.shape)}")
    return branches_between(x, turning_points(x, threshold=threshold).nonzero().flatten())


def branches_between(x: Tensor, turns: Tensor) -> Branches:
    """The branches of ``x`` (time,) between consecutive turning points ``turns`` (m,) long,
    in time order (:func:`reversal_ranges` on turning points already found)."""
    values = x.detach()[turns]
    return Branches(turns[:-1], turns[1:], (values[1:] - values[:-1]).abs())


def resolve_threshold(threshold: float | str | Tensor, xb: Tensor) -> Tensor:
    """Check ``threshold`` and return it as (batch, 1) for ``xb`` of shape (batch, time)."""
    if isinstance(threshold, str):
        if threshold != "auto":
            raise ValueError(f"threshold must be a number >= 0 or 'auto', got {threshold!r}")
        return estimate_threshold(xb).detach()[:, None]
    if isinstance(threshold, Tensor):
        th = threshold.detach().to(xb.dtype)
        values = concrete(th)
        ok = th.numel() in (1, xb.shape[0]) and (not values or bool(torch.isfinite(th).all()))
        if not ok or (values and bool((th < 0).any())):
            raise ValueError(
                f"threshold must be finite, >= 0, with 1 or batch={xb.shape[0]} values, "
                f"got {threshold!r}"
            )
        return th.reshape(-1, 1).expand(xb.shape[0], 1)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise TypeError(f"threshold must be a number or 'auto', got {type(threshold).__name__}")
    if not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be a finite number >= 0, got {threshold!r}")
    return xb.new_full((xb.shape[0], 1), float(threshold))


def turning_points(x: Tensor, *, threshold: float | str | Tensor = 0.0) -> Tensor:
    """Causal turning points (local extrema) of ``x`` as a boolean mask.

    Starting from the first sample, the detector tracks the running extremum in the
    current direction; a reversal counts once the input has moved back by more than
    ``threshold`` from it, and the extremum sample is then marked. Flat stretches never
    create turning points (of a flat extremum the first sample is marked). The first sample
    is never marked; the first direction is set once the input leaves the band
    ``x[0] +/- threshold / 2``. An extremum that is not confirmed by the end of the
    sequence is not marked.

    Supports batches; no autograd (the result is discrete); vectorized over time
    (``O(T log T)``, no loop over samples).

    Args:
        x: input, shape (time,) or (batch, time), floating point, finite.
        threshold: reversal threshold (>= 0, in the units of ``x``), a tensor of one value
            per sequence, or ``"auto"``: ``10 sigma`` with ``sigma`` a robust (MAD) estimate
            of the noise from the second difference (see :func:`estimate_threshold`).

    Returns:
        Mask of the same shape as ``x`` (bool), True at turning points.

    Raises:
        TypeError: ``x`` not a floating tensor, ``threshold`` of a wrong type.
        ValueError: wrong shape, NaN/inf in ``x``, negative or non-finite ``threshold``.

    References:
        Section 2 of "A neural networks based model of inverse hysteresis" (Neurocomputing,
        2011); the detector is the play operator of Eqs. (20)-(21).
    """
    xb, squeezed = as_batched_sequence(x, "x")
    th = resolve_threshold(threshold, xb)
    B, T = xb.shape
    z = zigzag(xb, th, xb[:, 0], xb.new_zeros(B, dtype=torch.long))
    extremum_prev = torch.cat([z.extremum.new_full((B, 1), -1), z.extremum[:, :-1]], dim=1)
    mask = torch.zeros(B, T, dtype=torch.bool, device=xb.device)
    rows, cols = z.confirm.nonzero(as_tuple=True)
    mask[rows, extremum_prev[rows, cols]] = True
    return mask[0] if squeezed else mask

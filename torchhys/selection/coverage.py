"""What no split of a training part can show: less than one closed loop, or loops of one
amplitude only (:func:`coverage_warning`); ``torchhys fit`` warns before it trains."""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor

from torchhys.functional.turning_points import (
    branches_between,
    estimate_threshold,
    turning_points,
)

__all__ = ["CLOSED_LOOP", "MIN_REVERSAL", "ONE_AMPLITUDE", "WHAT_TO_RECORD", "coverage_warning",
           "warn_coverage"]

ONE_AMPLITUDE = 0.8
"""Complete branches whose ranges all lie within this fraction of the largest one make
loops of one amplitude (:func:`coverage_warning`)."""
CLOSED_LOOP = 1.6
"""The scored samples of a row hold a closed loop when the input travels at least this
multiple of their span (a whole loop travels twice its span: :func:`coverage_warning`)."""
MIN_REVERSAL = 0.05
"""A reversal counts where the input swings back by more than this fraction of the
training input's span (or the noise threshold, if larger: :func:`coverage_warning`)."""
WHAT_TO_RECORD = "docs/training.md, 'What to record for a fit'"


def coverage_warning(x: Tensor, mask: Tensor, *, source: str = "the data") -> str | None:
    """What no split of a training part can show: a message when its scored samples hold
    less than one closed loop, or loops of one amplitude only; else None.

    Each row is run from its start through its last scored sample. A reversal counts where
    the input swings back by more than :data:`MIN_REVERSAL` (5 %) of the span of the
    scored input, or by more than the row's noise threshold
    (:func:`~torchhys.functional.estimate_threshold`) if that is larger.

    - **Less than one closed loop**: in no row does the input travel, between its first
      and last scored samples, :data:`CLOSED_LOOP` (1.6) times the span of its scored
      samples (a whole loop travels twice its span; part of one stroke, once). No split
      of it shows how a model predicts a reversal.
    - **One amplitude**: the complete branches (from one turning point to the next,
      :func:`~torchhys.functional.reversal_ranges`) that start at a scored sample or later
      (in a row with none, those that end after its first scored sample) all span at least
      :data:`ONE_AMPLITUDE` (80 %) of the largest. Every block of a
      blocked cross-validation then holds the same amplitude, so the scores cannot rank
      how the models predict smaller or larger loops (a model whose saturating output
      extrapolates the loop tip well may still predict smaller loops badly).

    Args:
        x: the training input, (rows, time), each row from its initial state.
        mask: its scored samples, (rows, time), bool or 0/1.
        source: the data's name, for the message.

    Returns:
        The message, or None: loops of several amplitudes, no scored sample, a constant
        input, or a closed loop without a complete branch to compare.

    Raises:
        ValueError: ``x`` and ``mask`` not of the same shape (rows, time).
    """
    if x.dim() != 2 or mask.shape != x.shape:
        raise ValueError(f"x and mask must have the same shape (rows, time), got "
                         f"{tuple(x.shape)} and {tuple(mask.shape)}")
    mask = mask.to(torch.bool)
    scored = x.detach()[mask]
    if scored.numel() == 0:
        return None
    span = float(scored.max() - scored.min())
    if not span > 0:
        return None  # a constant input: nothing to judge (the fits say so themselves)
    closed, ranges = False, []
    for r in range(x.shape[0]):
        idx = mask[r].nonzero().flatten().to(x.device)
        if idx.numel() < 3:
            continue
        first, last = int(idx[0]), int(idx[-1])
        row = x[r, :last + 1].detach()
        threshold = max(MIN_REVERSAL * span, float(estimate_threshold(row)))
        turns = turning_points(row, threshold=threshold).nonzero().flatten()
        branches = branches_between(row, turns)  # reversal_ranges, from the same turns
        inside = branches.start >= first
        ranges.append(branches.range[inside if bool(inside.any()) else branches.end > first])
        points = torch.cat([idx[:1], turns[(turns > first) & (turns < last)], idx[-1:]])
        travel = float((row[points[1:]] - row[points[:-1]]).abs().sum())
        scored_span = float(row[idx].max() - row[idx].min())
        closed |= scored_span > 0 and travel >= CLOSED_LOOP * scored_span
    guide = f"({WHAT_TO_RECORD})"
    if not closed:
        return (f"the scored training samples of {source} hold less than one closed loop "
                "(in no recording does the input travel its span there and back): no split "
                "of them shows how a model predicts a reversal; record whole cycles in both "
                f"directions, a few times over {guide}")
    size = torch.cat(ranges) if ranges else x.new_zeros(0)
    if size.numel() == 0:
        return None  # a closed loop without a complete branch: no amplitude to compare
    low, high = float(size.min()), float(size.max())
    if low >= ONE_AMPLITUDE * high:
        n = f"{size.numel()} complete branch" + ("es" if size.numel() != 1 else "")
        spans = f"{low:.4g}" if f"{low:.4g}" == f"{high:.4g}" else f"{low:.4g} to {high:.4g}"
        return (f"every branch of the training part of {source} spans {spans} ({n}): "
                "loops of one amplitude, so "
                "no split of it shows how a model predicts loops of other amplitudes; record "
                "several amplitudes across the range the device will be driven over "
                f"{guide}")
    return None


def warn_coverage(data: Any, prefix: str = "model.select") -> None:
    """Warn (:func:`coverage_warning`, a ``UserWarning`` starting with ``prefix``) about what
    the training part of a :class:`~torchhys.training.HysteresisDataModule` cannot show
    (other datamodules are not read)."""
    batches = getattr(data, "batches", None)
    if batches is None:
        return
    data.setup("fit")
    train = batches("train")
    if not train:
        return
    x, mask = train[0][0], train[0][3]
    message = coverage_warning(x, mask, source=getattr(data, "source", "the data"))
    if message is not None:
        warnings.warn(f"{prefix}: {message}", UserWarning, stacklevel=3)

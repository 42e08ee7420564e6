"""The tensors a fit reads from its recordings: a window's sequence, a stage's batch, and
the training rows that normalizations and data-dependent operators are fitted on.

A stage is one full batch of its sequences, one row per recording::

    x, y     (recordings, time)   each row: ``repeat - 1`` whole periods of the recording,
                                  then its rows up to the window's end; right-padded with
                                  the row's last sample to the longest row
    warmup   (recordings,)        index of each row's first scored sample
    mask     (recordings, time)   True on the scored samples: from ``warmup`` to the row's
                                  end (never on padding)

With operating conditions (``data.condition_columns``) a stage's batch has a fifth member::

    conditions  (recordings, time, n)  the rows' conditions, padded as x

Every row starts from a fresh operator state (the operators are causal, so the padding
after a row cannot change it).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys.data.files import Recording
from torchhys.data.splits import Window

__all__ = ["FitTensors", "StageBatch", "fit_tensors", "pad_rows", "stack_sequences",
           "stage_batch", "window_conditions", "window_sequence"]

StageBatch = tuple[Tensor, ...]
"""``(x, y, warmup, mask)`` of a stage, and ``conditions`` with operating conditions (see
the module docstring)."""


def pad_rows(rows: list[Tensor], length: int) -> Tensor:
    """Rows of different lengths, each right-padded with its last value, (rows, length); rows
    of (time, n) to (rows, length, n)."""
    return torch.stack([torch.cat([r, r[-1:].expand(length - r.shape[0], *r.shape[1:])])
                        for r in rows])


def window_sequence(rec: Recording, w: Window, *, repeat: int = 1,
                    warmup: int = 0) -> tuple[Tensor, Tensor, int]:
    """``(x, y, first)`` of the window ``w`` of the recording ``rec``: (time,) tensors,
    ``repeat - 1`` whole periods then rows ``[0, end)``, and the index of the first scored
    sample (at least ``warmup``)."""
    x, y = torch.from_numpy(rec.x), torch.from_numpy(rec.y)
    first = max(int(warmup), (repeat - 1) * x.numel() + w.start)
    if repeat == 1:
        return x[: w.end], y[: w.end], first
    x, y = (torch.cat([v.repeat(repeat - 1), v[: w.end]]) for v in (x, y))
    return x, y, first


def window_conditions(rec: Recording, w: Window, *, repeat: int = 1) -> Tensor | None:
    """The conditions (time, n) of :func:`window_sequence`'s sequence (None: none)."""
    if rec.conditions is None:
        return None
    c = torch.from_numpy(rec.conditions)
    if repeat == 1:
        return c[: w.end]
    return torch.cat([c.repeat(repeat - 1, 1), c[: w.end]])


def stage_batch(seqs: list[tuple[Tensor, Tensor, int]],
                conditions: list[Tensor] | None = None) -> StageBatch:
    """Sequences ``(x, y, first scored)``, each (time,), as one batch (module docstring);
    with their ``conditions`` (each (time, n)) as its fifth member."""
    length = max(s[0].numel() for s in seqs)
    steps = torch.arange(length)
    mask = torch.stack([(steps >= first) & (steps < x.numel()) for x, _, first in seqs])
    batch = (pad_rows([s[0] for s in seqs], length), pad_rows([s[1] for s in seqs], length),
             torch.tensor([s[2] for s in seqs]), mask)
    return batch if conditions is None else (*batch, pad_rows(conditions, length))


class FitTensors(NamedTuple):
    """The training data that normalizations and data-dependent operators are fitted on."""

    x: Tensor
    """Input, (rows, time): one row per recording, right-padded with its last sample."""
    y: Tensor
    """Target, (rows, time), padded as x."""
    warmup: int
    """Leading samples of every row left out of the fits (their states still run)."""
    mask: Tensor | None
    """None (every sample of every row), or the samples the fits may use, (rows, time)
    bool: False on a row's padding, on a held-out block, and on the samples of a longer
    warm-up than ``warmup`` (the targets there are not used; the states run through)."""


def fit_tensors(x: Tensor, y: Tensor, first: Tensor | Sequence[int], end: Tensor | Sequence[int],
                held: Tensor | None = None) -> FitTensors:
    """:class:`FitTensors` of rows ``x``, ``y`` (rows, time) whose row r is scored from
    sample ``first[r]`` to ``end[r]`` (exclusive; padding after it), without the samples
    ``held`` ((rows, time) bool, e.g. a cross-validation block; None: none). ``warmup`` is
    the least ``first``; the mask is None when every row is whole, scored from ``warmup``
    and holds nothing out."""
    first = torch.as_tensor(first, dtype=torch.long).reshape(-1, 1)
    end = torch.as_tensor(end, dtype=torch.long).reshape(-1, 1)
    T = x.shape[-1]
    w = int(first.min())
    if bool((first == w).all()) and bool((end == T).all()) and (held is None
                                                                or not bool(held.any())):
        return FitTensors(x, y, w, None)
    t = torch.arange(T)
    mask = (t < end) & ((t < w) | (t >= first))
    if held is not None:
        mask &= ~held.to(torch.bool)
    return FitTensors(x, y, w, mask)


def stack_sequences(seqs: list[tuple[Tensor, Tensor, int]]) -> FitTensors:
    """Training sequences ``(x, y, first scored)``, each (time,), as the tensors that
    normalizations and data-dependent operators are fitted on (:class:`FitTensors`): one
    row per sequence, each from its own initial state, right-padded with its last sample
    to the longest; with a mask when their lengths or warm-ups differ."""
    length = max(s[0].numel() for s in seqs)
    return fit_tensors(pad_rows([s[0] for s in seqs], length),
                       pad_rows([s[1] for s in seqs], length),
                       [s[2] for s in seqs], [s[0].numel() for s in seqs])

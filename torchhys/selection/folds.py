"""Cross-validation folds inside a record's training part, on tensors (rows, time):

- blocked (``cv=k``, :func:`block_split`): the scored samples of each training row cut into
  ``k`` contiguous blocks, each held out once;
- leave one recording out (``cv="recording"``): each training row held out once, whole, the
  candidate fitted on the others;
- either with a rolling origin (``mode="rolling"``, :func:`rolling_split`): each block (or
  recording) validated on a fit of those before it only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import check_choice, check_int
from torchhys.data.tensors import fit_tensors

__all__ = ["CV_MODES", "RECORDING", "Batch", "Fold", "block_split", "describe_cv", "fold_masks",
           "make_folds", "rolling_split"]


RECORDING = "recording"
"""``select_cv`` of leave-one-recording-out cross-validation (:class:`RecordingFold`)."""


CV_MODES = ("blocked", "rolling")
"""``select_cv_mode``: every block held out once and fitted on all the others
(``"blocked"``), or each block after the first validated on a fit of those before it
(``"rolling"``, a rolling origin)."""


def _ends(mask: Tensor) -> Tensor:
    """One past each row's last scored sample, (rows,) (the padding starts there)."""
    t = torch.arange(1, mask.shape[-1] + 1, device=mask.device)
    return (mask.to(torch.bool) * t).amax(-1)


def _blocks(mask: Tensor, k: int, source: str) -> list[tuple[Tensor, ...]]:
    """The scored samples (``mask``, (rows, time)) of each row cut into ``k`` contiguous
    blocks of indices (sizes differ by at most one); a row with fewer than ``2 k`` scored
    samples is an error naming ``model.select_cv``."""
    check_int(k, "model.select_cv", minimum=2)
    if mask.dim() != 2:
        raise ValueError(f"mask must have shape (rows, time), got {tuple(mask.shape)}")
    blocks = []
    for r in range(mask.shape[0]):
        idx = mask[r].to(torch.bool).nonzero().flatten()
        if idx.numel() < 2 * k:
            raise ValueError(
                f"model.select_cv={k}: training row {r} of {source} holds {idx.numel()} "
                f"scored samples, at least {2 * k} are needed; lower select_cv"
            )
        blocks.append(torch.tensor_split(idx, k))  # a mask may have gaps
    return blocks


def block_split(mask: Tensor, k: int, fold: int, *, source: str = "the data") -> Tensor:
    """Fold ``fold`` of ``k`` of blocked cross-validation (:class:`BlockFold`'s cut, on
    tensors): the scored samples (``mask``) of each row cut into ``k`` contiguous blocks
    (sizes differ by at most one), block ``fold`` held out.

    Args:
        mask: the scored samples, (rows, time), bool or 0/1.
        k: number of blocks, >= 2.
        fold: the held-out block, ``0 <= fold < k``.
        source: the data's name, for the error message.

    Returns:
        The held-out samples, (rows, time), bool. The candidate is fitted on the whole rows
        with the scored samples outside them (the states running through the block).

    Raises:
        ValueError: ``k`` or ``fold`` out of range, a mask that is not (rows, time), a row
            with fewer than ``2 k`` scored samples.
    """
    check_int(k, "model.select_cv", minimum=2)
    if not 0 <= fold < k:
        raise ValueError(f"fold must be in [0, {k}), got {fold}")
    held = torch.zeros_like(mask, dtype=torch.bool)
    for r, blocks in enumerate(_blocks(mask, k, source)):
        held[r, blocks[fold]] = True
    return held


def rolling_split(mask: Tensor, k: int, fold: int, *,
                  source: str = "the data") -> tuple[Tensor, Tensor]:
    """Fold ``fold`` of the ``k - 1`` folds of rolling-origin cross-validation
    (:class:`RollingFold`'s cut, on tensors): the scored samples (``mask``) of each row cut
    into ``k`` contiguous blocks as :func:`block_split` cuts them; blocks ``0 .. fold``
    are fitted, block ``fold + 1`` is held out, the later blocks are not used.

    Args:
        mask: the scored samples, (rows, time), bool or 0/1.
        k: number of blocks, >= 2 (``k - 1`` folds).
        fold: ``0 <= fold < k - 1``.
        source: the data's name, for the error message.

    Returns:
        ``(fitted, held)``, each (rows, time) bool: the samples the candidate is fitted on,
        and those it is scored on. Every fitted sample comes before every held-out one in
        its row; the states run from the row's start.

    Raises:
        ValueError: ``k`` or ``fold`` out of range, a mask that is not (rows, time), a row
            with fewer than ``2 k`` scored samples.
    """
    check_int(k, "model.select_cv", minimum=2)
    if not 0 <= fold < k - 1:
        raise ValueError(f"fold must be in [0, {k - 1}) (k - 1 rolling folds of k={k} "
                         f"blocks), got {fold}")
    fitted = torch.zeros_like(mask, dtype=torch.bool)
    held = torch.zeros_like(mask, dtype=torch.bool)
    for r, blocks in enumerate(_blocks(mask, k, source)):
        fitted[r, torch.cat(blocks[:fold + 1])] = True
        held[r, blocks[fold + 1]] = True
    return fitted, held


def fold_masks(mask: Tensor, k: int, fold: int, *, rolling: bool = False,
               source: str = "the data") -> tuple[Tensor, Tensor]:
    """``(fitted, held)`` of fold ``fold`` of blocked cross-validation on ``k`` blocks (the
    scored samples outside :func:`block_split`'s block, and the block), or with ``rolling``
    of rolling-origin cross-validation (:func:`rolling_split`); (rows, time) bool each.
    :class:`BlockFold` and :class:`RollingFold` cut their folds so."""
    if rolling:
        return rolling_split(mask, k, fold, source=source)
    held = block_split(mask, k, fold, source=source)
    return mask.to(torch.bool) & ~held, held


def describe_cv(cv: int | str | None, mode: str | None = None) -> str:
    """How the candidates are scored, in words (the CLI's report)."""
    if cv is None:
        return "the validation split"
    if mode == "rolling":
        return ("rolling-origin cross-validation over the training recordings" if cv == RECORDING
                else f"rolling-origin cross-validation on {cv} blocks ({cv - 1} folds)")
    return ("leave-one-recording-out cross-validation" if cv == RECORDING else
            f"{cv}-fold blocked cross-validation")


class Batch(NamedTuple):
    """Rows of a record: ``x``, ``y`` (rows, time) and the samples ``mask`` (rows, time)
    bool that a loss, a fit or a score uses (the states run through the others)."""

    x: Tensor
    y: Tensor
    mask: Tensor


class Fold(NamedTuple):
    """One fold of model selection on tensors: the candidate's model families and
    normalization are fitted on ``fit``, its readout on ``train``, and it is scored on
    ``val`` (each a :class:`Batch`: rows and the samples
    used, the states running through the others)."""

    train: Batch
    fit: Batch
    val: Batch
    warmup: int
    """Leading samples of ``fit``'s rows left out of the families' least squares."""


def _fit_batch(x: Tensor, y: Tensor, first: Tensor, end: Tensor,
               held: Tensor | None = None, scored: Tensor | None = None) -> tuple[Batch, int]:
    """The rows the families and normalization fit on, with the samples they may use
    (:func:`~torchhys.data.tensors.fit_tensors`: a longer warm-up than the least, the
    padding, ``held``, and the gaps of ``scored`` between a row's first and last scored
    sample left out), and the least warm-up."""
    t = torch.arange(x.shape[-1], device=x.device)
    if scored is not None:  # samples the record says do not exist (a gap in its mask)
        gaps = ~scored & (t >= first.reshape(-1, 1)) & (t < end.reshape(-1, 1))
        if bool(gaps.any()):
            held = gaps if held is None else held | gaps
    fit = fit_tensors(x, y, first, end, held)
    mask = fit.mask if fit.mask is not None else torch.ones(x.shape, dtype=torch.bool,
                                                               device=x.device)
    return Batch(fit.x, fit.y, mask), fit.warmup


def make_folds(x: Tensor, y: Tensor, first: Tensor, mask: Tensor, cv: int | str | None,
               mode: str | None = None, *, holdout: float = 0.25,
               source: str = "the data") -> list[Fold]:
    """The folds of ``cv`` (``mode``: None or ``"blocked"``, ``"rolling"``) on training rows
    ``x``, ``y`` (rows, time) whose row r is scored on ``mask[r]`` from sample ``first[r]``.

    ``cv=k``: blocked (or rolling-origin) cross-validation on ``k`` blocks of each row's
    scored samples (:func:`fold_masks`): the families fitted on the whole rows without the
    held-out block's targets, the readout on the scored samples outside it.
    ``cv="recording"``: each row held out once (rolling: each row after the first, fitted
    on those before it). ``cv=None``: one hold-out, the last ``holdout`` of each row's
    scored samples, fitted on the rows cut before it.

    Raises:
        ValueError: a ``cv`` or ``mode`` out of range, too few scored samples or rows.
    """
    rolling = check_choice(mode or "blocked", "cv_mode", CV_MODES) == "rolling"
    mask = mask.to(torch.bool)
    first = first.to(torch.long).reshape(-1)
    ends, T = _ends(mask), x.shape[-1]
    if cv is None:
        from torchhys.identification._nnls import holdout_cuts

        idx = [mask[r].nonzero().flatten() for r in range(mask.shape[0])]
        cuts = [int(i[holdout_cuts(i.numel(), 0, holdout)[1]]) for i in idx]
        t = torch.arange(T, device=x.device)
        if len(set(cuts)) == 1:  # one cut for all rows: fitted on the rows cut before it
            c = cuts[0]
            fit, w = _fit_batch(x[:, :c], y[:, :c], first, ends.clamp(max=c),
                                scored=mask[:, :c])
            return [Fold(Batch(x[:, :c], y[:, :c], mask[:, :c]), fit,
                         Batch(x, y, mask & (t >= c)), w)]
        late = t >= torch.tensor(cuts, device=x.device)[:, None]  # each row's own cut
        fit, w = _fit_batch(x, y, first, ends, mask & late, scored=mask)
        return [Fold(Batch(x, y, mask & ~late), fit, Batch(x, y, mask & late), w)]
    if cv == RECORDING:
        n = x.shape[0]
        if n < 2:
            raise ValueError(
                f"cv={RECORDING!r} holds each training recording out once, but {source} "
                f"holds {n}: give several recordings, or cross-validate inside the record "
                "(cv: k)")
        folds = []
        for j in range(n - 1 if rolling else n):
            keep, val = (list(range(j + 1)), j + 1) if rolling else (
                [r for r in range(n) if r != j], j)
            T_keep = int(ends[keep].max())  # the others' padding to the held-out one's
            fit, w = _fit_batch(x[keep, :T_keep], y[keep, :T_keep], first[keep], ends[keep],
                                scored=mask[keep, :T_keep])
            folds.append(Fold(Batch(x[keep], y[keep], mask[keep]), fit,
                              Batch(x[val:val + 1], y[val:val + 1], mask[val:val + 1]), w))
        return folds
    if isinstance(cv, str):
        raise ValueError(f"cv must be an int >= 2 (blocked cross-validation), {RECORDING!r} "
                         f"(leave one recording out) or None (a hold-out), got {cv!r}")
    check_int(cv, "cv", minimum=2)
    folds = []
    for j in range(cv - 1 if rolling else cv):
        fitted, held = fold_masks(mask, cv, j, rolling=rolling, source=source)
        fit, w = _fit_batch(x, y, first, ends, mask & ~fitted, scored=mask)
        folds.append(Fold(Batch(x, y, fitted), fit, Batch(x, y, held), w))
    return folds

"""Cross-validation folds inside a record's training part, on tensors (rows, time):

- blocked (``cv=k``, :func:`block_split`): the scored samples of each training row cut into
  ``k`` contiguous blocks, each held out once;
- leave one recording out (``cv="recording"``): each training row held out once, whole, the
  candidate fitted on the others;
- either with a rolling origin (``mode="rolling"``, :func:`rolling_split`): each block (or
  recording) validated on a fit of those before it only.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchhys._checks import check_int

__all__ = ["CV_MODES", "RECORDING", "block_split", "describe_cv", "fold_masks", "rolling_split"]


RECORDING = "recording"
"""``select_cv`` of leave-one-recording-out cross-validation (:class:`RecordingFold`)."""


CV_MODES = ("blocked", "rolling")
"""``select_cv_mode``: every block held out once and fitted on all the others
(``"blocked"``), or each block after the first validated on a fit of those before it
(``"rolling"``, a rolling origin)."""


def _ends(mask: Tensor) -> Tensor:
    """One past each row's last scored sample, (rows,) (the padding starts there)."""
    t = torch.arange(1, mask.shape[-1] + 1)
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

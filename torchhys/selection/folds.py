"""Cross-validation folds inside a record's training part, on tensors (rows, time):

- blocked (``cv=k``, :func:`block_split`): the scored samples of each training row cut into
  ``k`` contiguous blocks, each held out once;
- leave one recording out (``cv="recording"``): each training row held out once, whole, the
  candidate fitted on the others;
- leave one condition out (``cv="condition"``, with conditions): the rows of each operating
  condition held out together, the candidate fitted on the other conditions (a choice that
  rewards interpolating between conditions, not memorising them);
- either with a rolling origin (``mode="rolling"``, :func:`rolling_split`): each block (or
  recording) validated on a fit of those before it only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import check_choice, check_int
from torchhys.data.tensors import fit_tensors

__all__ = ["CONDITION", "CV_MODES", "RECORDING", "Batch", "Fold", "block_split",
           "condition_groups", "describe_cv", "fold_masks", "make_folds", "rolling_split"]


RECORDING = "recording"
"""``select_cv`` of leave-one-recording-out cross-validation (:class:`RecordingFold`)."""


CONDITION = "condition"
"""``select_cv`` of leave-one-condition-out cross-validation: the rows of each operating
condition (a row's conditions constant over its scored samples) held out together."""


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
    if cv == CONDITION:
        return "leave-one-condition-out cross-validation"
    return ("leave-one-recording-out cross-validation" if cv == RECORDING else
            f"{cv}-fold blocked cross-validation")


class Batch(NamedTuple):
    """Rows of a record: ``x``, ``y`` (rows, time) and the samples ``mask`` (rows, time)
    bool that a loss, a fit or a score uses (the states run through the others); the
    operating conditions (rows, time, n) where the record has them."""

    x: Tensor
    y: Tensor
    mask: Tensor
    conditions: Tensor | None = None


def _take(c: Tensor | None, rows: object = slice(None), end: int | None = None) -> Tensor | None:
    """The conditions of the rows ``rows`` and samples ``:end`` (None: none)."""
    return None if c is None else c[rows, :end]


def condition_groups(conditions: Tensor, mask: Tensor, *, source: str = "the data"
                     ) -> list[list[int]]:
    """The rows of each operating condition, in the order of the conditions: rows whose
    conditions (rows, time, n) are one value over their scored samples (``mask``), grouped
    by it.

    Raises:
        ValueError: a row whose conditions vary over its scored samples, fewer than three
            conditions (a fold must leave two, to fit a scheduling)."""
    values = []
    for r in range(conditions.shape[0]):
        c = conditions[r][mask[r].to(torch.bool)]
        if bool((c != c[:1]).any()):
            raise ValueError(f"model.select_cv={CONDITION!r}: the conditions of training row "
                             f"{r} of {source} vary over the row; leaving one condition out "
                             "needs each recording at one condition (use select_cv: "
                             f"{RECORDING!r} or k blocks)")
        values.append(tuple(float(v) for v in c[0]))
    keys = sorted(set(values))
    if len(keys) < 3:
        raise ValueError(f"model.select_cv={CONDITION!r}: {source} holds {len(keys)} "
                         "operating condition(s) in its training rows, at least 3 are "
                         "needed (each fold fits on the others)")
    return [[r for r, v in enumerate(values) if v == k] for k in keys]


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
               held: Tensor | None = None, scored: Tensor | None = None,
               conditions: Tensor | None = None) -> tuple[Batch, int]:
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
    return Batch(fit.x, fit.y, mask, conditions), fit.warmup


def make_folds(x: Tensor, y: Tensor, first: Tensor, mask: Tensor, cv: int | str | None,
               mode: str | None = None, *, holdout: float = 0.25,
               source: str = "the data", conditions: Tensor | None = None) -> list[Fold]:
    """The folds of ``cv`` (``mode``: None or ``"blocked"``, ``"rolling"``) on training rows
    ``x``, ``y`` (rows, time) whose row r is scored on ``mask[r]`` from sample ``first[r]``.

    ``cv=k``: blocked (or rolling-origin) cross-validation on ``k`` blocks of each row's
    scored samples (:func:`fold_masks`): the families fitted on the whole rows without the
    held-out block's targets, the readout on the scored samples outside it.
    ``cv="recording"``: each row held out once (rolling: each row after the first, fitted
    on those before it). ``cv=None``: one hold-out, the last ``holdout`` of each row's
    scored samples, fitted on the rows cut before it. ``cv="condition"`` (with
    ``conditions``, (rows, time, n)): the rows of each condition held out together
    (:func:`condition_groups`; rolling: each condition after the first, in increasing
    order, fitted on those before it). The conditions go with their rows into every batch.

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
            cc = _take(conditions, end=c)
            fit, w = _fit_batch(x[:, :c], y[:, :c], first, ends.clamp(max=c),
                                scored=mask[:, :c], conditions=cc)
            return [Fold(Batch(x[:, :c], y[:, :c], mask[:, :c], cc), fit,
                         Batch(x, y, mask & (t >= c), conditions), w)]
        late = t >= torch.tensor(cuts, device=x.device)[:, None]  # each row's own cut
        fit, w = _fit_batch(x, y, first, ends, mask & late, scored=mask, conditions=conditions)
        return [Fold(Batch(x, y, mask & ~late, conditions), fit,
                     Batch(x, y, mask & late, conditions), w)]
    if cv == CONDITION:
        if conditions is None:
            raise ValueError(f"cv={CONDITION!r} holds each operating condition out once, but "
                             f"{source} has no conditions (data.condition_columns)")
        groups = condition_groups(conditions, mask, source=source)
        folds = []
        for j in range(1, len(groups)) if rolling else range(len(groups)):
            keep = sorted(r for g in (groups[:j] if rolling else groups[:j] + groups[j + 1:])
                          for r in g)
            val = groups[j]
            T_keep = int(ends[keep].max())
            fit, w = _fit_batch(x[keep, :T_keep], y[keep, :T_keep], first[keep], ends[keep],
                                scored=mask[keep, :T_keep],
                                conditions=_take(conditions, keep, T_keep))
            folds.append(Fold(Batch(x[keep], y[keep], mask[keep], _take(conditions, keep)),
                              fit, Batch(x[val], y[val], mask[val], _take(conditions, val)), w))
        return folds
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
                                scored=mask[keep, :T_keep],
                                conditions=_take(conditions, keep, T_keep))
            folds.append(Fold(Batch(x[keep], y[keep], mask[keep], _take(conditions, keep)), fit,
                              Batch(x[val:val + 1], y[val:val + 1], mask[val:val + 1],
                                    _take(conditions, slice(val, val + 1))), w))
        return folds
    if isinstance(cv, str):
        raise ValueError(f"cv must be an int >= 2 (blocked cross-validation), {RECORDING!r} "
                         f"(leave one recording out), {CONDITION!r} (leave one condition out) "
                         f"or None (a hold-out), got {cv!r}")
    check_int(cv, "cv", minimum=2)
    folds = []
    for j in range(cv - 1 if rolling else cv):
        fitted, held = fold_masks(mask, cv, j, rolling=rolling, source=source)
        fit, w = _fit_batch(x, y, first, ends, mask & ~fitted, scored=mask,
                            conditions=conditions)
        folds.append(Fold(Batch(x, y, fitted, conditions), fit,
                          Batch(x, y, held, conditions), w))
    return folds

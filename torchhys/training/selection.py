"""Model selection on validation data: the candidates of ``torchhys fit``'s ``model.select``.

Each candidate is a dict of model arguments that replace those of the ``model`` section
(``{"operator": None}``: the plain network; ``{}``: the section as it is). Every candidate
is trained from the same seed with the same trainer settings and scored by its validation
MSE at the end of training, either

- on the datamodule's validation split (hold-out: the time-ordered validation part, or the
  validation recordings with ``split_by="recording"``), which must not overlap the
  training split; or
- by blocked cross-validation inside the training part (``select_cv=k``,
  :class:`BlockFold`): the scored samples of each training row are cut into ``k``
  contiguous blocks, each held out once, and the score is the MSE over all held-out
  samples; or
- by leave-one-recording-out cross-validation (``select_cv="recording"``,
  :class:`RecordingFold`): each training recording is held out once, whole, and the
  candidate is fitted on the others. Where the recordings differ (loops of other
  amplitudes, another operating point), this scores what a hold-out inside one recording
  cannot: how a candidate carries over to a recording it never saw.

Either cross-validation may instead roll its origin forward (``select_cv_mode="rolling"``,
:class:`RollingFold`, :func:`rolling_split`): each block (or recording) is validated on a
fit of the blocks (recordings) before it only, never of later ones, as the model will be
used: fitted on the past, run on what comes next. Blocked folds ask a model of a device
that drifts as it is used (a shape-memory alloy's ratcheting, a piezo's creep) to predict
earlier blocks from later ones; rolling folds do not, at the price of fitting on less data
(``k - 1`` folds, the first fitted on one block of ``k``).

A candidate whose family operator cannot be fitted to the data (no inverse, a diverged fit)
scores NaN and is never chosen. The test split is never read. :func:`run_selection` returns
one :class:`CandidateScore` per candidate (validation MSE and its standard error),
:func:`best` picks the lowest validation MSE (the first on ties), or with the
one-standard-error rule the first candidate (the baseline) when it is within one standard
error of the lowest, and
:func:`write_table` writes them as CSV.
"""

from __future__ import annotations

import csv
import inspect
import json
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from torchhys._checks import check_choice, check_int
from torchhys.functional.turning_points import (
    branches_between,
    estimate_threshold,
    turning_points,
)
from torchhys.training.data import FitTensors, fit_tensors
from torchhys.training.families import FitError

RECORDING = "recording"
"""``select_cv`` of leave-one-recording-out cross-validation (:class:`RecordingFold`)."""
CV_MODES = ("blocked", "rolling")
"""``select_cv_mode``: every block held out once and fitted on all the others
(``"blocked"``), or each block after the first validated on a fit of those before it
(``"rolling"``, a rolling origin)."""

__all__ = [
    "CV_MODES", "RECORDING", "RULES", "BlockFold", "Build", "CandidateScore", "RecordingFold",
    "RollingFold", "best", "block_split", "check_candidates", "check_holdout", "config_json",
    "coverage_warning", "cv_fold", "describe_cv", "fold_masks", "format_table",
    "model_arguments",
    "rolling_split", "run_selection", "standard_error", "warn_coverage", "write_table",
]

Build = Callable[[int, int | None], tuple[L.LightningModule, L.LightningDataModule, L.Trainer]]
"""``build(candidate, fold)``: a fresh, seeded ``(module, datamodule, trainer)`` for one run
of a candidate (``fold`` is None for the hold-out, else the cross-validation fold)."""


@dataclass(frozen=True)
class CandidateScore:
    """The validation error of one candidate."""

    index: int
    """Position of the candidate in ``model.select``."""
    overrides: dict[str, Any]
    """The candidate's model arguments."""
    val_mse: float
    """Validation MSE (cross-validation: over all held-out samples of all folds)."""
    folds: tuple[float, ...] = ()
    """Validation MSE of each cross-validation fold (empty for the hold-out)."""
    val_se: float = math.nan
    """Standard error of ``val_mse`` (:func:`standard_error`, batch means over the held-out
    squared errors; NaN where it could not be computed)."""
    error: str = ""
    """Why the candidate scored NaN (the fold and the reason: a family that cannot be fitted,
    a diverged training); empty when it scored."""


def model_arguments(model_class: type) -> list[str]:
    """The arguments a candidate may set: ``model_class.__init__``'s, except ``net`` (a
    ready network would ignore the others)."""
    params = inspect.signature(model_class.__init__).parameters.values()
    return [p.name for p in params if p.name not in ("self", "net")
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def check_candidates(select: object, valid: Sequence[str], *,
                     cv: object = None, mode: object = None) -> list[dict[str, Any]]:
    """The candidates as dicts, checked.

    Raises:
        ValueError: an empty list, a key that is not a model argument (the message names
            it and lists ``valid``), ``cv`` neither an int >= 2 nor ``"recording"``,
            ``mode`` not one of :data:`CV_MODES` (None: ``"blocked"``) or given without
            ``cv``.
        TypeError: ``select`` not a list, a candidate not a dict.
    """
    if isinstance(select, (str, bytes, Mapping)) or not isinstance(select, Sequence):
        raise TypeError(
            f"model.select must be a list of candidates (dicts of model arguments), got "
            f"{type(select).__name__} {select!r}"
        )
    if not select:
        raise ValueError(
            "model.select is empty: list the candidates, each a dict of model arguments "
            "that replace the model section's (e.g. [{hidden: 4}, {operator: null}]), or "
            "leave select out"
        )
    candidates = []
    for k, cand in enumerate(select):
        if not isinstance(cand, Mapping):
            raise TypeError(
                f"model.select[{k}] must be a dict of model arguments, got "
                f"{type(cand).__name__} {cand!r}"
            )
        unknown = sorted(set(cand) - set(valid))
        if unknown:
            verb = "is not a model argument" if len(unknown) == 1 else "are not model arguments"
            raise ValueError(
                f"model.select[{k}]: {', '.join(map(repr, unknown))} {verb}; valid: "
                f"{list(valid)}"
            )
        candidates.append(dict(cand))
    if cv is not None and cv != RECORDING:
        if isinstance(cv, str):
            raise ValueError(f"model.select_cv must be an int >= 2 (blocked cross-validation) "
                             f"or {RECORDING!r} (leave one recording out), got {cv!r}")
        check_int(cv, "model.select_cv", minimum=2)
    if mode is not None:
        check_choice(mode, "model.select_cv_mode", CV_MODES)
        if cv is None:
            raise ValueError(f"model.select_cv_mode={mode!r} needs model.select_cv (k blocks, "
                             f"or {RECORDING!r})")
    return candidates


def check_holdout(datamodule: L.LightningDataModule) -> None:
    """Raise ``ValueError`` unless ``datamodule`` holds validation data apart from its
    training data (a :class:`~torchhys.training.HysteresisDataModule`'s stage windows; for
    other datamodules, a non-empty ``val_dataloader()``)."""
    datamodule.setup("fit")
    windows = getattr(datamodule, "windows", None)
    if windows is None:
        problem = "" if datamodule.val_dataloader() else "is empty"
    else:
        val, train = windows.get("val", []), windows.get("train", [])
        overlap = any(v.index == t.index and max(v.start, t.start) < min(v.end, t.end)
                      for v in val for t in train)
        problem = ("is empty" if not val else
                   "is the training data (split='paper')"
                   if getattr(datamodule.hparams, "split", None) == "paper" and overlap
                   else "overlaps the training split" if overlap else "")
    if problem:
        source = getattr(datamodule, "source", "the data")
        raise ValueError(
            f"model.select scores candidates on held-out validation data, but the "
            f"validation split {problem} (data: {source}): hold some data out (data.split: "
            "[train, val, test] fractions, or data.split_by: recording with "
            "data.val_recordings), or cross-validate inside the training part "
            "(model.select_cv: k)"
        )


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


def warn_coverage(data: L.LightningDataModule, prefix: str = "model.select") -> None:
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
    x, _, _, mask = train[0]
    message = coverage_warning(x, mask, source=getattr(data, "source", "the data"))
    if message is not None:
        warnings.warn(f"{prefix}: {message}", UserWarning, stacklevel=3)


def _one(items: list[Any]) -> Any:
    """Collate a batch of one ready batch: the batch itself."""
    return items[0]


class _Fold(L.LightningDataModule):
    """A cross-validation fold of a datamodule's training batch: ``_train`` and ``_val``
    batches ``(x, y, warmup, mask)``, ``_fit`` the :class:`FitTensors` that the
    normalization and the data-dependent operators are fitted on, ``k`` folds, ``n_val``
    held-out samples."""

    k: int
    n_val: int
    _train: tuple[Tensor, Tensor, Tensor, Tensor]
    _val: tuple[Tensor, Tensor, Tensor, Tensor]
    _fit: FitTensors

    def train_tensors(self) -> tuple[Tensor, Tensor]:
        """The fold's training rows ``(x, y)``, (rows, time), to fit the normalization and
        the data-dependent operators on (their first :attr:`train_warmup` samples, and the
        samples outside :attr:`train_mask`, left out)."""
        return self._fit.x, self._fit.y

    @property
    def train_warmup(self) -> int:
        """Leading samples of :meth:`train_tensors` outside the data-dependent fits."""
        return self._fit.warmup

    @property
    def train_mask(self) -> Tensor | None:
        """The samples of :meth:`train_tensors` the fits may use (rows, time), or None: all."""
        return self._fit.mask

    def train_dataloader(self) -> DataLoader:
        return DataLoader([self._train], batch_size=1, collate_fn=_one)

    def val_dataloader(self) -> DataLoader:
        return DataLoader([self._val], batch_size=1, collate_fn=_one)


class BlockFold(_Fold):
    """Fold ``fold`` of ``k`` of blocked cross-validation inside a datamodule's training part.

    The training batch ``(x, y, warmup, mask)`` of a
    :class:`~torchhys.training.HysteresisDataModule` (one row per recording) keeps its
    sequences; only the masks change. The scored samples of each row are cut into ``k``
    contiguous blocks (sizes differ by at most one), and block ``fold`` of every row is held
    out::

        row      |-- warm-up --|-- block 0 --|-- block 1 --| ... |-- block k-1 --|
        train    not scored      scored        held out          scored           (fold 1)
        val      not scored      -             scored            -                (fold 1)

    The held-out block still runs the operator states (a warm-up inside the record), but
    its targets enter neither the training loss nor the fits of the data-dependent
    operators and the normalization: :meth:`train_tensors` are the whole rows and
    :attr:`train_mask` leaves the block out. (A family fitted in the ``inverse`` direction
    fits a model of the input from the target, so the block's targets run its states into
    the samples after the block, as a warm-up; they are never fitted or scored.)

    Args:
        data: the datamodule (set up here).
        k: number of blocks, >= 2.
        fold: the held-out block, ``0 <= fold < k``.

    Raises:
        ValueError: ``k`` or ``fold`` out of range, a training row with fewer than ``2 k``
            scored samples, or no training data.
    """

    rolling = False
    """Whether the folds roll their origin forward (:class:`RollingFold`)."""

    def __init__(self, data: L.LightningDataModule, k: int, fold: int) -> None:
        super().__init__()
        check_int(k, "model.select_cv", minimum=2)
        self.k = k - 1 if self.rolling else k
        """Number of folds."""
        x, y, warmup, mask, source = _train_batch(data)
        fitted, held = fold_masks(mask, k, fold, rolling=self.rolling, source=source)
        self.n_val = int(held.sum())
        """Number of held-out (validation) samples."""
        self._train = (x, y, warmup, fitted)
        self._val = (x, y, warmup, held)
        self._fit = fit_tensors(x, y, warmup, _ends(mask), mask & ~fitted)


def _train_batch(data: L.LightningDataModule) -> tuple[Tensor, Tensor, Tensor, Tensor, str]:
    """The training batch ``(x, y, warmup, mask)`` of a datamodule (set up here), the mask
    as bool, and the data's name; an error when it has no training data."""
    data.setup("fit")
    batches = data.batches("train")
    source = getattr(data, "source", "the data")
    if not batches:
        raise ValueError(f"{source}: no training data")
    x, y, warmup, mask = batches[0]
    return x, y, warmup, mask.to(torch.bool), source


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


class RollingFold(BlockFold):
    """Fold ``fold`` of rolling-origin cross-validation inside a datamodule's training part:
    the scored samples of each row cut into ``k`` contiguous blocks as :class:`BlockFold`
    cuts them, blocks ``0 .. fold`` fitted, block ``fold + 1`` validated, the later blocks
    not used (``k - 1`` folds)::

        row      |-- warm-up --|-- block 0 --|-- block 1 --|-- block 2 --| ... |-- block k-1 --|
        train    not scored      scored        scored        -                 -       (fold 1)
        val      not scored      -             -             scored            -

    Each block after the first is predicted by a model fitted on the samples before it
    only, as the model will be used (:func:`rolling_split`). The states run from each
    row's start; :meth:`train_tensors` are the whole rows and :attr:`train_mask` their
    fitted samples.

    Args:
        data: the datamodule (set up here).
        k: number of blocks, >= 2.
        fold: ``0 <= fold < k - 1``.

    Raises:
        ValueError: ``k`` or ``fold`` out of range, a training row with fewer than ``2 k``
            scored samples, or no training data.
    """

    rolling = True


class RecordingFold(_Fold):
    """Fold ``fold`` of leave-one-recording-out cross-validation: training recording
    ``fold`` held out whole, the candidate fitted on the others.

    The training batch ``(x, y, warmup, mask)`` of a
    :class:`~torchhys.training.HysteresisDataModule` holds one row per training recording
    (``data.split_by: recording``, or several files); fold ``j`` trains on every row but
    ``j`` and validates on row ``j`` (its scored samples, from its own initial state and
    warm-up)::

        rows     0        1        2
        train    scored   -        scored      (fold 1)
        val      -        scored   -

    With ``rolling=True`` the origin rolls forward through the recordings in their order:
    fold ``j`` trains on rows ``0 .. j`` and validates on row ``j + 1`` (one fold fewer than
    the recordings; for recordings taken one after another on a device that changes).

    :meth:`train_tensors` are the training rows, each from its own initial state
    (:func:`~torchhys.training.data.fit_tensors`).

    Args:
        data: the datamodule (set up here).
        fold: the fold, ``0 <= fold < k``: ``k`` the number of training recordings, or one
            fewer with ``rolling``.
        rolling: validate each recording on a fit of those before it only.

    Raises:
        ValueError: fewer than two training recordings, ``fold`` out of range.
    """

    def __init__(self, data: L.LightningDataModule, fold: int, *, rolling: bool = False) -> None:
        super().__init__()
        data.setup("fit")
        batches = data.batches("train")
        source = getattr(data, "source", "the data")
        x, y, warmup, mask = batches[0] if batches else (None,) * 4
        n = 0 if x is None else x.shape[0]
        if n < 2:
            raise ValueError(
                f"model.select_cv={RECORDING!r} holds each training recording out once, but "
                f"the training split of {source} holds {n}: give several (data.split_by: "
                "recording with data.train_recordings, or several data.path files), or use "
                "blocked cross-validation inside the record (model.select_cv: k)"
            )
        self.k = n - 1 if rolling else n
        """Number of folds: the training recordings (one fewer with ``rolling``)."""
        if not 0 <= fold < self.k:
            raise ValueError(f"fold must be in [0, {self.k}), got {fold}")
        mask = mask.to(torch.bool)
        if rolling:
            keep, val = list(range(fold + 1)), fold + 1
        else:
            keep, val = [r for r in range(n) if r != fold], fold
        self.n_val = int(mask[val].sum())
        """Number of held-out (validation) samples."""
        self._train = (x[keep], y[keep], warmup[keep], mask[keep])
        self._val = (x[val:val + 1], y[val:val + 1], warmup[val:val + 1], mask[val:val + 1])
        ends = _ends(mask[keep])
        T = int(ends.max())  # the other rows' padding to the held-out one's length goes
        self._fit = fit_tensors(x[keep, :T], y[keep, :T], warmup[keep], ends)


def cv_fold(data: L.LightningDataModule, cv: int | str, fold: int,
            mode: str | None = None) -> _Fold:
    """Fold ``fold`` of the cross-validation ``select_cv=cv``, ``select_cv_mode=mode`` (None:
    ``"blocked"``): a :class:`BlockFold`, :class:`RollingFold` or :class:`RecordingFold`
    (its ``k`` the number of folds)."""
    rolling = check_choice(mode or "blocked", "model.select_cv_mode", CV_MODES) == "rolling"
    if cv == RECORDING:
        return RecordingFold(data, fold, rolling=rolling)
    return RollingFold(data, cv, fold) if rolling else BlockFold(data, cv, fold)


def describe_cv(cv: int | str | None, mode: str | None = None) -> str:
    """How the candidates are scored, in words (the CLI's report)."""
    if cv is None:
        return "the validation split"
    if mode == "rolling":
        return ("rolling-origin cross-validation over the training recordings" if cv == RECORDING
                else f"rolling-origin cross-validation on {cv} blocks ({cv - 1} folds)")
    return ("leave-one-recording-out cross-validation" if cv == RECORDING else
            f"{cv}-fold blocked cross-validation")


def _squared_errors(module: L.LightningModule, datamodule: L.LightningDataModule) -> Tensor:
    """The trained module's squared errors on the scored validation samples, flat (empty for
    batches that are not ``(x, y, warmup, mask)``)."""
    errors = []
    with torch.no_grad():
        for batch in datamodule.val_dataloader():
            if not (isinstance(batch, (tuple, list)) and len(batch) == 4):
                continue
            x, y, _, mask = batch
            e = module(x, target=y).to(torch.float64) - y.to(torch.float64)
            errors.append(e.square()[mask.to(torch.bool)])
    return torch.cat(errors) if errors else torch.zeros(0, dtype=torch.float64)


def _validation(module: L.LightningModule, datamodule: L.LightningDataModule,
                trainer: L.Trainer, run: str) -> tuple[float, Tensor, str]:
    """Train, then the validation MSE of the trained module, its squared errors and why it
    failed: NaN, none and the reason (with a warning naming the ``run``) when a family
    operator cannot be fitted to the data (:class:`~torchhys.training.families.FitError`)
    or the validation MSE is not finite (a diverged training); else ``""``."""
    try:
        trainer.fit(module, datamodule=datamodule)
    except FitError as err:
        warnings.warn(f"model.select: {run} skipped: {err}", RuntimeWarning, stacklevel=3)
        return math.nan, torch.zeros(0, dtype=torch.float64), f"FitError: {err}"
    results = trainer.validate(module, datamodule=datamodule, verbose=False)
    if not results or "val_mse" not in results[0]:
        raise ValueError(
            "model.select: validation logged no val_mse (is trainer.limit_val_batches 0?)"
        )
    mse = float(results[0]["val_mse"])
    if not math.isfinite(mse):
        reason = f"validation MSE {mse}: the training diverged"
        warnings.warn(f"model.select: {run}: {reason}", RuntimeWarning, stacklevel=3)
        return math.nan, torch.zeros(0, dtype=torch.float64), reason
    return mse, _squared_errors(module, datamodule), ""


def standard_error(squared_errors: Tensor) -> float:
    """Standard error of the mean of ``squared_errors`` (in time order), by batch means: the
    errors of neighbouring samples are correlated, so they are cut into ``k = floor(sqrt(n))``
    contiguous blocks and the standard error is the standard deviation of the block means
    over ``sqrt(k)`` (NaN for fewer than four errors).

    References:
        G. S. Fishman, Discrete-Event Simulation, Springer, 2001, Sec. 6.6 (batch means).
    """
    n = squared_errors.numel()
    if n < 4:
        return math.nan
    k = math.isqrt(n)
    means = torch.stack([b.mean() for b in torch.tensor_split(squared_errors.reshape(-1), k)])
    return float(means.std() / math.sqrt(k))


def run_selection(candidates: Sequence[dict[str, Any]], build: Build, *,
                  cv: int | str | None = None, mode: str | None = None,
                  report: Callable[[CandidateScore], None] | None = None
                  ) -> list[CandidateScore]:
    """Train and score every candidate.

    Args:
        candidates: the checked candidates (:func:`check_candidates`).
        build: fresh, seeded ``(module, datamodule, trainer)`` of a candidate's run.
        cv: ``k`` for blocked cross-validation inside the training part,
            ``"recording"`` to hold out each training recording once, None for the
            datamodule's validation split (checked by :func:`check_holdout`).
        mode: with ``cv``, ``"blocked"`` (None) or ``"rolling"`` (:func:`cv_fold`).
        report: called with each candidate's score as soon as it is known (progress).

    Returns:
        One :class:`CandidateScore` per candidate, in order. A candidate whose fold scores
        NaN (it cannot be fitted to that fold's data, or its training diverged) scores NaN
        without training on the remaining folds (NaN there too).
    """
    if mode is not None and cv is None:
        raise ValueError(f"model.select_cv_mode={mode!r} needs model.select_cv (k blocks, or "
                         f"{RECORDING!r})")
    scores = []
    for i, overrides in enumerate(candidates):
        if cv is None:
            module, data, trainer = build(i, None)
            check_holdout(data)
            if i == 0:
                warn_coverage(data)
            mse, errors, reason = _validation(module, data, trainer, f"candidate {i}")
            scores.append(CandidateScore(i, overrides, mse, val_se=standard_error(errors),
                                         error=reason))
            if report is not None:
                report(scores[-1])
            continue
        folds, counts, errors, reason = [], [], [], ""
        j, k = 0, None
        while k is None or j < k:
            module, data, trainer = build(i, j)
            fold = cv_fold(data, cv, j, mode)
            if i == 0 and j == 0:
                warn_coverage(data)
            k = fold.k
            mse, e, why = _validation(module, fold, trainer,
                                      f"candidate {i}, fold {j + 1} of {k}")
            folds.append(mse)
            counts.append(fold.n_val)
            errors.append(e)
            j += 1
            if math.isnan(mse):  # the pooled MSE is NaN whatever the other folds give
                reason = f"fold {j} of {k}: {why}" + (
                    f" (folds {j + 1}-{k} not run)" if j < k else "")
                folds += [math.nan] * (k - j)
                counts += [1] * (k - j)
                break
        pooled = sum(m * n for m, n in zip(folds, counts, strict=True)) / sum(counts)
        se = standard_error(torch.cat(errors)) if math.isfinite(pooled) else math.nan
        scores.append(CandidateScore(i, overrides, pooled, tuple(folds), se, reason))
        if report is not None:
            report(scores[-1])
    return scores


RULES = ("min", "1se")
"""Selection rules of :func:`best`."""


def best(scores: Sequence[CandidateScore], rule: str = "min") -> CandidateScore:
    """The chosen candidate (NaN scores are never chosen).

    ``rule="min"``: the lowest validation MSE (the first on ties). ``rule="1se"`` (a
    one-standard-error rule with two levels of complexity): the first candidate, the
    baseline (e.g. the straight line), if its validation MSE is within one standard error
    of the lowest, else the lowest: on few or correlated validation samples, a more complex
    candidate must beat the baseline clearly to be chosen.

    Raises:
        ValueError: every score is NaN, an unknown rule.
    """
    check_choice(rule, "model.select_rule", RULES)
    finite = [s for s in scores if not math.isnan(s.val_mse)]
    if not finite:
        raise ValueError(
            f"model.select: every candidate's validation MSE is NaN ({len(scores)} "
            "candidates): training diverged"
        )
    lowest = min(finite, key=lambda s: s.val_mse)
    if rule == "min":
        return lowest
    bound = lowest.val_mse + (lowest.val_se if math.isfinite(lowest.val_se) else 0.0)
    baseline = scores[0]
    return baseline if baseline.val_mse <= bound else lowest


def config_json(overrides: Mapping[str, Any]) -> str:
    """A candidate's model arguments as one line of JSON."""
    return json.dumps(overrides, default=str)


def format_table(scores: Sequence[CandidateScore], chosen: CandidateScore) -> str:
    """The candidates and their validation MSE as a text table (``*`` marks the choice)."""
    width = max(len(f"{s.val_mse:.6g}") for s in scores)
    se = max(6, *(len(f"{s.val_se:.3g}") for s in scores))
    lines = [f"  {'candidate':>9}  {'val_mse':>{width}}  {'val_se':>{se}}  config"]
    for s in scores:
        mark = "*" if s.index == chosen.index else " "
        error = f"  error: {s.error}" if s.error else ""
        lines.append(f"{mark} {s.index:>9}  {s.val_mse:>{width}.6g}  {s.val_se:>{se}.3g}  "
                     f"{config_json(s.overrides)}{error}")
    return "\n".join(lines)


def write_table(scores: Sequence[CandidateScore], chosen: CandidateScore,
                path: str | Path) -> Path:
    """Write ``candidate, val_mse, val_se, selected, config, error`` (and ``fold_1 ..
    fold_k`` after cross-validation) as CSV, one row per candidate; ``config`` is the
    candidate's JSON, ``error`` why it scored NaN (empty when it scored)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n_folds = max(len(s.folds) for s in scores)
    with path.open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["candidate", "val_mse", "val_se", "selected", "config", "error",
                      *(f"fold_{j + 1}" for j in range(n_folds))])
        for s in scores:
            out.writerow([s.index, repr(s.val_mse), repr(s.val_se), int(s.index == chosen.index),
                          config_json(s.overrides), s.error, *(repr(f) for f in s.folds)])
    return path

"""Cross-validation folds inside a datamodule's training part, for model selection
(:mod:`torchhys.training.selection`):

- blocked (``select_cv=k``, :class:`BlockFold`, :func:`block_split`): the scored samples of
  each training row cut into ``k`` contiguous blocks, each held out once;
- leave one recording out (``select_cv="recording"``, :class:`RecordingFold`): each training
  recording held out once, whole, the candidate fitted on the others;
- leave one condition out (``select_cv="condition"``, :class:`ConditionFold`): the training
  recordings of each operating condition held out together;
- either with a rolling origin (``select_cv_mode="rolling"``, :class:`RollingFold`,
  :func:`rolling_split`): each block (or recording) validated on a fit of those before it
  only.
"""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from torchhys._checks import check_choice, check_int
from torchhys.data.tensors import FitTensors
from torchhys.selection.folds import CONDITION, CV_MODES, RECORDING, Fold, make_folds

__all__ = ["BlockFold", "ConditionFold", "RecordingFold", "RollingFold", "cv_fold"]


def _one(items: list[Any]) -> Any:
    """Collate a batch of one ready batch: the batch itself."""
    return items[0]


class _Fold(L.LightningDataModule):
    """A cross-validation fold of a datamodule's training batch: ``_train`` and ``_val``
    batches ``(x, y, warmup, mask)`` (and their conditions, a fifth member, where the data
    has them), ``_fit`` the :class:`FitTensors` that the normalization and the
    data-dependent operators are fitted on, ``k`` folds, ``n_val`` held-out samples."""

    k: int
    n_val: int
    _train: tuple[Tensor, ...]
    _val: tuple[Tensor, ...]
    _fit: FitTensors
    _fit_conditions: Tensor | None = None

    def _take(self, fold: Fold, warmup: Tensor, keep: list[int] | None = None,
              val: list[int] | None = None) -> None:
        """Hold ``fold`` (:func:`~torchhys.selection.folds.make_folds`) as Lightning batches:
        ``warmup`` the rows' first scored samples, ``keep`` and ``val`` the training and
        held-out rows of a recording or condition fold (None: every row in both)."""
        self.n_val = int(fold.val.mask.sum())
        """Number of held-out (validation) samples."""
        w_train = warmup if keep is None else warmup[keep]
        w_val = warmup if val is None else warmup[val]

        def conditions(b: Any) -> tuple[Tensor, ...]:
            return () if b.conditions is None else (b.conditions,)

        self._train = (fold.train.x, fold.train.y, w_train, fold.train.mask,
                       *conditions(fold.train))
        self._val = (fold.val.x, fold.val.y, w_val, fold.val.mask, *conditions(fold.val))
        mask = None if bool(fold.fit.mask.all()) else fold.fit.mask
        self._fit = FitTensors(fold.fit.x, fold.fit.y, fold.warmup, mask)
        self._fit_conditions = fold.fit.conditions

    def train_conditions(self) -> Tensor | None:
        """The conditions (rows, time, n) of :meth:`train_tensors`' rows (None: none)."""
        return self._fit_conditions

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
        if not 0 <= fold < self.k:
            rolls = f" (k - 1 rolling folds of k={k} blocks)" if self.rolling else ""
            raise ValueError(f"fold must be in [0, {self.k}){rolls}, got {fold}")
        self._take(make_folds(x, y, warmup, mask, k, "rolling" if self.rolling else None,
                              source=source, conditions=_train_conditions(data))[fold],
                   warmup)


def _train_batch(data: L.LightningDataModule) -> tuple[Tensor, Tensor, Tensor, Tensor, str]:
    """The training batch ``(x, y, warmup, mask)`` of a datamodule (set up here), the mask
    as bool, and the data's name; an error when it has no training data."""
    data.setup("fit")
    batches = data.batches("train")
    source = getattr(data, "source", "the data")
    if not batches:
        raise ValueError(f"{source}: no training data")
    x, y, warmup, mask = batches[0][:4]
    return x, y, warmup, mask.to(torch.bool), source


def _train_conditions(data: L.LightningDataModule) -> Tensor | None:
    """The conditions of the training batch (its fifth member), or None."""
    batch = data.batches("train")[0]
    return batch[4] if len(batch) == 5 else None


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
    (:func:`~torchhys.data.tensors.fit_tensors`).

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
        x, y, warmup, mask = batches[0][:4] if batches else (None,) * 4
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
        keep, val = (list(range(fold + 1)), fold + 1) if rolling else (
            [r for r in range(n) if r != fold], fold)
        f = make_folds(x, y, warmup, mask, RECORDING, "rolling" if rolling else None,
                       source=source, conditions=_train_conditions(data))[fold]
        self._take(f, warmup, keep, [val])


class ConditionFold(_Fold):
    """Fold ``fold`` of leave-one-condition-out cross-validation inside a datamodule's
    training part (``data.condition_columns``): the training recordings of the ``fold``-th
    operating condition (in increasing order) held out together, the candidate fitted on
    the others' (:func:`~torchhys.selection.folds.condition_groups`; with ``rolling``, each
    condition after the first validated on a fit of those before it).

    Raises:
        ValueError: no conditions, a recording whose conditions vary, fewer than three
            conditions, ``fold`` out of range.
    """

    def __init__(self, data: L.LightningDataModule, fold: int, *, rolling: bool = False) -> None:
        super().__init__()
        from torchhys.selection.folds import condition_groups

        x, y, warmup, mask, source = _train_batch(data)
        c = _train_conditions(data)
        folds = make_folds(x, y, warmup, mask, CONDITION, "rolling" if rolling else None,
                           source=source, conditions=c)
        self.k = len(folds)
        """Number of folds: the training conditions (one fewer with ``rolling``)."""
        if not 0 <= fold < self.k:
            raise ValueError(f"fold must be in [0, {self.k}), got {fold}")
        groups = condition_groups(c, mask, source=source)
        j = fold + 1 if rolling else fold
        keep = sorted(r for g in (groups[:j] if rolling else groups[:j] + groups[j + 1:])
                      for r in g)
        self._take(folds[fold], warmup, keep, groups[j])


def cv_fold(data: L.LightningDataModule, cv: int | str, fold: int,
            mode: str | None = None) -> _Fold:
    """Fold ``fold`` of the cross-validation ``select_cv=cv``, ``select_cv_mode=mode`` (None:
    ``"blocked"``): a :class:`BlockFold`, :class:`RollingFold`, :class:`RecordingFold` or
    :class:`ConditionFold`
    (its ``k`` the number of folds)."""
    rolling = check_choice(mode or "blocked", "model.select_cv_mode", CV_MODES) == "rolling"
    if cv == RECORDING:
        return RecordingFold(data, fold, rolling=rolling)
    if cv == CONDITION:
        return ConditionFold(data, fold, rolling=rolling)
    return RollingFold(data, cv, fold) if rolling else BlockFold(data, cv, fold)



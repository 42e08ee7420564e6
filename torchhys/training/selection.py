"""Model selection on validation data by Lightning runs: the candidates of ``torchhys fit``'s
``model.select`` where the trainer section asks for what :func:`torchhys.selection.select`
does not do (callbacks, gradient clipping or accumulation, step limits, mixed precision, a
GPU: :func:`torchhys.cli.selection.trainer_reason`), so each candidate trains as its trainer
says; every other run goes through ``select``. Each fold is scored by the library's loop
(:func:`torchhys.selection.run.score_folds`).

Each candidate is a dict of model arguments that replace those of the ``model`` section
(``{"operator": None}``: the plain network; ``{}``: the section as it is). Every candidate
is trained from the same seed with the same trainer settings and scored by its validation
MSE at the end of training, either

- on the datamodule's validation split (hold-out: the time-ordered validation part, or the
  validation recordings with ``split_by="recording"``), which must not overlap the
  training split; or
- by blocked cross-validation inside the training part (``select_cv=k``,
  :class:`~torchhys.training.folds.BlockFold`): the scored samples of each training row are
  cut into ``k`` contiguous blocks, each held out once, and the score is the MSE over all
  held-out samples; or
- by leave-one-recording-out cross-validation (``select_cv="recording"``,
  :class:`~torchhys.training.folds.RecordingFold`): each training recording is held out
  once, whole, and the candidate is fitted on the others. Where the recordings differ (loops
  of other amplitudes, another operating point), this scores what a hold-out inside one
  recording cannot: how a candidate carries over to a recording it never saw.

Either cross-validation may instead roll its origin forward (``select_cv_mode="rolling"``,
:class:`~torchhys.training.folds.RollingFold`,
:func:`~torchhys.selection.folds.rolling_split`): each block (or recording) is validated on a
fit of the blocks (recordings) before it only, never of later ones, as the model will be
used: fitted on the past, run on what comes next. Blocked folds ask a model of a device
that drifts as it is used (a shape-memory alloy's ratcheting, a piezo's creep) to predict
earlier blocks from later ones; rolling folds do not, at the price of fitting on less data
(``k - 1`` folds, the first fitted on one block of ``k``).

A run whose readout is affine and whose operators are fixed (the fitted families of
``configs/measured.yaml``) is not trained by its ``Trainer``: the readout's least-squares
solution is solved directly (:func:`~torchhys.training.readout.direct_validation`).

A candidate whose family operator cannot be fitted to the data (no inverse, a diverged fit)
scores NaN and is never chosen. The test split is never read. :func:`run_selection` returns
one :class:`CandidateScore` per candidate (validation MSE and its standard error),
:func:`best` picks the lowest validation MSE (the first on ties), or with the
one-standard-error rule the first candidate (the baseline) when it is within one standard
error of the lowest, and
:func:`write_table` writes them as CSV.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import lightning as L
import torch
from torch import Tensor

from torchhys.selection.coverage import warn_coverage
from torchhys.selection.folds import RECORDING
from torchhys.selection.run import score_folds, shared_key
from torchhys.selection.scores import CandidateScore, config_json
from torchhys.training.folds import cv_fold
from torchhys.training.readout import direct_validation, solvable

__all__ = ["Build", "check_holdout", "run_selection"]


Build = Callable[[int, int | None], tuple[L.LightningModule, L.LightningDataModule, L.Trainer]]
"""``build(candidate, fold)``: a fresh, seeded ``(module, datamodule, trainer)`` for one run
of a candidate (``fold`` is None for the hold-out, else the cross-validation fold)."""


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


def _squared_errors(module: L.LightningModule, datamodule: L.LightningDataModule) -> Tensor:
    """The trained module's squared errors on the scored validation samples, flat (empty for
    batches that are not ``(x, y, warmup, mask)``)."""
    errors = []
    with torch.no_grad():
        for batch in datamodule.val_dataloader():
            if not (isinstance(batch, (tuple, list)) and len(batch) in (4, 5)):
                continue
            x, y, _, mask = batch[:4]  # the data's float64, to the module's dtype
            c = batch[4] if len(batch) == 5 else None
            e = (module(x.to(module.dtype), target=y.to(module.dtype), conditions=c)
                 .to(torch.float64) - y.to(torch.float64))
            errors.append(e.square()[mask.to(torch.bool)])
    return torch.cat(errors) if errors else torch.zeros(0, dtype=torch.float64)


def _train_and_validate(module: L.LightningModule, datamodule: L.LightningDataModule,
                        trainer: L.Trainer) -> tuple[float, Tensor]:
    """Train (or, for a readout :func:`~torchhys.training.readout.solvable` directly, solve),
    then the validation MSE of the fitted module and its squared errors on the scored
    validation samples; raises :class:`~torchhys.identification.errors.FitError` where a
    family operator cannot be fitted (:func:`~torchhys.selection.run.score_folds` scores
    it NaN, as a MSE that is not finite)."""
    if solvable(module, datamodule, trainer):  # an affine readout: its least squares
        mse, errors = direct_validation(module, datamodule, trainer)
        if trainer.logger is not None:
            trainer.logger.log_metrics({"val_mse": mse}, step=0)
            trainer.logger.save()
        return mse, errors
    trainer.fit(module, datamodule=datamodule)
    results = trainer.validate(module, datamodule=datamodule, verbose=False)
    if not results or "val_mse" not in results[0]:
        raise ValueError(
            "model.select: validation logged no val_mse (is trainer.limit_val_batches 0?)"
        )
    mse = float(results[0]["val_mse"])
    return mse, (_squared_errors(module, datamodule) if math.isfinite(mse)
                 else torch.zeros(0, dtype=torch.float64))


def run_selection(candidates: Sequence[dict[str, Any]], build: Build, *,
                  cv: int | str | None = None, mode: str | None = None,
                  report: Callable[[CandidateScore], None] | None = None, jobs: int = 1,
                  budget_s: float | None = None) -> list[CandidateScore]:
    """Train and score every candidate.

    Args:
        candidates: the checked candidates (:func:`torchhys.cli.selection.check_candidates`).
        build: fresh, seeded ``(module, datamodule, trainer)`` of a candidate's run.
        cv: ``k`` for blocked cross-validation inside the training part,
            ``"recording"`` to hold out each training recording once, None for the
            datamodule's validation split (checked by :func:`check_holdout`).
        mode: with ``cv``, ``"blocked"`` (None) or ``"rolling"``
            (:func:`~torchhys.training.folds.cv_fold`).
        report: called with each candidate's score as soon as it is known (progress).
        jobs: candidates scored at a time, each in a process of its own
            (:mod:`torchhys.selection.jobs`); 1: all in this process.
        budget_s: seconds after which no further candidate starts (the first always runs);
            the candidates not started score NaN, ``error`` saying they were skipped.

    Returns:
        One :class:`CandidateScore` per candidate, in order. A candidate whose fold scores
        NaN (it cannot be fitted to that fold's data, or its training diverged) scores NaN
        without training on the remaining folds (NaN there too).
    """
    from torchhys.selection.jobs import run_candidates

    if mode is not None and cv is None:
        raise ValueError(f"model.select_cv_mode={mode!r} needs model.select_cv (k blocks, or "
                         f"{RECORDING!r})")
    return run_candidates(len(candidates), lambda i: score_candidate(
        i, candidates[i], build, cv, mode), lambda i: CandidateScore(
        i, candidates[i], math.nan, error=f"skipped: model.select_budget_s={budget_s:g} "
        "spent before it started"), report=report, jobs=jobs, budget_s=budget_s,
        together=[shared_key(c) for c in candidates],
        describe=lambda i: config_json(candidates[i]))


def score_candidate(i: int, overrides: dict[str, Any], build: Build, cv: int | str | None,
                    mode: str | None) -> CandidateScore:
    """Train and score candidate ``i`` (:func:`run_selection`) on each fold, a Lightning run
    each, by the library's loop (:func:`~torchhys.selection.run.score_folds`: its NaN
    rules, reasons, pooling and standard error); timed."""
    if cv is None:
        module, data, trainer = build(i, None)
        check_holdout(data)
        if i == 0:
            warn_coverage(data)
        runs = {0: (module, data, trainer)}
        k = 1
    else:
        module, data, trainer = build(i, 0)
        fold = cv_fold(data, cv, 0, mode)
        if i == 0:
            warn_coverage(data)
        runs = {0: (module, fold, trainer)}
        k = fold.k

    def run(j: int) -> tuple[float, Tensor, int]:
        if j in runs:
            module, data, trainer = runs.pop(j)
        else:
            module, data, trainer = build(i, j)
            data = cv_fold(data, cv, j, mode)
        mse, errors = _train_and_validate(module, data, trainer)
        return mse, errors, getattr(data, "n_val", errors.numel())

    return score_folds(i, overrides, k, run, cv)

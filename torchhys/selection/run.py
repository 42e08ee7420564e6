"""Model selection as one call: :func:`select` scores candidate models on a record by
cross-validation, chooses one and fits it, on tensors, without Lightning.

``torchhys fit`` with ``model.select`` calls it on its training split, and so does the
real-data benchmark's ``default`` row; in a notebook::

    from torchhys.selection import select
    result = select([{"operator": None},
                     {"operator": [{"fit": "stop_pi", "n_widths": 20, "segments": 4}]}],
                    x, y, warmup=200, cv=4, rule="1se")
    print(result.table())
    command = result.model(response)[0]
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import Tensor

from torchhys._checks import check_choice, check_int
from torchhys.identification.errors import FitError
from torchhys.networks import InverseHysteresisNet
from torchhys.selection.candidates import (
    _mean,
    candidate_spec,
    fit_candidate,
    squared_errors,
)
from torchhys.selection.coverage import coverage_warning
from torchhys.selection.folds import (
    CONDITION,
    CV_MODES,
    RECORDING,
    Batch,
    Fold,
    _ends,
    _fit_batch,
    describe_cv,
    make_folds,
)
from torchhys.selection.jobs import run_candidates
from torchhys.selection.scores import (
    RULES,
    CandidateScore,
    best,
    config_json,
    format_table,
    standard_error,
    write_table,
)

__all__ = ["FoldRun", "Progress", "Record", "Selection", "fit_record", "record", "record_folds",
           "score_candidate", "score_folds", "select", "shared_key"]


class Progress(Protocol):
    """What :func:`select` reports while it runs (the command line prints it)."""

    def starts(self, candidate: int, fold: int | None) -> None:
        """Candidate ``candidate`` starts fold ``fold`` (None: the hold-out)."""

    def scored(self, score: CandidateScore) -> None:
        """A candidate's score is known (in the candidates' order)."""


@dataclass(frozen=True)
class Record:
    """Training rows ``x``, ``y`` (rows, time), row r scored on ``mask[r]`` from sample
    ``first[r]`` (its warm-up before; its padding after ``mask``'s last sample)."""

    x: Tensor
    y: Tensor
    first: Tensor
    mask: Tensor
    source: str = "the data"
    conditions: Tensor | None = None
    """The operating conditions (rows, time, n), or None."""

    def whole(self) -> tuple[Batch, Batch, int]:
        """``(train, fit, warmup)`` of the whole record (the final fit)."""
        fit, warmup = _fit_batch(self.x, self.y, self.first, _ends(self.mask), scored=self.mask,
                                 conditions=self.conditions)
        return Batch(self.x, self.y, self.mask, self.conditions), fit, warmup


def record(x: Tensor, y: Tensor, *, warmup: int | Sequence[int] = 0,
           mask: Tensor | None = None, recordings: Tensor | None = None,
           source: str = "the data", conditions: Tensor | None = None) -> Record:
    """The :class:`Record` of ``x``, ``y``: (time,) or (rows, time), the same shape; with
    ``recordings`` ((time,) ids of 1-D ``x``) the consecutive samples of one id are a row,
    rows padded with their last sample; ``warmup`` leading samples of each row (an int, or
    one per row) and those outside ``mask`` ((rows, time) bool) are not scored.
    ``conditions``: the operating conditions, x's shape and n columns ((time, n) or (rows,
    time, n)), cut into rows as x is.

    Raises:
        ValueError: shapes that differ, a warm-up that leaves a row no scored sample, NaN
            or inf where a row is scored (in x, y or the conditions).
        TypeError: tensors that are not floating point.
    """
    named = [("x", x), ("y", y)] + ([] if conditions is None else [("conditions", conditions)])
    for name, t in named:
        if not isinstance(t, Tensor) or not t.is_floating_point():
            raise TypeError(f"{name} must be a floating-point tensor, got "
                            f"{getattr(t, 'dtype', type(t).__name__)}")
    if x.shape != y.shape or x.dim() not in (1, 2):
        raise ValueError(f"x and y must have one shape, (time,) or (rows, time), got "
                         f"{tuple(x.shape)} and {tuple(y.shape)}")
    c = conditions
    if c is not None and (c.dim() != x.dim() + 1 or c.shape[:-1] != x.shape or c.shape[-1] < 1):
        raise ValueError(f"conditions must have x's shape {tuple(x.shape)} and n >= 1 "
                         f"condition columns, got {tuple(c.shape)}")
    if recordings is not None:
        if mask is not None:
            raise ValueError("give recordings (ids that cut a 1-D record into rows) or mask "
                             "(rows, time), not both: with recordings, each row's samples "
                             "are its id's")
        if x.dim() != 1 or recordings.shape != x.shape:
            raise ValueError(f"recordings must be (time,) ids of 1-D x, y, got "
                             f"{tuple(recordings.shape)} for x {tuple(x.shape)}")
        cuts = (torch.nonzero(recordings[1:] != recordings[:-1]).flatten() + 1).tolist()
        parts = [(a, b) for a, b in zip([0, *cuts], [*cuts, x.numel()], strict=True)]
        T = max(b - a for a, b in parts)
        rows = [(x[a:b], y[a:b]) for a, b in parts]
        x = torch.stack([torch.cat([r[0], r[0][-1:].expand(T - r[0].numel())]) for r in rows])
        y = torch.stack([torch.cat([r[1], r[1][-1:].expand(T - r[1].numel())]) for r in rows])
        if c is not None:
            c = torch.stack([torch.cat([c[a:b], c[b - 1:b].expand(T - (b - a), -1)])
                             for a, b in parts])
        lengths = torch.tensor([b - a for a, b in parts])
        mask = torch.arange(T, device=x.device) < lengths.to(x.device)[:, None]
    x, y = x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1])
    if c is not None:
        c = c.reshape(*x.shape, c.shape[-1])
    rows, T = x.shape
    if mask is None:
        mask = torch.ones(rows, T, dtype=torch.bool, device=x.device)
    elif mask.shape != x.shape:
        raise ValueError(f"mask must have the shape of x, {tuple(x.shape)}, got "
                         f"{tuple(mask.shape)}")
    values = warmup.tolist() if isinstance(warmup, Tensor) else warmup
    if isinstance(values, (int, float)):
        values = [values]
    elif not isinstance(values, Sequence):
        raise TypeError(f"warmup must be an int or a list of ints, one per row, got "
                        f"{type(warmup).__name__}")
    values = list(values)
    if len(values) not in (1, rows):
        raise ValueError(f"warmup must be an int or one per row ({rows}), got {len(values)} "
                         "values")
    for v in values:
        check_int(v, "warmup", minimum=0)
    first = torch.tensor(values * (rows if len(values) == 1 else 1), dtype=torch.long,
                         device=x.device)
    t = torch.arange(T, device=x.device)
    scored = mask.to(torch.bool) & (t >= first[:, None])
    empty = (~scored.any(-1)).nonzero().flatten().tolist()
    if empty:
        raise ValueError(f"warmup={warmup}: row {empty[0]} of {source} has no scored sample "
                         f"(a warm-up shorter than the row is needed)")
    # the states run through every sample of a row up to its last scored one
    ends = (scored * (t + 1)).amax(-1, keepdim=True)
    finite = torch.isfinite(x) & torch.isfinite(y)
    if c is not None:
        finite &= torch.isfinite(c).all(-1)
    bad = ~finite & (t < ends)
    if bool(bad.any()):
        r, i = (int(v) for v in bad.nonzero()[0])
        what = "x or y" if c is None else "x, y or a condition"
        raise ValueError(f"{source}: {what} is not finite at row {r}, sample {i}; drop or "
                         "fill the missing samples first")
    return Record(x, y, first, scored, source, c)


@dataclass(frozen=True)
class Selection:
    """What :func:`select` found."""

    scores: list[CandidateScore]
    """One score per candidate, in order (NaN: could not be fitted, diverged, or skipped
    for the time budget; ``error`` says which)."""
    chosen: CandidateScore
    """The chosen candidate's score."""
    spec: dict[str, Any]
    """The chosen candidate's model arguments (its overrides over the base, completed)."""
    model: InverseHysteresisNet | None
    """The chosen candidate fitted on the whole record (None with ``refit=False``:
    :meth:`fit`)."""
    cv: int | str | None
    mode: str | None
    rule: str
    validation: bool = False
    """Scored on a validation record of its own (``select(val=...)``), not on folds."""
    _refit: Callable[[], InverseHysteresisNet] | None = field(default=None, repr=False,
                                                              compare=False)
    """What :meth:`fit` runs (:func:`select` sets it)."""

    def fit(self) -> InverseHysteresisNet:
        """The chosen candidate fitted on the whole record, once: :attr:`model`, or with
        ``select(refit=False)`` fitted now (a caller writes its table first), the same
        network on every call. Scored on a validation record of its own in this process,
        it is the network its score fitted (the same fit: not run twice).

        Raises:
            FitError: a model family that cannot be fitted to the whole record.
            ValueError: a :class:`Selection` built without :func:`select` (no record).
        """
        if self.model is not None:
            return self.model
        if self._refit is None:
            raise ValueError("this Selection holds no record to fit on: build it with "
                             "torchhys.selection.select")
        return self._refit()

    def table(self) -> str:
        """The candidates and their validation MSE as a text table (``*``: the choice)."""
        return format_table(self.scores, self.chosen)

    def write_csv(self, path: str | Path) -> Path:
        """The table as CSV (:func:`~torchhys.selection.scores.write_table`)."""
        return write_table(self.scores, self.chosen, path)

    def describe(self) -> str:
        """How the candidates were scored, in words."""
        if self.validation:
            return "the validation split"
        if self.cv is None:
            return "a hold-out of the last quarter of each row"
        return describe_cv(self.cv, self.mode)


def record_folds(data: Record, cv: int | str | None = None, mode: str | None = None, *,
                 val: Record | None = None) -> list[Fold]:
    """The folds :func:`select` scores the candidates on: those of ``cv`` and ``mode`` on
    the record ``data`` (:func:`~torchhys.selection.folds.make_folds`), or with ``val`` one
    fold: fitted on the whole of ``data`` (:meth:`Record.whole`, as the final fit) and
    scored on ``val``'s rows and samples (a validation record: each row may run through
    its training part first, as a warm-up outside ``val``'s mask).

    Raises:
        ValueError: ``val`` with ``cv`` or ``mode``; the errors of ``make_folds``.
        TypeError: ``val`` not a :class:`Record`.
    """
    if val is not None and not isinstance(val, Record):
        raise TypeError(f"val must be a Record (torchhys.selection.run.record(x, y, ...)), got "
                        f"{type(val).__name__}")
    if val is None:
        return make_folds(data.x, data.y, data.first, data.mask, cv, mode, source=data.source,
                          conditions=data.conditions)
    if cv is not None or mode is not None:
        raise ValueError(f"val (a validation record of its own) needs cv=None and mode=None, "
                         f"got cv={cv!r}, mode={mode!r}: score on folds or on val, not both")
    if (val.conditions is None) != (data.conditions is None):
        raise ValueError("val must have conditions where the record has them, and none "
                         "where it has none")
    train, fit, w = data.whole()
    return [Fold(train, fit, Batch(val.x, val.y, val.mask, val.conditions), w)]


def shared_key(overrides: Mapping[str, Any]) -> str | None:
    """The key of the fit a candidate may share with its neighbours: its first family
    operator's spec without its iteration counts, or None (candidates of one key run in one
    process, where the fit is shared: :mod:`torchhys.identification._fit_cache`)."""
    import json

    ops = overrides.get("operator")
    first = ops[0] if isinstance(ops, list) and ops else ops
    if not isinstance(first, dict) or "fit" not in first:
        return None
    spec = {k: v for k, v in first.items() if k not in ("epochs", "sample_iterations")}
    try:
        return json.dumps(spec, sort_keys=True)
    except (TypeError, ValueError):
        return None


FoldRun = Callable[[int], tuple[float, Tensor, int]]
"""``run(j)``: fit a candidate on fold ``j`` and score it: its validation MSE, the squared
errors of its held-out samples (float64, flat) and their number; raises
:class:`~torchhys.identification.errors.FitError` where it cannot be fitted."""


def score_folds(i: int, overrides: Mapping[str, Any], k: int, run: FoldRun,
                cv: int | str | None, *, progress: Progress | None = None) -> CandidateScore:
    """Candidate ``i`` scored on its ``k`` folds, each fitted and scored by ``run``
    (:func:`score_candidate`'s on tensors, or a Lightning run's:
    :func:`torchhys.training.selection.run_selection`): the MSE over all held-out samples
    (a hold-out's, ``cv`` None: its one fold's), its standard error (batch means), the
    folds' MSEs (none for a hold-out); NaN with the reason where a fold cannot be fitted
    (:class:`~torchhys.identification.errors.FitError`) or its MSE is not finite, the later
    folds then not run. Timed."""
    start = time.perf_counter()
    mses, counts, errors, reason = [], [], [], ""
    for j in range(k):
        if progress is not None:
            progress.starts(i, None if cv is None else j)
        name = f"candidate {i}" if cv is None else f"candidate {i}, fold {j + 1} of {k}"
        try:
            mse, e, held = run(j)
            why = ""
        except FitError as err:
            warnings.warn(f"model.select: {name} skipped: {err}", RuntimeWarning, stacklevel=2)
            e, mse, held = torch.zeros(0, dtype=torch.float64), math.nan, 1
            why = f"FitError: {err}"
        if not why and not math.isfinite(mse):
            why = f"validation MSE {mse}: the training diverged"
            warnings.warn(f"model.select: {name}: {why}", RuntimeWarning, stacklevel=2)
            e, mse = torch.zeros(0, dtype=torch.float64), math.nan
        mses.append(mse)
        counts.append(held)
        errors.append(e)
        if math.isnan(mse):
            reason = why if cv is None else f"fold {j + 1} of {k}: {why}" + (
                f" (folds {j + 2}-{k} not run)" if j + 1 < k else "")
            mses += [math.nan] * (k - j - 1)
            counts += [1] * (k - j - 1)
            break
    pooled = mses[0] if k == 1 else sum(
        m * n for m, n in zip(mses, counts, strict=True)) / sum(counts)
    se = standard_error(torch.cat(errors)) if math.isfinite(pooled) else math.nan
    return CandidateScore(i, dict(overrides), pooled, () if cv is None else tuple(mses), se,
                          reason, time.perf_counter() - start)


def score_candidate(i: int, overrides: Mapping[str, Any], spec: Mapping[str, Any],
                    folds: Sequence[Fold], cv: int | str | None, *,
                    dtype: torch.dtype = torch.float64, seed: int | None = 0, epochs: int = 10,
                    seconds: float | None = None, progress: Progress | None = None,
                    keep: Callable[[InverseHysteresisNet], None] | None = None,
                    ) -> CandidateScore:
    """Fit and score candidate ``i`` (model arguments ``spec``) on every fold of ``folds``
    (:func:`make_folds`, or the one fold of a validation record: :func:`record_folds`), as
    :func:`score_folds` scores them; ``keep`` is given each fold's fitted network."""

    def run(j: int) -> tuple[float, Tensor, int]:
        fold = folds[j]
        net = fit_candidate(spec, fold.train, fold.fit, warmup=fold.warmup, dtype=dtype,
                            seed=seed, epochs=epochs, seconds=seconds)
        if keep is not None:
            keep(net)
        e = squared_errors(net, fold.val)
        return _mean(e), e, int(fold.val.mask.sum())

    return score_folds(i, overrides, len(folds), run, cv, progress=progress)


def select(candidates: Sequence[Mapping[str, Any]], x: Tensor, y: Tensor, *,
           base: Mapping[str, Any] | None = None, warmup: int | Sequence[int] = 0,
           mask: Tensor | None = None, recordings: Tensor | None = None,
           cv: int | str | None = 4, mode: str | None = None, rule: str = "min",
           jobs: int | str = 1, budget_s: float | None = None,
           dtype: torch.dtype = torch.float64, seed: int | None = 0, epochs: int = 10,
           seconds: float | None = None, refit: bool = True,
           progress: Progress | None = None, source: str = "the data",
           warn_coverage: bool = True, val: Record | None = None,
           conditions: Tensor | None = None) -> Selection:
    """Score ``candidates`` on the record ``(x, y)``, choose one by ``rule`` and fit it.

    Args:
        candidates: dicts of model arguments over ``base`` (``{"operator": None}``: the
            straight line; ``{"operator": [{"fit": "stop_pi", ...}]}``: a model family
            identified on the training data; keys of
            :data:`~torchhys.selection.candidates.MODEL_DEFAULTS`).
        x, y: the record, (time,) or (rows, time): the model maps ``x`` to ``y`` (an inverse
            model, the response to the command, as a compensator).
        base: model arguments every candidate starts from (default: an affine readout by
            L-BFGS, :data:`~torchhys.selection.candidates.MODEL_DEFAULTS`).
        warmup, mask, recordings: the samples scored, and the rows (:func:`record`).
        cv: ``k`` for blocked cross-validation on ``k`` blocks of each row, ``"recording"``
            to hold out each row once, ``"condition"`` to hold out each operating
            condition's rows once (with ``conditions``), None to hold out the last quarter
            of each row.
        mode: ``"blocked"`` (None) or ``"rolling"``: each block (row) validated on a fit of
            those before it only.
        rule: ``"min"`` (the lowest validation MSE) or ``"1se"`` (the first candidate when
            within one standard error of the lowest: :func:`~torchhys.selection.scores.best`).
        jobs: candidates scored at a time, each in a forked process; ``"auto"``: the usable
            cores, at most 4 (:mod:`torchhys.selection.jobs`).
        budget_s: seconds after which no further candidate starts (those not started score
            NaN, their ``error`` says so).
        dtype, seed: the candidates' dtype and the seed each is built from.
        epochs, seconds: training steps (and a time cap) of a candidate whose readout is not
            solved directly (:func:`~torchhys.selection.candidates.fit_candidate`).
        refit: fit the chosen candidate on the whole record, once (:attr:`Selection.model`;
            scored on ``val`` with ``jobs`` 1, the network its score fitted); False: later,
            by :meth:`Selection.fit`.
        progress: told when each fold starts and each score is known (:class:`Progress`).
        source: the data's name in messages.
        warn_coverage: warn (``UserWarning``) when the record holds less than one closed
            loop or loops of one amplitude only
            (:func:`~torchhys.selection.coverage.coverage_warning`).
        val: a validation record of its own (:func:`record`; with ``cv=None``): the
            candidates are fitted on the whole of ``x``, ``y`` and scored on ``val``
            (:func:`record_folds`), as ``torchhys fit`` scores them on its validation
            split.
        conditions: operating conditions, x's shape and n columns (:func:`record`): a
            candidate with ``condition_degree`` is a network that takes them
            (:class:`~torchhys.InverseHysteresisNet`'s ``n_conditions``), the others do not
            see them.

    Raises:
        ValueError: no candidate, a bad option (the message names it), every candidate NaN.
        FitError: the chosen candidate cannot be fitted on the whole record.
    """
    if isinstance(candidates, (str, bytes, Mapping)) or not isinstance(candidates, Sequence):
        raise TypeError(f"candidates must be a list of dicts of model arguments, got "
                        f"{type(candidates).__name__}")
    if not candidates:
        raise ValueError("candidates is empty: give at least one dict of model arguments")
    check_choice(rule, "rule", RULES)
    if mode is not None:
        check_choice(mode, "mode", CV_MODES)
        if cv is None:
            raise ValueError(f"mode={mode!r} needs cv (k blocks, or {RECORDING!r}); cv=None "
                             "holds out the last quarter of each row")
    if cv is not None and cv not in (RECORDING, CONDITION):
        check_int(cv, "cv", minimum=2)
    overrides = [dict(c) for c in candidates]
    specs = [candidate_spec(base, c) for c in overrides]
    data = record(x, y, warmup=warmup, mask=mask, recordings=recordings, source=source,
                  conditions=conditions)
    if warn_coverage:
        message = coverage_warning(data.x, data.mask, source=source)
        if message is not None:
            warnings.warn(f"model.select: {message}", UserWarning, stacklevel=2)
    folds = record_folds(data, cv, mode, val=val)  # checked before any candidate runs

    # scored on a validation record, a candidate's one fit is the final fit (Record.whole):
    # its network comes back with its score (from a forked process too: pickled with it)
    def score(i: int) -> CandidateScore:
        nets: list[InverseHysteresisNet] = []
        keep = nets.append if val is not None else None
        s = score_candidate(i, overrides[i], specs[i], folds, cv, dtype=dtype, seed=seed,
                            epochs=epochs, seconds=seconds, progress=progress, keep=keep)
        return _Fitted(**{f.name: getattr(s, f.name) for f in fields(CandidateScore)},
                       network=nets[-1]) if nets else s

    def skipped(i: int) -> CandidateScore:
        return CandidateScore(i, overrides[i], math.nan, error=f"skipped: model.select_budget_s="
                              f"{budget_s:g} spent before it started")

    scores = run_candidates(len(specs), score, skipped,
                            report=None if progress is None else progress.scored, jobs=jobs,
                            budget_s=budget_s, together=[shared_key(c) for c in overrides],
                            describe=lambda i: config_json(overrides[i]))
    kept = getattr(scores[best(scores, rule).index], "network", None)
    scores = [CandidateScore(**{f.name: getattr(s, f.name) for f in fields(CandidateScore)})
              if isinstance(s, _Fitted) else s for s in scores]
    chosen = best(scores, rule)
    done = [] if kept is None else [kept]

    def fit() -> InverseHysteresisNet:
        if not done:
            done.append(fit_record(specs[chosen.index], data, dtype=dtype, seed=seed,
                                   epochs=epochs, seconds=seconds))
        return done[0]

    return Selection(list(scores), chosen, specs[chosen.index], fit() if refit else None, cv,
                     mode, rule, val is not None, fit)


@dataclass(frozen=True)
class _Fitted(CandidateScore):
    """A score with the network its one fit made (scored on a validation record), carried
    back from the process that scored it; :func:`select` keeps the chosen one's."""

    network: InverseHysteresisNet | None = None


def fit_record(spec: Mapping[str, Any], data: Record, *, dtype: torch.dtype = torch.float64,
               seed: int | None = 0, epochs: int = 10,
               seconds: float | None = None) -> InverseHysteresisNet:
    """A candidate's model arguments (:attr:`Selection.spec`) fitted on the whole record
    (:func:`record`), as :func:`select` (or :meth:`Selection.fit`) fits the chosen one.

    Raises:
        FitError: a model family that cannot be fitted to the record.
    """
    train, fit, w = data.whole()
    return fit_candidate(spec, train, fit, warmup=w, dtype=dtype, seed=seed, epochs=epochs,
                         seconds=seconds)


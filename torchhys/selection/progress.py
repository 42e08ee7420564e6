"""Progress of model selection: what runs next and about how long the rest takes.

Before each candidate a line names it briefly (:func:`brief`: its family and size; its full
model arguments are in ``selection.csv``), says how many trainings it takes and estimates the
time left: the mean seconds per training so far times the trainings left, smoothed (the mean
of that and the last estimate less the time since, so that one slow or fast candidate does not
make it jump); after it, its validation MSE (or why it failed) and the seconds it took. When
standard error is a terminal a progress bar over all the trainings is drawn under the lines
(``tqdm``, as Lightning's bar), else the lines are plain. ``--quiet`` (or
``TORCHHYS_QUIET=1``) prints none of it; the table of the candidates and the choice are still
printed at the end.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

from torchhys.selection.scores import CandidateScore

__all__ = ["SelectionProgress", "brief"]

_SIZES = ("n_widths", "n", "units", "segments")
"""The arguments of an identified family that :func:`brief` shows (its size)."""


def brief(overrides: dict[str, Any]) -> str:
    """A candidate's model arguments in a few words: ``straight line``, ``stop_pi 20/4``,
    ``pi_nonneg 10 inverse + drift``, then up to two other arguments (``hidden=16``)."""
    parts = []
    if "operator" in overrides:
        op = overrides["operator"]
        if op is None:
            parts.append("straight line")
        else:
            for spec in op if isinstance(op, list) else [op]:
                if isinstance(spec, dict):
                    name = str(spec.get("fit") or spec.get("name") or "operator")
                    sizes = "/".join(str(spec[k]) for k in _SIZES if k in spec)
                    way = spec.get("direction")
                    extra = " ".join(f"{k}={spec[k]}" for k in ("epochs",) if k in spec)
                    parts.append(" ".join(p for p in (name, sizes, way if way not in (
                        None, "direct") else "", extra) if p))
                else:
                    parts.append(str(spec))
    text = " + ".join(parts)
    rest = [f"{k}={v}" for k, v in overrides.items() if k != "operator"]
    if rest:
        text = ", ".join(([text] if text else []) + rest[:2]) + (", ..." if len(rest) > 2
                                                                 else "")
    return text or "the base model"

_RANK_VARIABLES = ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")
"""Where a distributed launcher (torchrun, Lightning, SLURM, LSF) gives a process its rank."""


def _rank_zero_only(method: Any) -> Any:
    """Run ``method`` in the process of rank 0 only (each rank of a distributed run selects:
    one prints)."""

    @functools.wraps(method)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        rank = next((os.environ[v] for v in _RANK_VARIABLES if v in os.environ), "0")
        return method(*args, **kwargs) if rank == "0" else None

    return wrapped

def _short(s: float) -> str:
    """Seconds of one candidate: tenths, or thousandths below a tenth."""
    return f"{s:.1f}" if s >= 0.1 else f"{s:.3f}"


def _seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


class SelectionProgress:
    """Lines (and, on a terminal, a bar) around the candidates' trainings.

    Args:
        candidates: the candidates' model arguments.
        folds: trainings per candidate (the blocked cross-validation's k; None: one, or
            unknown until the first candidate has run, as with leave-one-recording-out).
        quiet: print nothing.
    """

    def __init__(self, candidates: Sequence[dict[str, Any]], folds: int | None, *,
                 quiet: bool = False) -> None:
        self.n = len(candidates)
        self.candidates = list(candidates)
        self.folds = folds
        self.quiet = quiet
        self.start = self.last = time.perf_counter()
        self.runs_done = 0
        self.eta: tuple[float, float] | None = None  # the last estimate and when
        self.started = False
        self.bar = None
        if not quiet and sys.stderr.isatty():
            try:
                from tqdm import tqdm
            except ImportError:  # plain lines only
                tqdm = None
            if tqdm is not None:
                total = self.n * folds if folds else None
                self.bar = tqdm(total=total, desc="model selection", unit="training",
                                file=sys.stderr, leave=False, dynamic_ncols=True)

    def _print(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text, file=sys.stdout)
        else:
            print(text, flush=True)

    def left(self, index: int) -> str:
        """The estimate of the time left before candidate ``index`` starts."""
        if self.runs_done == 0:
            return "time left: estimated after the first training"
        now = time.perf_counter()
        per_run = (now - self.start) / self.runs_done
        per_candidate = self.folds or max(1, round(self.runs_done / max(index, 1)))
        estimate = per_run * (self.n - index) * per_candidate
        if self.eta is not None:  # smoothed with the last estimate, less the time since
            estimate = 0.5 * (estimate + max(0.0, self.eta[0] - (now - self.eta[1])))
        self.eta = (estimate, now)
        return f"about {_seconds(estimate)} left"

    @_rank_zero_only
    def starts(self, index: int, fold: int | None) -> None:
        """Before each training (each one that starts ends the one before): a line before a
        candidate's first training; the bar moves."""
        if self.started:
            self._advance()
        self.started = True
        if fold not in (None, 0) or self.quiet:
            return
        runs = (f"{self.folds} trainings" if self.folds else "1 training" if fold is None
                else "one training per training recording")
        self._print(f"candidate {index} ({index + 1} of {self.n}) starts, {runs}, "
                    f"{self.left(index)}: {brief(self.candidates[index])}")

    def _advance(self) -> None:
        self.runs_done += 1
        if self.bar is not None:
            self.bar.update(1)

    @_rank_zero_only
    def scored(self, score: CandidateScore) -> None:
        """After each candidate: its validation MSE (or why it failed) and its seconds."""
        now = time.perf_counter()
        if self.quiet:
            self.last = now
            return
        folds = f", {len(score.folds)} folds" if score.folds else ""
        failed = ""
        if math.isnan(score.val_mse):
            failed = f" (failed: {score.error})" if score.error else " (failed)"
        seconds = score.seconds if math.isfinite(score.seconds) else now - self.last
        self._print(f"candidate {score.index} ({score.index + 1} of {self.n}): val_mse "
                    f"{score.val_mse:.6g}{failed}{folds}, {_short(seconds)} s: "
                    f"{brief(score.overrides)}")
        self.last = now

    def close(self) -> None:
        """The last training ended: remove the bar (the lines stay)."""
        if self.started:
            self._advance()
            self.started = False
        if self.bar is not None:
            self.bar.close()
            self.bar = None

"""The scores of model selection's candidates, the choice among them and their table:
:class:`CandidateScore`, :func:`standard_error`, :func:`best` (:data:`RULES`),
:func:`format_table`, :func:`write_table`."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchhys._checks import check_choice

__all__ = ["RULES", "CandidateScore", "best", "config_json", "format_table", "standard_error",
           "write_table"]


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
    seconds: float = math.nan
    """Wall seconds of its scoring, in the process that scored it (NaN: not run)."""


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
        ValueError: every score is NaN (naming each candidate's reason), an unknown rule.
    """
    check_choice(rule, "model.select_rule", RULES)
    finite = [s for s in scores if not math.isnan(s.val_mse)]
    if not finite:
        reasons = "; ".join(f"candidate {s.index}: {s.error or 'not run'}" for s in scores)
        raise ValueError(f"model.select: every candidate's validation MSE is NaN "
                         f"({len(scores)} candidates): {reasons}")
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

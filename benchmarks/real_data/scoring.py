"""The budgets of the rows, a fitted row (its prediction, choice and hold-out RMSE), the
hold-out inside the training part, the held-out RMSE, and the scaled training data the
family rows fit."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys.identification._family_spec import VALIDATION
from torchhys.identification._nnls import holdout_cuts

from .datasets import Split


class Budget(NamedTuple):
    """Candidate grids and training budgets."""

    pi_n: tuple[int, ...]
    powers: tuple[float, ...]
    preisach_n: tuple[int, ...]
    gpi_units: tuple[int, ...]
    gpi_epochs: int
    net_steps: int
    """L-BFGS steps (of up to 20 iterations) of the EIHO network."""
    default_epochs: int | None
    """Cap on the config's ``max_epochs`` (None: as configured)."""
    seconds: float
    """Time cap of one training of the config's model."""
    ja_starts: int = 8
    ja_iterations: int = 60
    """Random starts and Levenberg-Marquardt iterations of the Jiles-Atherton fit."""
    stop_n: tuple[int, ...] = (5, 10, 20)
    stop_segments: tuple[int, ...] = (1, 2, 4, 8)
    stop_powers: tuple[float, ...] = (1.0, 2.0)
    """Thresholds, characteristic segments and grid powers of the stop-type PI model."""


FULL = Budget((5, 10, 20, 40), (1.0, 2.0, 3.0), (10, 20, 30), (2, 4, 8), 1000, 40, None, 60.0)
QUICK = Budget((5, 10), (2.0,), (8,), (2,), 20, 4, 20, 5.0, 2, 5, (5,), (1, 4))


Predict = Callable[[Tensor], Tensor]
"""Model output for an input (rows, time), physical units."""


class Fitted(NamedTuple):
    predict: Predict
    choice: str
    holdout: float
    """RMSE (target units) on the hold-out of the chosen settings, fitted before it."""


def holdout(T: int, warmup: int) -> int:
    """First hold-out sample of a training row: the last quarter of its scored samples
    (as :func:`torchhys.training.baselines.holdout_mask` cuts the scored samples)."""
    return warmup + holdout_cuts(T - warmup, 0, VALIDATION)[1]


def test_rmse(predict: Predict, split: Split) -> tuple[float, int]:
    """RMSE over the scored samples of all held-out recordings, and their number."""
    errors = []
    with torch.no_grad():
        for x, y, w in split.test:
            errors.append((predict(x[None])[0] - y)[w:])
    e = torch.cat(errors)
    return float(e.square().mean().sqrt()), e.numel()


def _rmse(a: Tensor, b: Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def _scored(split: Split) -> Tensor:
    mask = torch.zeros_like(split.x, dtype=torch.bool)
    mask[:, split.warmup:] = True
    return mask


class Scaled(NamedTuple):
    """Training rows, the input divided by its std, the target standardized."""

    x: Tensor
    y: Tensor
    warmup: int
    sx: float
    my: float
    sy: float

    @property
    def cut(self) -> int:
        return holdout(self.x.shape[1], self.warmup)

    @property
    def validation(self) -> float:
        """The hold-out share as ``select_pi_ridge`` / ``select_penalty`` take it."""
        return (self.x.shape[1] - self.cut) / self.x.shape[1]

    def fitted(self, f: Callable[[Tensor], Tensor], choice: str, score: float) -> Fitted:
        """Physical-unit model and hold-out RMSE from a model of the scaled data."""
        return Fitted(lambda v: f(v / self.sx) * self.sy + self.my, choice, score * self.sy)

    def score(self, f: Callable[[Tensor], Tensor]) -> float:
        with torch.no_grad():
            return _rmse(f(self.x)[:, self.cut:], self.y[:, self.cut:])


def scaled(split: Split) -> Scaled:
    x, y = split.x[:, split.warmup:], split.y[:, split.warmup:]
    sx, my, sy = float(x.std()), float(y.mean()), float(y.std())
    return Scaled(split.x / sx, (split.y - my) / sy, split.warmup, sx, my, sy)



class NotApplicable(ValueError):
    """A model that does not apply to this data set (its row reads n/a)."""

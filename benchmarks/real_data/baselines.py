"""The memoryless baselines: the least-squares line and the polynomial."""

from __future__ import annotations

from torchhys.training.baselines import fit_polynomial

from .datasets import Split
from .scoring import Budget, Fitted, _scored


def line(split: Split, budget: Budget) -> Fitted:
    p = fit_polynomial(split.x, split.y, _scored(split), degrees=(1,))
    b, k = (*p.p.convert().coef, 0.0)[:2]  # a constant input: the mean, slope 0
    return Fitted(p, f"slope={k:.4g}, offset={b:.4g}", p.validation_rmse)


def poly(split: Split, budget: Budget) -> Fitted:
    p = fit_polynomial(split.x, split.y, _scored(split))
    return Fitted(p, f"degree={p.degree}", p.validation_rmse)

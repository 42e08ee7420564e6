"""Memoryless baselines: a straight line and a polynomial of the input, fitted by least squares.

A hysteresis model earns its place only where it predicts held-out data better than the
better of these two, fitted on the same training samples (the ``ratio`` of
``docs/real-data.md`` and of ``torchhys test``).

The polynomial's degree is chosen on a time-ordered hold-out inside the training part: the last
``validation`` share of each row's scored samples (the cut of
:func:`torchhys.identification.fitting.select_pi_ridge`); the chosen degree is then refitted on all
of them. The fits are numpy's :class:`numpy.polynomial.Polynomial` least squares in float64 (on a
scaled domain, well conditioned up to degree 9).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchhys._checks import check_int
from torchhys.identification._family_spec import VALIDATION
from torchhys.identification._nnls import check_validation, holdout_cuts

__all__ = ["MAX_DEGREE", "Polynomial", "fit_polynomial", "holdout_mask", "max_degree"]

MAX_DEGREE = 9
"""The highest degree :func:`fit_polynomial` tries by default."""


class Polynomial(NamedTuple):
    """A memoryless polynomial ``y = p(x)``, fitted by :func:`fit_polynomial`.

    Call it on a tensor of inputs, any shape: the outputs, the same shape and dtype.
    """

    p: np.polynomial.Polynomial
    """The fitted polynomial (numpy, on its scaled domain)."""
    degree: int
    validation_rmse: float
    """RMSE of this degree on the hold-out (:func:`holdout_mask`) when fitted before it."""

    def __call__(self, x: Tensor) -> Tensor:
        out = self.p(x.detach().to(torch.float64).cpu().numpy())
        return torch.as_tensor(out, dtype=x.dtype, device=x.device)


def holdout_mask(mask: Tensor, validation: float = VALIDATION) -> Tensor:
    """The hold-out of a training part: the last ``validation`` share (at least one sample) of each
    row's scored samples (:func:`torchhys.identification.fitting.select_pi_ridge`'s cut of a row,
    :func:`torchhys.identification._nnls.holdout_cuts`, applied to the row's scored samples).

    Args:
        mask: the scored samples, (rows, time), bool.
        validation: share in (0, 1).

    Returns:
        (rows, time) bool, inside ``mask``.
    """
    validation = check_validation(validation)
    mask = torch.as_tensor(mask).to(torch.bool)
    held = torch.zeros_like(mask)
    for r in range(mask.shape[0]):
        idx = mask[r].nonzero().flatten()
        if idx.numel():
            held[r, idx[holdout_cuts(idx.numel(), 0, validation)[1]:]] = True
    return held


def max_degree(mask: Tensor, validation: float = VALIDATION) -> int:
    """The highest degree the scored samples before the hold-out determine (their number
    less one; 0 or below: not even a line), for :func:`fit_polynomial` on a short record."""
    mask = torch.as_tensor(mask).to(torch.bool)
    return int((mask & ~holdout_mask(mask, validation)).sum()) - 1


def _samples(x: Tensor, y: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    x, y = torch.as_tensor(x), torch.as_tensor(y)
    mask = torch.ones_like(x, dtype=torch.bool) if mask is None else torch.as_tensor(mask)
    if x.dim() not in (1, 2) or y.shape != x.shape:
        raise ValueError(f"x and y must have the same shape, (time,) or (rows, time), got "
                         f"{tuple(x.shape)} and {tuple(y.shape)}")
    if mask.shape != x.shape:
        raise ValueError(f"mask must have the shape of x {tuple(x.shape)}, got "
                         f"{tuple(mask.shape)}")
    if x.dim() == 1:
        x, y, mask = x[None], y[None], mask[None]
    mask = mask.to(torch.bool)
    for name, v in (("x", x), ("y", y)):
        if not bool(v[mask].isfinite().all()):
            raise ValueError(f"{name} holds NaN or inf among the scored samples")
    return x.detach().to(torch.float64).cpu(), y.detach().to(torch.float64).cpu(), mask.cpu()


def _fit(x: np.ndarray, y: np.ndarray, degree: int) -> np.polynomial.Polynomial:
    if np.ptp(x) == 0:  # a constant input: the mean (a polynomial of degree 0)
        return np.polynomial.Polynomial([float(np.mean(y))])
    with warnings.catch_warnings():  # a rank-deficient degree: the hold-out judges it
        warnings.simplefilter("ignore", np.exceptions.RankWarning)
        return np.polynomial.Polynomial.fit(x, y, degree)


def fit_polynomial(
    x: Tensor,
    y: Tensor,
    mask: Tensor | None = None,
    *,
    degrees: Iterable[int] = range(1, MAX_DEGREE + 1),
    validation: float = VALIDATION,
) -> Polynomial:
    """The least-squares polynomial of y in x over the scored samples, of the degree (among
    ``degrees``; ``degrees=(1,)``: the straight line) with the least RMSE on the hold-out
    (:func:`holdout_mask`) when fitted before it.

    Args:
        x, y: input and target, (time,) or (rows, time).
        mask: the scored samples, the shape of x (default: all).
        degrees: the degrees to try, each >= 1.
        validation: the hold-out share of each row's scored samples.

    Returns:
        The :class:`Polynomial` refitted on all scored samples.

    Raises:
        ValueError: shapes differ, NaN or inf among the scored samples, no degree or one
            below 1, fewer scored samples before the hold-out than the highest degree + 1.
    """
    xs, ys, mask = _samples(x, y, mask)
    if not isinstance(degrees, Iterable):
        raise TypeError(f"degrees must be an iterable of ints >= 1 (e.g. (1,) or range(1, 6)), "
                        f"got {degrees!r}")
    degrees = sorted({check_int(d, "degrees", minimum=1) for d in degrees})
    if not degrees:
        raise ValueError("degrees must hold at least one degree >= 1")
    held = holdout_mask(mask, validation)
    fit = mask & ~held
    if int(fit.sum()) < degrees[-1] + 1:
        raise ValueError(f"a polynomial of degree {degrees[-1]} needs at least "
                         f"{degrees[-1] + 1} scored samples before the hold-out, got "
                         f"{int(fit.sum())} (of {int(mask.sum())} scored)")
    fx, fy, hx, hy = (v.numpy() for v in (xs[fit], ys[fit], xs[held], ys[held]))
    scores = {d: float(np.sqrt(np.mean((_fit(fx, fy, d)(hx) - hy) ** 2))) for d in degrees}
    best = min(scores, key=lambda d: (not math.isfinite(scores[d]), scores[d]))
    return Polynomial(_fit(xs[mask].numpy(), ys[mask].numpy(), best), best, scores[best])

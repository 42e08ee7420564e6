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

__all__ = ["MAX_DEGREE", "ConditionPolynomial", "Polynomial", "fit_condition_polynomial",
           "fit_polynomial", "holdout_mask", "max_degree"]

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


class ConditionPolynomial(NamedTuple):
    """A memoryless polynomial ``y = p(x, c)`` of the input and the operating conditions,
    fitted by :func:`fit_condition_polynomial`: a tensor-product Legendre basis of total
    degree ``degree`` in the variables, each scaled to [-1, 1] over its fitted range.

    Call it on x (...) and conditions (..., n): the outputs, x's shape and dtype.
    """

    coef: Tensor
    exponents: list[list[int]]
    low: Tensor
    high: Tensor
    degree: int
    validation_rmse: float

    def __call__(self, x: Tensor, conditions: Tensor) -> Tensor:
        z = torch.cat([x.detach().to(torch.float64).cpu()[..., None],
                       conditions.detach().to(torch.float64).cpu()], -1)
        out = _condition_design(z, self.low, self.high, self.exponents, self.degree) @ self.coef
        return out.to(dtype=x.dtype, device=x.device)


def _condition_design(z: Tensor, low: Tensor, high: Tensor, exponents: list[list[int]],
                      degree: int) -> Tensor:
    from torchhys.conditions.basis import legendre_basis, scaled_conditions

    span = torch.where(high > low, high - low, torch.ones_like(high))
    return legendre_basis(scaled_conditions(z, low, low + span), exponents, degree)


def fit_condition_polynomial(
    x: Tensor, conditions: Tensor, y: Tensor, mask: Tensor | None = None, *,
    degrees: Iterable[int] = range(1, 6), validation: float = VALIDATION,
) -> ConditionPolynomial:
    """The least-squares polynomial of y in x and the conditions over the scored samples
    (float64), of the total degree (among ``degrees``) with the least RMSE on the hold-out
    (:func:`holdout_mask`) when fitted before it, refitted on all scored samples: the
    memoryless baseline of a model that sees the conditions.

    Args:
        x, y: input and target, (time,) or (rows, time); conditions: (..., n), x's shape
            and n columns.
        mask, degrees, validation: as :func:`fit_polynomial`'s.

    Raises:
        ValueError: shapes that differ, NaN or inf among the scored samples, no degree,
            fewer scored samples before the hold-out than the highest degree's terms.
    """
    from torchhys.conditions.basis import total_degree

    xs, ys, mask = _samples(x, y, mask)
    c = torch.as_tensor(conditions).detach().to(torch.float64).cpu()
    c = c[None] if c.dim() == 2 and xs.shape[0] == 1 and c.shape[0] != 1 else c
    if c.shape[:-1] != xs.shape:
        raise ValueError(f"conditions must have x's shape {tuple(xs.shape)} and n columns, "
                         f"got {tuple(torch.as_tensor(conditions).shape)}")
    if not bool(c[mask].isfinite().all()):
        raise ValueError("conditions hold NaN or inf among the scored samples")
    degrees = sorted({check_int(d, "degrees", minimum=1) for d in degrees})
    if not degrees:
        raise ValueError("degrees must hold at least one degree >= 1")
    z = torch.cat([xs[..., None], c], -1)
    held = holdout_mask(mask, validation)
    fit = mask & ~held
    lo, hi = z[mask].amin(0), z[mask].amax(0)

    def solve(rows: Tensor, d: int) -> tuple[Tensor, list[list[int]]]:
        e = total_degree(z.shape[-1], d)
        a = _condition_design(z[rows], lo, hi, e, d)
        if a.shape[0] < a.shape[1]:
            raise ValueError(f"a polynomial of total degree {d} in {z.shape[-1]} variables "
                             f"needs at least {a.shape[1]} scored samples before the "
                             f"hold-out, got {a.shape[0]}")
        return torch.linalg.lstsq(a, ys[rows][:, None], driver="gelsd").solution[:, 0], e

    scores = {}
    for d in degrees:
        coef, e = solve(fit, d)
        pred = _condition_design(z[held], lo, hi, e, d) @ coef
        scores[d] = float((pred - ys[held]).square().mean().sqrt())
    best = min(scores, key=lambda d: (not math.isfinite(scores[d]), scores[d]))
    coef, e = solve(mask, best)
    return ConditionPolynomial(coef, e, lo, hi, best, scores[best])

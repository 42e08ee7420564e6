"""Penalised non-negative least squares from the normal equations, and the choice of a penalty
on a time-ordered hold-out: shared by the Preisach and Prandtl-Ishlinskii identifications
(:func:`torchhys.fit_preisach`, :func:`torchhys.identification.fitting.fit_prandtl_ishlinskii`).

Both fits reduce to a design ``A`` (rows: samples, columns: features) and a target ``y``; a
:class:`Moments` holds what a solve or a score needs of one segment of the samples
(``A'A``, ``A'y``, ``y'y`` and the number of rows), so a penalty is scored on the hold-out
without touching the samples again.

References:
    C. L. Lawson and R. J. Hanson, Solving Least Squares Problems, SIAM, 1995, Ch. 23.
"""

from __future__ import annotations

import math
import numbers
import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import check_penalty, fitted_samples


class Moments(NamedTuple):
    """Second moments of one segment of a least-squares problem, float64."""

    gram: Tensor
    """``A'A``, (m, m)."""
    moment: Tensor
    """``A'y``, (m,)."""
    yy: Tensor
    """``y'y``, 0-dim."""
    count: int
    """Rows (samples) of the segment."""


def moments(A: Tensor, y: Tensor) -> Moments:
    """The :class:`Moments` of a design ``A`` (rows, m) and target ``y`` (rows,), float64."""
    A, y = A.to(torch.float64), y.to(torch.float64)
    return Moments(A.T @ A, A.T @ y, y @ y, int(y.numel()))


def moments_rmse(m: Moments, theta: Tensor) -> float:
    """The RMS error of the solution ``theta`` on the rows of the moments ``m``, from them:
    ``sqrt((y'y - 2 theta'A'y + theta'A'A theta) / rows)`` (0 where rounding makes it
    negative)."""
    sse = m.yy - 2.0 * theta @ m.moment + theta @ m.gram @ theta
    return math.sqrt(max(float(sse) / m.count, 0.0))


def check_validation(validation: object) -> float:
    """The hold-out share of a penalty selection: a real number in (0, 1) (None, which
    :func:`holdout_cuts` reads as "no hold-out", is an error here)."""
    if (isinstance(validation, bool) or not isinstance(validation, numbers.Real)
            or not 0.0 < validation < 1.0):
        raise ValueError(f"validation must be in (0, 1), got {validation!r}")
    return float(validation)


def holdout_cuts(T: int, warmup: int, validation: float | None) -> list[int]:
    """Segment boundaries of each row of T samples: ``[warmup, T]`` (fit on all), or
    ``[warmup, split, T]`` with the last ``validation`` share (at least one sample) held out.

    Raises:
        ValueError: ``validation`` not in (0, 1), or no training sample before the split.
    """
    if validation is None:
        return [warmup, T]
    if (isinstance(validation, bool) or not isinstance(validation, numbers.Real)
            or not 0.0 < validation < 1.0):
        raise ValueError(f"validation must be in (0, 1), got {validation!r}")
    split = T - max(1, round(validation * T))
    if split <= warmup:
        raise ValueError(f"warmup ({warmup}) leaves no training samples before the "
                         f"validation split at {split}")
    return [warmup, split, T]


def fit_segments(shape: tuple[int, int], warmup: int, mask: Tensor | None,
                 validation: float | None) -> list[Tensor]:
    """The samples of each segment of a fit, (rows, time) bool each: ``[fitted]``, or
    ``[training, hold-out]`` with ``validation`` in (0, 1).

    The fitted samples are :func:`~torchhys._checks.fitted_samples`'. Without a mask the
    hold-out is :func:`holdout_cuts`' (the last ``validation`` share of every row's T
    samples); with one, the last ``validation`` share of each row's masked samples (at least
    one, where it has any).

    Raises:
        TypeError, ValueError: a bad mask, ``validation`` not in (0, 1), no training sample
            before the hold-out.
    """
    fitted = fitted_samples(mask, shape, warmup)
    if validation is None:
        return [fitted]
    validation = check_validation(validation)
    if mask is None:
        _, split, _ = holdout_cuts(shape[1], warmup, validation)
        held = torch.zeros_like(fitted)
        held[:, split:] = True
        return [fitted & ~held, held]
    count = fitted.sum(1, keepdim=True)
    held = torch.where(count > 0, (validation * count).round().clamp_min(1), 0)
    valid = fitted & (fitted.cumsum(1) > count - held)
    train = fitted & ~valid
    if not bool(train.any()):
        raise ValueError(f"the mask's {int(count.sum())} samples leave no training sample "
                         f"before the validation share ({validation:g}) of each row")
    return [train, valid]


def select_on_holdout(
    train: Moments, valid: Moments, penalties: Sequence[float],
    solve: Callable[[Tensor, Tensor, float], Tensor], *, name: str = "penalties",
) -> tuple[float, dict[float, float]]:
    """Score each penalty by the RMS error on the hold-out of the fit on the training part.

    Args:
        train, valid: moments of the training and the held-out samples.
        penalties: the candidates (each finite and >= 0), at least one.
        solve: ``solve(G, h, penalty) -> theta`` with the training moments per sample
            (``A'A / n``, ``A'y / n``).
        name: the argument's name in error messages.

    Returns:
        The penalty with the least hold-out RMS error (the first on ties), and the RMS
        error of each (from the moments: ``(y'y - 2 theta'A'y + theta'A'A theta) / n``).

    Raises:
        ValueError, TypeError: no penalty, or a bad one.
    """
    if isinstance(penalties, (str, bytes)) or not hasattr(penalties, "__len__") or (
            isinstance(penalties, Tensor) and penalties.dim() == 0):
        raise TypeError(f"{name} must be a sequence of candidate values (e.g. [0.0, 1e-4]), "
                        f"got {type(penalties).__name__} {penalties!r}")
    if len(penalties) == 0:
        raise ValueError(f"{name} must hold at least one value, got none")
    values = [check_penalty(p, name) for p in penalties]
    scores: dict[float, float] = {}
    for p in values:
        theta = solve(train.gram / train.count, train.moment / train.count, p)
        scores[p] = moments_rmse(valid, theta)
    return min(scores, key=scores.__getitem__), scores


STALLED_STEPS = 10
"""Steps in a row that do not lower the objective after which :func:`nnls_gram` stops."""


def nnls_gram(G: Tensor, h: Tensor, free: Tensor, init: Tensor | None = None) -> Tensor:
    """Lawson-Hanson active set for ``min w'Gw/2 - h'w`` subject to ``w[~free] >= 0``.

    The free variables are always in the passive set; the columns are scaled to a unit
    diagonal first. A warm start ``init`` (e.g. the solution for a neighbouring penalty)
    starts the passive set at its positive entries: the same solution, in fewer steps when
    the two supports are close.

    Args:
        G: (m, m) symmetric positive (semi)definite, float64 (``A'A`` plus penalties).
        h: (m,), float64 (``A'y``).
        free: (m,) bool, the unconstrained variables.
        init: (m,) float64 starting point, or None (start from the free variables alone).
            Its negative constrained entries count as 0.

    Every step of the method lowers the objective in exact arithmetic. On a singular or
    nearly singular ``G`` (collinear features and no penalty) rounding can make the steps
    cycle among supports at the same objective: after ``STALLED_STEPS`` steps in a row
    that do not lower it, the method stops and returns the best point it met (the
    optimum to rounding; a positive penalty makes the problem well posed).

    Returns:
        The solution w, (m,).

    Warns:
        RuntimeWarning: it stopped after ``3 m + 10`` iterations before convergence.
    """
    diag = G.diagonal()
    s = torch.where(diag > 0, diag.clamp_min(1e-300).rsqrt(), torch.ones_like(diag))
    G, h = s[:, None] * G * s, s * h
    m = h.numel()
    blocked = torch.zeros_like(free)
    if init is None:
        passive = free.clone()
        w = _passive_solve(G, h, passive)
    else:
        # a feasible start, positive on its constrained passive entries: the inner loop of
        # the active set method moves it to the optimum on its support, dropping entries
        # that reach 0 on the way
        w = torch.where(free, init / s, (init / s).clamp_min(0.0)).to(h.dtype)
        passive = free | (w > 0)
        w = _feasible_descent(G, h, free, passive, w)
    tol = 1e-12 * max(1.0, float(h.abs().max())) if m else 0.0
    dual = h - G @ w
    best, lowest, stalled = w, _objective(w, h, dual), 0
    for _ in range(3 * m + 10):
        cand = ~passive & ~blocked & (dual > tol)
        if not bool(cand.any()):
            break
        j = int(torch.where(cand, dual, -math.inf).argmax())
        passive[j] = True
        z = _passive_solve(G, h, passive)
        if bool(z[j] <= 0) and not bool(free[j]) and float(w[j]) == 0.0:
            # rounding: the new index does not enter
            passive[j], blocked[j] = False, True
            continue
        w, blocked = _feasible_descent(G, h, free, passive, w, z), torch.zeros_like(free)
        dual = h - G @ w
        value = _objective(w, h, dual)
        if value < lowest:
            best, lowest, stalled = w, value, 0
            continue
        stalled += 1
        if stalled >= STALLED_STEPS:  # cycling at rounding level
            w = best
            break
    else:
        warnings.warn(f"NNLS stopped after {3 * m + 10} iterations before convergence",
                      RuntimeWarning, stacklevel=3)
    return s * w


def _objective(w: Tensor, h: Tensor, dual: Tensor) -> float:
    """``w'Gw/2 - h'w`` from the dual ``h - G w``."""
    return -0.5 * float(w @ (h + dual))


def _feasible_descent(G: Tensor, h: Tensor, free: Tensor, passive: Tensor, w: Tensor,
                      z: Tensor | None = None) -> Tensor:
    """The inner loop of the active set method: from a feasible w, move towards the
    solution z on the passive set until a constrained entry reaches 0, drop it, repeat; the
    optimum on the final passive set (which it updates in place)."""
    while True:
        z = _passive_solve(G, h, passive) if z is None else z
        neg = passive & ~free & (z <= 0)
        if not bool(neg.any()):
            return z
        ratio = torch.where(neg, w / (w - z).clamp_min(1e-300), math.inf)
        k = int(ratio.argmin())
        w = w + ratio[k] * (z - w)
        w[k] = 0.0
        drop = passive & ~free & (w <= 0)
        passive &= ~drop
        w[drop] = 0.0
        z = None


def _passive_solve(G: Tensor, h: Tensor, passive: Tensor) -> Tensor:
    """Solve the equations of the passive set (Cholesky; if singular, the minimum-norm
    least-squares solution by SVD: pivoted QR (``gelsy``) decides the rank of a singular
    set differently from call to call, with the data's memory alignment, and the active
    set's path with it)."""
    z = torch.zeros_like(h)
    idx = passive.nonzero().squeeze(1)
    if idx.numel():
        A, b = G[idx][:, idx], h[idx]
        L, info = torch.linalg.cholesky_ex(A)
        sol = (torch.cholesky_solve(b[:, None], L)[:, 0] if int(info) == 0
               else torch.linalg.lstsq(A, b[:, None], driver="gelsd").solution[:, 0])
        z[idx] = sol
    return z

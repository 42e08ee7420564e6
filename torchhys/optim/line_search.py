"""Line searches along a direction for :class:`torchhys.optim.PowellBealeCG`.

Both searches work on the one-dimensional restriction ``phi(a) = f(x + a d)`` given as a
callable that returns the loss, the slope ``phi'(a) = g(x + a d) . d`` and the flat gradient
``g(x + a d)`` of shape ``(n,)``. Both accept a trial step ``a`` when it satisfies

* sufficient decrease: ``phi(a) <= phi(0) + alpha * a * phi'(0)`` and ``phi(a) < phi(0)``,
* the slope condition: ``|phi'(a)| <= beta * |phi'(0)|``,

and both treat a trial point where the loss or the slope is NaN or infinite as a step that
is too long: the step shrinks and the point is never returned.

References:
    C. Charalambous, "Conjugate gradient algorithm for efficient training of artificial
    neural networks", IEE Proceedings G 139(3), 1992.
    J. Nocedal and S. J. Wright, "Numerical Optimization", 2nd ed., Springer, 2006,
    Algorithms 3.5 and 3.6.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

from torch import Tensor

__all__ = ["LineSearchFn", "LineSearchResult", "PhiFn", "charalambous", "strong_wolfe"]

PhiFn = Callable[[float], tuple[float, float, Tensor]]
"""``phi(a) -> (loss, slope, flat_grad)`` at the point ``x + a d``; ``flat_grad: (n,)``."""

# Fraction of the way back towards the best point when a trial point is not finite.
_NONFINITE_SHRINK = 0.1
# Bounds on an extrapolated step, as multiples of the current step.
_EXTRAPOLATE_MIN = 1.1
_EXTRAPOLATE_MAX = 10.0


class LineSearchResult(NamedTuple):
    """Outcome of a line search.

    Attributes:
        step: accepted step ``a > 0``, or ``0.0`` when no decrease was found.
        loss: ``phi(step)`` (``phi(0)`` on failure).
        grad: flat gradient at ``x + step d``, shape ``(n,)``; ``None`` on failure.
        evals: number of calls to ``phi``.
        status: ``"ok"`` (both conditions hold), ``"tolerance"`` / ``"max_evals"`` (the best
            point with sufficient decrease is returned although the slope condition does not
            hold), ``"minimum_step"`` / ``"no_decrease"`` (failure, ``step == 0``).
    """

    step: float
    loss: float
    grad: Tensor | None
    evals: int
    status: str


LineSearchFn = Callable[[PhiFn, float, float, float], LineSearchResult]
"""``search(phi, f0, s0, a1) -> LineSearchResult``: a user-supplied search gets ``phi``,
``phi(0)``, ``phi'(0) < 0`` and the suggested first step ``a1``."""


def cubic_minimizer(a: float, fa: float, sa: float, b: float, fb: float, sb: float) -> float:
    """Minimizer of the cubic through ``(a, fa)``, ``(b, fb)`` with slopes ``sa``, ``sb``.

    Returns:
        The minimizer, or NaN when the cubic has no local minimizer (or ``a == b``).
    """
    if a == b:
        return math.nan
    d1 = sa + sb - 3.0 * (fa - fb) / (a - b)
    disc = d1 * d1 - sa * sb
    if not math.isfinite(disc) or disc < 0.0:
        return math.nan
    d2 = math.copysign(math.sqrt(disc), b - a)
    denom = sb - sa + 2.0 * d2
    if denom == 0.0:
        return math.nan
    return b - (b - a) * (sb + d2 - d1) / denom


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def charalambous(
    phi: PhiFn,
    f0: float,
    s0: float,
    a1: float,
    *,
    alpha: float = 1e-3,
    beta: float = 0.1,
    gamma: float = 0.1,
    scale_tol: float = 20.0,
    min_step: float = 0.0,
    max_evals: int = 100,
) -> LineSearchResult:
    """Cubic-interpolation search in the manner of Charalambous (1992).

    The search keeps a bracket: ``lo`` is the best trial with sufficient decrease (initially
    ``0``) and ``hi`` the other end, so that a point satisfying both conditions lies between
    them. While no upper end is known the step grows by cubic extrapolation through the last
    two trials, kept in ``[1.1 a, 10 a]`` (``10 a`` where the cubic has no finite
    minimizer). Inside a bracket of width ``w`` the next trial is
    the minimizer of the cubic through both ends (their losses and slopes), kept at least
    ``gamma * w`` away from either end; a non-finite end shrinks the step to
    ``lo + 0.1 (hi - lo)``. The search stops when

    * both conditions hold (``"ok"``);
    * ``lo > 0`` and the bracket is narrower than ``lo / scale_tol`` (``"tolerance"``, ``lo``
      is returned);
    * no decrease was found and the bracket ``[0, hi]`` is shorter than ``min_step``
      (``"minimum_step"``, failure);
    * ``max_evals`` evaluations were spent (``"max_evals"`` returning ``lo`` if ``lo > 0``,
      otherwise ``"no_decrease"``).

    Args:
        phi: ``phi(a) -> (loss, slope, flat_grad)``, ``flat_grad: (n,)``.
        f0: ``phi(0)``.
        s0: ``phi'(0)``, negative.
        a1: first trial step, positive.
        alpha: sufficient-decrease constant.
        beta: slope constant, ``alpha < beta < 1``.
        gamma: minimum relative distance of an interpolated step from the bracket ends.
        scale_tol: ratio of the best step to the bracket width at which the search stops.
        min_step: smallest step worth trying while no decrease has been found.
        max_evals: maximum number of calls to ``phi``.

    Returns:
        A :class:`LineSearchResult`.
    """
    lo, f_lo, s_lo, g_lo = 0.0, f0, s0, None
    hi, f_hi, s_hi = math.inf, math.nan, math.nan
    prev, f_prev, s_prev = 0.0, f0, s0
    a = a1
    for evals in range(1, max_evals + 1):
        f, s, g = phi(a)
        if not _finite(f, s):
            hi, f_hi, s_hi = a, math.nan, math.nan
        elif f > f0 + alpha * a * s0 or f >= f_lo:
            hi, f_hi, s_hi = a, f, s
        elif abs(s) <= -beta * s0:
            return LineSearchResult(a, f, g, evals, "ok")
        else:
            if s * (a - lo) > 0.0:
                hi, f_hi, s_hi = lo, f_lo, s_lo
            lo, f_lo, s_lo, g_lo = a, f, s, g
        if math.isinf(hi):
            step = cubic_minimizer(prev, f_prev, s_prev, a, f, s)
            low, high = _EXTRAPOLATE_MIN * a, _EXTRAPOLATE_MAX * a
            a_next = min(max(step, low), high) if math.isfinite(step) else high
        else:
            width = abs(hi - lo)
            if lo > 0.0 and width * scale_tol < lo:
                return LineSearchResult(lo, f_lo, g_lo, evals, "tolerance")
            if lo == 0.0 and hi < min_step:
                return LineSearchResult(0.0, f0, None, evals, "minimum_step")
            if math.isnan(f_hi):
                a_next = lo + _NONFINITE_SHRINK * (hi - lo)
            else:
                step = cubic_minimizer(lo, f_lo, s_lo, hi, f_hi, s_hi)
                left, right = min(lo, hi) + gamma * width, max(lo, hi) - gamma * width
                a_next = min(max(step, left), right) if math.isfinite(step) else 0.5 * (lo + hi)
        if _finite(f, s):
            prev, f_prev, s_prev = a, f, s
        a = a_next
    if lo > 0.0:
        return LineSearchResult(lo, f_lo, g_lo, max_evals, "max_evals")
    return LineSearchResult(0.0, f0, None, max_evals, "no_decrease")


def strong_wolfe(
    phi: PhiFn,
    f0: float,
    s0: float,
    a1: float,
    *,
    alpha: float = 1e-3,
    beta: float = 0.1,
    gamma: float = 0.1,
    min_step: float = 0.0,
    max_evals: int = 100,
) -> LineSearchResult:
    """Strong-Wolfe bracketing and zoom search (Nocedal and Wright, Algorithms 3.5-3.6).

    Bracketing phase: the step doubles until a trial fails sufficient decrease, does not
    decrease the loss below the previous trial, or has a non-negative slope. Zoom phase:
    the next trial is the minimizer of the cubic through the two bracket ends, replaced by
    bisection when it is not finite or lies within ``gamma * w`` of an end (``w`` the
    bracket width). Non-finite trials shrink the step to ``lo + 0.1 (hi - lo)``. The search
    stops with ``"ok"`` when both conditions hold, with ``"tolerance"`` (best point) or
    ``"minimum_step"`` (failure) when the bracket is shorter than ``min_step``, and with
    ``"max_evals"`` / ``"no_decrease"`` after ``max_evals`` evaluations.

    Args:
        phi: ``phi(a) -> (loss, slope, flat_grad)``, ``flat_grad: (n,)``.
        f0: ``phi(0)``.
        s0: ``phi'(0)``, negative.
        a1: first trial step, positive.
        alpha: sufficient-decrease constant (``c1``).
        beta: curvature constant (``c2``), ``alpha < beta < 1``.
        gamma: relative distance from a bracket end below which bisection is used.
        min_step: bracket width (in units of the step) at which the search stops.
        max_evals: maximum number of calls to ``phi``.

    Returns:
        A :class:`LineSearchResult`.
    """
    lo, f_lo, s_lo, g_lo = 0.0, f0, s0, None
    hi, f_hi, s_hi = math.inf, math.nan, math.nan
    a = a1
    for evals in range(1, max_evals + 1):
        f, s, g = phi(a)
        if not _finite(f, s) or f > f0 + alpha * a * s0 or f >= f_lo:
            hi, f_hi, s_hi = (a, f, s) if _finite(f, s) else (a, math.nan, math.nan)
        elif abs(s) <= -beta * s0:
            return LineSearchResult(a, f, g, evals, "ok")
        else:
            if s * (a - lo) > 0.0:
                hi, f_hi, s_hi = lo, f_lo, s_lo
            lo, f_lo, s_lo, g_lo = a, f, s, g
        if math.isinf(hi):
            a = 2.0 * a
            continue
        width = abs(hi - lo)
        if width < min_step or width <= 1e-15 * max(lo, hi):
            if lo > 0.0:
                return LineSearchResult(lo, f_lo, g_lo, evals, "tolerance")
            return LineSearchResult(0.0, f0, None, evals, "minimum_step")
        if math.isnan(f_hi):
            a = lo + _NONFINITE_SHRINK * (hi - lo)
            continue
        step = cubic_minimizer(lo, f_lo, s_lo, hi, f_hi, s_hi)
        left, right = min(lo, hi) + gamma * width, max(lo, hi) - gamma * width
        a = step if math.isfinite(step) and left <= step <= right else 0.5 * (lo + hi)
    if lo > 0.0:
        return LineSearchResult(lo, f_lo, g_lo, max_evals, "max_evals")
    return LineSearchResult(0.0, f0, None, max_evals, "no_decrease")

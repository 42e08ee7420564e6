"""Plain float64 Python-loop references for turning points and the branch operators."""

from __future__ import annotations

import math
from collections.abc import Callable


def ref_turning_points(x: list[float], threshold: float) -> list[bool]:
    """Zigzag detector written sample by sample (independent of the play formulation)."""
    r = threshold / 2
    mark = [False] * len(x)
    d, m, mi = 0, x[0], 0
    for t, xt in enumerate(x):
        if d == 0:
            if abs(xt - x[0]) > r:
                d, m, mi = (1 if xt > x[0] else -1), xt, t
        elif d * (xt - m) > 0:
            m, mi = xt, t
        elif d * (m - xt) > threshold:
            mark[mi] = True
            d, m, mi = -d, xt, t
    return mark


def _g(u: float, a: float, kind: str) -> float:
    return a * math.sqrt(u) if kind == "eiho" else (1 - math.exp(-u)) * u


def ref_branch(
    x: list[float], *, a_up: float = 1.0, a_down: float = 1.0, threshold: float = 0.0,
    rule: str = "recent", kind: str = "eiho", depth: int = 32, a_seg: list[float] | None = None,
    a_anchor: Callable[[int, float], float] | None = None, branch: bool = False,
) -> list[float]:
    """The branch operator (EIHO / Zhao-Tan) written as a per-sample loop.

    ``a_anchor(direction, x_e)``: a coefficient that depends on the branch's start point.
    ``branch``: return ``f - f(x_e)`` (the committed anchor's output subtracted).
    """

    def coef(s: int, seg: int, x_e: float) -> float:
        if a_anchor is not None:
            return a_anchor(s, x_e)
        if a_seg is not None:
            return a_seg[min(seg, len(a_seg) - 1)]
        return a_up if s >= 0 else a_down

    def anchor(stack: list[tuple[float, float, int]], m: float, d: int) -> int:
        top = len(stack) - 1
        while d != 0 and top >= 2 and d * (m - stack[top - 1][0]) >= 0:
            top -= 2
        return top

    r = threshold / 2
    d, m, nseg = 0, x[0], 0
    stack = [(x[0], 0.0, 0)]
    out = []
    for xt in x:
        moved = 0
        if d == 0:
            if abs(xt - x[0]) > r:
                moved = 1 if xt > x[0] else -1
        elif d * (xt - m) > 0:
            moved = d
        elif d * (m - xt) > threshold:
            moved = -d
        if moved:
            if d != 0 and moved != d:
                top = anchor(stack, m, d) if rule == "dominant" else len(stack) - 1
                ax, af, aseg = stack[top]
                fv = af + d * _g(abs(m - ax), coef(d, aseg, ax), kind)
                nseg += 1
                if rule == "recent":
                    stack = [(m, fv, nseg)]
                else:
                    stack = stack[: top + 1]
                    if len(stack) == depth:
                        del stack[1:3]
                    stack.append((m, fv, nseg))
            d, m = moved, xt
        top = anchor(stack, m, d) if rule == "dominant" else len(stack) - 1
        ax, af, aseg = stack[top]
        f_m = (0.0 if branch else af) + d * _g(abs(m - ax), coef(d, aseg, ax), kind)
        s = -d if d != 0 else (1 if xt > m else (-1 if xt < m else 0))
        u = max(s * (xt - m), 0.0)
        out.append(f_m + s * _g(u, coef(s, nseg + 1 if d != 0 else nseg, m), kind))
    return out

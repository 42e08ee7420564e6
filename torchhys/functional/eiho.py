"""The elementary inverse hysteresis operator (EIHO, Eq. (2)) and Zhao-Tan's operator.

See :mod:`torchhys.functional._branch` for the shared turning-point machinery (rules
``"recent"`` / ``"dominant"``, behavior between a turning point and its confirmation).
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_choice,
    check_finite,
    check_floating,
    check_int,
    check_same_shape,
)
from torchhys.functional._branch import (
    BranchState,
    SquareRoot,
    ZhaoTanShape,
    branch_operator,
    check_a,
)
from torchhys.functional.turning_points import turning_points

__all__ = ["NonCausalWarning", "eiho", "segment_coefficients", "zhao_tan"]

_FORMULAS = ("sqrt", "paper")
_OUTPUTS = ("level", "branch")


class NonCausalWarning(UserWarning):
    """A result uses future samples (e.g. the paper's per-segment coefficients)."""


def _check_depth(max_depth: int) -> None:
    check_int(max_depth, "max_depth", minimum=3)


def _check_output(output: str) -> bool:
    return check_choice(output, "output", _OUTPUTS) == "branch"


def eiho(
    x: Tensor,
    a: Tensor | float = 1.0,
    *,
    rule: str = "recent",
    threshold: float | str | Tensor = 0.0,
    state: BranchState | None = None,
    per_segment: bool = False,
    eps: float = 1e-8,
    max_depth: int = 32,
    anchor_slope: Tensor | float | None = None,
    output: str = "level",
) -> tuple[Tensor, BranchState]:
    """Elementary inverse hysteresis operator, Eq. (2).

    ``f(x) = f(x_e) + a (x - x_e)^(1/2)`` while ``x`` increases and
    ``f(x) = f(x_e) - a (x_e - x)^(1/2)`` while it decreases, ``x_e`` being the anchor
    turning point chosen by ``rule``. A fresh state starts at ``x_e = x[0]``, ``f = 0``.

    Supports batches, autograd in ``x`` and ``a`` (finite everywhere: the square root has a
    bounded slope below ``eps``, see :func:`safe_sqrt`), and streaming: calling it on
    consecutive chunks with the returned state equals one call on the whole sequence.

    Args:
        x: input, (time,) or (batch, time).
        a: positive coefficient: a scalar, ``(ascending, descending)`` of shape (2,), or with
            ``per_segment=True`` one per branch, shape (batch, segments) (segment ``k``
            starts at the ``k``-th confirmed turning point; the last value is reused).
        rule: ``"recent"`` (last turning point, Eq. (2) as printed) or ``"dominant"``
            (return-point memory, bounded on periodic inputs).
        threshold: reversal threshold of the turning-point detector (see
            :func:`turning_points`); ``"auto"`` is estimated per call, so stream with a number.
        state: :class:`BranchState` from a previous call, or None for a fresh start.
        per_segment: index ``a`` by branch number (see :func:`segment_coefficients`).
        eps: below ``|x - x_e| = eps`` (squared input units) the square root is linear.
        max_depth: stack size of the ``"dominant"`` rule (>= 3; on overflow the two oldest
            turning points above the start are forgotten).
        anchor_slope: ``k``, a scalar or ``(ascending, descending)``: the coefficient of a
            branch becomes a positive function of its start point ``x_e``,
            ``a_d exp(k_d x_e)`` (causal; ``k = 0`` is a constant ``a``). Not with
            ``per_segment``.
        output: ``"level"`` (default): ``f``; ``"branch"``: the branch-local value
            ``f - f(x_e)`` (``x_e`` the committed anchor; between a turning point and its
            confirmation the tentative reversed branch is included), i.e.
            ``+/- a |x - x_e|^(1/2)`` on a committed branch: bounded and free of the level
            that ``f`` accumulates along the history. Same state and streaming guarantees.

    Returns:
        ``(f, state)``: ``f`` of the shape of ``x``; state tensors have a leading batch
        dimension (1 for a 1-D input).

    Raises:
        TypeError, ValueError: bad ``x`` (shape, dtype, NaN/inf), ``a``, ``rule``,
            ``threshold``, ``state`` or ``max_depth``, each naming the argument.

    References:
        Eq. (2) of "A neural networks based model of inverse hysteresis" (Neurocomputing,
        2011).
    """
    xb, _ = as_batched_sequence(x, "x")
    _check_depth(max_depth)
    branch = _check_output(output)
    a_t = check_a(a if isinstance(a, Tensor) else xb.new_tensor(a), per_segment, xb.shape[0])
    slope = None if anchor_slope is None else _check_slope(anchor_slope, per_segment, xb)
    return branch_operator(
        x, a_t.to(xb.dtype), SquareRoot(eps), rule, threshold, state, per_segment, max_depth,
        anchor_slope=slope, branch=branch,
    )


def _check_slope(anchor_slope: Tensor | float, per_segment: bool, xb: Tensor) -> Tensor:
    if per_segment:
        raise ValueError("anchor_slope cannot be combined with per_segment coefficients")
    if isinstance(anchor_slope, bool) or not isinstance(anchor_slope, (Tensor, int, float)):
        raise TypeError(f"anchor_slope must be a tensor or a number, got {anchor_slope!r}")
    k = anchor_slope if isinstance(anchor_slope, Tensor) else xb.new_tensor(anchor_slope)
    check_floating(k, "anchor_slope")
    check_finite(k, "anchor_slope")
    if k.numel() not in (1, 2) or k.dim() > 1:
        raise ValueError(
            f"anchor_slope must be a scalar or (ascending, descending), got {tuple(k.shape)}"
        )
    return k.reshape(-1).expand(2).to(xb.dtype)


def zhao_tan(
    x: Tensor,
    *,
    rule: str = "recent",
    threshold: float | str | Tensor = 0.0,
    state: BranchState | None = None,
    max_depth: int = 32,
    output: str = "level",
    scale: float = 1.0,
) -> tuple[Tensor, BranchState]:
    """Zhao and Tan's expanded-input-space operator (the paper's Ref. [8]).

    ``f(x) = (1 - exp(-|x - x_p| / s)) (x - x_p) + f(x_p)``, ``x_p`` the anchor turning
    point, ``s`` the input scale (``s = 1``: the published form).
    This form is the project's definition (as usually quoted; not checked against the
    primary text). Same machinery, arguments and guarantees as :func:`eiho`; smooth at
    ``x = x_p``.

    Args:
        x: input, (time,) or (batch, time).
        rule: ``"recent"`` or ``"dominant"``.
        threshold: reversal threshold of the turning-point detector.
        state: state from a previous call, or None.
        max_depth: stack size of the ``"dominant"`` rule.
        output: ``"level"`` (default) or ``"branch"`` (``f - f(x_p)``), as for :func:`eiho`.
        scale: input scale ``s > 0`` of the branch shape.

    Returns:
        ``(f, state)`` as for :func:`eiho`.

    References:
        Zhao and Tan, expanded input space neural network model of hysteresis.
    """
    xb, _ = as_batched_sequence(x, "x")
    _check_depth(max_depth)
    branch = _check_output(output)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (
            math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    a = xb.new_ones(2)
    return branch_operator(
        x, a, ZhaoTanShape(float(scale)), rule, threshold, state, False, max_depth,
        branch=branch,
    )


def segment_coefficients(
    x: Tensor, y: Tensor, *, threshold: float | str | Tensor = 0.0, formula: str = "sqrt",
    min_step: float = 1e-12,
) -> Tensor:
    """The paper's per-segment coefficients ``a_i`` from recorded (input, target) data.

    For consecutive turning points ``(x_i, y_i)``, ``(x_{i+1}, y_{i+1})`` of the input
    (the start and the last sample close the first and last segments):
    ``"sqrt"``: ``a_i = |y_{i+1} - y_i| / |x_{i+1} - x_i|^(1/2)`` (consistent with Eq. (2):
    the EIHO then passes through every output extremum); ``"paper"``: Eq. (19) as printed,
    ``a_i = |y_{i+1} - y_i| / (x_{i+1} - x_i)^2``.

    Not causal: ``a_i`` uses the target's *next* extremum. Use it to reproduce the paper's
    protocol on recorded data, not in a deployed compensator (a :class:`NonCausalWarning`
    says so).

    Args:
        x: operator input, (time,) or (batch, time).
        y: targets, same shape.
        threshold: reversal threshold of the turning-point detector.
        formula: ``"sqrt"`` (default) or ``"paper"``.
        min_step: lower bound on ``|x_{i+1} - x_i|`` and on ``a_i`` (keeps them positive).

    Returns:
        ``a``, shape (batch, segments) (``segments`` = most turning points in a row + 1;
        shorter rows repeat their last value). Detached.

    Raises:
        ValueError: mismatched shapes, NaN/inf, unknown ``formula``.
    """
    warnings.warn(
        "per-segment coefficients use the target's next extremum: the operator is not "
        "causal (fine for replaying recorded data, not for a deployed compensator)",
        NonCausalWarning, stacklevel=2,
    )
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    check_choice(formula, "formula", _FORMULAS)
    mask = turning_points(xb, threshold=threshold)
    mask[:, 0] = True
    mask[:, -1] = True
    B, T = xb.shape
    n = mask.sum(dim=1)
    index = torch.arange(T, device=xb.device)
    order = torch.where(mask, index, T).sort(dim=1).values[:, : int(n.max())]
    order = torch.minimum(order, (order.gather(1, (n - 1)[:, None])))  # pad with last index
    xe, ye = xb.detach().gather(1, order), yb.detach().gather(1, order)
    dx = (xe[:, 1:] - xe[:, :-1]).abs().clamp(min=min_step)
    dy = (ye[:, 1:] - ye[:, :-1]).abs()
    power = 0.5 if formula == "sqrt" else 2.0
    a = (dy / dx**power).clamp(min=min_step)
    if T < 2 or a.shape[1] == 0:
        return xb.new_ones(B, 1)
    # Rows with fewer segments repeat their last real coefficient.
    k = torch.arange(a.shape[1], device=a.device).expand(B, -1)
    last = a.gather(1, (n - 2).clamp(min=0)[:, None])
    return torch.where(k <= (n - 2)[:, None], a, last)

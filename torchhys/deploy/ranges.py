"""What a compensator takes from its model: the command limits (the training target's range),
the input range of the clamp and the direction of the guard (see
:mod:`torchhys.deploy.streaming`)."""

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import check_real

__all__ = [
    "DIRECTIONS", "MIN_TREND", "RANGES", "default_condition_ranges", "default_direction",
    "default_input_range", "default_limits", "training_ranges",
]

#: values of ``StreamingCompensator(direction=...)``
DIRECTIONS = ("auto", "increasing", "decreasing", "none")


def default_limits(model: nn.Module) -> tuple[float, float]:
    """Command limits of a model: its recorded training-target range.

    Uses ``model.out_min`` / ``model.out_max`` (the training targets' range, recorded by
    :meth:`~torchhys.InverseHysteresisNet.fit_normalization`).

    Raises:
        ValueError: the model records no output range (a :class:`PrandtlIshlinskiiInverse`,
            or a network whose normalization was never fitted): pass ``limits=``.
    """
    lo, hi = getattr(model, "out_min", None), getattr(model, "out_max", None)
    if isinstance(lo, Tensor) and isinstance(hi, Tensor):
        low, high = float(lo), float(hi)
        if math.isfinite(low) and math.isfinite(high) and low < high:
            return low, high
    raise ValueError(
        f"{type(model).__name__} records no training output range (normalization not fitted, "
        "or an analytic inverse): pass limits=(low, high) in command units"
    )


def _recorded(model: nn.Module, name: str) -> float:
    """A scalar buffer the model records (``nan`` when it has none or it is not fitted)."""
    value = getattr(model, name, None)
    if isinstance(value, Tensor) and value.numel() == 1:
        return float(value)
    return math.nan


def default_input_range(model: nn.Module) -> tuple[float, float] | None:
    """The training input's range recorded by the model (``in_min``, ``in_max``, set by
    :meth:`~torchhys.InverseHysteresisNet.fit_normalization`), or None when it records none
    (then a compensator does not clamp its input unless given ``input_range``)."""
    lo, hi = _recorded(model, "in_min"), _recorded(model, "in_max")
    if math.isfinite(lo) and math.isfinite(hi) and lo < hi:
        return lo, hi
    return None


MIN_TREND = 0.5
"""The least absolute correlation of the training input and target (the model's recorded
``trend``) that gives a compensator a direction by default: a device whose command rises or
falls with its response. Below it (the friction force of a seal against its position,
r = 0.00; a damper's force against its position, r = 0.1-0.5) the data have no direction to
keep, and ``direction="auto"`` sets no guard."""


def default_direction(model: nn.Module) -> int:
    """The direction of the target's trend in the input recorded by the model: the sign of
    its ``trend`` (the training input's and target's correlation coefficient, recorded by
    :meth:`~torchhys.InverseHysteresisNet.fit_normalization`) when ``|trend| >=``
    :data:`MIN_TREND`, else 0 (no clear direction, or none recorded)."""
    r = _recorded(model, "trend")
    return int(math.copysign(1.0, r)) if math.isfinite(r) and abs(r) >= MIN_TREND else 0


def _check_limits(limits: Sequence[float], name: str = "limits") -> tuple[float, float]:
    if isinstance(limits, (str, bytes)) or len(limits) != 2:
        raise ValueError(f"{name} must be a pair (low, high), got {limits!r}")
    low, high = (float(v) for v in limits)
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"{name} must be finite with low < high, got ({low}, {high})")
    return low, high


def _direction(model: nn.Module, direction: str) -> int:
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {list(DIRECTIONS)}, got {direction!r}")
    if direction == "auto":
        return default_direction(model)
    return {"increasing": 1, "decreasing": -1, "none": 0}[direction]


def _input_bounds(model: nn.Module, input_range: Sequence[float] | None,
                  input_margin: float | None) -> tuple[float, float] | None:
    """The clamp's bounds: the range widened by the margin on each side, or None."""
    if input_margin is None:
        return None
    margin = check_real(input_margin, "input_margin")
    if margin < 0:
        raise ValueError(f"input_margin must be >= 0 (a share of the input range) or None, "
                         f"got {margin}")
    rng = (default_input_range(model) if input_range is None
           else _check_limits(input_range, "input_range"))
    if rng is None:
        return None
    return _widened(rng, margin)


def _widened(rng: tuple[float, float], margin: float) -> tuple[float, float]:
    """``(lo, hi)`` widened by ``margin`` of its width on each side (the clamp's bounds)."""
    lo, hi = rng
    return lo - margin * (hi - lo), hi + margin * (hi - lo)


def default_condition_ranges(model: nn.Module, n: int) -> list[tuple[float, float]] | None:
    """The training conditions' ranges recorded by a conditioned model (buffers ``cond_min``,
    ``cond_max`` of ``n`` values, :class:`~torchhys.protocols.Conditioned`), or None when it
    records none (then a compensator does not clamp the conditions unless given
    ``condition_ranges``)."""
    lo, hi = getattr(model, "cond_min", None), getattr(model, "cond_max", None)
    if not (isinstance(lo, Tensor) and isinstance(hi, Tensor)
            and lo.numel() == n and hi.numel() == n):
        return None
    pairs = [(float(a), float(b)) for a, b in zip(lo.reshape(-1).tolist(),
                                                    hi.reshape(-1).tolist(), strict=True)]
    if all(math.isfinite(a) and math.isfinite(b) and a < b for a, b in pairs):
        return pairs
    return None


def _condition_bounds(model: nn.Module, n: int, condition_ranges: Sequence | None,
                      input_margin: float | None) -> tuple[Tensor, Tensor] | None:
    """The condition clamp's bounds, (n,) float64 each: each range widened by the margin on
    each side, or None (no margin, or no ranges recorded nor given)."""
    if n == 0:
        if condition_ranges is not None:
            raise ValueError("condition_ranges given, but the model takes no conditions "
                             "(n_conditions is 0)")
        return None
    if condition_ranges is None:
        ranges = default_condition_ranges(model, n)
    else:
        if isinstance(condition_ranges, (str, bytes)) or len(condition_ranges) != n:
            raise ValueError(f"condition_ranges must be {n} pair(s) (low, high), one per "
                             f"condition, got {condition_ranges!r}")
        ranges = [_check_limits(r, f"condition_ranges[{i}]")
                  for i, r in enumerate(condition_ranges)]
    if input_margin is None or ranges is None:
        return None
    bounds = [_widened(r, check_real(input_margin, "input_margin")) for r in ranges]
    return (torch.tensor([lo for lo, _ in bounds], dtype=torch.float64),
            torch.tensor([hi for _, hi in bounds], dtype=torch.float64))


#: the buffers a model records its training data's ranges in (what this module reads)
RANGES = ("in_min", "in_max", "out_min", "out_max", "trend")


def training_ranges(xs: Tensor, ys: Tensor) -> tuple[float, float, float, float, float]:
    """The :data:`RANGES` of flat training samples xs, ys (the fitted ones, not constant):
    the min and max of each and ``trend``, their correlation coefficient, in float64."""
    xs, ys = xs.detach().double().flatten(), ys.detach().double().flatten()
    xc, yc = xs - xs.mean(), ys - ys.mean()
    trend = (xc * yc).sum() / (xc.square().sum() * yc.square().sum()).sqrt()
    return (float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max()),
            float(trend))

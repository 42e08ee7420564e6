"""Input checks shared by the public entry points.

Every public function validates its arguments once, here, and raises a
``TypeError`` or ``ValueError`` that names the argument and what was received.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "check_finite",
    "check_floating",
    "check_tensor",
    "check_widths",
    "as_batched_sequence",
]


def check_tensor(value: object, name: str) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a tensor."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_floating(value: Tensor, name: str) -> Tensor:
    """Raise ``TypeError`` unless ``value`` has a floating-point dtype."""
    if not value.is_floating_point():
        raise TypeError(
            f"{name} must have a floating-point dtype (e.g. torch.float32), got {value.dtype}; "
            f"convert it with {name}.float()"
        )
    return value


def check_finite(value: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` if ``value`` holds a NaN or an infinity."""
    if value.numel() > 0 and not bool(torch.isfinite(value).all()):
        bad = (~torch.isfinite(value)).nonzero()[0].tolist()
        raise ValueError(
            f"{name} must be finite, but it holds NaN or inf (first at index {tuple(bad)})"
        )
    return value


def check_widths(widths: Tensor, name: str = "widths") -> Tensor:
    """Validate dead-band widths: a finite, non-negative floating tensor of shape (N,)."""
    check_tensor(widths, name)
    check_floating(widths, name)
    if widths.dim() != 1:
        raise ValueError(f"{name} must have shape (N,), got shape {tuple(widths.shape)}")
    if widths.numel() == 0:
        raise ValueError(f"{name} must hold at least one width, got an empty tensor")
    check_finite(widths, name)
    if bool((widths < 0).any()):
        raise ValueError(
            f"{name} must be non-negative, got minimum {widths.min().item():.6g}"
        )
    return widths


def as_batched_sequence(x: Tensor, name: str = "x") -> tuple[Tensor, bool]:
    """Check a sequence of shape (T,) or (B, T) and return it as (B, T).

    Returns:
        The tensor as (B, T) and whether a batch dimension was added.
    """
    check_tensor(x, name)
    check_floating(x, name)
    if x.dim() not in (1, 2):
        raise ValueError(
            f"{name} must have shape (time,) or (batch, time), got shape {tuple(x.shape)}"
        )
    if x.shape[-1] == 0:
        raise ValueError(f"{name} must hold at least one sample, got shape {tuple(x.shape)}")
    check_finite(x, name)
    if x.dim() == 1:
        return x.unsqueeze(0), True
    return x, False

"""Checks shared by the dynamic models: the sampling frequency and a carried state."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def check_fs(fs: object, name: str = "fs") -> float:
    """A positive, finite sampling frequency (Hz) as a float."""
    if isinstance(fs, bool) or not isinstance(fs, (int, float)) or not math.isfinite(fs) \
            or fs <= 0:
        raise ValueError(f"{name} must be a positive finite float (Hz), got {fs!r}")
    return float(fs)


def check_scale(value: object, name: str) -> float:
    """A positive, finite unit (a signal's scale) as a float."""
    if isinstance(value, Tensor):
        value = float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite float, got {value!r}")
    return float(value)


def scale_buffer(value: object, name: str) -> Tensor:
    """A checked unit as a float64 0-dim tensor (a float32 one would round 1e-3 by 5e-8)."""
    return torch.tensor(check_scale(value, name), dtype=torch.float64)

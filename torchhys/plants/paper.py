"""The paper's simulated backlash-hysteresis experiments (Section 5.2 and Fig. 6)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys.functional.prandtl_ishlinskii import prandtl_ishlinskii

__all__ = ["Simulation", "fig6_simulation", "paper_simulation", "paper_plant_widths"]


class Simulation(NamedTuple):
    """A simulated experiment: unpacks as ``t, x, h``."""

    t: Tensor
    """Sample times, shape (T,)."""
    x: Tensor
    """Plant input, shape (T,): the inverse model's target."""
    h: Tensor
    """Plant output H[x], shape (T,): the inverse model's input."""


def _time(dt: float, t_end: float, dtype: torch.dtype) -> Tensor:
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive finite number, got {dt!r}")
    if not (isinstance(t_end, (int, float)) and math.isfinite(t_end) and t_end > dt):
        raise ValueError(f"t_end must be a finite number larger than dt={dt}, got {t_end!r}")
    return torch.arange(0.0, t_end, dt, dtype=torch.float64).to(dtype)


def paper_plant_widths(dtype: torch.dtype = torch.float32) -> Tensor:
    """Dead-band widths of the paper's plant: 15 evenly spaced in [1/6, 15/6], shape (15,)."""
    return torch.linspace(1.0 / 6.0, 15.0 / 6.0, 15, dtype=torch.float64).to(dtype)


def _simulate(x: Tensor, widths: Tensor, dtype: torch.dtype) -> Tensor:
    h = prandtl_ishlinskii(x, widths, torch.ones_like(widths))
    return h.to(dtype)


def paper_simulation(
    dt: float = 0.01, t_end: float = 8 * math.pi, *, dtype: torch.dtype = torch.float32
) -> Simulation:
    """The paper's Section 5.2 simulation.

    Backlash hysteresis ``H[x] = sum_{i=1}^{15} y_i`` of 15 play operators with full
    widths evenly spaced in [1/6, 15/6], zero initial outputs, driven by
    ``x(t) = 4 sin(0.5 t) + 2 sin(3 t)`` sampled at ``t = 0, dt, 2 dt, ... < t_end``
    (2514 samples with the defaults; the paper does not give its sampling step).
    The plant is computed in float64 and returned in ``dtype``.

    Args:
        dt: sampling step (s).
        t_end: end of the time span (exclusive).
        dtype: dtype of the returned tensors.

    Returns:
        :class:`Simulation` ``(t, x, h)``, each of shape (T,). ``h`` is the inverse
        model's input and ``x`` its target.
    """
    t = _time(dt, t_end, torch.float64)
    x = 4.0 * torch.sin(0.5 * t) + 2.0 * torch.sin(3.0 * t)
    h = _simulate(x, paper_plant_widths(torch.float64), dtype)
    return Simulation(t.to(dtype), x.to(dtype), h)


def fig6_simulation(
    dt: float = 0.01, t_end: float = 8 * math.pi, *, dtype: torch.dtype = torch.float32
) -> Simulation:
    """The paper's Fig. 6 illustration.

    Ten play operators with full widths evenly spaced in [0.5, 5], unit weights,
    zero initial outputs, driven by ``x(t) = 2 sin(3 t) + 3 sin(0.5 t)``.

    Args:
        dt: sampling step (s).
        t_end: end of the time span (exclusive).
        dtype: dtype of the returned tensors.

    Returns:
        :class:`Simulation` ``(t, x, h)``, each of shape (T,).
    """
    t = _time(dt, t_end, torch.float64)
    x = 2.0 * torch.sin(3.0 * t) + 3.0 * torch.sin(0.5 * t)
    widths = torch.linspace(0.5, 5.0, 10, dtype=torch.float64)
    return Simulation(t.to(dtype), x.to(dtype), _simulate(x, widths, dtype))

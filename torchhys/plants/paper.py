"""The paper's simulated backlash-hysteresis experiments (Section 5.2 and Fig. 6)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys.functional.prandtl_ishlinskii import prandtl_ishlinskii
from torchhys.signals import sum_of_sines, time_grid

__all__ = ["Simulation", "fig6_simulation", "paper_simulation", "paper_plant_widths"]


class Simulation(NamedTuple):
    """A simulated experiment: unpacks as ``t, x, h``."""

    t: Tensor
    """Sample times, shape (T,)."""
    x: Tensor
    """Plant input, shape (T,): the inverse model's target."""
    h: Tensor
    """Plant output H[x], shape (T,): the inverse model's input."""


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
    t = time_grid(dt=dt, t_end=t_end, dtype=torch.float64)
    x = sum_of_sines(t, amplitudes=(4.0, 2.0), frequencies=(0.5, 3.0))
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
    t = time_grid(dt=dt, t_end=t_end, dtype=torch.float64)
    x = sum_of_sines(t, amplitudes=(2.0, 3.0), frequencies=(3.0, 0.5))
    widths = torch.linspace(0.5, 5.0, 10, dtype=torch.float64)
    return Simulation(t.to(dtype), x.to(dtype), _simulate(x, widths, dtype))

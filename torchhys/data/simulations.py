"""The simulated sources of a fit's data: the paper's plants and a Bouc-Wen plant."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchhys._checks import check_choice

__all__ = ["SIMULATIONS", "simulate"]

SIMULATIONS = ("paper", "fig6", "bouc_wen")
"""Simulated sources: the paper's Section 5.2 plant, its Fig. 6 plant, a Bouc-Wen plant."""


def simulate(name: str, *, dt: float = 0.01, t_end: float = 8 * math.pi,
             seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """``(t, x, y)`` of a simulated source in float64: model input ``x`` (the plant's
    output) and target ``y`` (the plant's input), shape (time,).

    ``"bouc_wen"``: the default :class:`torchhys.plants.BoucWen` plant driven by a
    multisine (band 0.2-3 rad/s, 8 tones, random phases from ``seed``) scaled to +-6.
    """
    from torchhys.plants import bouc_wen, fig6_simulation, paper_simulation
    from torchhys.signals import multisine, time_grid, to_range

    check_choice(name, "simulation", SIMULATIONS)
    if name == "paper":
        t, u, h = paper_simulation(dt, t_end, dtype=torch.float64)
    elif name == "fig6":
        t, u, h = fig6_simulation(dt, t_end, dtype=torch.float64)
    else:  # "bouc_wen"
        t = time_grid(dt=dt, t_end=t_end, dtype=torch.float64)
        u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=seed), -6.0, 6.0)
        h = bouc_wen(u, t)
    return t, h, u

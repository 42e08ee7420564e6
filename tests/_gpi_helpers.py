"""A generalized Prandtl-Ishlinskii model and inputs shared by its tests."""

from __future__ import annotations

import torch
from _helpers import random_walk

from torchhys.operators.generalized_pi import GeneralizedPrandtlIshlinskii

F64 = torch.float64
WIDTHS = [0.0, 0.4, 1.0, 1.7, 2.5]


def model(dtype: torch.dtype = F64, **kw) -> GeneralizedPrandtlIshlinskii:
    """Positive play weights and a g with three units of different slopes."""
    args = dict(weights=[0.3, 0.8, 0.05, 0.5, 0.2], linear_weight=0.4,
                centers=[-1.0, 0.2, 1.5], slopes=[0.7, 2.0, 1.2], unit_weights=[0.5, 0.3, 0.9],
                gain=0.3, offset=-0.2)
    args.update(kw)
    return GeneralizedPrandtlIshlinskii(torch.tensor(WIDTHS, dtype=dtype), **args)


def walks(T: int = 200) -> torch.Tensor:
    """Three random walks, (3, T), two of them with repeated samples."""
    return torch.stack([random_walk(s, T=T, quantize=s % 2 == 0) for s in range(3)])

"""Shared set-up of the Preisach tests."""

from __future__ import annotations

import torch

from torchhys.operators.preisach import Preisach

F64 = torch.float64


def signal(B: int, T: int, n: int, seed: int = 0) -> torch.Tensor:
    """A random walk over [-1.3, 1.3] with samples exactly on the grid levels, repeats and
    a flat stretch (ties and saturation)."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.randn(B, T, generator=g, dtype=F64) * 0.35).cumsum(1)
    x = 1.3 * torch.sin(x)
    levels = -1.0 + 2.0 * (torch.arange(n, dtype=F64) + 0.5) / n
    on = torch.rand(B, T, generator=g) < 0.3
    x = torch.where(on, levels[torch.randint(n, (B, T), generator=g)], x)
    x[:, T // 3: T // 3 + 5] = x[:, T // 3: T // 3 + 1]
    return x


def model(n: int = 9, seed: int = 0, **options) -> Preisach:
    m = Preisach(-1.0, 1.0, n, **options).double()
    with torch.no_grad():
        m.weights.copy_(torch.rand(m.n_relays, generator=torch.Generator().manual_seed(seed),
                                   dtype=F64))
        m.linear.fill_(0.3)
        m.offset.fill_(-0.2)
    return m

"""Write ``examples/data/bouc_wen.csv``: a recorded-like (command, response) experiment.

The default :class:`torchhys.plants.BoucWen` plant (a piezo-like counter-clockwise loop)
is driven by a multisine command (band 0.2-3 rad/s, 8 tones, seed 0) scaled to +-6,
sampled at 100 Hz for 30 s (3000 rows); the response gets Gaussian sensor noise of
standard deviation 0.005 (seed 1). Columns: ``time`` (s), ``command``, ``response``.

Usage: ``python examples/make_example_data.py [--out PATH]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torchhys.plants import bouc_wen
from torchhys.signals import multisine, time_grid, to_range


def make(t_end: float = 30.0, dt: float = 0.01, noise: float = 0.005) -> np.ndarray:
    """Rows ``(time, command, response)``, float64, shape (T, 3)."""
    t = time_grid(dt=dt, t_end=t_end, dtype=torch.float64)
    u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=0), -6.0, 6.0)
    y = bouc_wen(u, t)
    gen = torch.Generator().manual_seed(1)
    y = y + noise * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    return torch.stack([t, u, y], dim=1).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "data/bouc_wen.csv")
    args = parser.parse_args()
    rows = make()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(args.out, rows, delimiter=",", header="time,command,response", comments="",
               fmt=["%.2f", "%.6f", "%.6f"])
    print(f"wrote {args.out}: {len(rows)} rows")


if __name__ == "__main__":
    main()

"""The plant part of the reproduction: the paper's backlash loops and the inverse to learn."""

from __future__ import annotations

from pathlib import Path

import torch


def plot_plant(out_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchhys.plants import fig6_simulation, paper_simulation

    t, x, h = paper_simulation(dtype=torch.float64)
    _, x6, h6 = fig6_simulation(dtype=torch.float64)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    axes[0].plot(t, x, label="x (plant input)")
    axes[0].plot(t, h / 15, label="H[x] / 15 (plant output)")
    axes[0].set(xlabel="t (s)", title="Section 5.2: signals")
    axes[0].legend(loc="lower left", fontsize=8)
    axes[1].plot(x, h, lw=0.9)
    axes[1].set(xlabel="x", ylabel="H[x]", title="backlash hysteresis (15 play operators)")
    axes[2].plot(h, x, lw=0.9, color="C3", label="Section 5.2")
    axes[2].plot(h6 * 15 / 10, x6, lw=0.7, color="C2", alpha=0.7, label="Fig. 6 (scaled)")
    axes[2].set(xlabel="H[x] (model input)", ylabel="x (model target)",
                title="inverse hysteresis to learn")
    axes[2].legend(loc="lower right", fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    path = out_dir / "plant_loop.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

"""``make reproduce``: the paper's simulation experiment (Section 5.2).

Until the full reproduction (EIHO network, Zhao-Tan network and plain MLP trained
with conjugate gradient and Adam) lands, this runs the real part that exists: it
simulates the paper's backlash plant (15 play operators, d_i in [1/6, 15/6]) on the
paper's input, checks it against the analytic expectations, and plots the
hysteresis loop and the inverse loop the models must learn, plus the Fig. 6
illustration. Outputs go to ``runs/reproduce/``.
"""

from __future__ import annotations

import argparse
import time
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    from torchhys.plants import paper_simulation

    start = time.perf_counter()
    t, x, h = paper_simulation(dtype=torch.float64)
    print(f"paper simulation: {t.numel()} samples, x in [{x.min():.3f}, {x.max():.3f}], "
          f"H[x] in [{h.min():.3f}, {h.max():.3f}]")
    flat = (h.diff() == 0) & (x.diff() != 0)
    print(f"samples where H[x] is flat while x moves (set-valued inverse): "
          f"{flat.double().mean().item():.1%}")
    path = plot_plant(args.out)
    print(f"wrote {path} in {time.perf_counter() - start:.1f} s")
    print("note: this is the plant part of the reproduction; the model training runs "
          "once the EIHO network and the training issue land")


if __name__ == "__main__":
    main()

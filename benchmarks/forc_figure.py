"""Figure of docs/real-data.md: a Preisach model identified from first-order reversal curves.

Fitted, as the ``preisach`` row of ``benchmarks.real_data`` (its ``feco_forc`` protocol:
30 levels, no smoothness penalty, the row's choice on the training part's hold-out), on the
even reversal curves of the FeCo nanowire array (field -> moment). Left: held-out (odd)
curves, measured and predicted from their calibration point. Right: the identified density
on the (beta, alpha) grid, the relay switching down at beta and up at alpha: the Preisach
counterpart of a FORC diagram. Printed beside the RMSE: the relays' weighted mean
half-width (alpha - beta) / 2 and the coercive field of the held-out curve that reverses
lowest (the major loop's rising branch), measured independently of the fit.

    python -m benchmarks.forc_figure [--out docs/figures/feco_forc_preisach.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.real_data import FULL, forc, line, poly, test_rmse  # noqa: E402
from torchhys import fit_preisach  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LEVELS = 30
"""Levels per axis: the ``preisach`` row's choice on this protocol (docs/real-data.md)."""


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path,
                        default=ROOT / "docs" / "figures" / "feco_forc_preisach.png")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    split = forc()
    model = fit_preisach(split.x, split.y, n=LEVELS, warmup=split.warmup)

    def predict(x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return model(x)[0]

    rmse = test_rmse(predict, split)[0]
    baseline = min(test_rmse(line(split, FULL).predict, split)[0],
                   test_rmse(poly(split, FULL).predict, split)[0])

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    shown = split.test[::8]
    colors = plt.cm.viridis(np.linspace(0, 1, len(shown)))
    for (x, y, w), color in zip(shown, colors, strict=True):
        a.plot(x[w:], 1e3 * y[w:], "k", lw=0.8)
        a.plot(x[w:], 1e3 * predict(x[None])[0, w:], "--", color=color, lw=1.0)
    a.plot([], [], "k", lw=0.8, label="measured (held out)")
    a.plot([], [], "--", color=colors[0],
           label=f"Preisach, {LEVELS} levels\n({rmse / baseline:.2f} of the baseline's RMSE)")
    a.set(xlabel="applied field (Oe)", ylabel="moment (1e-3 emu)",
          title="every 8th held-out reversal curve")
    a.legend(fontsize=7, loc="lower right")

    levels = torch.unique(model.alpha)
    density = torch.full((LEVELS, LEVELS), float("nan"), dtype=torch.float64)
    ia, ib = torch.searchsorted(levels, model.alpha), torch.searchsorted(levels, model.beta)
    density[ia, ib] = model.weights.detach().clamp_min(0.0).double()
    extent = [float(levels[0]), float(levels[-1]), float(levels[0]), float(levels[-1])]
    im = b.imshow(1e3 * density.numpy(), origin="lower", extent=extent, cmap="magma_r")
    b.set(xlabel="beta: switches down (Oe)", ylabel="alpha: switches up (Oe)",
          title="identified density (the fit's relay weights, 1e-3 emu)")
    fig.colorbar(im, ax=b)
    fig.suptitle("FeCo nanowire array: first-order reversal curves (even curves fitted)",
                 fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    w = model.weights.detach().clamp_min(0.0)
    half_width = float((w * (model.alpha - model.beta) / 2).sum() / w.sum())
    print(f"wrote {args.out}; held-out RMSE: Preisach {rmse:.4g} emu, baseline {baseline:.4g} "
          f"emu; relays' weighted mean half-width {half_width:.0f} Oe, coercive field "
          f"{coercive_field(*split.test[-1]):.0f} Oe")


def coercive_field(x: torch.Tensor, y: torch.Tensor, warmup: int) -> float:
    """Where a rising curve's moment crosses zero (linear interpolation between samples):
    on the curve that reverses lowest, the major loop's coercive field."""
    h, m = x[warmup:].numpy(), y[warmup:].numpy()
    i = int(np.flatnonzero((m[:-1] < 0) & (m[1:] >= 0))[0])
    return float(h[i] - m[i] * (h[i + 1] - h[i]) / (m[i + 1] - m[i]))


if __name__ == "__main__":
    main()

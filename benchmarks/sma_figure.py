"""Figure of docs/models.md: a drift beside the stop-type model on the shape-memory-alloy record.

Fitted, as in ``benchmarks.real_data`` (its ``sma_actuator`` protocol), on the first four
thermal cycles of the SMA specimen (chamber temperature -> extension), the default
(``configs/measured.yaml``; its cross-validation chooses the 40 stops beside a drift of the
accumulated temperature variation), the ``stop_pi_drift`` row (the same pair, its stops'
settings chosen on the training part's hold-out) and the ``stop_pi`` row (no drift) predict
the three cycles the fit never saw, beside the least-squares line; the extension ratchets up
from cycle to cycle.

    python -m benchmarks.sma_figure [--out docs/figures/sma_drift.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from benchmarks.real_data import (  # noqa: E402
    FULL,
    REAL,
    default,
    line,
    read_csv,
    sma,
    stop_pi,
    stop_pi_drift,
)

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "sma_drift.png")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    split = sma()
    t = torch.from_numpy(read_csv(REAL / "sma_isobaric_thermal_cycles.csv")["t_h"])
    models = {"default": default(split, FULL), "stop_pi_drift": stop_pi_drift(split, FULL),
              "stop_pi": stop_pi(split, FULL), "line": line(split, FULL)}
    x, y, cut = split.test[0]
    with torch.no_grad():
        pred = {k: m.predict(x[None])[0].detach() for k, m in models.items()}
    rmse = {k: float((p - y)[cut:].square().mean().sqrt()) for k, p in pred.items()}
    bias = {k: float((p - y)[cut:].mean()) for k, p in pred.items()}
    labels = {"default": "measured.yaml: 40 stops + drift",
              "stop_pi_drift": "stops + drift, settings from the hold-out",
              "stop_pi": "stop-type PI alone", "line": "line"}
    styles = {"default": ("C0", 1.0), "stop_pi_drift": ("C2", 0.9), "stop_pi": ("C1", 0.8),
              "line": ("C3", 0.6)}
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    a.plot(t, y, "k", lw=0.9, label="measured")
    for k, p in pred.items():
        a.plot(t, p, color=styles[k][0], lw=styles[k][1],
               label=f"{labels[k]} (RMSE {rmse[k]:.2f} mm, mean error {bias[k]:+.2f})")
    a.axvline(float(t[cut]), color="0.5", ls="--", lw=0.8)
    a.set(xlabel="time (h)", ylabel="extension (mm)",
          title="cycles 1-4 fitted, 5-7 (right of the dashes) never seen")
    a.set_ylim(-9.0, 28.0)  # room for the legend below the loops
    a.legend(fontsize=7, loc="lower right")
    b.plot(x[cut:], y[cut:], "k", lw=0.8, label="measured, cycles 5-7")
    b.plot(x[cut:], pred["default"][cut:], "C0", lw=0.8, label=labels["default"])
    b.plot(x[cut:], pred["stop_pi_drift"][cut:], "C2", lw=0.7, label=labels["stop_pi_drift"])
    b.plot(x[cut:], pred["stop_pi"][cut:], "C1", lw=0.6, label=labels["stop_pi"])
    b.set(xlabel="chamber temperature (C)", ylabel="extension (mm)",
          title="extension against temperature")
    b.legend(fontsize=7)
    fig.suptitle("Shape-memory alloy cycled under a constant load: the loop climbs from cycle "
                 "to cycle", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}; RMSE on cycles 5-7: " +
          ", ".join(f"{k} {v:.3f} mm" for k, v in rmse.items()) + "; mean error: " +
          ", ".join(f"{k} {v:+.3f} mm" for k, v in bias.items()))


if __name__ == "__main__":
    main()

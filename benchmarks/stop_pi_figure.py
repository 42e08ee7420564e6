"""Figure of docs/models.md: the stop-type Prandtl-Ishlinskii model on the friction damper.

Fitted, as in ``benchmarks.real_data`` (its ``stop_pi`` row: settings chosen on the
training part's hold-out), on the sine tests of the banded rotary friction damper, it
predicts the force of an earthquake displacement history it never saw, beside the
least-squares line fitted on the same sines.

    python -m benchmarks.stop_pi_figure [--out docs/figures/stop_pi_friction_damper.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from benchmarks.real_data import FULL, friction_damper, line, stop_pi  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path,
                        default=ROOT / "docs" / "figures" / "stop_pi_friction_damper.png")
    parser.add_argument("--record", type=int, default=2,
                        help="which held-out earthquake (0-3: recordings 10-13)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    split = friction_damper()
    model, straight = stop_pi(split, FULL), line(split, FULL)
    x, y, _ = split.test[args.record]
    with torch.no_grad():
        pred, lin = model.predict(x[None])[0], straight.predict(x[None])[0]
    t = torch.arange(x.numel()) / 64.0  # 64 Hz
    rmse = {k: float((v - y).square().mean().sqrt()) for k, v in
            (("stop_pi", pred), ("line", lin))}
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    a.plot(t, y, "k", lw=0.8, label="measured")
    a.plot(t, pred, "C0", lw=0.8, label=f"stop-type PI (RMSE {rmse['stop_pi']:.2f} kip)")
    a.plot(t, lin, "C3", lw=0.6, alpha=0.7, label=f"line (RMSE {rmse['line']:.2f} kip)")
    a.set(xlabel="time (s)", ylabel="force (kip)",
          title=f"earthquake record {10 + args.record}, never seen in the fit")
    a.legend(fontsize=8)
    b.plot(x, y, "k", lw=0.6, label="measured")
    b.plot(x, pred, "C0", lw=0.6, label="stop-type PI")
    b.set(xlabel="displacement (in)", ylabel="force (kip)", title="force against displacement")
    b.legend(fontsize=8)
    fig.suptitle("Friction damper with backlash: fitted on the sine tests 0-9 "
                 f"({model.choice})", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}; RMSE on record {10 + args.record}: " +
          ", ".join(f"{k} {v:.3f} kip" for k, v in rmse.items()))


if __name__ == "__main__":
    main()

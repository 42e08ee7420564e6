"""Figure of docs/real-data.md: the piezo micromanipulator, whose loop is mostly a time lag.

Left: the identification record's loop (sensor displacement against drive voltage, 1 Hz), as
measured and with the sensor shifted back by the lag (0-12 samples) at which a memoryless
polynomial (degree 5) fits it best. Right: on the test record, the compensator's error
(predicted minus applied voltage) of the default (``configs/measured.yaml``) and of the
least-squares line, both fitted on the identification record as in
``benchmarks.real_data`` (its ``piezo_manipulator`` protocol).

    python -m benchmarks.micromanipulator_figure [--out docs/figures/piezo_micromanipulator.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from benchmarks.real_data import FULL, REAL, default, line, micromanipulator, read_csv  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEGREE = 5


def lag_fit(volt: np.ndarray, disp: np.ndarray, lag: int, start: int) -> float:
    """RMSE of the degree-5 least-squares polynomial of the displacement ``lag`` samples later
    in the voltage, over the record from sample ``start`` on."""
    x, y = volt[start:len(volt) - lag], disp[start + lag:]
    coef = np.polynomial.polynomial.polyfit(x, y, DEGREE)
    return float(np.sqrt(np.mean((y - np.polynomial.polynomial.polyval(x, coef)) ** 2)))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path,
                        default=ROOT / "docs" / "figures" / "piezo_micromanipulator.png")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    split = micromanipulator(compensator=True)
    # one period of the identification sine (1 Hz): the benchmark's warm-up, which only runs
    # the states
    period = split.warmup
    disp, volt = split.x[0].numpy(), split.y[0].numpy()  # the identification record
    fits = {lag: lag_fit(volt, disp, lag, period) for lag in range(13)}
    lag = min(fits, key=fits.get)

    d = read_csv(REAL / "piezo_micromanipulator.csv")
    models = {"default": default(split, FULL), "line": line(split, FULL)}
    x, y, start = split.test[0]
    t = d["t_s"][d["recording"] == 1]
    with torch.no_grad():
        err = {k: (m.predict(x[None])[0] - y).detach().numpy() for k, m in models.items()}
    rmse = {k: float(np.sqrt(np.mean(e[start:] ** 2))) for k, e in err.items()}

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    one = slice(3 * period, 4 * period + 1)  # one period of the steady loop, closed
    a.plot(volt[one], disp[one], "k", lw=0.9, label=f"measured (polynomial RMSE {fits[0]:.2f} um)")
    a.plot(volt[one], disp[3 * period + lag:4 * period + 1 + lag], "C0", lw=0.9,
           label=f"sensor {lag} samples ({1000 * lag / period:.0f} ms) earlier "
                 f"({fits[lag]:.2f} um)")
    a.set(xlabel="drive voltage (V)", ylabel="sensor displacement (um)",
          title="identification record, 1 Hz: most of the loop is a lag")
    a.legend(fontsize=7, loc="upper left")
    labels = {"default": "measured.yaml", "line": "line"}
    for k, color, width in (("line", "C3", 0.6), ("default", "C0", 0.7)):
        b.plot(t[start:], err[k][start:], color=color, lw=width,
               label=f"{labels[k]} (RMSE {rmse[k]:.3f} V)")
    b.axhline(0.0, color="0.5", lw=0.6)
    b.set(xlabel="time (s)", ylabel="predicted - applied voltage (V)",
          title="test record: compensator error")
    b.legend(fontsize=7, loc="lower right")
    fig.suptitle("Piezo micromanipulator (capacitive sensor, 200 Hz)", fontsize=9)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}; polynomial RMSE: {fits[0]:.3f} um unshifted, {fits[lag]:.3f} um "
          f"with the sensor {lag} samples earlier; RMSE on the test record: "
          + ", ".join(f"{k} {v:.4f} V" for k, v in rmse.items()))


if __name__ == "__main__":
    main()

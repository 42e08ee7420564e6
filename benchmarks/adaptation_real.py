"""The closed-loop harness on a measured device: the piezo micromanipulator's two records.

    python benchmarks/adaptation_real.py

``examples/data/real/piezo_micromanipulator.csv`` holds two records of the same device
(drive voltage -> capacitive displacement, 200 Hz): recording 0, a 1 Hz sine over the full
0-3.6 V range (40 periods); recording 1, a later test record (a decaying sine, a rest, two
drives of many amplitudes inside the first loop). The compensator's side sees recording 0
only: the Prandtl-Ishlinskii inverse (``identify_pi``, as the harness's static row), the
sensor's offset (the intercept of the voltage -> displacement line), the command limits, the
PI gains (tuned as the harness tunes them, on a forward PI model of recording 0) and the
adaptive rows' options (the harness's, chosen on simulated plants). The plant is a
Prandtl-Ishlinskii model fitted (``fit_prandtl_ishlinskii``, nonnegative) on recording 1
alone, which the compensator's side never sees; its own error on recording 1 is printed. The
reference: the harness's multisine (seed 11) over 90 % of recording 1's displacement range,
3 x 60 s at 200 Hz, faded in from rest. Scored as the harness scores (RMSE % of the
reference's range, whole run and second half).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a file: the checkout
from benchmarks.adaptation import (  # noqa: E402
    PI_GRID,
    ROWS,
    DriftingPlant,
    Fit,
    closed_loop,
    pi_step,
    play,
    rmse_pct,
)
from benchmarks.compensation import fade_in, identify_pi, static_line  # noqa: E402
from torchhys.identification.fitting import fit_prandtl_ishlinskii  # noqa: E402
from torchhys.signals import multisine, to_range  # noqa: E402

DATA = ROOT / "examples" / "data" / "real" / "piezo_micromanipulator.csv"
FS = 200.0


class PIPlant(DriftingPlant):
    """A Prandtl-Ishlinskii forward model stepped one sample at a time (gain and width
    factors as the harness's plants; 1 here)."""

    def __init__(self, model) -> None:
        self.d = model.fixed_widths.double().detach().numpy()
        self.w = model.weights.double().detach().numpy()
        self.lin = float(model.linear_weight)
        self.reset()

    def reset(self) -> None:
        self.p = np.zeros_like(self.d)

    def step(self, u: float, gain: float, width: float) -> float:
        self.p = play(self.p, u, width * self.d)
        return gain * (self.lin * u + float(self.w @ self.p))


def records() -> list[tuple[torch.Tensor, torch.Tensor]]:
    raw = np.genfromtxt(DATA, delimiter=",", names=True)
    return [(torch.from_numpy(raw["voltage_V"][raw["recording"] == r].copy()),
             torch.from_numpy(raw["displacement_um"][raw["recording"] == r].copy()))
            for r in (0, 1)]


def widths_of(u: torch.Tensor) -> torch.Tensor:
    span = float(u.max() - u.min())
    return torch.linspace(span / 40, span / 2, 20, dtype=torch.float64)


def main() -> None:
    torch.set_num_threads(1)
    start = time.perf_counter()
    (u0, d0), (u1, d1) = records()
    _, offset = static_line(u0, d0)  # the sensor's offset, from recording 0 only
    y0, y1 = d0 - offset, d1 - offset
    k, _ = static_line(u0, y0)
    limits = (float(u0.min()) * 1.05, float(u0.max()) * 1.05)
    fit = Fit("piezo", u0, y0, k, limits, identify_pi(u0, y0, k).inverse())
    train_plant = PIPlant(fit_prandtl_ishlinskii(u0, y0, widths_of(u0), nonnegative=True))
    n = len(u0) // 4
    ref0, flat = y0[:n].numpy(), np.zeros(n)
    scores = {}
    for g in PI_GRID:  # the harness's tuning, on recording 0's forward model
        score = rmse_pct(closed_loop(train_plant, pi_step(fit, g, feedforward=False),
                                     ref0, flat)[0], ref0)
        margin = rmse_pct(closed_loop(train_plant, pi_step(fit, g, feedforward=False), ref0,
                                      flat, 2.0)[0], ref0)
        if margin <= score:
            scores[g] = score
    fit.pi_gains = min(scores, key=scores.get)
    plant_model = fit_prandtl_ishlinskii(u1, y1, widths_of(u1), nonnegative=True)
    with torch.no_grad():
        on1 = plant_model(u1)[0] if isinstance(plant_model(u1), tuple) else plant_model(u1)
        on0 = plant_model(u0)[0] if isinstance(plant_model(u0), tuple) else plant_model(u0)
    pct = 100.0 / float(y1.max() - y1.min())
    print(f"static gain {k:.3f} um/V, offset {offset:.2f} um, limits {limits}, "
          f"PI (a, b) = {fit.pi_gains}")
    print(f"plant model (PI fitted on recording 1): RMSE on recording 1 "
          f"{float((on1 - y1).square().mean().sqrt()):.3f} um "
          f"({float((on1 - y1).square().mean().sqrt()) * pct:.2f} % of its range); on "
          f"recording 0 {float((on0 - y0).square().mean().sqrt()):.3f} um")
    t = torch.linspace(0.0, 180.0, int(180 * FS), dtype=torch.float64)
    low, high = float(y1.min()), float(y1.max())
    mid, half = 0.5 * (low + high), 0.45 * (high - low)
    ref = fade_in(to_range(multisine(t, band=(0.1, 1.5), n_tones=12, seed=11),
                           mid - half, mid + half), t, mid).numpy()
    plant = PIPlant(plant_model)
    cut = len(ref) // 2
    print("\n| method | RMSE (%) | RMSE 2nd half (%) | ratio to static (2nd half) |")
    print("|---|---|---|---|")
    static = None
    for method, make in ROWS.items():
        y, _ = closed_loop(plant, make(fit), ref, np.zeros(len(ref)))
        second = rmse_pct(y[cut:], ref[cut:])
        static = second if static is None else static
        print(f"| {method} | {rmse_pct(y, ref):.3f} | {second:.3f} | {second / static:.3f} |",
              flush=True)
    print(f"\ntotal {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()

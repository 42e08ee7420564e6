"""The adaptive compensator over a long run with a bad sensor: does it stay bounded?

    python benchmarks/adaptation_robustness.py [--steps 1000000] [--rules rls nlms]

The paper plant of ``benchmarks/adaptation.py``, identified undrifted as there, runs in the
closed loop for ``--steps`` samples under the thermal cycle (two warm-ups and cool-downs of
gain +30 % and loop width +40 % over the run) on a multisine reference (the harness's, seed
11, at the record's rate, repeated over the run). The compensator is fed a corrupted
measurement of the plant's output (the plant and the score see the true one):

- Gaussian noise of standard deviation 1 % of the record's output range on every sample;
- NaN bursts: 50 samples in a row every 100 000 (the sensor drops out);
- outliers: one sample in 10 000 (at random) off by 10 times the output range.

Reported per update rule: the largest ``|W - W0| / bound`` over all samples (the normalized
weights' distance from the offline fit in units of ``adapt_bound``'s box: at most 1), the
commands outside the limits, the direction reversals (samples where the clamped reference
rises and the command falls, or the reverse: the guard's rule), the counters (updates
applied, pairs skipped, updates refused), the tracking RMSE over the last 10 % (true output,
% of the reference's range) and the static compensator's on the same run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: the checkout
from benchmarks.adaptation import (  # noqa: E402
    DRIFTS,
    GAIN_DRIFT,
    WIDTH_DRIFT,
    PaperPlant,
    adaptive_compensator,
    identify,
    rmse_pct,
    static_step,
)
from benchmarks.compensation import fade_in  # noqa: E402
from torchhys.signals import multisine, to_range  # noqa: E402

NOISE, BURST, BURST_EVERY, OUTLIER_EVERY, OUTLIER_SIZE = 0.01, 50, 100_000, 10_000, 10.0


def long_reference(fit, steps: int, rate: float) -> np.ndarray:
    """The harness's multisine (seed 11) at ``rate`` samples per second over ``steps``."""
    t = torch.arange(steps, dtype=torch.float64) / rate
    low, high = float(fit.y.min()), float(fit.y.max())
    mid, half = 0.5 * (low + high), 0.45 * (high - low)
    sig = to_range(multisine(t, band=(0.1, 1.5), n_tones=12, seed=11), mid - half, mid + half)
    return fade_in(sig, t, mid).numpy()


def corruption(steps: int, span: float, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(additive error per sample, NaN mask) of the measurement."""
    rng = np.random.default_rng(seed)
    err = rng.normal(0.0, NOISE * span, steps)
    hits = rng.random(steps) < 1.0 / OUTLIER_EVERY
    err[hits] += OUTLIER_SIZE * span * rng.choice([-1.0, 1.0], int(hits.sum()))
    nan = np.zeros(steps, bool)
    for start in range(BURST_EVERY // 2, steps, BURST_EVERY):
        nan[start:start + BURST] = True
    return err, nan


def run(fit, adapt: str | None, ref: np.ndarray, drift: np.ndarray, err: np.ndarray,
        nan: np.ndarray) -> dict:
    """One closed-loop run; ``adapt`` None: the static compensator."""
    plant = PaperPlant()
    steps = len(ref)
    y, u = np.zeros(steps), np.zeros(steps)
    worst = 0.0
    comp = None if adapt is None else adaptive_compensator(fit, adapt)
    static = static_step(fit) if adapt is None else None
    if comp is not None:
        bound, slot = comp.bound.clone(), 2 * comp.k
        low_in, high_in = float(comp.in_low), float(comp.in_high)
    buf = torch.zeros(3, 1, dtype=torch.float64)
    meas = u_prev = 0.0
    for t in range(steps):
        if comp is None:
            u[t] = static(float(ref[t]), meas, u_prev)
        else:
            buf[0, 0], buf[1, 0], buf[2, 0] = float(ref[t]), meas, u_prev
            u[t] = float(comp.step(buf[0], measured_prev=buf[1], applied_prev=buf[2])[0])
            worst = max(worst, float((comp.state[slot].abs() / bound).max()))
        e = drift[t]
        y[t] = plant.step(u[t], 1 + GAIN_DRIFT * e, 1 + WIDTH_DRIFT * e)
        meas = float("nan") if nan[t] else y[t] + err[t]
        u_prev = u[t]
    tail = steps - steps // 10
    out = {"rmse": rmse_pct(y[tail:], ref[tail:]),
           "outside": int(((u < fit.limits[0]) | (u > fit.limits[1])).sum())}
    if comp is not None:
        xc = np.clip(ref, low_in, high_in)
        dx, du = np.diff(xc), np.diff(u)
        out.update(worst=worst, reversals=int(((dx > 0) & (du < 0)).sum()
                                               + ((dx < 0) & (du > 0)).sum()),
                   updates=int(comp.updates_count()[0]), skipped=int(comp.skipped_count()[0]),
                   refused=int(comp.refused_count()[0]),
                   finite=bool(np.isfinite(u).all()))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--rules", nargs="+", choices=["rls", "nlms"], default=["rls", "nlms"])
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    fit = identify("paper", 2000)
    ref = long_reference(fit, args.steps, 2000 / 60.0)
    drift = DRIFTS["thermal cycle"](np.linspace(0.0, 1.0, args.steps))
    span = float(fit.y.max() - fit.y.min())
    err, nan = corruption(args.steps, span)
    print(f"{args.steps} steps, noise {NOISE * span:.4f} (1 % of range), "
          f"{int(nan.sum())} NaN samples, {int((np.abs(err) > 5 * span).sum())} outliers")
    print("| row | max abs(W - W0) / bound | commands outside limits | direction reversals "
          "| updates | skipped | refused | RMSE last 10 % (%) | time (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for adapt in [None, *args.rules]:
        start = time.perf_counter()
        r = run(fit, adapt, ref, drift, err, nan)
        sec = time.perf_counter() - start
        if adapt is None:
            print(f"| static compensator | - | {r['outside']} | - | - | - | - | "
                  f"{r['rmse']:.3f} | {sec:.0f} |", flush=True)
        else:
            print(f"| adaptive {adapt.upper()} | {r['worst']:.3f} | {r['outside']} | "
                  f"{r['reversals']} | {r['updates']} | {r['skipped']} | {r['refused']} | "
                  f"{r['rmse']:.3f} | {sec:.0f} |", flush=True)


if __name__ == "__main__":
    main()

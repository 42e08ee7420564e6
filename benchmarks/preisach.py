"""Benchmark: the Preisach model, forward + backward, and its identification.

T = 1e5 samples, n = 31 levels (K = 496 relays), batch 1, float32. For each method the time
(median of several repeats) and the peak memory, measured as the growth of the process's
peak resident set size over the resident size before the first call, each method in a fresh
subprocess.

Methods:
    chunked       torchhys.functional.preisach: forward + backward of ``(y * probe).sum()``
                  with respect to the weights (the custom backward recomputes the relays)
    smooth        the same with smooth relays (tau = 0.05), gradients to weights and x
    materialised  relay_states (batch, time, K) @ weights with autograd: the naive layout
    fit           fit_preisach (float64 normal equations, chunked, + Lawson-Hanson NNLS)
    step          the scripted per-sample PreisachStep, time per sample (1e4 samples)
    inverse       the exact inverse (PreisachInverse, linear term 1) of the model's output:
                  its sequence path (windows of samples between the relays' switches),
                  time per sample (1e4 samples)
    inverse_loop  the same by a Python loop of preisach_inverse_step over time (what the
                  windows replace), time per sample (1e4 samples)
    inverse_slow  the inverse's sequence path on a recorded loop's kind of signal: two
                  periods of a sine, 5000 samples each, with noise of 0.3 % of its amplitude
                  (fewer switches per sample than the input above), time per sample
    inverse_step  the inverse's scripted PreisachInverseStep, time per sample (1e4 samples)

Usage: python benchmarks/preisach.py [--repeats N] [--threads N] [--length T]

References:
    I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.
"""

from __future__ import annotations

import warnings
from statistics import median

import torch
from _isolated import main_or_run, measure, walk_signal

N_LEVELS = 31
METHODS = ("chunked", "smooth", "materialised", "fit", "step", "inverse", "inverse_loop",
           "inverse_slow", "inverse_step")
PER_SAMPLE = ("step", "inverse", "inverse_loop", "inverse_slow", "inverse_step")


def inverse_loop(inverse, y: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
    """The inverse's sequence path as a loop of its per-sample function: y (1, T) -> x."""
    from torchhys.functional.preisach_inverse import (
        preisach_inverse_constants,
        preisach_inverse_step,
    )

    tables = preisach_inverse_constants(inverse.alpha, inverse.beta, inverse.weights,
                                        inverse.linear, inverse.offset, inverse.center,
                                        inverse.scale)
    r, xs = inverse.initial_relays.expand(y.shape[0], -1), []
    for t in range(y.shape[1]):
        x, r = preisach_inverse_step(y[:, t:t + 1], r, inverse.alpha, inverse.beta, *tables,
                                     inverse.linear, inverse.center, inverse.scale)
        xs.append(x)
    return torch.cat(xs, 1)


def run_one(method: str, T: int, repeats: int) -> dict:
    from torchhys.functional.preisach import preisach, preisach_grid, relay_states
    from torchhys.identification.preisach import fit_preisach
    from torchhys.operators.preisach import Preisach

    x = walk_signal(T)
    alpha, beta = preisach_grid(-1.0, 1.0, N_LEVELS)
    K = alpha.numel()
    w = torch.rand(K, requires_grad=True)
    probe = torch.randn_like(x)
    xg = x.clone().requires_grad_()
    y_fit = None
    step = None

    def call() -> None:
        nonlocal y_fit, step
        if method == "chunked":
            (preisach(x, w, alpha, beta) * probe).sum().backward()
        elif method == "smooth":
            (preisach(xg, w, alpha, beta, smooth=0.05) * probe).sum().backward()
        elif method == "materialised":
            ((relay_states(x, alpha, beta) @ w) * probe).sum().backward()
        elif method == "fit":
            if y_fit is None:
                with torch.no_grad():
                    y_fit = preisach(x, w, alpha, beta).double()
            fit_preisach(x.double(), y_fit, lo=-1.0, hi=1.0, n=N_LEVELS)
        elif method in ("step", "inverse_step"):
            if step is None:
                model = Preisach(-1.0, 1.0, N_LEVELS)
                with torch.no_grad():
                    model.linear.fill_(1.0)
                    y_fit = model(x[:, :10_000])[0]
                op = model if method == "step" else model.inverse()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", DeprecationWarning)
                    eager = op.streaming_step(torch.float32)
                    step = (eager, torch.jit.script(eager))
            xs = x[:, :10_000] if method == "step" else y_fit
            state = step[0].initial_state(xs[:, :1])
            with torch.no_grad():
                for xt in xs.unbind(1):
                    _, state = step[1](xt.unsqueeze(1), state)
        elif method in ("inverse", "inverse_loop", "inverse_slow"):
            if step is None:
                model = Preisach(-1.0, 1.0, N_LEVELS)
                u = x[:, :10_000]
                if method == "inverse_slow":
                    t = torch.arange(10_000, dtype=torch.float64)
                    noise = 0.0027 * torch.randn(10_000, dtype=torch.float64)
                    u = (0.9 * torch.sin(2 * torch.pi * t / 5000) + noise).float()[None]
                with torch.no_grad():
                    model.linear.fill_(1.0)
                    y_fit = model(u)[0]
                step = model.inverse()
            with torch.no_grad():
                if method == "inverse_loop":
                    inverse_loop(step, y_fit)
                else:
                    step(y_fit)
        w.grad = None
        xg.grad = None

    times, peak = measure(call, repeats)
    per = median(times) / 10_000 * 1e6 if method in PER_SAMPLE else None
    return {"method": method, "T": T, "K": K, "median_s": median(times), "min_s": min(times),
            "repeats": len(times), "peak_bytes": peak, "us_per_sample": per,
            "relay_bytes": T * K * 4}


def main() -> None:
    ran = main_or_run(__doc__, __file__, METHODS, run_one, few=("fit", "materialised"))
    if ran is None:
        return
    args, rows = ran
    threads = args.threads or torch.get_num_threads()
    print(f"Preisach, T={args.length}, K={rows[0]['K']} relays (n={N_LEVELS}), batch 1, "
          f"float32 (fit: float64), torch {torch.__version__}, {threads} threads\n")
    print("| method | median time (s) | min time (s) | peak memory (MB) | peak / (T K float32) |")
    print("|---|---|---|---|---|")
    for r in rows:
        label = r["method"]
        if r["us_per_sample"] is not None:
            label += f" ({r['us_per_sample']:.1f} us/sample)"
        print(f"| {label} | {r['median_s']:.3f} | {r['min_s']:.3f} "
              f"| {r['peak_bytes'] / 2**20:.0f} | {r['peak_bytes'] / r['relay_bytes']:.2f} |")


if __name__ == "__main__":
    main()
